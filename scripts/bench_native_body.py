"""Where the native rigid-body step pays: its rollout against the torch engines' for one body or two.

    python scripts/bench_native_body.py [--json FILE] [--threads 1 2] [--batches 1 10 100 1000 2000 4000 8000 16000]
        [--groups SO3 SE3 SE3xSO3] [--nn-force]

For each thread count, group (SO(3), SE(3), SE(3) x SO(3)), MLP potential (none, 10 x 2, 32 x 3, 64 x 3;
Rayleigh damping, h 0.05) and batch size: microseconds per step per trajectory (best of 3) of
`models.liedflnn.engines.native` and of the torch engine `engines/choose.py` would take without it (SO(3):
Python floats for a few trajectories, the row layout up to 31, the column layout from 32; the others: the row
layout), their ratio (`torch_over_native` > 1: the native step is faster) and whether `native.applies` takes
the batch (its `MLP_ROWS` rule, set from these figures). Timing only; the engines' equality is
tests/test_native_body.py's. `--nn-force` adds a learned force F(g, xi~) (`NNForce`, 32 x 3) to every model
(its value and Jacobian at every Newton iteration; the torch engine is then the row layout for every group).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench_peer import best_of  # noqa: E402

from liedfl_cli.files.io_utils import write_json  # noqa: E402
from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, so3  # noqa: E402
from liedfl_cli.models.liedflnn.engines import choose  # noqa: E402
from liedfl_cli.models.liedflnn.engines import native as fused_native  # noqa: E402
from liedfl_cli.models.liedflnn.model import LieDFLNN  # noqa: E402
from liedfl_cli.solvers.options import SolverOptions  # noqa: E402

H = 0.05
MLPS = {"none": None, "mlp_10x2": (10, 2), "mlp_32x3": (32, 3), "mlp_64x3": (64, 3)}
GROUPS = {"SO3": SO3, "SE3": SE3, "SE3xSO3": ProductGroup(1, 1)}  # the last: the two-body scene's group


def model_for(G, size, nn_force: bool = False) -> LieDFLNN:
    forces = {"rayleigh": {}, "nn": {"width": 32, "depth": 3}} if nn_force else {"rayleigh": {}}
    if size is None:
        return LieDFLNN(G, H, potential="none", forces=forces).requires_grad_(False)
    return LieDFLNN(G, H, potential="mlp", forces=forces, mlp_width=size[0], mlp_depth=size[1]).requires_grad_(False)


def starts(G, n: int) -> tuple[Pose, Pose]:
    gen = torch.Generator().manual_seed(n)
    R0 = so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64))
    g0 = Pose(R0, torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64))
    return g0, G.retract(g0, H * torch.randn(n, G.dim, generator=gen, dtype=torch.float64))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 10, 100, 1000, 2000, 4000, 8000, 16000])
    ap.add_argument("--groups", nargs="+", default=list(GROUPS), choices=list(GROUPS))
    ap.add_argument("--nn-force", action="store_true", help="add a learned force (NNForce 32 x 3) to every model")
    args = ap.parse_args()
    out: dict = {"load_avg_start": list(os.getloadavg()), "h": H, "nn_force": args.nn_force, "rows": []}
    opts = SolverOptions()
    for threads in args.threads:
        torch.set_num_threads(threads)
        for group in args.groups:
            G = GROUPS[group]
            for name, size in MLPS.items():
                torch.manual_seed(0)
                model = model_for(G, size, args.nn_force)
                for n in args.batches:
                    steps = int(max(6, min(200, 4e5 / n)))
                    if group != "SO3" or args.nn_force:  # the row layout: fewer steps (a few seconds a row)
                        steps = int(max(6, min(200, 4e4 / n)))
                    g0, g1 = starts(G, n)
                    with torch.no_grad():
                        engine = next(e for e in choose.ENGINES if e.applies(model, g0))
                        native = lambda m=model, g0=g0, g1=g1, s=steps: fused_native.rollout(m, g0, g1, s + 1, opts)
                        other = lambda m=model, g0=g0, g1=g1, s=steps, e=engine: e.rollout(m, g0, g1, s + 1, opts)
                        native(), other()
                        t_native = best_of(native) / steps / n * 1e6
                        t_torch = best_of(other) / steps / n * 1e6
                        takes = fused_native.applies(model, g0)
                    row = {
                        "threads": threads,
                        "group": group,
                        "potential": name,
                        "batch": n,
                        "steps": steps,
                        "native_us_per_step_traj": t_native,
                        "torch_engine": engine.name,
                        "torch_us_per_step_traj": t_torch,
                        "torch_over_native": t_torch / t_native,
                        "native_applies": takes,
                    }
                    out["rows"].append(row)
                    print(
                        f"threads {threads} {group} {name:>9} batch {n:>6}: native {t_native:8.3f} us, "
                        f"{engine.name} {t_torch:8.3f} us, x{t_torch / t_native:6.2f}, native applies: {takes}",
                        flush=True,
                    )
    out["load_avg_end"] = list(os.getloadavg())
    if args.json:
        write_json(Path(args.json), out)


if __name__ == "__main__":
    main()
