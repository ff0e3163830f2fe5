"""How far a motion is from obeying its joints: the check a file's declared joints must pass at load.

For relative rotations R_rel (..., N+1, 3, 3) of one joint over a trajectory (R_rel = R_parent^T R_b,
the root's: its world attitude; `lie.joints`), with the joint's axes (2, 3) as `Tree.axes`:

    weld       the geodesic distance |log(R_rel_0^T R_rel_k)| of R_rel_k to R_rel_0 (R_rel = C);
    hinge      the angle between R_rel_k a and R_rel_0 a (R_rel = C exp(t a): the axis a, in the body
               frame, stays fixed in the parent frame) and the off-axis part |w - (w.a) a| of every
               increment w = log(R_rel_k^T R_rel_k+1) (which is (t_k+1 - t_k) a), the larger of the two;
    universal  |asin(a1^T R_rel_k a2) - asin(a1^T R_rel_0 a2)| (R_rel = exp(t1 a1) C exp(t2 a2) keeps
               a1^T R_rel a2 = a1^T C a2: the angle between the two axes is fixed);
    ball/free  0.

The largest over the N+1 samples, in radians, per trajectory. Exact joint motion gives rounding error
(MuJoCo's RK4 data: ~1e-12 rad); `violation_tolerance` is what a file may have and still declare them.
"""

from __future__ import annotations

import torch

from . import so3

VIOLATION_TOLERANCE = 1e-6
"""Largest violation (rad) a float64 file may have and still declare its joints: about 1e6 times the
rounding error of exact joint motion (MuJoCo data: ~1e-12), far below any real wobble. A recording
with noise should leave its joints undeclared (`model.joints=auto` infers them)."""

VIOLATION_TOLERANCE_FLOAT32 = 1e-4
"""The same for a file stored in float32 (rounding of R: ~1e-7 rad per sample)."""


def violation_tolerance(dtype: torch.dtype = torch.float64) -> float:
    """The violation (rad) a file of stored precision `dtype` may have: 1e-6 (float64) or 1e-4 (float32)."""
    return VIOLATION_TOLERANCE if torch.finfo(dtype).bits >= 64 else VIOLATION_TOLERANCE_FLOAT32


def _angle_between(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Angles (...,) between unit vectors u, v (..., 3), accurate for small angles."""
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(u, v, dim=-1), dim=-1), (u * v).sum(-1))


def joint_violation(kind: str, axes: torch.Tensor, R_rel: torch.Tensor) -> torch.Tensor:
    """The largest violation (...,) in radians of joint `kind` ("free", "ball", "hinge", "universal",
    "weld") with axes (2, 3) (row 0: a hinge's axis, body frame, or a universal's a1, parent frame; row 1:
    a universal's a2, body frame) by the relative rotations R_rel (..., N+1, 3, 3) of one trajectory
    each. ValueError for an unknown kind."""
    lead = R_rel.shape[:-3]
    if kind in ("ball", "free"):
        return R_rel.new_zeros(lead)
    if R_rel.shape[-3] == 0:
        return R_rel.new_zeros(lead)
    axes = torch.as_tensor(axes, dtype=R_rel.dtype, device=R_rel.device)
    R0 = R_rel[..., :1, :, :]
    if kind == "weld":
        return so3.log(R0.transpose(-1, -2) @ R_rel).norm(dim=-1).amax(-1)
    if kind == "hinge":
        a = axes[0]
        v = R_rel @ a  # (..., N+1, 3): the axis in the parent frame
        fixed = _angle_between(v, v[..., :1, :].expand_as(v)).amax(-1)
        if R_rel.shape[-3] < 2:
            return fixed
        w = so3.log(R_rel[..., :-1, :, :].transpose(-1, -2) @ R_rel[..., 1:, :, :])  # (..., N, 3)
        off = (w - (w @ a)[..., None] * a).norm(dim=-1).amax(-1)
        return torch.maximum(fixed, off)
    if kind == "universal":
        a1, a2 = axes[0], axes[1]
        c = torch.asin(torch.einsum("i,...ij,j->...", a1, R_rel, a2).clamp(-1.0, 1.0))  # (..., N+1)
        return (c - c[..., :1]).abs().amax(-1)
    raise ValueError(f"unknown joint type {kind!r}")


__all__ = ["VIOLATION_TOLERANCE", "VIOLATION_TOLERANCE_FLOAT32", "joint_violation", "violation_tolerance"]
