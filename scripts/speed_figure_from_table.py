"""Redraw `error_vs_speed.png` from the summary table of a `liedfl report` (report.md or a copy of it,
e.g. the Exp 3 table in docs/figures.md) when the sweep's run folders are gone.

python scripts/speed_figure_from_table.py docs/figures.md docs/img/exp3_error_vs_speed.png

Reads the first Markdown table whose header has `model / setting`, `seeds`, `rel. rotation error`,
`training [s]` and `rollout [s/step/traj.]` (cells `mean ± std`). With two seeds the seed values are
recovered exactly from mean ± std (mean ± std/√2, up to the table's 4 significant digits); with more,
only the mean and std are used (a lower bar that would cross zero then stops at the mean / 10).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from liedfl_cli.commands import report
from liedfl_cli.commands.outputs import write_outputs
from liedfl_cli.evaluation import EvalOutputs

COLUMNS = {
    "rel. rotation error": report.ERROR,
    "training [s]": "train_seconds",
    "rollout [s/step/traj.]": "rollout_s_per_step_per_trajectory",
}


def _stat(cell: str, n: int) -> tuple[float | None, float | None, int]:
    mean, _, std = cell.partition("±")
    return float(mean), float(std) if std.strip() else 0.0, n


def read_summary(path: Path) -> list[dict]:
    lines = [line.strip() for line in path.read_text().splitlines()]
    split = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    found = [k for k, c in enumerate(split) if lines[k].startswith("|") and c[0] == "model / setting"]
    i = next((k for k in found if set(COLUMNS) <= set(split[k])), None)
    if i is None:
        raise SystemExit(f"{path}: no summary table with the columns {', '.join(COLUMNS)}")
    header = split[i]
    out = []
    for line in lines[i + 2 :]:
        if not line.startswith("|"):
            break
        row = dict(zip(header, (c.strip() for c in line.strip("|").split("|"))))
        n = int(row["seeds"])
        s: dict = {"label": row["model / setting"], "model": row["model / setting"].split()[0], "seeds": n}
        runs: list[dict] = [{} for _ in range(n)]
        for col, key in COLUMNS.items():
            s[key] = _stat(row[col], n)
            mean, std, _ = s[key]
            if n == 2:  # two values: mean ± std/√2 (sample std, ddof=1)
                half = std / math.sqrt(2)
                runs[0][key], runs[1][key] = mean - half, mean + half
            else:
                for r in runs:
                    r[key] = mean / 10  # unknown seeds: a clipped bar stops at a tenth of the mean
        s["runs"] = runs
        out.append(s)
    return out


def main() -> None:
    src, dst = Path(sys.argv[1]), Path(sys.argv[2])
    summary = read_summary(src)
    fig = report.draw_error_vs_speed(summary)
    if fig is None:
        raise SystemExit(f"{src}: no point to draw")
    write_outputs(EvalOutputs({}, dst.parent, {dst.name: fig}))  # the one writer (atomic)
    print(f"{dst}: {len(summary)} points from {src}")


if __name__ == "__main__":
    main()
