"""docs/guarantees.md lists a guarantee only with the tests that prove it: every test it cites exists
(`tests/<file>.py::<test>`, `::<test>` of the file cited last on the same line, and a parametrised
case `[id]` of that test)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CITATION = re.compile(r"(tests/[\w/]+\.py)?::(\w+)(?:\[([^\]]+)\])?")


def citations(text: str) -> list[tuple[str, str, str | None]]:
    out = []
    for line in text.splitlines():
        current = None
        for m in CITATION.finditer(line):
            current = m.group(1) or current
            if current is not None:
                out.append((current, m.group(2), m.group(3)))
    return out


def _case_in(case: str, src: str) -> bool:
    """A case id is a string in the file, or built by pytest from parametrize values (SIGTERM-143)."""
    return f'"{case}"' in src or f"'{case}'" in src or all(part in src for part in case.split("-"))


def test_every_test_the_guarantees_cite_exists():
    cited = citations((ROOT / "docs" / "guarantees.md").read_text())
    assert len(cited) > 50  # the page cites its tests (the pattern still reads them)
    missing = []
    for file, name, case in cited:
        src = (ROOT / file).read_text() if (ROOT / file).is_file() else ""
        if not re.search(rf"^(async )?def {name}\(", src, re.M):
            missing.append(f"{file}::{name}")
        elif case is not None and not _case_in(case, src):
            missing.append(f"{file}::{name}[{case}]")
    assert not missing, f"docs/guarantees.md cites tests that do not exist: {missing}"


def test_the_reader_follows_a_line_and_its_cases():
    line = "| x | `tests/a.py::t1`, `::t2`, `tests/b.py::t3[case-1]`, `::t4` |"
    assert citations(line) == [
        ("tests/a.py", "t1", None),
        ("tests/a.py", "t2", None),
        ("tests/b.py", "t3", "case-1"),
        ("tests/b.py", "t4", None),
    ]
    assert citations("`::orphan`") == []
