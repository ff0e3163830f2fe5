"""Forward + backward of Exp 4's constant per-body Rayleigh force, three ways (docs/benchmarks.md, "Round 6").

    python scripts/bench_damping.py [--batch 63] [--repeats 200]

Exp 4's group (1 SE(3) body and 22 SO(3) bodies, dim 72), F = -D xi~ with D block diagonal:
  blocks   round 5's `RayleighForce`: the blocks from the stacked parameters (`PerBodySPSD.block_matrices`),
           applied body by body (`damping.apply_blocks`), no 72x72 matrix
  dense    `RayleighForce` since round 6: the same blocks placed in the 72x72 matrix with one scatter
           (`PerBodySPSD()`), times xi~
  modules  the matrix from each body's own `SPSDMatrix` module, one after the other (23 small
           parameterisations), times xi~: how the matrix was built before round 5
Prints the median of `repeats` interleaved timings in ms per call (one torch thread) and checks that
the three forces agree to 1e-14 relative.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import time

import torch

from liedfl_cli.lie import ProductGroup
from liedfl_cli.mechanics.damping import apply_blocks, block_diagonal
from liedfl_cli.mechanics.forces import RayleighForce


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=63, help="triplets per batch (Exp 4's: 63)")
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    G = ProductGroup(1, 22)
    force = RayleighForce(G, coupling="per_body").double()
    with torch.no_grad():  # away from the initial multiple of the identity
        for p in force.parameters():
            p.add_(0.1 * torch.randn_like(p))
    D = force.D
    xi = torch.randn(args.batch, G.dim, dtype=torch.float64)

    def blocks():
        return -apply_blocks(G, *D.block_matrices(), xi)

    def dense():
        return -(xi @ D().T)

    def modules():
        se = torch.stack([b() for b in D.blocks[: G.n_se3]])
        so = torch.stack([b() for b in D.blocks[G.n_se3 :]])
        return -(xi @ block_diagonal(G, se, so).T)

    ways = {"blocks": blocks, "dense": dense, "modules": modules}
    ref = blocks().detach()
    for name, fn in ways.items():
        err = float((fn().detach() - ref).abs().max() / ref.abs().max())
        assert err < 1e-14, (name, err)
    times: dict[str, list[float]] = {name: [] for name in ways}
    order = list(ways) * args.repeats
    random.Random(0).shuffle(order)
    for name in order:
        force.zero_grad(set_to_none=True)
        t = time.perf_counter()
        ways[name]().square().sum().backward()
        times[name].append(time.perf_counter() - t)
    print(
        f"load {os.getloadavg()[0]:.2f}, batch {args.batch}, dim {G.dim},"
        f" median of {args.repeats} (ms, forward + backward)"
    )
    base = statistics.median(times["blocks"])
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"  {name:8s} {1e3 * med:7.3f}  ({med / base:.2f}x blocks)")


if __name__ == "__main__":
    main()
