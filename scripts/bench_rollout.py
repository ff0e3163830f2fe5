"""Rollout speed of the Newton DEL solver: seconds per step for batches of trajectories.

    python scripts/bench_rollout.py [--steps 100] [--batches 10 1000]

Uses the true-parameter schemes (same cost as a learned model of the same components) of the
free rigid body (SO(3), no potential), the heavy body (SO(3), potential) and the heavy SE(3)
body, plus a LieDFLNN with an MLP potential (64x3). Prints a markdown table.
"""

import argparse
import platform
import time

import torch

from liedfl_cli.lie import SE3, SO3, Pose, so3
from liedfl_cli.models.liedflnn import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model

PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0]}


def cases():
    yield "free body SO(3), true scheme", physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.05] * 3}), SO3, 0.1
    yield "heavy body SO(3), true scheme", physics_model(SO3, 0.05, {**PHYS, "g": 9.81, "D": [0.1] * 3}), SO3, 0.05
    yield (
        "heavy body SE(3), true scheme",
        physics_model(SE3, 0.05, {**PHYS, "g": 9.81, "D": [0.1] * 3 + [0] * 3}),
        SE3,
        0.05,
    )
    m = LieDFLNN(SE3, 0.05, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3)
    m.requires_grad_(False)
    yield "SE(3) LieDFLNN, MLP potential 64x3", m, SE3, 0.05


def start(G, n, h, seed=0):
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )
    g1 = G.retract(g0, h * torch.randn(n, G.dim, generator=gen, dtype=torch.float64))
    return g0, g1


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--batches", type=int, nargs="+", default=[10, 1000])
    args = ap.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {platform.processor() or platform.machine()}")
    print("| model | trajectories | ms / step | ms / step / trajectory | Newton iterations / step | failures |")
    print("|---|---|---|---|---|---|")
    for name, model, G, h in cases():
        for n in args.batches:
            g0, g1 = start(G, n, h)
            model.rollout(g0, g1, 3)  # warm-up
            t = time.perf_counter()
            ro = model.rollout(g0, g1, args.steps)
            ms = (time.perf_counter() - t) / (args.steps - 1) * 1e3
            print(f"| {name} | {n} | {ms:.2f} | {ms / n:.4f} | {ro.iterations.double().mean():.2f} | {ro.n_failed} |")


if __name__ == "__main__":
    main()
