"""SO(3): rotation matrices R of shape (..., 3, 3), tangent vectors w of shape (..., 3).

Conventions: hat(w) x = w x x; exp(hat(w)) = I + sinc hat(w) + cosc hat(w)^2 (Rodrigues);
left perturbation R exp(hat(eta)); vee is the inverse of hat on skew matrices and the
skew-projection vee((A - A^T)/2) on general matrices.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .series import _poly, cosc, sinc
from .tolerances import tol

DIM = 3


def hat(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) skew matrix with hat(w) x = w x x."""
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), -2)


def vee(A: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3): vee of the skew part (A - A^T)/2; inverse of `hat` on so(3)."""
    return 0.5 * torch.stack(
        (A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]), -1
    )


def identity(
    batch_shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device: torch.device | None = None
) -> torch.Tensor:
    """Identity rotations of shape (*batch_shape, 3, 3)."""
    return torch.eye(3, dtype=dtype, device=device).expand(*batch_shape, 3, 3).clone()


def exp(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3): exp(hat(w)) = I + sinc hat(w) + cosc hat(w)^2 (Rodrigues), Taylor
    branch for |w| small; log(exp(w)) = w for |w| < pi."""
    t2 = (w * w).sum(-1)[..., None, None]
    W = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + sinc(t2) * W + cosc(t2) * (W @ W)


def to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method).

    The branch with the largest pivot is used, so the result is accurate for every angle,
    including theta -> pi where the trace formula loses all precision.
    """
    r = R
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    pivots = torch.stack((tr, r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]), -1)
    choice = pivots.argmax(-1)
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s01, s02, s12 = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    # Every candidate is computed with a clamped pivot so the unused branches stay finite
    # (a NaN there would poison gradients through the gather).
    s0 = 2.0 * torch.sqrt(torch.clamp(1.0 + tr, min=1e-12))
    s1 = 2.0 * torch.sqrt(torch.clamp(1.0 + r[..., 0, 0] - r[..., 1, 1] - r[..., 2, 2], min=1e-12))
    s2 = 2.0 * torch.sqrt(torch.clamp(1.0 - r[..., 0, 0] + r[..., 1, 1] - r[..., 2, 2], min=1e-12))
    s3 = 2.0 * torch.sqrt(torch.clamp(1.0 - r[..., 0, 0] - r[..., 1, 1] + r[..., 2, 2], min=1e-12))
    q0 = torch.stack((s0 / 4, d21 / s0, d02 / s0, d10 / s0), -1)
    q1 = torch.stack((d21 / s1, s1 / 4, s01 / s1, s02 / s1), -1)
    q2 = torch.stack((d02 / s2, s01 / s2, s2 / 4, s12 / s2), -1)
    q3 = torch.stack((d10 / s3, s02 / s3, s12 / s3, s3 / 4), -1)
    cand = torch.stack((q0, q1, q2, q3), -2)
    q = torch.gather(cand, -2, choice[..., None, None].expand(*choice.shape, 1, 4)).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def from_quaternion(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternion (w, x, y, z), not necessarily unit -> (..., 3, 3) rotation."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
            torch.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
            torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def log(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3) with exp(log(R)) = R and |log(R)| <= pi (quaternion route)."""
    q = to_quaternion(R)
    qw, qv = q[..., 0], q[..., 1:]
    n2 = (qv * qv).sum(-1)
    small = n2 < tol(R.dtype, "taylor") ** 2
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    # 2 atan2(n, qw)/n; for small n (then qw ~ 1) its series in x = n/qw. The series of
    # atan(x)/x converges only geometrically (x^2k / (2k+1)), so it is kept to x^14: at the
    # threshold (x ~ 0.1 in float64, 0.31 in float32) the dropped tail is below epsilon.
    # qw is replaced by 1 outside the series region so that the discarded branch stays
    # finite at theta = pi (qw = 0) and cannot put NaN into the gradient.
    qw_s = torch.where(small, qw, torch.ones_like(qw))
    x2 = n2 / (qw_s * qw_s)
    series = (2.0 / qw_s) * _poly(x2, (1.0, -1 / 3, 1 / 5, -1 / 7, 1 / 9, -1 / 11, 1 / 13, -1 / 15))
    scale = torch.where(small, series, 2.0 * torch.atan2(n, qw) / n)
    return scale[..., None] * qv


def compose(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """R1 R2 (batched matmul): (..., 3, 3), (..., 3, 3) -> (..., 3, 3) (leading shapes broadcast)."""
    return R1 @ R2


def inverse(R: torch.Tensor) -> torch.Tensor:
    """R^{-1} = R^T: (..., 3, 3) -> (..., 3, 3)."""
    return R.transpose(-1, -2)


def act(R: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """R x: R (..., 3, 3), x (..., 3) -> (..., 3) (leading shapes broadcast)."""
    return (R @ x[..., None])[..., 0]


def adjoint(R: torch.Tensor) -> torch.Tensor:
    """Ad_R = R on so(3) ~ R^3, since R hat(w) R^T = hat(R w): (..., 3, 3) -> (..., 3, 3)."""
    return R


def retract(R: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Left perturbation R exp(hat(eta)): R (..., 3, 3), eta (..., 3) -> (..., 3, 3)."""
    return R @ exp(eta)


def geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """|log(R1^T R2)| in radians, in [0, pi]: (..., 3, 3), (..., 3, 3) -> (...)."""
    return torch.linalg.vector_norm(log(R1.transpose(-1, -2) @ R2), dim=-1)


def project(M: torch.Tensor) -> torch.Tensor:
    """Nearest rotation in Frobenius norm (SVD with det fix), (..., 3, 3) -> (..., 3, 3)."""
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.diag_embed(torch.stack((torch.ones_like(d), torch.ones_like(d), d), -1))
    return U @ D @ Vh


def orthogonality_error(R: torch.Tensor) -> torch.Tensor:
    """||R^T R - I||_F: (..., 3, 3) -> (...)."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    return torch.linalg.matrix_norm(R.transpose(-1, -2) @ R - eye)


def random(
    batch_shape: Sequence[int] = (), generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Haar-uniform random rotations of shape (*batch_shape, 3, 3)."""
    q = torch.randn(*batch_shape, 4, generator=generator, dtype=dtype)
    return from_quaternion(q)
