"""Potentials V(g) on a product group; the discrete Lagrangian carries -h V(g_k).

Every potential maps a Pose with leading dims (...) to a tensor of shape (...).
"""
from __future__ import annotations

import torch
from torch import nn

from ..lie import Pose, ProductGroup
from .mlp import MLP


class MLPPotential(nn.Module):
    """V_theta(g) = MLP(flatten(g)): rotation entries of every body and SE(3) positions."""

    def __init__(self, G: ProductGroup, width: int = 64, depth: int = 3):
        super().__init__()
        self.G = G
        self.net = MLP(9 * G.n_bodies + 3 * G.n_se3, 1, width, depth)

    def forward(self, g: Pose) -> torch.Tensor:
        return self.net(self.G.flatten(g))[..., 0]


class GravityPotential(nn.Module):
    """V(g) = sum_i m_i g e3 . (p_i + R_i rho_i) (p_i = 0 for SO(3) bodies: a pivot at the origin).

    masses (B,), rhos (B, 3) are fixed buffers: this is the known potential of the scenes.
    """

    def __init__(self, G: ProductGroup, masses, rhos, gravity: float):
        super().__init__()
        self.G = G
        self.register_buffer("masses", torch.as_tensor(masses, dtype=torch.float64).reshape(G.n_bodies))
        self.register_buffer("rhos", torch.as_tensor(rhos, dtype=torch.float64).reshape(G.n_bodies, 3))
        self.gravity = float(gravity)

    def forward(self, g: Pose) -> torch.Tensor:
        com_height = (g.R[..., 2, :] * self.rhos).sum(-1)  # e3 . R rho per body
        m = self.G.n_se3
        if m:
            com_height = torch.cat((com_height[..., :m] + g.p[..., 2], com_height[..., m:]), -1)
        return self.gravity * (self.masses * com_height).sum(-1)
