"""How far a motion is from obeying its joints: the check a file's declared joints must pass at load.

For relative rotations R_rel (..., N+1, 3, 3) of one joint over a trajectory (`lie.joints`):
    weld       geodesic distance of R_rel_k to R_rel_0;
    hinge      the angle between R_rel_k a and R_rel_0 a (a in the body frame stays fixed in the parent
               frame) and the off-axis part |w - (w.a) a| of every increment w = log(R_rel_k^T R_rel_k+1);
    universal  |asin(a1^T R_rel_k a2) - asin(a1^T R_rel_0 a2)| (the angle between the two axes is fixed);
    ball/free  0.
The largest over the trajectory, in radians.
"""

from __future__ import annotations

import torch

from . import so3

VIOLATION_TOLERANCE = 1e-3
"""Largest violation (rad) a file may have and still declare its joints (MuJoCo data: ~1e-12; a noisier
recording should leave its joints undeclared and let `model.joints=auto` infer them)."""


def _angle_between(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Angles (...,) between unit vectors u, v (..., 3), accurate for small angles."""
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(u, v), dim=-1), (u * v).sum(-1))


def joint_violation(kind: str, axes: torch.Tensor, R_rel: torch.Tensor) -> torch.Tensor:
    """The largest violation (...,) in radians of joint `kind` with axes (2, 3) by R_rel (..., N+1, 3, 3)."""
    lead = R_rel.shape[:-3]
    if kind in ("ball", "free"):
        return R_rel.new_zeros(lead)
    R0 = R_rel[..., :1, :, :]
    if kind == "weld":
        return so3.log(R0.transpose(-1, -2) @ R_rel).norm(dim=-1).amax(-1)
    if kind == "hinge":
        a = axes[0].to(R_rel)
        fixed = _angle_between(so3.act(R_rel, a), so3.act(R0, a).expand_as(so3.act(R_rel, a))).amax(-1)
        if R_rel.shape[-3] < 2:
            return fixed
        w = so3.log(R_rel[..., :-1, :, :].transpose(-1, -2) @ R_rel[..., 1:, :, :])
        off = (w - (w @ a)[..., None] * a).norm(dim=-1).amax(-1)
        return torch.maximum(fixed, off)
    if kind == "universal":
        a1, a2 = axes[0].to(R_rel), axes[1].to(R_rel)
        c = torch.asin(torch.einsum("i,...ij,j->...", a1, R_rel, a2).clamp(-1.0, 1.0))
        return (c - c[..., :1]).abs().amax(-1)
    raise ValueError(f"unknown joint type {kind!r}")


__all__ = ["VIOLATION_TOLERANCE", "joint_violation"]
