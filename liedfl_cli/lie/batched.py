"""Batched group maps of a `ProductGroup` on its flat tangent, for the fused engine (`models.liedflnn.engines.core`).

The same maths as `ProductGroup.exp / compose / retract` (`lie/product.py`) with the three series
coefficients (sinc, cosc, sinc3) of each body evaluated together and hat(w)^2 = w w^T - |w|^2 I formed
directly: fewer, wider kernels. They round differently from the generic maps (about 1e-16, e.g.
4.4e-16 in `group_exp`), and the fused training and rollout paths are defined by these operations, so
they are kept as they are rather than replaced by the generic ones (tests/test_fused.py compares both).

Shapes: xi (..., G.dim); poses `Pose(R (..., n_bodies, 3, 3), p (..., n_se3, 3))`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from . import so3
from .product import Pose, ProductGroup
from .tolerances import tol

EXP_TAYLOR = (
    (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880),  # sinc
    (0.5, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),  # cosc
    (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),  # sinc3
)
"""Taylor coefficients in t^2 of (sinc, cosc, sinc3), as in `lie.series`."""

_CONSTANTS: dict[tuple, dict[str, Any]] = {}


def _constants(dtype: torch.dtype, device: torch.device | None = None) -> dict[str, Any]:
    """eye (3, 3), hat (3, 9) (w @ hat = hat(w).flatten(), entries +-1, exact) and the Taylor
    coefficients by degree, built once per dtype/device."""
    key = (dtype, device)
    if key not in _CONSTANTS:
        eye = torch.eye(3, dtype=dtype, device=device)
        _CONSTANTS[key] = {
            "eye": eye,
            "hat": so3.hat(eye).reshape(3, 9),
            "taylor_by_degree": tuple(torch.tensor(EXP_TAYLOR, dtype=dtype, device=device).T.contiguous()),
        }
    return _CONSTANTS[key]


def vee2(M: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3): vee(M - M^T) = (M21 - M12, M02 - M20, M10 - M01)."""
    return torch.stack((M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]), -1)


def exp_coefficients(t2: torch.Tensor) -> torch.Tensor:
    """t2 (...) -> (..., 3): (sinc, cosc, sinc3) of `lie.series` as functions of t^2, stacked on
    a new last axis.

    The same Taylor polynomials, threshold and closed forms as `series.sinc/cosc/sinc3`,
    evaluated together (one Horner pass over the stacked coefficients)."""
    small = t2 < tol(t2.dtype, "taylor") ** 2
    s2 = t2.masked_fill(small, 1.0)
    t = torch.sqrt(s2)
    c0, c1, c2, c3, c4 = _constants(t2.dtype, t2.device)["taylor_by_degree"]  # (3,) each
    x = t2[..., None]
    taylor = torch.addcmul(c3, c4, x)
    for c in (c2, c1, c0):
        taylor = torch.addcmul(c, taylor, x)
    sin_t = torch.sin(t)
    half = torch.sin(0.5 * t)
    closed = torch.stack((sin_t / t, 2.0 * (half * half) / s2, (t - sin_t) / (s2 * t)), -1)
    return torch.where(small[..., None], taylor, closed)


