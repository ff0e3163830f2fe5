"""Noise study: LieDFLNN on the default scene (damped free rigid body, Exp 2 setting, training length 100,
1000 epochs) trained on rotations with measurement noise R exp(sigma N(0, I)), sigma = 0, 1e-3, 1e-2 rad
per axis, without and with the group-preserving Savitzky-Golay smoother (`dataset.smoothing`), then
rolled out on the CLEAN test trajectories (`liedfl rollout run=<run> dataset=free_rigid_body`).

python scripts/noise_study.py [--sigmas 0 1e-3 1e-2] [--window 15] [--order 4] [--epochs 1000]
                              [--out outputs/noise_study] [--figure docs/img/noise_study.png]

Per run: parameter recovery (recovery.json: J_d and D after dividing by tr J_d) and the rollout error on
the clean data (mean relative rotation error over 10 trajectories x 500 steps; the true-parameter
scheme's error beside it). Writes <out>/summary.md, summary.csv and the figure.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

LIEDFL = [sys.executable, "-c", "from liedfl_cli.cli import main; main()"]


def sh(args: list[str]) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    proc = subprocess.run([*LIEDFL, *args], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"liedfl {' '.join(args)} failed:\n{proc.stderr[-2000:]}")


def one(out: Path, sigma: float, smoothing: tuple[int, int] | None, epochs: int) -> dict:
    tag = f"sigma{sigma:g}_" + (f"sg{smoothing[0]}-{smoothing[1]}" if smoothing else "raw")
    run = out / "runs" / tag
    if not (run / "recovery.json").is_file() and (run / "checkpoints" / "last.pt").is_file():
        sh(["train", f"resume={run}", "ui.progress=false"])  # an interrupted run continues
    if not (run / "recovery.json").is_file():
        args = ["train", f"dataset.noise.rotation={sigma!r}", f"train.epochs={epochs}", "rollout.enabled=false"]
        if smoothing:
            args.append(f"dataset.smoothing={{window: {smoothing[0]}, order: {smoothing[1]}}}")
        sh([*args, "ui.progress=false", f"hydra.run.dir={run}"])
    clean = sorted((run / "rollouts").glob("*_free_rigid_body_steps500")) if (run / "rollouts").is_dir() else []
    if not clean:
        sh(["rollout", f"run={run}", "dataset=free_rigid_body", "ui.progress=false", "eval.plots=false"])
        clean = sorted((run / "rollouts").glob("*_free_rigid_body_steps500"))
    with open(clean[-1] / "eval.csv") as f:
        ev = {r["model"]: r for r in csv.DictReader(f)}
    rec = json.loads((run / "recovery.json").read_text())
    return {
        "sigma_rad": sigma,
        "smoothing": f"window {smoothing[0]}, order {smoothing[1]}" if smoothing else "none",
        "Jd_error": rec["Jd_over_trace_max_rel_error"],
        "D_error": rec["D_over_trace_max_rel_error"],
        "rollout_error": float(ev["model"]["rel_rot_error_mean"]),
        "rollout_error_true_scheme": float(ev["true_scheme"]["rel_rot_error_mean"]),
        "run": str(run),
    }


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sigmas = sorted({r["sigma_rad"] for r in rows})
    x = range(len(sigmas))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for smooth, style in (("none", "o-"), (None, "s--")):
        sel = [r for r in rows if (r["smoothing"] == "none") == (smooth == "none")]
        sel = sorted(sel, key=lambda r: r["sigma_rad"])
        if not sel:
            continue
        label = "raw (no smoothing)" if smooth == "none" else f"smoothed ({sel[0]['smoothing']})"
        for ax, key in zip(axes, ("Jd_error", "D_error", "rollout_error")):
            ax.semilogy(list(x), [r[key] for r in sel], style, label=label)
    true = sorted(rows, key=lambda r: r["sigma_rad"])[0]["rollout_error_true_scheme"]
    axes[2].axhline(true, color="0.5", linestyle=":", label="true-parameter scheme")
    titles = (
        "J_d / tr J_d: max relative error",
        "D / tr J_d: max relative error",
        "rollout error on clean data (mean rel. rot.)",
    )
    for ax, title in zip(axes, titles):
        ax.set_xticks(list(x), [f"{s:g}" for s in sigmas])
        ax.set_xlabel("rotation noise sigma [rad per axis]")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    axes[2].legend(fontsize=8)
    fig.suptitle("Noise study: free rigid body (length 100, 1000 epochs), trained on noisy rotations", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 1e-3, 1e-2])
    ap.add_argument("--window", type=int, default=15)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=Path("outputs/noise_study"))
    ap.add_argument("--figure", type=Path, default=Path("docs/img/noise_study.png"))
    args = ap.parse_args()
    rows = []
    for sigma in args.sigmas:
        for sm in (None, (args.window, args.order)):
            rows.append(one(args.out, sigma, sm, args.epochs))
            print(json.dumps(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    cols = ["sigma_rad", "smoothing", "Jd_error", "D_error", "rollout_error", "rollout_error_true_scheme"]
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in rows]
    (args.out / "summary.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    figure(rows, args.figure)
    print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
