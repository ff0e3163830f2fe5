"""Product groups G = SE(3)^m x SO(3)^n with one shared interface.

A configuration is a `Pose(R, p)`: R of shape (..., m + n, 3, 3) holds every body's rotation
(SE(3) bodies first), p of shape (..., m, 3) the SE(3) bodies' positions (m may be 0).
A tangent vector is one flat tensor of length 6m + 3n ordered body by body:
(w_1, v_1, ..., w_m, v_m, w_{m+1}, ..., w_{m+n}).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from . import se3, so3


class Pose(NamedTuple):
    """Configuration of a product group: R (..., B, 3, 3), p (..., m, 3)."""

    R: torch.Tensor
    p: torch.Tensor

    # Deliberately shadows tuple.index (find a value's position), which makes no sense for a
    # pose; Pose.index indexes the batch instead, and every caller uses it that way.
    def index(self, idx: Any) -> Pose:  # type: ignore[override]
        """Index the leading (batch/time) dimensions of both parts alike.

        R (*lead, B, 3, 3), p (*lead, m, 3) -> R[idx] (*lead', B, 3, 3), p[idx] (*lead', m, 3),
        where lead' is the shape of `torch.empty(lead)[idx]`.
        """
        return Pose(self.R[idx], self.p[idx])

    def to(self, *args: Any, **kwargs: Any) -> Pose:
        """Both parts through `Tensor.to` (dtype/device); shapes unchanged: (..., B, 3, 3), (..., m, 3)."""
        return Pose(self.R.to(*args, **kwargs), self.p.to(*args, **kwargs))


@dataclass(frozen=True)
class ProductGroup:
    """SE(3)^n_se3 x SO(3)^n_so3 (group layout only; holds no tensors)."""

    n_se3: int = 0
    n_so3: int = 1

    def __post_init__(self):
        if self.n_se3 < 0 or self.n_so3 < 0 or self.n_se3 + self.n_so3 == 0:
            raise ValueError(f"product group needs at least one body, got n_se3={self.n_se3}, n_so3={self.n_so3}")

    @property
    def n_bodies(self) -> int:
        """B = n_se3 + n_so3."""
        return self.n_se3 + self.n_so3

    @property
    def dim(self) -> int:
        """Length of a flat tangent vector: 6 n_se3 + 3 n_so3."""
        return 6 * self.n_se3 + 3 * self.n_so3

    @property
    def name(self) -> str:
        """Readable name, e.g. "SE(3) x SO(3)^2"."""
        parts = []
        if self.n_se3:
            parts.append("SE(3)" + (f"^{self.n_se3}" if self.n_se3 > 1 else ""))
        if self.n_so3:
            parts.append("SO(3)" + (f"^{self.n_so3}" if self.n_so3 > 1 else ""))
        return " x ".join(parts)

    # ----------------------------------------------------------------- tangent layout
    def split(self, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., dim) -> (w (..., B, 3), v (..., m, 3)): the rotational part of every body (SE(3)
        bodies first) and the translational part of the SE(3) bodies. Inverse of `join`."""
        m = self.n_se3
        lead = xi.shape[:-1]
        se = xi[..., : 6 * m].reshape(*lead, m, 2, 3)
        w_so = xi[..., 6 * m :].reshape(*lead, self.n_so3, 3)
        return torch.cat((se[..., 0, :], w_so), -2), se[..., 1, :]

    def join(self, w: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Inverse of `split`: (w (..., B, 3), v (..., m, 3)) -> (..., dim)."""
        m = self.n_se3
        lead = w.shape[:-2]
        se = torch.stack((w[..., :m, :], v), -2).reshape(*lead, 6 * m)
        return torch.cat((se, w[..., m:, :].reshape(*lead, 3 * self.n_so3)), -1)

    def body_slices(self) -> list[slice]:
        """Slices of each body's block in the flat tangent vector (..., dim): 6 entries (w, v) per
        SE(3) body, then 3 entries w per SO(3) body."""
        out, start = [], 0
        for i in range(self.n_bodies):
            d = 6 if i < self.n_se3 else 3
            out.append(slice(start, start + d))
            start += d
        return out

    # ----------------------------------------------------------------- group operations
    def identity(
        self, batch_shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device: torch.device | None = None
    ) -> Pose:
        """The identity e: R = I of shape (*batch_shape, B, 3, 3), p = 0 of shape (*batch_shape, m, 3)."""
        R = so3.identity((*batch_shape, self.n_bodies), dtype, device)
        return Pose(R, torch.zeros(*batch_shape, self.n_se3, 3, dtype=dtype, device=device))

    def compose(self, g: Pose, h: Pose) -> Pose:
        """g h body by body: (R_g R_h, p_g + R_g p_h).

        Pose (..., B, 3, 3), (..., m, 3) twice (leading shapes broadcast) -> Pose of the same layout.
        """
        m = self.n_se3
        return Pose(g.R @ h.R, g.p + so3.act(g.R[..., :m, :, :], h.p))

    def inverse(self, g: Pose) -> Pose:
        """g^{-1} = (R^T, -R^T p) body by body, so g g^{-1} = e; Pose (..., B, 3, 3), (..., m, 3) -> same shapes."""
        Rt = g.R.transpose(-1, -2)
        return Pose(Rt, -so3.act(Rt[..., : self.n_se3, :, :], g.p))

    def increment(self, g: Pose, g_next: Pose) -> Pose:
        """g^{-1} g_next = (W, z) with W = R^T R', z = R^T (p' - p).

        Pose (..., B, 3, 3), (..., m, 3) twice -> increment Pose (W (..., B, 3, 3), z (..., m, 3)).
        """
        Rt = g.R.transpose(-1, -2)
        return Pose(Rt @ g_next.R, so3.act(Rt[..., : self.n_se3, :, :], g_next.p - g.p))

    def exp(self, xi: torch.Tensor) -> Pose:
        """xi (..., dim) -> Pose (R (..., B, 3, 3), p (..., m, 3)): the group exponential, SE(3) exp
        (R, p) = (exp(w), V(w) v) per SE(3) body and SO(3) exp otherwise; log(exp(xi)) = xi for |w| < pi."""
        w, v = self.split(xi)
        m = self.n_se3
        R = so3.exp(w)
        p = so3.act(se3.V_matrix(w[..., :m, :]), v)
        return Pose(R, p)

    def log(self, g: Pose) -> torch.Tensor:
        """Pose (R (..., B, 3, 3), p (..., m, 3)) -> xi (..., dim) with exp(log(g)) = g, |w| <= pi per body."""
        w = so3.log(g.R)
        m = self.n_se3
        v = so3.act(se3.V_inverse(w[..., :m, :]), g.p)
        return self.join(w, v)

    def retract(self, g: Pose, xi: torch.Tensor) -> Pose:
        """g exp(xi) (exact group exponential, used by rollouts).

        g: Pose (..., B, 3, 3), (..., m, 3); xi (..., dim) -> Pose of the same shapes.
        """
        return self.compose(g, self.exp(xi))

    def perturb(self, g: Pose, eta: torch.Tensor) -> Pose:
        """First-order left perturbation g exp(eta) ~ (R exp(eta_w), p + R eta_v).

        Exact in rotation and exact to first order in translation, which is all the DEL
        residual (a derivative at eta = 0) needs.

        g: Pose (..., B, 3, 3), (..., m, 3); eta (..., dim) -> Pose of the same shapes.
        """
        w, v = self.split(eta)
        m = self.n_se3
        return Pose(g.R @ so3.exp(w), g.p + so3.act(g.R[..., :m, :, :], v))

    def flatten(self, g: Pose) -> torch.Tensor:
        """Pose -> (..., 9 B + 3 m) network input (rotation entries then positions)."""
        lead = g.R.shape[:-3]  # (sizes, not -1: an empty batch has no size to infer)
        return torch.cat((g.R.reshape(*lead, 9 * self.n_bodies), g.p.reshape(*lead, 3 * self.n_se3)), -1)

    def orthogonality_error(self, g: Pose) -> torch.Tensor:
        """max over bodies of ||R^T R - I||_F: Pose (R (..., B, 3, 3), p) -> shape (...)."""
        return so3.orthogonality_error(g.R).amax(-1)

    def check(self, g: Pose) -> None:
        """Raise ValueError unless g is R (..., B, 3, 3), p (..., m, 3) with the same leading shape (...)."""
        if g.R.shape[-3:] != (self.n_bodies, 3, 3):
            raise ValueError(f"R has shape {tuple(g.R.shape)}, expected (..., {self.n_bodies}, 3, 3) for {self.name}")
        if g.p.shape[-2:] != (self.n_se3, 3):
            raise ValueError(f"p has shape {tuple(g.p.shape)}, expected (..., {self.n_se3}, 3) for {self.name}")
        if g.R.shape[:-3] != g.p.shape[:-2]:
            raise ValueError(
                f"R and p have different leading (batch) shapes {tuple(g.R.shape[:-3])} and {tuple(g.p.shape[:-2])}"
            )


SO3 = ProductGroup(0, 1)
SE3 = ProductGroup(1, 0)
