"""External forces F(g, xi~) -> (..., dim) covectors in the flat tangent layout.

They enter the DEL residual as F^-_k = F^+_k = (h/2) F(g_k, xi~_k) with xi~_k the paper's
velocity estimate from the increment g_k^{-1} g_{k+1} (`kinetic.velocity_estimate`).
"""
from __future__ import annotations

import torch
from torch import nn

from ..lie import Pose, ProductGroup
from .parameterizations import SPSDMatrix


class RayleighForce(nn.Module):
    """F = -D xi~ with a constant SPSD D (dim x dim); D starts at init_diag * scale * I."""

    name = "rayleigh"

    def __init__(self, G: ProductGroup, scale: float = 1.0, init_diag: float = 0.01):
        super().__init__()
        self.D = SPSDMatrix(G.dim, init_diag=init_diag * scale)

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        return -(xi @ self.D().T)

    def jacobian_xi(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        """dF/d xi~ = -D, broadcast to (..., dim, dim)."""
        return (-self.D()).expand(*xi.shape[:-1], xi.shape[-1], xi.shape[-1])


FORCES = {"rayleigh": RayleighForce}


def force_jacobian_xi(force: nn.Module, g: Pose, xi: torch.Tensor) -> torch.Tensor:
    """dF(g, xi~)/d xi~ (..., dim, dim): the force's closed form if it has one, else autodiff
    (one reverse pass per tangent direction; rows of the batch are independent)."""
    if hasattr(force, "jacobian_xi"):
        return force.jacobian_xi(g, xi)
    with torch.enable_grad():
        x = xi.detach().requires_grad_(True)
        F = force(g, x)
        rows = [torch.autograd.grad(F[..., i].sum(), x, retain_graph=True, create_graph=False)[0]
                for i in range(F.shape[-1])]
    return torch.stack(rows, -2)


def build_forces(G: ProductGroup, forces, scale: float) -> list[nn.Module]:
    """Instantiate forces from names or from a mapping name -> kwargs (extra keys like
    `_target_` are ignored: the registry key decides the class)."""
    items = forces.items() if hasattr(forces, "items") else [(f, {}) for f in forces]
    out = []
    for name, kwargs in items:
        if name not in FORCES:
            raise ValueError(f"unknown force {name!r}; choose from {sorted(FORCES)}")
        kw = {k: v for k, v in dict(kwargs or {}).items() if not k.startswith("_")}
        out.append(FORCES[name](G, scale=scale, **kw))
    return out
