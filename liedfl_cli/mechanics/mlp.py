"""GELU multilayer perceptron (width x depth hidden layers), float64."""

from __future__ import annotations

import math

import torch
from torch import nn

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)


class MLP(nn.Sequential):
    """in_dim -> [width]*depth (GELU) -> out_dim; the last layer starts at `out_scale` of default size."""

    def __init__(self, in_dim: int, out_dim: int, width: int = 64, depth: int = 3, out_scale: float = 0.1):
        layers: list[nn.Module] = []
        d = in_dim
        for _ in range(depth):
            layers += [nn.Linear(d, width, dtype=torch.float64), nn.GELU()]
            d = width
        last = nn.Linear(d, out_dim, dtype=torch.float64)
        with torch.no_grad():
            last.weight.mul_(out_scale)
            last.bias.zero_()
        layers.append(last)
        super().__init__(*layers)


def value_and_input_jacobian(
    net: nn.Sequential, x: torch.Tensor, cols: slice
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """net(x) (..., out) and its Jacobian with respect to the inputs x[..., cols] (..., out, k), by
    forward mode through the layers (one pass; an exact-GELU MLP of `MLP`'s form), or None for any
    other layer."""
    out, J = x, None
    for layer in net:
        if isinstance(layer, nn.Linear):
            J = layer.weight[:, cols] if J is None else layer.weight @ J
            out = nn.functional.linear(out, layer.weight, layer.bias)
        elif isinstance(layer, nn.GELU) and layer.approximate == "none" and J is not None:
            z = out
            slope = 0.5 + 0.5 * torch.erf(z * _INV_SQRT2) + z * torch.exp(-0.5 * z * z) * _INV_SQRT2PI
            out = layer(z)
            J = slope[..., None] * J
        else:
            return None
    if J is None:
        return None
    return out, J.expand(*out.shape, J.shape[-1])
