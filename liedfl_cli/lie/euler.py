"""ZYX Euler angles q = (phi, theta, psi) <-> rotation matrices, for the Euler-angle baseline.

Convention: R = Rz(psi) Ry(theta) Rx(phi) (yaw psi about z, pitch theta about y, roll phi about x),
so body angular velocity w = E(q) qdot with E given by `rate_matrix`. theta lies in [-pi/2, pi/2];
phi and psi in (-pi, pi]. At gimbal lock (theta = +-pi/2) only phi - psi (theta = pi/2) or
phi + psi (theta = -pi/2) is determined; `from_matrix` then returns psi = 0.

`from_matrix` is accurate to rounding for every rotation, including near gimbal lock: phi is
computed from psi and the combination phi -+ psi, which is well conditioned on each hemisphere:
    (1 + sin theta) (sin, cos)(phi - psi) = (R01 - R12, R11 + R02)
    (1 - sin theta) (sin, cos)(phi + psi) = (-(R01 + R12), R11 - R02)
"""

from __future__ import annotations

import math

import torch

GIMBAL_TOL = 1e-12
"""|cos theta| below which psi is set to 0 (it is not determined by R)."""


def _rot_x(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack((torch.stack((i, o, o), -1), torch.stack((o, c, -s), -1), torch.stack((o, s, c), -1)), -2)


def _rot_y(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack((torch.stack((c, o, s), -1), torch.stack((o, i, o), -1), torch.stack((-s, o, c), -1)), -2)


def _rot_z(a: torch.Tensor) -> torch.Tensor:
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack((torch.stack((c, -s, o), -1), torch.stack((s, c, o), -1), torch.stack((o, o, i), -1)), -2)


def to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 3) angles (phi, theta, psi) -> (..., 3, 3) rotation Rz(psi) Ry(theta) Rx(phi). Differentiable."""
    phi, theta, psi = q.unbind(-1)
    return _rot_z(psi) @ _rot_y(theta) @ _rot_x(phi)


def wrap(a: torch.Tensor) -> torch.Tensor:
    """Angles to (-pi, pi], elementwise: a (...) -> (...) with wrap(a) = a mod 2 pi."""
    return torch.atan2(torch.sin(a), torch.cos(a))


def from_matrix(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) ZYX angles (phi, theta, psi); see the module docstring."""
    r = R
    cth = torch.hypot(r[..., 0, 0], r[..., 1, 0])
    theta = torch.atan2(-r[..., 2, 0], cth)
    psi = torch.atan2(r[..., 1, 0], r[..., 0, 0])
    psi = torch.where(cth < GIMBAL_TOL, torch.zeros_like(psi), psi)
    diff = torch.atan2(r[..., 0, 1] - r[..., 1, 2], r[..., 1, 1] + r[..., 0, 2])  # phi - psi
    summ = torch.atan2(-(r[..., 0, 1] + r[..., 1, 2]), r[..., 1, 1] - r[..., 0, 2])  # phi + psi
    phi = torch.where(-r[..., 2, 0] >= 0, diff + psi, summ - psi)
    return torch.stack((wrap(phi), theta, psi), -1)


def unwrap(q: torch.Tensor, dim: int = -2) -> torch.Tensor:
    """Remove 2 pi jumps along `dim` (like numpy.unwrap): consecutive differences are brought
    to [-pi, pi) and re-accumulated from the first element. Works on (..., L, 3) angle sequences
    (theta never jumps by 2 pi, so unwrapping every component is harmless)."""
    d = torch.diff(q, dim=dim)
    d = d - 2 * math.pi * torch.floor((d + math.pi) / (2 * math.pi))
    first = q.narrow(dim, 0, 1)
    return torch.cat((first, first + torch.cumsum(d, dim)), dim)


def rate_matrix(q: torch.Tensor) -> torch.Tensor:
    """q (..., 3) -> E(q) (..., 3, 3) with body angular velocity w = E(q) (phi', theta', psi'); det E = cos theta."""
    phi, theta = q[..., 0], q[..., 1]
    cf, sf, ct, st = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    o, i = torch.zeros_like(phi), torch.ones_like(phi)
    return torch.stack(
        (torch.stack((i, o, -st), -1), torch.stack((o, cf, sf * ct), -1), torch.stack((o, -sf, cf * ct), -1)), -2
    )


__all__ = ["to_matrix", "from_matrix", "wrap", "unwrap", "rate_matrix", "GIMBAL_TOL"]
