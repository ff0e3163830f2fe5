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


def activation_slope(act: nn.Module, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """act'(z) as a differentiable expression."""
    if isinstance(act, nn.GELU) and act.approximate == "none":
        Phi = 0.5 + 0.5 * torch.erf(z * _INV_SQRT2)
        return Phi + z * torch.exp(-0.5 * z * z) * _INV_SQRT2PI
    if isinstance(act, nn.Tanh):
        return 1.0 - a * a
    if isinstance(act, nn.Softplus):
        bz = act.beta * z
        return torch.where(bz > act.threshold, torch.ones_like(z), torch.sigmoid(bz))
    if isinstance(act, nn.SiLU):
        s = torch.sigmoid(z)
        return s * (1.0 + z * (1.0 - s))
    # GELU, tanh form: 0.5 (1 + t) + 0.5 z (1 - t^2) u'(z), u = c (z + 0.044715 z^3), t = tanh(u)
    c = math.sqrt(2.0 / math.pi)
    t = torch.tanh(c * (z + 0.044715 * z * z * z))
    return 0.5 * (1.0 + t) + 0.5 * z * (1.0 - t * t) * c * (1.0 + 3 * 0.044715 * z * z)


def value_and_input_jacobian(
    net: nn.Sequential, x: torch.Tensor, cols: slice
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """net(x) (..., out) and its Jacobian with respect to the inputs x[..., cols] (..., out, k), by
    forward mode through the layers (one pass; Linear layers and the activations `activation_slope`
    knows), or None for any other layer."""
    out, J = x, None
    for layer in net:
        if isinstance(layer, nn.Linear):
            J = layer.weight[:, cols] if J is None else layer.weight @ J
            out = nn.functional.linear(out, layer.weight, layer.bias)
        elif isinstance(layer, (nn.GELU, nn.Tanh, nn.Softplus, nn.SiLU)) and J is not None:
            z = out
            out = layer(z)
            J = activation_slope(layer, z, out)[..., None] * J
        else:
            return None
    if J is None:
        return None
    return out, J.expand(*out.shape, J.shape[-1])
