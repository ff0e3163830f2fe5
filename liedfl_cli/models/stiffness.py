"""Stiffness of a DEL model's constant damping: what the scheme does with a strongly damped body.

The forces enter the DEL step as (h/2)(F(xi~_{k-1}) + F(xi~_k)) (trapezoidal). Linearised at
rest, with M = -h H the mass matrix (H the kinetic mixed Hessian at the identity increment: J for
an SO(3) body, the 6x6 spatial inertia for an SE(3) body) and F = -D xi~, one step maps

    (M + h D / 2) xi_k = (M - h D / 2) xi_{k-1},

so a velocity along an eigenvector of M^-1 D (eigenvalue lambda) is multiplied by
(1 - h lambda / 2) / (1 + h lambda / 2) per step instead of exp(-h lambda): for h lambda > 2 the
factor is negative and the scheme reverses that velocity every step while Newton converges
(measured figures in docs/math.md, "Stiff damping"). `damping_stiffness` gives h lambda_max.
"""

from __future__ import annotations

from typing import Any

import torch

from ..lie import Pose
from ..mechanics import kinetic
from ..mechanics.forces import RayleighForce

STIFF_DAMPING = 2.0
"""h lambda_max(M^-1 D) above which the per-step factor (1 - h lambda/2)/(1 + h lambda/2) is negative."""


def step_factor(stiffness: float) -> float:
    """(1 - s/2) / (1 + s/2): what one step does to a velocity along M^-1 D's eigenvector with h lambda = s."""
    return (1.0 - 0.5 * stiffness) / (1.0 + 0.5 * stiffness)


@torch.no_grad()
def damping_stiffness(model: Any) -> float | None:
    # model: a LieDFLNN (its `damping_stiffness` hook calls in here, so its class is not imported)
    """h lambda_max(M^-1 D) of a LieDFLNN's constant (Rayleigh) damping D, with M = -h H the mass
    matrix of its kinetic term (block diagonal over bodies); None for a model without constant
    damping (a configuration-dependent D(g) is not checked). Other models: `Model.damping_stiffness`."""
    Ds = [f.D() for f in model.forces if isinstance(f, RayleighForce)]
    if not Ds:
        return None
    D = torch.stack(Ds).sum(0)
    G, h = model.G, model.h
    Jd, mass, rho = model._params()
    eye = torch.eye(3, dtype=Jd.dtype, device=Jd.device).expand(G.n_bodies, 3, 3)
    identity = Pose(eye, Jd.new_zeros(G.n_se3, 3))
    M = torch.block_diag(*(-h * b for b in kinetic.mixed_hessian_blocks(G, identity, Jd, mass, rho, h)))
    A = torch.linalg.solve(M, D)
    if not torch.isfinite(A).all():  # unusable weights: LAPACK would print an error of its own
        return None
    lam = torch.linalg.eigvals(A).real.max()
    return float(h * lam)
