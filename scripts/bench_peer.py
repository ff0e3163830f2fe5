"""Rollout speed against the peer LieFVIN (thaipduong/LieFVIN, SO3FVIN), side by side in one process.

    python scripts/bench_peer.py --peer DIR [--json FILE] [--batches 1 10 1000 10000]

DIR is a checkout of https://github.com/thaipduong/LieFVIN (its `LieFVIN` package is imported from
there; nothing of it is copied here). The peer is timed with its own defaults: `SO3FVIN(device=cpu,
u_dim=1, time_step=h)` (networks of width 10, a fixed 5 Newton iterations per step without line
search or convergence check), rolled out by its `predict` from random rotations, unit angular
velocity scale and zero control. liedfl is timed on (a) the free rigid body with true parameters
and (b) an SO(3) LieDFLNN with an MLP potential of width 10 x 2 and Rayleigh damping (the peer's
network size), Newton to tolerance 1e-5 with line search: as a rollout runs by default (the engine
`models.liedflnn.engines.choose` picks, named in `<model>_engine`: the native step where it serves), on the
torch engines alone (`_torch`: `runtime.compile=false`, so Python floats for a few trajectories, the column
layout for many), on the fused step in the row layout (`_rows`) and on the reference paths (`_reference`).
Figures: microseconds per step per trajectory (best of 3), peer and liedfl
alternately, and their ratios (peer_over_X > 1: liedfl is faster).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from liedfl_cli.lie import SO3, Pose, so3  # noqa: E402
from liedfl_cli.models.liedflnn.engines.choose import choose_rollout_engine  # noqa: E402
from liedfl_cli.models.liedflnn.model import LieDFLNN  # noqa: E402
from liedfl_cli.models.true_scheme import physics_model  # noqa: E402
from liedfl_cli.solvers import runtime  # noqa: E402
from liedfl_cli.solvers.execution import ExecutionPlan  # noqa: E402
from liedfl_cli.solvers.options import SolverOptions  # noqa: E402
from liedfl_cli.solvers.rollout import rollout_implicit  # noqa: E402

H = 0.05
PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 0.0, "D": [0.05] * 3}


def best_of(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", required=True, help="a checkout of thaipduong/LieFVIN")
    ap.add_argument("--json", default=None)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 10, 1000, 10000])
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    sys.path.insert(0, str(Path(args.peer).resolve()))
    from LieFVIN import SO3FVIN  # the peer's package (it sets torch's default dtype to float64)

    runtime.configure(runtime.RuntimeOptions(threads=args.threads))
    torch.manual_seed(0)
    peer = SO3FVIN(device=torch.device("cpu"), u_dim=1, time_step=H)
    ours = {
        "free_body_true": physics_model(SO3, H, PHYS),
        "so3_mlp_10x2": LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=10, mlp_depth=2),
    }
    for m in ours.values():
        m.requires_grad_(False)
    out: dict = {"threads": torch.get_num_threads(), "load_avg_start": list(os.getloadavg()), "h": H, "rows": []}
    for n in args.batches:
        steps = int(max(6, min(200, 2e5 / n)))
        gen = torch.Generator().manual_seed(n)
        R0 = so3.exp(torch.randn(n, 3, generator=gen, dtype=torch.float64))
        w0 = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        x0 = torch.cat((R0.reshape(n, 9), w0, torch.zeros(n, 1, dtype=torch.float64)), 1).requires_grad_(True)
        g0 = Pose(R0[:, None], torch.zeros(n, 0, 3, dtype=torch.float64))
        g1 = SO3.retract(g0, H * w0)
        peer.predict(2, x0)
        t_peer = best_of(lambda x0=x0, steps=steps: peer.predict(steps, x0)) / steps / n * 1e6
        row = {"batch": n, "steps": steps, "peer_us_per_step_traj": t_peer}
        for name, model in ours.items():
            with torch.no_grad():
                row[f"{name}_engine"] = choose_rollout_engine(model, g0, steps + 1).name
            for label, path in (("", "fused"), ("_torch", "torch"), ("_rows", "rows"), ("_reference", "reference")):
                on_path = model.with_path("reference" if path == "reference" else "fused")
                if path == "torch":
                    on_path.plan = ExecutionPlan(path="fused", compile="false")
                if path == "rows":  # the fused step in the row layout (before the column rollout)
                    run = lambda m=on_path, g0=g0, g1=g1, s=steps: rollout_implicit(m, g0, g1, s + 1, SolverOptions())
                else:
                    run = lambda m=on_path, g0=g0, g1=g1, s=steps: m.rollout(g0, g1, s + 1)
                run()
                t = best_of(run)
                t = t / steps / n * 1e6
                row[f"{name}{label}_us_per_step_traj"] = t
                row[f"peer_over_{name}{label}"] = t_peer / t
        out["rows"].append(row)
        print(json.dumps(row), flush=True)
    out["load_avg_end"] = list(os.getloadavg())
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
