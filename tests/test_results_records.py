"""Every number in the tables of docs/results.md and docs/benchmarks.md is in a raw record that its section
names, or its section (or its row) says it is historical (measured before records kept the machine; its
run folders are gone).

Sections are the page's `##` / `###` headings. A section names a record by writing its path,
`docs/bench/<file>.json` or `docs/bench/<file>.md`, anywhere in its text (its prose or a row). A table
number (a decimal, a number in scientific notation or an integer of at least 4 digits, in a row of a
markdown table) matches when some number in one of the records its section names (any depth of a json, any
number in an md) prints as it (rounded to the printed digits, or truncated to them). Strict, so that a
match means something: with hundreds of records of thousands of numbers a three-digit figure would match
some record by chance, but rarely the few its section names. So:

- a section with table numbers that names no record fails, naming the section; so does a section that
  names a record that does not exist;
- a number quoted in two sections needs a record named in each;
- a section opts out only by saying "historical" in its text, which the reader sees; a single row opts out
  the same way, by saying "historical" in one of its cells.

Not measurements, so not checked: the first cell of a row (it names the row), text in backticks (commands
and keys), integers below 1000 (step counts, sizes, seeds), dates (2026-11-28), and a bare integer in a
column whose header names a setting (`batch`, `epochs`, `steps`, `train length`). Derived numbers
(ratios, sums, per-unit conversions, figures from two records) cannot be checked: a page keeps them out
of its tables, in prose that states the derivation.
"""

from __future__ import annotations

import bisect
import functools
import json
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results.md"
BENCHMARKS = ROOT / "docs" / "benchmarks.md"
PAGES = {"results.md": RESULTS, "benchmarks.md": BENCHMARKS}
BENCH = ROOT / "docs" / "bench"
NUMBER = re.compile(r"(?<![\w.])[-−]?(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?:e[-−+]?\d+)?(?![\w.])")
RECORD_NAME = re.compile(r"docs/bench/([\w.\-]+\.(?:json|md))")
DATE = re.compile(r"(?<![\w.])\d{4}-\d{2}-\d{2}(?![\d.])")
# A column whose header is one of these holds the run's settings (what was asked), not what was measured.
SETTING_HEADER = re.compile(r"batch|batch size|epochs|steps|train length")
BARE_INTEGER = re.compile(r"\**[\d,]+\**")


def _values(x, out: list[float]) -> None:
    if isinstance(x, bool):
        return
    if isinstance(x, (int, float)):
        if math.isfinite(x):
            out.append(float(x))
    elif isinstance(x, dict):
        for v in x.values():
            _values(v, out)
    elif isinstance(x, list):
        for v in x:
            _values(v, out)
    elif isinstance(x, str):
        for m in NUMBER.finditer(x):
            out.extend(_parse(m.group(0)))


def _parse(text: str) -> list[float]:
    t = text.replace("−", "-").replace(",", "")
    try:
        return [float(t)]
    except ValueError:
        return []


@functools.cache
def _record(path: Path) -> tuple[float, ...]:
    """Every number in one record (absolute values, sorted): a json at any depth, or an md's text."""
    out: list[float] = []
    if path.suffix == ".json":
        _values(json.loads(path.read_text(), parse_constant=lambda c: None), out)
    else:
        _values(path.read_text(), out)
    return tuple(sorted({abs(v) for v in out}))


def record_values(paths: list[Path] | None = None) -> list[float]:
    """Every number in the given records (all of docs/bench/ when None): absolute values, sorted."""
    if paths is None:
        paths = sorted(BENCH.glob("*.json")) + sorted(BENCH.glob("*.md"))
    return sorted({v for p in paths for v in _record(p)})


def _digits(text: str) -> tuple[float, float]:
    """(value, one unit of the last printed digit) of a printed number."""
    t = text.replace("−", "-").replace(",", "")
    mant, _, exp = t.lower().partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    unit = 10.0 ** (-decimals) * (10.0 ** int(exp) if exp else 1.0)
    return abs(float(t)), unit


