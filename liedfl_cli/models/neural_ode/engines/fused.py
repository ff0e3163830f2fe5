"""Fused training path of the Neural ODE baseline (`models.neural_ode`, `runtime.fused`): its vector field

    y = (x, v) (N, 2n),   y' = (v, f_theta(y)),   f_theta an MLP (Linear, activation, ..., Linear)

for `solvers.dopri5`, which runs the whole adaptive solve as one autograd node. The forward keeps each
hidden layer's input and activation slope (exact GELU: value and slope from one erf and one exp), so the
backward is two matrix products and one multiply per layer, with no activation re-evaluated and no
autograd graph; the parameters' gradients accumulate in place over every evaluation of the solve.
Same losses and gradients as the reference path (torchdiffeq over the module, `runtime.fused=false`) to
rounding (tests/test_fused_baselines.py).
"""

from __future__ import annotations

import torch
from torch import nn

from ... import mlp_derivatives


class MLPField:
    """`solvers.dopri5.Field` of y' = (v, f(y)), f an MLP given by `mlp_derivatives.layers`; params: every
    layer's (weight, bias), in order (`params_of`)."""

    def __init__(self, net: nn.Module, n: int):
        lys = mlp_derivatives.layers(net)
        if lys is None:
            raise ValueError("MLPField needs a Sequential of Linear layers and supported activations")
        # every hidden Linear has its activation (`layers` guarantees it); the last has none
        self.acts: list[nn.Module] = [act for _, act in lys[:-1] if act is not None]
        self.n = n

    @staticmethod
    def params_of(net: nn.Module) -> tuple[torch.Tensor, ...]:
        """(W_1, b_1, ..., W_L, b_L) of the MLP's Linear layers."""
        lys = mlp_derivatives.layers(net)
        assert lys is not None
        return tuple(t for lin, _ in lys for t in (lin.weight, lin.bias))

    def forward(self, y: torch.Tensor, params) -> tuple[torch.Tensor, tuple]:
        """y (N, 2n) -> (y' (N, 2n), [(layer input, activation slope)] and the last layer's input)."""
        saved = []
        a = y
        for k, act in enumerate(self.acts):
            z = torch.addmm(params[2 * k + 1], a, params[2 * k].T)
            a_next, slope = mlp_derivatives._act_and_slope(act, z)
            saved.append((a, slope))
            a = a_next
        out = torch.addmm(params[-1], a, params[-2].T)
        return torch.cat((y[:, self.n :], out), -1), (saved, a)

    def vjp(self, saved, g: torch.Tensor, params, acc: list) -> torch.Tensor:
        """g = dL/dy' (N, 2n) -> dL/dy (N, 2n); the parameters' gradients are summed into acc in place."""
        hidden, a_last = saved
        if not acc:
            acc.extend(torch.zeros_like(p) for p in params)
        g_out = g[:, self.n :]
        acc[-2].addmm_(g_out.T, a_last)
        acc[-1].add_(g_out.sum(0))
        g_a = g_out @ params[-2]
        for k in range(len(self.acts) - 1, -1, -1):
            a_in, slope = hidden[k]
            g_z = g_a * slope
            acc[2 * k].addmm_(g_z.T, a_in)
            acc[2 * k + 1].add_(g_z.sum(0))
            g_a = g_z @ params[2 * k]
        g_a[:, self.n :] += g[:, : self.n]
        return g_a

    def param_grads(self, acc: list, params) -> tuple:
        """The summed gradients, one per parameter tensor (zeros when the solve took no step)."""
        return tuple(acc) if acc else tuple(torch.zeros_like(p) for p in params)
