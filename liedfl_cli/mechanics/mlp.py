"""GELU multilayer perceptron (width x depth hidden layers), float64."""

from __future__ import annotations

import torch
from torch import nn


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
