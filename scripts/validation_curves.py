"""Validation one-step error over constant velocity against training time, for several runs.

    python scripts/validation_curves.py --out docs/img/articulated_validation.png \\
        "5-link chain, articulated=outputs/articulated_chains/c5world_articulated" ...

Each argument is LABEL=RUN_DIR (a run folder with train_metrics.csv, written by `liedfl train`); one panel per
distinct text before the first comma of the labels (e.g. "5-link chain"), a line per run, log y axis, the
constant-velocity level dashed.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def curve(run: Path) -> tuple[list[float], list[float]]:
    xs, ys = [], []
    for row in csv.DictReader((run / "train_metrics.csv").open()):
        if row.get("val_one_step_vs_cv"):
            xs.append(float(row["seconds"]))
            ys.append(float(row["val_one_step_vs_cv"]))
    return xs, ys


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    panels: dict[str, list[tuple[str, Path]]] = {}
    for item in args.runs:
        label, _, run = item.partition("=")
        panels.setdefault(label.split(",")[0], []).append((label.partition(",")[2].strip() or label, Path(run)))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.0), squeeze=False)
    labels = list(dict.fromkeys(label for runs in panels.values() for label, _ in runs))
    color = {label: f"C{i}" for i, label in enumerate(labels)}  # one colour per model in every panel
    for ax, (title, runs) in zip(axes[0], panels.items()):
        for label, run in runs:
            xs, ys = curve(run)
            ax.plot(xs, ys, marker="o", ms=3, label=label, color=color[label])
        ax.axhline(1.0, color="grey", ls="--", lw=1, label="constant velocity")
        ax.set_yscale("log")
        ax.set_title(title)
        ax.set_xlabel("training time [s]")
        ax.set_ylabel("validation one-step rotation error / constant velocity")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
