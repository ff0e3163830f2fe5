"""Which training loss predicts best per unit of training time: `train.loss` del / newton / rollout.

Runs `liedfl train` for every (case, loss) below (one at a time, one thread), then reads each run's
eval.csv (rollout: geodesic_error_mean, rel_rot_error_mean, Newton failures) and summary.json
(training seconds) and computes the teacher-forced one-step error on the test split with
`solvers.one_step.one_step_predictions`, beside the constant-velocity guess
(`constant_velocity_one_step`): mean geodesic rotation error per body (rad) and, for SE(3) bodies,
mean position error. The machine load (`uptime`) is recorded before and after each run.

    python scripts/loss_study.py [--out docs/bench/loss_study] [--runs /tmp/loss_runs/study] [--only CASE]

Writes <out>.json and <out>.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from liedfl_cli.api import load_run  # noqa: E402
from liedfl_cli.lie import so3  # noqa: E402
from liedfl_cli.solvers.one_step import constant_velocity_one_step, one_step_predictions  # noqa: E402

CASES = {
    # Exp 2 (free rigid body, training length 10): the reduced budget (100 of 1000 epochs) and the full one
    "exp2_len10_e100": ["experiment=exp2_discrete_vs_continuous", "dataset.train_steps=10", "epoch_scale=0.1"],
    "exp2_len10_e1000": ["experiment=exp2_discrete_vs_continuous", "dataset.train_steps=10", "epoch_scale=1.0"],
    # multibody: two_body (SE(3) x SO(3), MLP interaction potential, coupled Rayleigh D), 200 of 2000 epochs
    "two_body_e200": ["experiment=two_body", "train.epochs=200", "train.rollout_loss.epochs=20"],
}
LOSSES = ("del", "newton", "rollout")


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def one_step_errors(run_dir: Path) -> dict:
    run = load_run(run_dir)
    ds, model = run.dataset, run.model
    truth = ds.pose(ds.test_idx)
    with torch.no_grad():
        pred, conv = one_step_predictions(model, truth)
        cv = constant_velocity_one_step(ds.group, truth)
    true_next = truth.index((slice(None), slice(2, None)))

    def errs(p):
        rot = so3.log(true_next.R.transpose(-1, -2) @ p.R).norm(dim=-1)  # (T, N-1, B)
        out = {"rot": float(rot.mean())}
        if p.p.shape[-2]:
            out["pos"] = float((p.p - true_next.p).norm(dim=-1).mean())
        return out

    return {"model": errs(pred), "constant_velocity": errs(cv), "not_converged": int((~conv).sum())}


def eval_row(run_dir: Path) -> dict:
    with open(run_dir / "eval.csv") as f:
        for row in csv.DictReader(f):
            if row["model"] == "model":
                return row
    raise RuntimeError(f"{run_dir}: no model row in eval.csv")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "docs/bench/loss_study"))
    ap.add_argument("--runs", default="/tmp/loss_runs/study")
    ap.add_argument("--only", default=None, help="one case name")
    ap.add_argument("--losses", default=",".join(LOSSES))
    args = ap.parse_args()
    out = Path(args.out)
    json_path = out.with_suffix(".json")
    results = json.loads(json_path.read_text()) if json_path.exists() else []
    for case, overrides in CASES.items():
        if args.only and case != args.only:
            continue
        for loss in args.losses.split(","):
            run_dir = Path(args.runs) / f"{case}_{loss}"
            cmd = [
                sys.executable, "-m", "liedfl_cli", "train", *overrides, f"train.loss={loss}",
                "runtime.threads=1", "ui.progress=false", "eval.plots=false",
                f"hydra.run.dir={run_dir}", f"paths.data_dir={Path(args.runs) / 'data'}",
            ]  # fmt: skip
            load_before = uptime()
            t0 = time.perf_counter()
            proc = subprocess.run(
                cmd, cwd=ROOT, capture_output=True, text=True, env={"PYTHONPATH": str(ROOT), **_env()}
            )
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                print(proc.stdout[-2000:], proc.stderr[-2000:])
                raise SystemExit(f"{case} {loss}: liedfl train failed")
            summary = json.loads((run_dir / "summary.json").read_text())
            ev = eval_row(run_dir)
            rec = {
                "case": case,
                "loss": loss,
                "command": "liedfl train " + " ".join(cmd[4:]),
                "train_seconds": summary["timings"]["train_seconds"],
                "finetune_seconds": summary["timings"].get("finetune_seconds"),
                "geodesic_error_mean": float(ev["geodesic_error_mean"]),
                "rel_rot_error_mean": float(ev["rel_rot_error_mean"]),
                "newton_failures": int(float(ev["newton_failures"] or 0)),
                "one_step": one_step_errors(run_dir),
                "wall_seconds": wall,
                "load_before": load_before,
                "load_after": uptime(),
            }
            print(json.dumps(rec), flush=True)
            results = [r for r in results if (r["case"], r["loss"]) != (case, loss)] + [rec]
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(json.dumps(results, indent=1))
    write_markdown(results, out.with_suffix(".md"))


def _env() -> dict:
    import os

    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def write_markdown(results: list[dict], path: Path) -> None:
    lines = [
        "# Which training loss predicts best (scripts/loss_study.py)",
        "",
        "| case | train.loss | train s (fine-tune s) | rollout geodesic error (mean) | rollout rel. rot. error | "
        "Newton failures | one-step rot. error (rad) | constant velocity | one-step pos. error | constant velocity | "
        "load (1-min avg before / after) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        o = r["one_step"]
        ft = f" ({r['finetune_seconds']:.1f})" if r.get("finetune_seconds") else ""
        pos = f"{o['model']['pos']:.3e}" if "pos" in o["model"] else "–"
        cvp = f"{o['constant_velocity']['pos']:.3e}" if "pos" in o["constant_velocity"] else "–"
        la = r["load_before"].split("load average:")[-1].split(",")[0].strip()
        lb = r["load_after"].split("load average:")[-1].split(",")[0].strip()
        lines.append(
            f"| {r['case']} | {r['loss']} | {r['train_seconds']:.1f}{ft} | {r['geodesic_error_mean']:.4g} | "
            f"{r['rel_rot_error_mean']:.4g} | {r['newton_failures']} | {o['model']['rot']:.3e} | "
            f"{o['constant_velocity']['rot']:.3e} | {pos} | {cvp} | {la} / {lb} |"
        )
    lines += ["", "Commands: the `command` field of each record in loss_study.json."]
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