def split_tangent(G: ProductGroup, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """xi (..., G.dim) -> (w (..., n_bodies, 3), v (..., n_se3, 3)): `G.split`, a plain view for
    SO(3)-only groups."""
    if not G.n_se3:
        return xi.unflatten(-1, (G.n_bodies, 3)), xi.new_zeros(*xi.shape[:-1], 0, 3)
    return G.split(xi)


def group_exp(G: ProductGroup, xi: torch.Tensor) -> Pose:
    """xi (..., G.dim) -> Pose (R (..., n_bodies, 3, 3), p (..., n_se3, 3)): `G.exp` with shared
    coefficients, R = I + sinc W + cosc W^2, p = (I + cosc W + sinc3 W^2) v."""
    w, v = split_tangent(G, xi)
    t2 = (w * w).sum(-1)
    c = exp_coefficients(t2)[..., None, None, :]
    const = _constants(w.dtype, w.device)
    W = (w @ const["hat"]).unflatten(-1, (3, 3))
    eye = const["eye"]
    W2 = w[..., :, None] * w[..., None, :] - t2[..., None, None] * eye  # hat(w)^2 = w w^T - |w|^2 I
    R = eye + c[..., 0] * W + c[..., 1] * W2
    m = G.n_se3
    if not m:
        return Pose(R, v)
    V = eye + c[..., :m, :, :, 1] * W[..., :m, :, :] + c[..., :m, :, :, 2] * W2[..., :m, :, :]
    return Pose(R, (V @ v[..., None])[..., 0])


def compose(G: ProductGroup, g: Pose, h: Pose) -> Pose:
    """g, h Pose (R (..., n_bodies, 3, 3), p (..., n_se3, 3)) -> g h: `G.compose` body by body; for
    SO(3)-only groups just the rotation product."""
    if not G.n_se3:
        return Pose(g.R @ h.R, g.p)
    return G.compose(g, h)


def group_retract(G: ProductGroup, g: Pose, xi: torch.Tensor) -> Pose:
    """g Pose, xi (..., G.dim) -> g exp(xi) (`G.retract` with `group_exp`)."""
    return compose(G, g, group_exp(G, xi))


def retract_increment(G: ProductGroup, x: Pose, delta: torch.Tensor) -> Pose:
    """x exp(delta) (`group_retract`): x poses, delta (..., G.dim). For rotation-only groups without
    a graph (rollouts) in a few wide kernels, R exp(hat(w)) = R (cos t I + sinc(t) hat(w) + cosc(t)
    w w^T), with the closed forms at every angle (cos t, sin(t)/t and 2 sin^2(t/2)/t^2 are accurate to
    rounding down to the smallest normal t; at t = 0 w is 0 and the coefficients do not matter),
    where `group_exp` switches to Taylor polynomials below `taylor`: equal to rounding."""
    R = x.R
    if G.n_se3 or (torch.is_grad_enabled() and (delta.requires_grad or R.requires_grad)):
        return group_retract(G, x, delta)
    w = delta.reshape(*R.shape[:-2], 3)
    t = torch.linalg.vector_norm(w, dim=-1).clamp_(min=torch.finfo(w.dtype).tiny)
    sinc = torch.sin(t).div_(t)
    cosc = torch.sin(0.5 * t).div_(t).square_().mul_(2.0)
    E = (cosc[..., None] * w)[..., :, None] * w[..., None, :]  # cosc w w^T
    E.view(*E.shape[:-2], 9).add_((sinc[..., None] * w) @ _constants(w.dtype, w.device)["hat"])
    E.diagonal(dim1=-2, dim2=-1).add_(torch.cos(t)[..., None])
    return Pose(R @ E, x.p)


def extrapolate_increments(G: ProductGroup, incs: Sequence[Pose]) -> Pose:
    """The warm start of an implicit step from the last increments W_j = g_j^{-1} g_{j+1}, oldest first,
    poses (..., B, 3, 3), (..., m, 3): the next increment W_{k+1} predicted by a polynomial through them.

    One increment: W_k (off the next by O(h^2)). Two: E W_k with E = D = W_k W_{k-1}^{-1}, i.e.
    W_k W_{k-1}^{-1} W_k, the group's form of 2 xi_k - xi_{k-1} (symmetric, so its log is that up to
    third-order brackets: off by O(h^3)). Three: E = D D'^{-1} D with D' = W_{k-1} W_{k-2}^{-1}: the
    ratio D of successive increments carried on by the same symmetric rule (D is the identity up to
    O(h^2), so the brackets between D's are O(h^4)), the group's form of 3 xi_k - 3 xi_{k-1} + xi_{k-2}:
    off by O(h^4). The guess is E W_k, so it moves W_k by |E - I| (Frobenius, W_k orthogonal).

    W_k on rows where that move exceeds `TRUST` times W_k's own distance from the identity (rotations:
    sum over bodies of 3 - tr, which is |M - I|^2 / 2 for a rotation M; SE(3) translations apart, by
    their squared norms): a history that does not look smooth (a spin reversed every step by stiff
    damping, a body at a turning point) and a prediction that is not finite (a failed step never
    seeds a guess) start from W_k, as without history."""
    last = incs[-1]
    if len(incs) == 1:
        return last
    if not G.n_se3:  # rotations only: the products directly (inverse = transpose), as the rollouts use it
        W, W1 = last.R, incs[-2].R
        E = W @ W1.mT
        if len(incs) == 3:
            E = E @ (W1 @ incs[-3].R.mT).mT @ E
        guess = Pose(E @ W, last.p)
    else:
        E_pose = compose(G, last, G.inverse(incs[-2]))
        if len(incs) == 3:
            D_prev = compose(G, incs[-2], G.inverse(incs[-3]))
            E_pose = compose(G, compose(G, E_pose, G.inverse(D_prev)), E_pose)
        E = E_pose.R
        guess = compose(G, E_pose, last)
    t2 = TRUST * TRUST
    trace = lambda M: M.diagonal(dim1=-2, dim2=-1).sum((-2, -1))
    ok = 3.0 * G.n_bodies - trace(E) <= t2 * (3.0 * G.n_bodies - trace(last.R))  # NaN compares false
    if G.n_se3:
        ok = ok & ((guess.p - last.p).square().sum((-2, -1)) <= t2 * last.p.square().sum((-2, -1)))
    if bool(ok.all()):  # the usual case: no selects
        return guess
    R = torch.where(ok[..., None, None, None], guess.R, last.R)
    p = torch.where(ok[..., None, None], guess.p, last.p)
    return Pose(R, p)


TRUST = 0.5
"""`extrapolate_increments` keeps its prediction where it moves the last increment W_k by at most this
fraction of W_k's distance from the identity: on a smooth motion the move is O(h) of it (the second
difference against the first), on a spin reversed every step it is about three times it."""
HISTORY = 3
"""How many increments a rollout keeps for `extrapolate_increments` (the last and the two before it)."""
