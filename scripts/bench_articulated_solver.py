"""Articulated rollouts: Newton against chord steps, speed against the solver's error (issue 34).

    python scripts/bench_articulated_solver.py [--steps 40] [--repeats 2] [--json FILE]

Subjects: the 5-body branched MuJoCo tree's true-parameter scheme (free root, four ball joints, per-DoF
damping, h 0.05; `bench.articulated_models`; batch 1 and 1,000) and the untrained 23-body Exp 4
articulated model (batch 200, a quarter of the steps), from random starts. Figures: microseconds per
step per trajectory (best of `repeats`, one thread), mean Newton iterations per step, failed steps,
and the solver's own error: the largest attitude-entry distance after the rollout (mean over
trajectories) to the same rollout solved by Newton to tol 1e-13. Every setting of one model runs in
one process, alternately; the machine's CPU and load are written beside. What it answers: what
`solver=chord` (one Jacobian per step) buys at a given solver error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench import ROOT, articulated_models, chord_options, runtime, start
from machine_info import cpu_model

from liedfl_cli.files.io_utils import write_json
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit

NEWTON = "newton 1e-5 (default)"


def settings(newton_only: bool) -> dict:
    """name -> SolverOptions (`--newton-only`: the default alone, which also runs on code before chord steps)."""
    out = {NEWTON: SolverOptions(tol=1e-5)}
    if not newton_only:
        out["chord 1e-5"] = chord_options(tol=1e-5)
        out["chord 1e-6"] = chord_options(tol=1e-6)
        out[f"chord {chord_options().tol:.0e} (solver=chord)".replace("e-0", "e-")] = chord_options()
    return out


def measure(model, G, h, n: int, steps: int, repeats: int, setups: dict) -> dict:
    g0, g1 = start(G, n, h)
    m = model.with_path("fused")
    tight = rollout_implicit(m, g0, g1, steps, SolverOptions(tol=1e-13, max_iter=30))
    best: dict[str, float] = {}
    rows: dict[str, dict] = {}
    for _ in range(repeats):
        for name, opts in setups.items():
            t = time.perf_counter()
            ro = rollout_implicit(m, g0, g1, steps, opts)
            us = (time.perf_counter() - t) / (steps - 1) / n * 1e6
            best[name] = min(best.get(name, float("inf")), us)
            err = (ro.pose.R[:, -1] - tight.pose.R[:, -1]).abs().flatten(1).amax(-1).mean()
            rows[name] = {
                "us_per_step_traj": best[name],
                "mean_iterations": float(ro.iterations.double().mean()),
                "failed_steps": ro.n_failed,
                "solver_error_after_steps": float(err),
            }
    base = rows[NEWTON]["us_per_step_traj"]
    for row in rows.values():
        row["speedup_vs_newton"] = base / row["us_per_step_traj"]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--newton-only", action="store_true", help="the default solver alone (an A/B against older code)")
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    args = ap.parse_args()
    runtime.configure(runtime.RuntimeOptions(threads=1, compile="false"))
    load_start = os.getloadavg()[0]
    out: dict = {"cpu": cpu_model(), "steps": args.steps, "load_1min_start": load_start, "models": {}}
    setups = settings(args.newton_only)
    with torch.no_grad():
        for name, (model, G, h) in articulated_models(args.data_dir).items():
            batches = (1, 1000) if name == "tree5_true" else (200,)
            for n in batches:
                steps = args.steps if n == 1000 else max(6, args.steps // 4)
                rows = measure(model, G, h, n, steps, args.repeats, setups)
                out["models"][f"{name} batch {n}"] = rows
                for setting, row in rows.items():
                    print(
                        f"{name} batch {n:5d} {setting:26s} {row['us_per_step_traj']:9.1f} us/step/traj "
                        f"({row['speedup_vs_newton']:.2f}x)  iterations {row['mean_iterations']:.2f}  "
                        f"failed {row['failed_steps']}  solver error {row['solver_error_after_steps']:.1e}"
                    )
    out["load_1min_end"] = os.getloadavg()[0]
    print(f"CPU {out['cpu']}, load {load_start:.2f} -> {out['load_1min_end']:.2f}")
    if args.json:
        write_json(args.json, out)  # write then rename: a killed run never leaves half a record


if __name__ == "__main__":
    main()
