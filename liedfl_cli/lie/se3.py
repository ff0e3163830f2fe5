"""SE(3) as pairs (R, p): R (..., 3, 3), p (..., 3); tangent xi = (w, v) of shape (..., 6).

Group law (R1, p1)(R2, p2) = (R1 R2, p1 + R1 p2); exp(w, v) = (exp(w), V(w) v) with
V = I + cosc hat(w) + sinc3 hat(w)^2. The left perturbation used by the DEL residual is
(R, p) exp(eta) whose first-order part is (R exp(eta_w), p + R eta_v).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from . import so3
from .series import cosc, se3_vinv_coeff, sinc3

DIM = 6


def hat(xi: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 4, 4) matrix [[hat(w), v], [0, 0]]."""
    top = torch.cat((so3.hat(xi[..., :3]), xi[..., 3:, None]), -1)
    return torch.cat((top, torch.zeros_like(top[..., :1, :])), -2)


def vee(X: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) -> (..., 6), inverse of `hat`: vee(hat(xi)) = xi."""
    return torch.cat((so3.vee(X[..., :3, :3]), X[..., :3, 3]), -1)


def to_matrix(R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """R (..., 3, 3), p (..., 3) -> homogeneous [[R, p], [0, 1]] of shape (..., 4, 4)."""
    top = torch.cat((R, p[..., None]), -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), -2)


def from_matrix(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Homogeneous (..., 4, 4) -> (R (..., 3, 3), p (..., 3)), inverse of `to_matrix`."""
    return T[..., :3, :3], T[..., :3, 3]


def identity(
    batch_shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device: torch.device | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity (R, p) = (I, 0): R (*batch_shape, 3, 3), p (*batch_shape, 3)."""
    return so3.identity(batch_shape, dtype, device), torch.zeros(*batch_shape, 3, dtype=dtype, device=device)


def V_matrix(w: torch.Tensor) -> torch.Tensor:
    """Left Jacobian of SO(3), the translation part of exp: (..., 3) -> (..., 3, 3)."""
    t2 = (w * w).sum(-1)[..., None, None]
    W = so3.hat(w)
    return torch.eye(3, dtype=w.dtype, device=w.device) + cosc(t2) * W + sinc3(t2) * (W @ W)


def V_inverse(w: torch.Tensor) -> torch.Tensor:
    """Inverse of `V_matrix`, (..., 3) -> (..., 3, 3): V(w)^{-1} = I - hat(w)/2 + c(t) hat(w)^2
    (finite for |w| < 2 pi)."""
    t2 = (w * w).sum(-1)[..., None, None]
    W = so3.hat(w)
    return torch.eye(3, dtype=w.dtype, device=w.device) - 0.5 * W + se3_vinv_coeff(t2) * (W @ W)


def exp(xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """xi = (w, v) (..., 6) -> (R (..., 3, 3), p (..., 3)) = expm([[hat(w), v], [0, 0]]) = (exp(w), V(w) v)."""
    w, v = xi[..., :3], xi[..., 3:]
    return so3.exp(w), so3.act(V_matrix(w), v)


def log(R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """R (..., 3, 3), p (..., 3) -> xi (..., 6) with exp(log(R, p)) = (R, p) and |w| <= pi."""
    w = so3.log(R)
    return torch.cat((w, so3.act(V_inverse(w), p)), -1)


def compose(
    R1: torch.Tensor, p1: torch.Tensor, R2: torch.Tensor, p2: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(R1, p1)(R2, p2) = (R1 R2, p1 + R1 p2): R (..., 3, 3), p (..., 3) each -> (R (..., 3, 3), p (..., 3))."""
    return R1 @ R2, p1 + so3.act(R1, p2)


def inverse(R: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, p)^{-1} = (R^T, -R^T p): R (..., 3, 3), p (..., 3) -> (R (..., 3, 3), p (..., 3))."""
    Rt = R.transpose(-1, -2)
    return Rt, -so3.act(Rt, p)


def act(R: torch.Tensor, p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Transform points: R (..., 3, 3), p (..., 3), x (..., 3) -> R x + p (..., 3)."""
    return so3.act(R, x) + p


def adjoint(R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Ad_(R,p) on xi = (w, v): [[R, 0], [hat(p) R, R]], so g hat(xi) g^{-1} = hat(Ad_g xi).

    R (..., 3, 3), p (..., 3) -> (..., 6, 6).
    """
    Z = torch.zeros_like(R)
    return torch.cat((torch.cat((R, Z), -1), torch.cat((so3.hat(p) @ R, R), -1)), -2)


def retract(R: torch.Tensor, p: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Left perturbation (R, p) exp(eta): R (..., 3, 3), p (..., 3), eta (..., 6) -> (R (..., 3, 3), p (..., 3))."""
    dR, dp = exp(eta)
    return compose(R, p, dR, dp)
