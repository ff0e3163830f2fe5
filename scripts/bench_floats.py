"""The float path's crossover (docs/benchmarks.md, "A few trajectories in Python floats").

    python scripts/bench_floats.py [--steps 100]

One torch thread, float64, best of 3: µs per step per trajectory of `fused_scalar.rollout` (Python
floats, its size limits lifted) against `rollout_implicit` (the row layout) on the same model and
starts, for an SO(3) MLP 10x2 + damping and no potential at batches 1-12, and for larger MLPs at
batches 1 and 2. These figures set `fused_scalar.MAX_ROWS`, `STEP_COST` and `BUDGET`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from liedfl_cli.lie import SO3, Pose, so3
from liedfl_cli.models.liedflnn.engines import scalar as fused_scalar
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit


def starts(n: int) -> tuple[Pose, Pose]:
    gen = torch.Generator().manual_seed(0)
    R = so3.exp(torch.randn(n, 1, 3, generator=gen, dtype=torch.float64))
    g0 = Pose(R, torch.zeros(n, 0, 3, dtype=torch.float64))
    return g0, SO3.retract(g0, 0.1 * torch.randn(n, 3, generator=gen, dtype=torch.float64))


def per_step_us(rollout, args: tuple, n: int, steps: int) -> float:
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        rollout(*args)
        best = min(best, time.perf_counter() - t)
    return best / (steps - 1) / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100)
    steps = ap.parse_args().steps
    torch.set_num_threads(1)
    fused_scalar.MAX_ROWS, fused_scalar.BUDGET = 10**6, 10**12  # time it where it would not be taken
    cases = [
        ("MLP 10x2 + damping", dict(potential="mlp", mlp_width=10, mlp_depth=2), (1, 3, 4, 6, 8, 12)),
        ("no potential + damping", dict(potential="none"), (1, 3, 4, 6, 8, 12)),
        *((f"MLP {w}x{d} + damping", dict(potential="mlp", mlp_width=w, mlp_depth=d), (1, 2)) for w, d in
          ((16, 2), (32, 2), (32, 3), (64, 3))),
    ]  # fmt: skip
    print("model | batch | floats µs | rows µs (per step per trajectory)")
    for name, kw, batches in cases:
        model = LieDFLNN(SO3, 0.1, init_jitter=0.3, seed=1, forces=["rayleigh"], **kw).requires_grad_(False)
        for n in batches:
            g0, g1 = starts(n)
            args = (model, g0, g1, steps, SolverOptions())
            floats = per_step_us(fused_scalar.rollout, args, n, steps)
            rows = per_step_us(rollout_implicit, args, n, steps)
            print(f"{name} | {n} | {floats:.0f} | {rows:.0f}", flush=True)


if __name__ == "__main__":
    main()