def matches(text: str, values: list[float]) -> bool:
    """Does some record value print as `text` (rounded, or truncated, to its digits)?"""
    v, unit = _digits(text)
    lo, hi = v - unit * 0.5001, v + unit * 0.9999  # rounded to the digits printed, or truncated
    i = bisect.bisect_left(values, lo)
    return i < len(values) and values[i] <= hi


def sections(text: str) -> list[tuple[str, str]]:
    """(heading, body) of every `##` / `###` section."""
    parts = re.split(r"^(#{2,3} .*)$", text, flags=re.M)
    return [(parts[i].strip(), parts[i + 1]) for i in range(1, len(parts) - 1, 2)]


def _cells(row: str) -> list[str]:
    """A table row's cells (an escaped `\\|` stays inside its cell, as markdown renders it)."""
    return re.split(r"(?<!\\)\|", row.strip().strip("|"))


def _is_setting_column(header: str) -> bool:
    return SETTING_HEADER.fullmatch(re.sub(r"[`*_]", "", header).strip().lower()) is not None


def table_numbers(body: str) -> list[str]:
    """The measured-looking numbers of the body's table rows (not the header or separator rows)."""
    out = []
    header: list[str] = []
    lines = body.splitlines()
    for j, line in enumerate(lines):
        if not line.startswith("|") or set(line) <= set("|-: "):
            continue
        if j + 1 < len(lines) and set(lines[j + 1].strip()) <= set("|-: ") and lines[j + 1].strip():
            header = _cells(line)  # a header row: it says which columns hold settings
            continue
        if historical(line):
            continue  # the row says it is historical
        for k, cell in enumerate(_cells(line)[1:], start=1):  # the first cell names the row
            cell = re.sub(r"`[^`]*`", "", cell)  # commands and keys: settings, not measurements
            cell = DATE.sub("", cell)  # when it ran, not what it measured
            if k < len(header) and _is_setting_column(header[k]) and BARE_INTEGER.fullmatch(cell.strip()):
                continue  # a batch size or an epoch budget, as asked
            for m in NUMBER.finditer(cell):
                t = m.group(0)
                is_int = re.fullmatch(r"[-−]?[\d,]+", t) is not None
                if is_int and abs(float(t.replace(",", "").replace("−", "-"))) < 1000:
                    continue
                out.append(t)
    return out


def historical(text: str) -> bool:
    return "historical" in text.lower()


def prose(body: str) -> str:
    """The body without its table rows (a row saying "historical" opts out only itself)."""
    return "\n".join(line for line in body.splitlines() if not line.startswith("|"))


def named_records(body: str, bench: Path = BENCH) -> list[Path]:
    """The records a section names (`docs/bench/<file>`), in order of first mention; some may not exist."""
    return [bench / name for name in dict.fromkeys(RECORD_NAME.findall(body))]


def section_problems(body: str, bench: Path = BENCH) -> list[str]:
    """What is wrong with one section: its table numbers that no record it names holds, a record it names
    that does not exist, or that it has table numbers and names no record. Empty when it is historical."""
    if historical(prose(body)):
        return []
    numbers = table_numbers(body)
    if not numbers:
        return []
    named = named_records(body, bench)
    if not named:
        return ["its table has numbers and it names no record (docs/bench/<file>.json)"]
    absent = [f"docs/bench/{p.name} does not exist" for p in named if not p.exists()]
    values = record_values([p for p in named if p.exists()])
    return absent + [t for t in numbers if not matches(t, values)]


def unrecorded(page: Path = RESULTS) -> dict[str, list[str]]:
    """Each section of the page with problems (section_problems), by heading."""
    bad: dict[str, list[str]] = {}
    for head, body in sections(page.read_text()):
        problems = section_problems(body)
        if problems:
            bad[head] = problems
    return bad


@pytest.mark.parametrize("name", list(PAGES))
def test_every_table_number_is_in_a_record_its_section_names_or_is_historical(name):
    bad = unrecorded(PAGES[name])
    assert not bad, (
        f"docs/{name}: table numbers that no record their section names holds (name the record in the "
        "section, move a derived figure to prose, or mark the row or section historical): "
        + "; ".join(f"{h}: {', '.join(v[:8])}" for h, v in bad.items())
    )


