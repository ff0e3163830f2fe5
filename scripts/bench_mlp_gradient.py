"""A training step's MLP input gradient, three ways (docs/benchmarks.md, "Round 8").

    python scripts/bench_mlp_gradient.py [--points 2048] [--width 64] [--depth 3] [--repeats 60]

What the DEL losses do with a potential MLP V(x): they need dV/dx at every point, and the loss's
backward then needs the parameters' gradients through dV/dx. Timed: value and gradient at `points`
inputs of dimension 3 (Exp 1's Euler-angle DFLNN: 1024 triplets = 2048 midpoints of a 64 x 3 GELU MLP),
then the backward of a scalar of both.
  double      `torch.autograd.grad(V, x, create_graph=True)`, then a backward through that graph
              (the reference path, `runtime.fused=false`)
  expressions the gradient written as plain tensor expressions, batch major, which autograd
              differentiates once (`mlp_derivatives.value_and_gradient` before round 8)
  library     `mlp_derivatives.value_and_gradient` now: feature major, one autograd node per
              activation (`_ActAndSlope`)
Prints the median (and minimum) of `repeats` interleaved timings in ms (one torch thread) and checks
that the three agree: gradients to 1e-12 of their largest entry.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import time

import torch
from torch import nn

from liedfl_cli.mechanics.mlp import MLP
from liedfl_cli.models import mlp_derivatives as md


def expressions(lys: list[md.Layer], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The gradient as the batch-major tensor expressions `value_and_gradient` used before round 8."""
    out, saved = md._forward(lys, x)
    g = lys[-1][0].weight[0]
    for (lin, act), (z, a) in zip(reversed(lys[:-1]), reversed(saved)):
        assert act is not None
        g = (g * md._act_slope(act, z, a)) @ lin.weight
    return out[..., 0], g


def double(net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    xg = x.detach().requires_grad_(True)
    v = net(xg)[..., 0]
    (g,) = torch.autograd.grad(v.sum(), xg, create_graph=True)
    return v, g


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2048, help="inputs per batch (Exp 1 Euler: 2048)")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--depth", type=int, default=3)
    ap.add_argument("--inputs", type=int, default=3, help="input dimension (Euler angles: 3; a rotation: 9)")
    ap.add_argument("--repeats", type=int, default=60)
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    net = MLP(args.inputs, 1, args.width, args.depth).double()
    lys = md.layers(net)
    assert lys is not None
    x = torch.randn(args.points, args.inputs, dtype=torch.float64)
    c = torch.randn(args.points, args.inputs, dtype=torch.float64)
    ways = {
        "double": lambda: double(net, x),
        "expressions": lambda: expressions(lys, x),
        "library": lambda: md.value_and_gradient(net, x),
    }

    def step(name: str) -> list[torch.Tensor]:
        net.zero_grad(set_to_none=True)
        got = ways[name]()
        assert got is not None
        v, g = got
        ((g * c).sum() + (v * v).sum()).backward()
        return [g.detach(), *(p.grad.detach().clone() for p in net.parameters() if p.grad is not None)]

    ref = step("double")
    for name in ways:
        for a, b in zip(step(name), ref):
            assert (a - b).abs().max() <= 1e-12 * b.abs().max(), name
    times: dict[str, list[float]] = {k: [] for k in ways}
    order = list(ways)
    for _ in range(args.repeats):
        random.shuffle(order)
        for name in order:
            t = time.perf_counter()
            step(name)
            times[name].append(time.perf_counter() - t)
    load = os.getloadavg()[0]
    print(f"MLP {args.inputs}->{args.width}x{args.depth}->1, {args.points} points, 1 thread, load {load:.2f}")
    base = statistics.median(times["double"])
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"  {name:12s} median {1e3 * med:7.2f} ms  min {1e3 * min(ts):7.2f} ms  ({base / med:.2f}x double's)")


if __name__ == "__main__":
    main()
