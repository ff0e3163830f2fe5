"""Every number in the tables of docs/results.md and docs/benchmarks.md is in a raw record under docs/bench/,
or its section (or its row) says it is historical (measured before records kept the machine; its run folders
are gone).

Sections are the page's `##` / `###` headings. A table number (a decimal, a number in scientific notation
or an integer of at least 4 digits, in a row of a markdown table) matches a record when some number in
some docs/bench/*.json (any depth) or docs/bench/*.md prints as it (rounded to the printed digits, or
truncated to them). Not brittle: any record may hold
it (a number quoted in two sections needs one record), settings such as step counts (integers below 1000)
are not checked, and a section opts out only by saying "historical" in its text, which the reader sees; a
single row opts out the same way, by saying "historical" in one of its cells. Derived numbers (ratios,
sums, per-unit conversions) cannot be checked: a page keeps them out of its tables, in prose that states
the derivation.
"""

from __future__ import annotations

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


def record_values() -> list[float]:
    """Every number in every record (absolute values, sorted)."""
    out: list[float] = []
    for path in sorted(BENCH.glob("*.json")):
        _values(json.loads(path.read_text(), parse_constant=lambda c: None), out)
    for path in sorted(BENCH.glob("*.md")):
        _values(path.read_text(), out)
    return sorted({abs(v) for v in out})


def _digits(text: str) -> tuple[float, float]:
    """(value, half a unit of the last printed digit) of a printed number."""
    t = text.replace("−", "-").replace(",", "")
    mant, _, exp = t.lower().partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    unit = 10.0 ** (-decimals) * (10.0 ** int(exp) if exp else 1.0)
    return abs(float(t)), unit


def matches(text: str, values: list[float]) -> bool:
    """Does some record value print as `text` (rounded, or truncated, to its digits)?"""
    import bisect

    v, unit = _digits(text)
    lo, hi = v - unit * 0.5001, v + unit * 0.9999  # rounded to the digits printed, or truncated
    i = bisect.bisect_left(values, lo)
    return i < len(values) and values[i] <= hi


def sections(text: str) -> list[tuple[str, str]]:
    """(heading, body) of every `##` / `###` section."""
    parts = re.split(r"^(#{2,3} .*)$", text, flags=re.M)
    return [(parts[i].strip(), parts[i + 1]) for i in range(1, len(parts) - 1, 2)]


def table_numbers(body: str) -> list[str]:
    """The measured-looking numbers of the body's table rows (not the header or separator rows)."""
    out = []
    lines = body.splitlines()
    for j, line in enumerate(lines):
        if not line.startswith("|") or set(line) <= set("|-: "):
            continue
        if j + 1 < len(lines) and set(lines[j + 1].strip()) <= set("|-: ") and lines[j + 1].strip():
            continue  # a header row
        if historical(line):
            continue  # the row says it is historical
        cells = line.strip().strip("|").split("|")
        for cell in cells[1:]:  # the first cell names the row
            cell = re.sub(r"`[^`]*`", "", cell)  # commands and keys: settings, not measurements
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


def unrecorded(page: Path = RESULTS) -> dict[str, list[str]]:
    values = record_values()
    bad: dict[str, list[str]] = {}
    for head, body in sections(page.read_text()):
        if historical(prose(body)):
            continue
        missing = [t for t in table_numbers(body) if not matches(t, values)]
        if missing:
            bad[head] = missing
    return bad


@pytest.mark.parametrize("name", list(PAGES))
def test_every_table_number_is_recorded_or_its_section_is_historical(name):
    bad = unrecorded(PAGES[name])
    assert not bad, f"numbers in docs/{name} tables with no record under docs/bench/ (mark the section " + (
        "historical or add the record): " + "; ".join(f"{h}: {', '.join(v[:8])}" for h, v in bad.items())
    )


def test_the_matcher_is_honest():
    values = sorted({0.0536, 2191.55, 1.2e-3, 0.566})
    assert matches("0.0536", values) and matches("2,192", values) and matches("1.2e-3", values)
    assert not matches("0.0537", values) and not matches("0.57", [0.5]) and not matches("2.3e-3", values)
    body = "| a | b |\n|---|---|\n| row 1 | 0.0536 / 7 | `x=0.5` 12,000 |\n"
    assert table_numbers(body) == ["0.0536", "12,000"]
    row = "| a | b |\n|---|---|\n| row 1 | 0.0536 |\n| row 2 | 1,775 (historical: no record) |\n"
    assert table_numbers(row) == ["0.0536"] and not historical(prose(row))


def test_headline_sections_are_not_historical():
    """The whole-paper run and its bands carry records: they may not opt out."""
    heads = {h: b for h, b in sections(RESULTS.read_text())}
    whole = next(b for h, b in heads.items() if h.startswith("## The whole paper in one run"))
    assert not historical(whole) and "docs/bench/paper_full.json" in whole


def test_newest_benchmark_sections_are_not_historical():
    """docs/benchmarks.md's current sections carry records: they may not opt out as a whole."""
    heads = {h: b for h, b in sections(BENCHMARKS.read_text())}
    for prefix, record in (
        ("## Current figures", "docs/bench/bench_2026-11-28_idle.json"),
        ("## Speed against error beside MuJoCo", "docs/bench/mujoco_vs_liedfl.json"),
        ("## The whole paper in one run", "docs/bench/paper_full.json"),
    ):
        body = next(b for h, b in heads.items() if h.startswith(prefix))
        assert not historical(prose(body)), f"docs/benchmarks.md {prefix!r} says historical"
        assert record in body, f"docs/benchmarks.md {prefix!r} does not name {record}"