def test_the_matcher_is_honest():
    values = sorted({0.0536, 2191.55, 1.2e-3, 0.566})
    assert matches("0.0536", values) and matches("2,192", values) and matches("1.2e-3", values)
    assert not matches("0.0537", values) and not matches("0.57", [0.5]) and not matches("2.3e-3", values)
    body = "| a | b |\n|---|---|\n| row 1 | 0.0536 / 7 | `x=0.5` 12,000 |\n"
    assert table_numbers(body) == ["0.0536", "12,000"]
    row = "| a | b |\n|---|---|\n| row 1 | 0.0536 |\n| row 2 | 1,775 (historical: no record) |\n"
    assert table_numbers(row) == ["0.0536"] and not historical(prose(row))


def test_settings_are_not_measurements():
    """Dates and bare integers under a setting's header are skipped; a measurement in the same column is not."""
    body = (
        "| job | epochs | batch | batch 1,000 | CPU s |\n|---|---|---|---|---|\n"
        "| a | 2500 | 1024 | 1,553 | 4,702 on 2026-11-27 |\n"
        "| b | 3,581 of 10,000 | **1,000** | 2,497 | 1.5 |\n"
    )
    assert table_numbers(body) == ["1,553", "4,702", "3,581", "10,000", "2,497", "1.5"]


def test_a_section_is_checked_against_the_records_it_names(tmp_path):
    """A number held only by a record the section does not name fails; so does a section naming none."""
    (tmp_path / "a.json").write_text(json.dumps({"x": 0.0536, "nested": [{"y": 4702}]}))
    (tmp_path / "b.json").write_text(json.dumps({"z": 0.777}))
    table = "| job | s |\n|---|---|\n| one | 0.0536 |\n| two | 0.777 |\n| three | 4,702 |\n"
    assert section_problems("Raw: `docs/bench/a.json`.\n\n" + table, tmp_path) == ["0.777"]
    assert section_problems("Raw: docs/bench/b.json.\n\n" + table, tmp_path) == ["0.0536", "4,702"]
    assert section_problems("Raw: docs/bench/a.json and docs/bench/b.json.\n\n" + table, tmp_path) == []
    assert section_problems("No record named.\n\n" + table, tmp_path) == [
        "its table has numbers and it names no record (docs/bench/<file>.json)"
    ]
    assert section_problems("Raw: docs/bench/c.json.\n\n" + table, tmp_path)[0] == "docs/bench/c.json does not exist"
    assert section_problems("Historical: no record.\n\n" + table, tmp_path) == []
    row_only = "Raw: docs/bench/a.json.\n\n" + table.replace("| 0.777 |", "| 0.777 (historical: no record) |")
    assert section_problems(row_only, tmp_path) == []
    assert section_problems("No table numbers here: 0.777.\n\n| job | n |\n|---|---|\n| one | 12 |\n", tmp_path) == []


def test_headline_sections_are_not_historical():
    """The whole-paper run and its bands carry records: they may not opt out."""
    heads = {h: b for h, b in sections(RESULTS.read_text())}
    whole = next(b for h, b in heads.items() if h.startswith("## The whole paper in one run"))
    assert not historical(whole) and "docs/bench/paper_full_2026-11-28_before_exp4_rerun.json" in whole


def test_newest_benchmark_sections_are_not_historical():
    """docs/benchmarks.md's current sections carry records: they may not opt out as a whole."""
    heads = {h: b for h, b in sections(BENCHMARKS.read_text())}
    for prefix, record in (
        ("## Current figures", "docs/bench/bench_2026-11-28_idle.json"),
        ("## Speed against error beside MuJoCo", "docs/bench/mujoco_vs_liedfl.json"),
        ("## The whole paper in one run", "docs/bench/paper_full_2026-11-28_before_exp4_rerun.json"),
    ):
        body = next(b for h, b in heads.items() if h.startswith(prefix))
        assert not historical(prose(body)), f"docs/benchmarks.md {prefix!r} says historical"
        assert record in body, f"docs/benchmarks.md {prefix!r} does not name {record}"
