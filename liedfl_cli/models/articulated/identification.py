"""System identification of an articulated model: what the data determine, a physically consistent
least-squares start, and a Levenberg-Marquardt fit of the one-step prediction error (docs/identification.md).

Linearity. Per body, with increment (W, z) and X = z + (W - I) rho, the kinetic term is
    K = (tr J_d - tr(W J_d))/h + m |X|^2/(2h).
Expanding |X|^2 = |z|^2 + 2 z^T (W - I) rho + rho^T (W - I)^T (W - I) rho and (W - I)^T (W - I) = 2I - W - W^T,
    m rho^T (2I - W - W^T) rho = 2 tr((I - W) m rho rho^T),
so K = tr((I - W) Q)/h + m |z|^2/(2h) + z^T (W - I) c/h with
    pi_b = (m_b, c_b = m_b rho_b, Q_b = J_d,b + m_b rho_b rho_b^T)        (10 numbers),
Q_b the second moment int x x^T dm about the joint (J_d = tr(J)/2 I - J is the second moment about the
centre of mass). Uniform gravity gamma.(m p + R c) is linear in (m, c), and per-DoF damping in its
coefficients d. The model's (reduced) batch residual is therefore r = Y pi + r0 over the triplets, and its
Newton Jacobian in the next pose H = H0 + sum_j pi_j Hb_j (the derivative of a linear function), where r0,
H0 come from parts with no such parameter (an MLP potential, other forces), held at their values.
Y and Hb are exact by forward-mode autodiff (`torch.func.jacfwd`) of the model's own
`_batch_residual(batch, params)` and `newton_jacobian_batch(batch)` (the latter through a context
manager that substitutes the parameters, `explicit_parameters`).

Physical consistency. The 4 x 4 pseudo-inertia P_b = [[Q_b, c_b], [c_b^T, m_b]] is positive definite
exactly for physical bodies (m > 0, J_d about the centre of mass positive definite, i.e. J positive
definite with the triangle inequality). Its log-Cholesky factor (Rucker & Wensing 2022) P = U U^T,
    U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]],
parameterises exactly the consistent set: m = e^(2 alpha), rho = t, J_d = m U3 U3^T (U3 the upper 3 x 3
block). theta_b = (alpha, d1, d2, d3, s12, s13, s23, t1, t2, t3) is taken in units of the tree (length L:
the median joint offset, mass M: the total mass, time h), and damping as log(d h / (M L^2)), so metres
and millimetres give the same iterates.

Fit. The objective is sum |x|^2 with x = H(pi)^-1 r(pi) per triplet (the one-step prediction error to
first order; a free root's translation rows divided by L): the weighted linear least-squares start
(reweighted 3 times, the scale fixed by sum m = M, each body's pseudo-inertia projected onto the
consistent set), then Levenberg-Marquardt (Marquardt scaling, Nielsen's damping update) in theta with the
exact Jacobian from Y and Hb, stopping on relative decrease. `identify` writes the result into the model.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch

from ...lie import so3

MAX_TRIPLETS = 1000
"""Triplets the regressor is built on (evenly strided over the training set)."""
MOVABLE = {"free": 0, "ball": 1, "universal": 1, "hinge": 3, "weld": 10}
"""Per joint, the inertial parameters of the body the data cannot see (mass that can move onto the parent,
or the world for a pinned root, without changing the Lagrangian): a point mass at a ball or universal
joint; a mass distribution on a hinge's axis line (m, c.a, a^T Q a); the whole body at a weld."""


# ---------------------------------------------------------------------------------------------- packing
def sym6(Q: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) symmetric -> (..., 6): xx, yy, zz, xy, xz, yz."""
    return torch.stack((Q[..., 0, 0], Q[..., 1, 1], Q[..., 2, 2], Q[..., 0, 1], Q[..., 0, 2], Q[..., 1, 2]), -1)


def unsym6(q: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3) symmetric (inverse of `sym6`)."""
    xx, yy, zz, xy, xz, yz = q.unbind(-1)
    return torch.stack(
        (torch.stack((xx, xy, xz), -1), torch.stack((xy, yy, yz), -1), torch.stack((xz, yz, zz), -1)), -2
    )


def to_pi(Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """(J_d (B, 3, 3) about the COM, m (B,), rho (B, 3)) -> pi (B, 10) = (m, c = m rho, sym6(Q)),
    Q = J_d + m rho rho^T (the second moment about the joint)."""
    c = m[:, None] * rho
    Q = Jd + m[:, None, None] * rho[:, :, None] * rho[:, None, :]
    return torch.cat((m[:, None], c, sym6(Q)), -1)


def from_pi(pi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """pi (B, 10) -> (J_d (B, 3, 3), m (B,), rho (B, 3)) (inverse of `to_pi`; m != 0)."""
    m, c, Q = pi[:, 0], pi[:, 1:4], unsym6(pi[:, 4:])
    return Q - c[:, :, None] * c[:, None, :] / m[:, None, None], m, c / m[:, None]


def pseudo_inertia(pi: torch.Tensor) -> torch.Tensor:
    """pi (B, 10) -> P (B, 4, 4) = [[Q, c], [c^T, m]]; positive definite iff the body is physical."""
    m, c, Q = pi[:, 0], pi[:, 1:4], unsym6(pi[:, 4:])
    top = torch.cat((Q, c[:, :, None]), -1)
    bottom = torch.cat((c, m[:, None]), -1)[:, None, :]
    return torch.cat((top, bottom), -2)


def log_cholesky_to_pi(theta: torch.Tensor) -> torch.Tensor:
    """theta (B, 10) = (alpha, d1, d2, d3, s12, s13, s23, t1, t2, t3) -> pi (B, 10) of P = U U^T with
    U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]]:
    m = e^(2 alpha), c = m t, Q = m (U3 U3^T + t t^T). Every theta gives a consistent body."""
    a, d, s, t = theta[:, 0], theta[:, 1:4], theta[:, 4:7], theta[:, 7:10]
    e = torch.exp(d)
    z = torch.zeros_like(a)
    U3 = torch.stack(
        (
            torch.stack((e[:, 0], s[:, 0], s[:, 1]), -1),
            torch.stack((z, e[:, 1], s[:, 2]), -1),
            torch.stack((z, z, e[:, 2]), -1),
        ),
        -2,
    )
    m = torch.exp(2.0 * a)
    S = U3 @ U3.transpose(-1, -2) + t[:, :, None] * t[:, None, :]
    return torch.cat((m[:, None], m[:, None] * t, m[:, None] * sym6(S)), -1)


def pi_to_log_cholesky(pi: torch.Tensor) -> torch.Tensor:
    """Inverse of `log_cholesky_to_pi` for consistent pi (B, 10): alpha = log(m)/2, t = c/m, U3 the upper
    Cholesky factor of J_d/m (the lower factor of the index-reversed matrix, reversed back)."""
    Jd, m, rho = from_pi(pi)
    A = Jd / m[:, None, None]
    A = 0.5 * (A + A.transpose(-1, -2))
    L = torch.linalg.cholesky(A.flip(-1, -2))
    U3 = L.flip(-1, -2)  # upper triangular, U3 U3^T = A
    d = torch.log(U3.diagonal(dim1=-2, dim2=-1))
    s = torch.stack((U3[:, 0, 1], U3[:, 0, 2], U3[:, 1, 2]), -1)
    return torch.cat((0.5 * torch.log(m)[:, None], d, s, rho), -1)


def project_consistent(pi: torch.Tensor, floor: float = 1e-3) -> tuple[torch.Tensor, list[int]]:
    """Each body's pseudo-inertia (B, 4, 4) projected onto the consistent set: its eigenvalues raised to
    floor * its largest (Frobenius-nearest positive definite matrix with that margin). pi in units where
    the bodies' entries are O(1) (`Scales`). Returns (pi (B, 10), the bodies changed)."""
    P = pseudo_inertia(pi)
    P = 0.5 * (P + P.transpose(-1, -2))
    lam, V = torch.linalg.eigh(P)
    low = floor * lam.abs().amax(-1, keepdim=True)
    lam2 = torch.maximum(lam, low)
    changed = [int(b) for b in torch.nonzero((lam2 != lam).any(-1)).flatten()]
    P2 = V @ torch.diag_embed(lam2) @ V.transpose(-1, -2)
    return torch.cat((P2[:, 3, 3:4], P2[:, :3, 3], sym6(P2[:, :3, :3])), -1), changed


# ---------------------------------------------------------------------------------------------- model access
@dataclass
class Scales:
    """Units of the tree: length L (median non-zero joint offset), mass M (the total mass the fit keeps),
    time h. Body parameters in these units are O(1): m / M, c / (M L), Q / (M L^2), d h / (M L^2)."""

    L: float
    M: float
    h: float

    def body(self, like: torch.Tensor) -> torch.Tensor:
        """(10,): the unit of each entry of a body's pi."""
        M, L = self.M, self.L
        return torch.tensor([M] + [M * L] * 3 + [M * L * L] * 6, dtype=like.dtype, device=like.device)

    @property
    def damping(self) -> float:
        return self.M * self.L * self.L / self.h


def _geodesic(R_pred: torch.Tensor, R_true: torch.Tensor) -> torch.Tensor:
    """|log(R_pred^T R_true)| per rotation (..., B) (the metric `evaluation.metrics.geodesic_error` reports)."""
    return so3.geodesic_distance(so3.project(R_pred), R_true)


def tree_length(tree: Any) -> float:
    """The median non-zero joint offset of a tree (1.0 when there is none)."""
    lengths = sorted(math.sqrt(sum(x * x for x in o)) for o in tree.offsets)
    positive = [x for x in lengths if x > 0]
    return float(positive[(len(positive) - 1) // 2]) if positive else 1.0  # torch's median: the lower one


def damping_of(model: Any) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(the per-DoF damping d (n,), the mask (n,) of the damped DoF), or (None, None) without per-DoF damping."""
    damper = getattr(model, "dof_damper", None)
    if damper is None:
        return None, None
    return damper.coefficients().detach(), damper.damped.clone()


@torch.no_grad()
def write_parameters(
    model: Any, Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor, d: torch.Tensor | None, floor: float = 1e-9
) -> None:
    """Set the model's inertia (J = tr(J_d) I - J_d), mass, centre of mass and per-DoF damping; the body
    must be consistent (m > 0; J_d's eigenvalues are raised to floor * their largest)."""
    eye = torch.eye(3, dtype=Jd.dtype, device=Jd.device)
    mu, V = torch.linalg.eigh(0.5 * (Jd + Jd.transpose(-1, -2)))
    mu = mu.clamp_min(floor * mu.amax(-1, keepdim=True))  # J's triangle inequality strictly, after rounding
    Jd = V @ torch.diag_embed(mu) @ V.transpose(-1, -2)
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye - Jd
    model.inertia.set_J(0.5 * (J + J.transpose(-1, -2)))
    model.mass.set_value(m)
    model.rho.copy_(rho)
    if d is not None and getattr(model, "dof_damper", None) is not None:
        model.dof_damper.set_coefficients(d.clamp_min(0.0))


@contextlib.contextmanager
def explicit_parameters(
    model: Any, Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor, d: torch.Tensor | None
) -> Iterator[None]:
    """Within the block the model's `_params()` returns (J_d, m, rho) and its per-DoF damping d (n,):
    tensors that may carry forward-mode tangents (the hook `newton_jacobian_batch` lacks)."""
    model._params = lambda: (Jd, m, rho)
    damper = getattr(model, "dof_damper", None)
    if damper is not None and d is not None:
        damper.coefficients = lambda: d
    try:
        yield
    finally:
        del model._params
        if damper is not None and d is not None:
            del damper.coefficients


# ---------------------------------------------------------------------------------------------- the linear problem
@dataclass
class LinearProblem:
    """r(pi) = Y pi + r0 (N, n) and H(pi) = H0 + Hb pi (N, n, n) over N triplets of n residual rows.
    pi (P,) = (per body pi_b (10), then the damped DoF's coefficients (k,)). unit (n,): row weights of
    x = unit * H^-1 r (1/L on a free root's translation rows)."""

    Y: torch.Tensor  # (N, n, P)
    r0: torch.Tensor  # (N, n)
    Hb: torch.Tensor  # (N, n, n, P)
    H0: torch.Tensor  # (N, n, n)
    unit: torch.Tensor  # (n,)
    B: int
    damped: torch.Tensor | None  # (n,) bool
    scales: Scales

    @property
    def P(self) -> int:
        return self.Y.shape[-1]

    def split(self, pi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """pi (P,) -> (J_d, m, rho, d (n,) or None)."""
        Jd, m, rho = from_pi(pi[: 10 * self.B].reshape(self.B, 10))
        return Jd, m, rho, self.full_damping(pi[10 * self.B :])

    def full_damping(self, dk: torch.Tensor) -> torch.Tensor | None:
        """The damped DoF's coefficients dk (k,) -> d (n,) (0 on the undamped DoF), or None."""
        return None if self.damped is None else _spread(self.damped, dk)

    def residual(self, pi: torch.Tensor) -> torch.Tensor:
        """r (N, n) = Y pi + r0."""
        return self.Y @ pi + self.r0

    def jacobian(self, pi: torch.Tensor) -> torch.Tensor:
        """H (N, n, n) = H0 + Hb pi."""
        return self.Hb @ pi + self.H0

    def prediction_error(self, pi: torch.Tensor) -> torch.Tensor:
        """x (N, n) = unit * H^-1 r: the one-step error to first order (radians; root translation / L)."""
        return self.unit * torch.linalg.solve(self.jacobian(pi), self.residual(pi)[..., None])[..., 0]

    def error_and_jacobian(self, pi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x (N n,), dx/dpi (N n, P)): dx/dpi_j = unit * H^-1 (Y_j - Hb_j H^-1 r)."""
        H = self.jacobian(pi)
        LU, piv = torch.linalg.lu_factor(H)
        xr = torch.linalg.lu_solve(LU, piv, self.residual(pi)[..., None])[..., 0]
        rhs = self.Y - torch.einsum("nabj,nb->naj", self.Hb, xr)
        D = torch.linalg.lu_solve(LU, piv, rhs)
        return (self.unit * xr).reshape(-1), (self.unit[:, None] * D).reshape(-1, self.P)


def _spread(mask: torch.Tensor, dk: torch.Tensor) -> torch.Tensor:
    """dk (k,) onto the True entries of mask (n,), zeros elsewhere (a product: forward-mode friendly)."""
    E = torch.eye(mask.shape[0], dtype=dk.dtype, device=dk.device)[:, mask.to(dk.device)]
    return E @ dk


def _strided(n: int, k: int, device) -> torch.Tensor:
    k = min(n, k)
    return ((torch.arange(k, device=device) * (n - 1) + (k - 1) // 2) // max(k - 1, 1)).unique()


def linear_problem(
    model: Any, triplets: Any, total_mass: float | None = None, max_triplets: int = MAX_TRIPLETS
) -> tuple[LinearProblem, torch.Tensor]:
    """The exact linear structure of the model's residual and Newton Jacobian over (a strided subset of)
    `triplets` (`ArticulatedTriplets`), by forward-mode autodiff. Returns (the problem, pi of the model's
    current parameters (P,))."""
    if getattr(triplets, "A_next", None) is None:
        triplets.enable_jacobian()
    idx = _strided(triplets.n, max_triplets, triplets.cur.R.device)
    batch = triplets.batch(idx, torch.Generator().manual_seed(0), 0)
    B = model.tree.n_bodies
    with torch.no_grad():
        Jd0, m0, rho0 = (t.detach() for t in model._params())
    d0, damped = damping_of(model)
    pieces = [to_pi(Jd0, m0, rho0).reshape(-1)]
    if d0 is not None and damped is not None:
        pieces.append(d0[damped])
    pi0 = torch.cat(pieces)

    def parts(pi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        Jd, m, rho = from_pi(pi[: 10 * B].reshape(B, 10))
        d = None if damped is None else _spread(damped, pi[10 * B :])
        return Jd, m, rho, d

    def residual(pi: torch.Tensor) -> torch.Tensor:
        return model._batch_residual(batch, parts(pi))

    def newton(pi: torch.Tensor) -> torch.Tensor:
        Jd, m, rho, d = parts(pi)
        with explicit_parameters(model, Jd, m, rho, d):
            return model.newton_jacobian_batch(batch)

    with torch.no_grad():
        Y = torch.func.jacfwd(residual)(pi0).detach()  # (N, n, P)
        Hb = torch.func.jacfwd(newton)(pi0).detach()  # (N, n, n, P)
        r0 = residual(pi0).detach() - Y @ pi0
        H0 = newton(pi0).detach() - Hb @ pi0
    L = tree_length(model.tree)
    unit = torch.ones(Y.shape[1], dtype=Y.dtype, device=Y.device)
    if model.tree.free_root:
        unit[3:6] = 1.0 / L
    M = float(m0.sum()) if total_mass is None else float(total_mass)
    prob = LinearProblem(Y, r0, Hb, H0, unit, B, damped, Scales(L, M, float(model.h)))
    return prob, pi0


# ---------------------------------------------------------------------------------------------- identifiability
PINNED_ROOT = {"ball": (1, 4), "universal": (1, 4), "hinge": (7, 9), "weld": (10, 10)}
"""A pinned root's parameters the data cannot see (with, without a uniform gravity): its joint is fixed, so
a ball or universal root shows its inertia about the joint and (through gravity) its first moment; a hinge
root only its moment about the axis and (through gravity) the first moment across the axis."""


def expected_gauge(tree: Any, gravity: bool) -> int:
    """The exact null dimension of the regressor from the joints: per non-root body the parameters that
    can move onto its parent (`MOVABLE`), and a pinned root's invisible ones (`PINNED_ROOT`). The overall
    scale is not counted (it is a null direction of Y only for data the model fits exactly)."""
    kinds = list(tree.joint_kinds)
    root = 0 if tree.free_root else PINNED_ROOT[kinds[0]][0 if gravity else 1]
    return root + sum(MOVABLE[k] for k in kinds[1:])


def _normalise_columns(X: torch.Tensor, floor: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """(X / n, n): columns scaled to unit norm, norms floored at floor * the largest (a column that is
    rounding noise, e.g. a pinned root's mass, stays negligible instead of becoming a unit column)."""
    n = X.norm(dim=0)
    n = n.clamp_min(floor * float(n.max()))
    return X / n, n


def base_parameters(tree: Any, Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor) -> dict[str, torch.Tensor]:
    """The combinations a ball/universal-joint tree's data determine, regrouped from the leaves up with
    each child's subtree mass M_c as a point mass at its joint offset o_c (parent frame):
    subtree_mass (B,) M_b = m_b + sum_c M_c (only the root's is determined, and only up to the scale);
    first_moment (B, 3) m_b rho_b + sum_c M_c o_c; inertia_about_joint (B, 3, 3)
    J_b + m_b (|rho_b|^2 I - rho_b rho_b^T) + sum_c M_c (|o_c|^2 I - o_c o_c^T). (A hinge child also moves
    its first moment along the axis and its second moment along the axis onto the parent.)"""
    B = tree.n_bodies
    o = torch.tensor(tree.offsets, dtype=Jd.dtype, device=Jd.device)
    eye = torch.eye(3, dtype=Jd.dtype, device=Jd.device)
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye - Jd
    sub = m.clone()
    first = m[:, None] * rho
    inert = J + m[:, None, None] * ((rho * rho).sum(-1)[:, None, None] * eye - rho[:, :, None] * rho[:, None, :])
    sub_l, first_l, inert_l = list(sub.unbind(0)), list(first.unbind(0)), list(inert.unbind(0))
    for c in range(B - 1, 0, -1):  # parents come first: children are done before their parents
        p = tree.parents[c]
        oc = o[c]
        sub_l[p] = sub_l[p] + sub_l[c]
        first_l[p] = first_l[p] + sub_l[c] * oc
        inert_l[p] = inert_l[p] + sub_l[c] * ((oc @ oc) * eye - torch.outer(oc, oc))
    return {
        "subtree_mass": torch.stack(sub_l),
        "first_moment": torch.stack(first_l),
        "inertia_about_joint": torch.stack(inert_l),
    }


def _ball_gauge_directions(tree: Any, P: int, dtype, device) -> torch.Tensor:
    """(B-1, P): for each non-root body c, the direction moving unit mass from c onto its parent as a
    point mass at the joint offset o_c (pi_c.m -1; parent: m +1, c + o_c, Q + o_c o_c^T)."""
    o = torch.tensor(tree.offsets, dtype=dtype, device=device)
    out = []
    for c in range(1, tree.n_bodies):
        p = tree.parents[c]
        v = torch.zeros(P, dtype=dtype, device=device)
        v[10 * c] = -1.0
        v[10 * p] = 1.0
        v[10 * p + 1 : 10 * p + 4] = o[c]
        v[10 * p + 4 : 10 * p + 10] = sym6(torch.outer(o[c], o[c]))
        out.append(v)
    return torch.stack(out) if out else torch.zeros(0, P, dtype=dtype, device=device)


def _column_units(prob: LinearProblem, like: torch.Tensor) -> torch.Tensor:
    """(P,): the unit of each column of pi (`Scales`)."""
    body = prob.scales.body(like).repeat(prob.B)
    k = prob.P - 10 * prob.B
    return torch.cat((body, torch.full((k,), prob.scales.damping, dtype=like.dtype, device=like.device)))


def identifiability(model: Any, triplets: Any, tol: float = 1e-9, prob: LinearProblem | None = None) -> dict:
    """What the data determine, at the model's current parameters: the SVD of the prediction-weighted
    regressor X = unit * H^-1 Y (rows: every triplet's residual components; columns in the tree's units,
    then scaled to unit norm). Returns a JSON-ready dict: n_params, rank (singular values above tol * the
    largest), null_dimension, expected_gauge (from the joints, `expected_gauge`), scale_singular_value (the
    smallest singular value above the gauge, relative: the overall scale, near zero when the model fits
    the data), singular_values (relative, the smallest 12), ball_gauge_in_null_space (for every non-root
    ball/universal body, |X v| / (|X| |v|) of the analytic gauge direction: ~1e-16 when it is exact), and
    base_parameters of the current model over its total mass (`base_parameters`)."""
    if prob is None:
        prob, pi = linear_problem(model, triplets)
    else:
        with torch.no_grad():
            Jd0, m0, rho0 = (t.detach() for t in model._params())
        d0, damped = damping_of(model)
        pi = to_pi(Jd0, m0, rho0).reshape(-1)
        if d0 is not None and damped is not None:
            pi = torch.cat((pi, d0[damped]))
    H = prob.jacobian(pi)
    X = (prob.unit[:, None] * torch.linalg.solve(H, prob.Y)).reshape(-1, prob.P)
    cu = _column_units(prob, X)
    Xu = X * cu
    Xs, s = _normalise_columns(Xu)
    S = torch.linalg.svdvals(Xs)
    rel = S / S[0]
    rank = int((rel > tol).sum())
    gauge = expected_gauge(model.tree, getattr(model, "potential_world", None) is not None)
    k_scale = prob.P - gauge - 1
    V = _ball_gauge_directions(model.tree, prob.P, X.dtype, X.device)
    in_null = []
    Xn = float(torch.linalg.matrix_norm(Xs, ord=2))
    for c, v in zip(range(1, model.tree.n_bodies), V):
        if model.tree.joint_kinds[c] in ("ball", "universal"):
            vs = v / cu * s  # in the scaled columns' coordinates
            in_null.append({"body": c, "relative_residual": float((Xs @ vs).norm() / (Xn * vs.norm()))})
    Jd, m, rho, _ = prob.split(pi)
    base = base_parameters(model.tree, Jd, m, rho)
    M = float(m.sum())
    return {
        "n_params": prob.P,
        "rank": rank,
        "null_dimension": prob.P - rank,
        "expected_gauge": gauge,
        "expected_rank": prob.P - gauge,
        "scale_singular_value": float(rel[k_scale]) if 0 <= k_scale < len(rel) else None,
        "singular_values": [float(x) for x in rel[-24:]],
        "ball_gauge_in_null_space": in_null,
        "base_parameters_over_total_mass": {
            "total_mass": M,
            "first_moment": (base["first_moment"] / M).tolist(),
            "inertia_about_joint": (base["inertia_about_joint"] / M).tolist(),
        },
    }


# ---------------------------------------------------------------------------------------------- the fit
@dataclass
class IdentificationResult:
    """What `identify` did: seconds per stage, the first-order one-step error (RMS of x, radians) at the
    start, after each least-squares pass and each accepted LM step, the regressor's rank, the bodies the
    least-squares start had to project, and the fitted parameters (also written into the model)."""

    seconds: dict[str, float] = field(default_factory=dict)
    start_rms: float = float("nan")
    ls_rms: list[float] = field(default_factory=list)
    lm_rms: list[float] = field(default_factory=list)
    lm_iterations: int = 0
    rank: int = 0
    n_params: int = 0
    projected: list[int] = field(default_factory=list)
    started_from: str = ""
    stop: str = ""
    Jd: torch.Tensor | None = None
    m: torch.Tensor | None = None
    rho: torch.Tensor | None = None
    d: torch.Tensor | None = None

    def line(self) -> str:
        ls = " -> ".join(f"{x:.3g}" for x in self.ls_rms)
        lm = f"{self.lm_rms[-1]:.3g}" if self.lm_rms else "-"
        return (
            f"identification: {self.seconds.get('total', 0.0):.1f} s; one-step error (first order) "
            f"{self.start_rms:.3g} "
            f"-> least squares {ls} -> LM {lm} ({self.lm_iterations} iterations, {self.stop}; started from "
            f"{self.started_from}); rank {self.rank} of {self.n_params}"
            + (f"; projected bodies {self.projected}" if self.projected else "")
        )

    def as_dict(self) -> dict:
        return {
            "seconds": self.seconds,
            "start_rms": self.start_rms,
            "least_squares_rms": self.ls_rms,
            "lm_rms": self.lm_rms,
            "lm_iterations": self.lm_iterations,
            "rank": self.rank,
            "n_params": self.n_params,
            "projected_bodies": self.projected,
            "started_from": self.started_from,
            "stop": self.stop,
        }


class _Theta:
    """theta (p,) = per body the log-Cholesky parameters in the tree's units (B x 10), then the damped
    DoF's log(d h / (M L^2)) -> pi (P,) in physical units."""

    def __init__(self, prob: LinearProblem, like: torch.Tensor):
        self.prob = prob
        self.bu = prob.scales.body(like)
        self.du = prob.scales.damping
        self.B = prob.B

    def pi(self, theta: torch.Tensor) -> torch.Tensor:
        body = log_cholesky_to_pi(theta[: 10 * self.B].reshape(self.B, 10)) * self.bu
        return torch.cat((body.reshape(-1), self.du * torch.exp(theta[10 * self.B :])))

    def theta(self, pi: torch.Tensor, floor: float = 1e-9) -> torch.Tensor:
        body = pi_to_log_cholesky(pi[: 10 * self.B].reshape(self.B, 10) / self.bu)
        dk = (pi[10 * self.B :] / self.du).clamp_min(floor)
        return torch.cat((body.reshape(-1), torch.log(dk)))


def _weighted_ls(prob: LinearProblem, pi_w: torch.Tensor, pi_ref: torch.Tensor, ridge: float = 1e-8) -> torch.Tensor:
    """min |unit H(pi_w)^-1 (Y pi + r0)|^2 + ridge |pi - pi_ref|^2 (columns in the tree's units, then
    unit norm) subject to sum_b m_b = M. Returns pi (P,)."""
    H = prob.jacobian(pi_w)
    LU, piv = torch.linalg.lu_factor(H)
    X = (prob.unit[:, None] * torch.linalg.lu_solve(LU, piv, prob.Y)).reshape(-1, prob.P)
    x0 = (prob.unit * torch.linalg.lu_solve(LU, piv, prob.r0[..., None])[..., 0]).reshape(-1)
    s = _column_units(prob, X)
    Xs, n = _normalise_columns(X * s)
    A = Xs.T @ Xs
    lam = ridge * float(A.diagonal().mean())
    P = prob.P
    eye = torch.eye(P, dtype=X.dtype, device=X.device)
    rhs = -(Xs.T @ x0) + lam * (pi_ref / s * n)
    e = torch.zeros(P, dtype=X.dtype, device=X.device)
    e[0 : 10 * prob.B : 10] = 1.0
    es = e * s / n  # the constraint in scaled coordinates: sum m = es . y
    K = torch.zeros(P + 1, P + 1, dtype=X.dtype, device=X.device)
    K[:P, :P] = A + lam * eye
    K[:P, P] = es
    K[P, :P] = es
    sol = torch.linalg.solve(K, torch.cat((rhs, rhs.new_tensor([prob.scales.M]))))
    return sol[:P] * s / n


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt())


def _consistent_pi(prob: LinearProblem, pi: torch.Tensor, floor_d: float = 1e-9) -> tuple[torch.Tensor, list[int]]:
    """pi projected onto the consistent set in the tree's units (bodies) and d >= floor (damping)."""
    bu = prob.scales.body(pi)
    body, changed = project_consistent(pi[: 10 * prob.B].reshape(prob.B, 10) / bu)
    dk = pi[10 * prob.B :].clamp_min(floor_d * prob.scales.damping)
    return torch.cat(((body * bu).reshape(-1), dk)), changed


def levenberg_marquardt(
    f: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    theta: torch.Tensor,
    iterations: int = 30,
    ftol: float = 1e-6,
    log: Callable[[str], Any] | None = None,
    prior: float = 0.0,
) -> tuple[torch.Tensor, list[float], int, str]:
    """Minimise |x(theta)|^2 + w^2 |theta - theta_0|^2 from theta_0 (p,); f(theta) -> (x (R,), dx/dtheta
    (R, p)); w^2 = prior * the mean diagonal of J^T J at theta_0 (a pull too weak to move what the data
    determine, which keeps the gauge directions, which they do not, where they started). Marquardt scaling
    (the diagonal of J^T J, floored), Nielsen's damping update; stops after `iterations` Jacobians, when
    an accepted step lowers the objective by less than ftol relative, or when the damping exceeds 1e12.
    Returns (theta, RMS of x after each accepted step, Jacobians evaluated, why it stopped)."""
    theta0 = theta.clone()
    x0, J0 = f(theta)
    w = math.sqrt(prior * float((J0 * J0).sum(0).mean()))
    eye = w * torch.eye(theta.shape[0], dtype=theta.dtype, device=theta.device)

    def g_full(th: torch.Tensor, pair=None) -> tuple[torch.Tensor, torch.Tensor]:
        xx, JJ = f(th) if pair is None else pair
        return torch.cat((xx, w * (th - theta0))), torch.cat((JJ, eye))

    n_data = x0.numel()
    x, J = g_full(theta, (x0, J0))
    F = float(x @ x)
    lam, nu = 1e-3, 2.0
    hist: list[float] = []
    evals = 1
    stop = "iterations"
    while evals <= iterations:
        A = J.T @ J
        g = J.T @ x
        D = A.diagonal().clamp_min(1e-12 * float(A.diagonal().max()))
        try:
            step = -torch.linalg.solve(A + lam * torch.diag(D), g)
        except torch.linalg.LinAlgError:
            lam, nu = lam * nu, nu * 2
            continue
        pred = float(-(step @ g) - 0.5 * step @ (A @ step))  # predicted decrease of |x|^2 / 2
        cand = theta + step
        try:
            x2, J2 = g_full(cand)
            F2 = float(x2 @ x2)
        except (torch.linalg.LinAlgError, RuntimeError):
            F2 = float("inf")
        if not math.isfinite(F2):
            F2 = float("inf")
        gain = (0.5 * (F - F2)) / pred if pred > 0 else -1.0
        if gain > 0:
            rel = (F - F2) / max(F, 1e-300)
            theta, x, J, F = cand, x2, J2, F2
            evals += 1
            hist.append(float(x[:n_data].pow(2).mean().sqrt()))
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            nu = 2.0
            if log is not None:
                log(f"  LM {evals - 1:3d}: one-step error (first order) {hist[-1]:.4g}, damping {lam:.2g}")
            if rel < ftol:
                stop = "converged"
                break
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e12:
                stop = "no further decrease"
                break
    return theta, hist, evals, stop


def identify(
    model: Any,
    triplets: Any,
    total_mass: float | None = None,
    weighting: str = "newton",
    iterations: int = 30,
    log: Callable[[str], Any] | None = print,
    passes: int = 3,
    max_triplets: int = MAX_TRIPLETS,
    epsilon: float | None = None,
) -> IdentificationResult:
    """Identify the articulated `model`'s inertial parameters and per-DoF damping from `triplets`
    (`ArticulatedTriplets`) and write them into the model (module docstring).

    total_mass: the scale (sum_b m_b) the data cannot see; None: model.total_mass (dataset.total_mass)
    when set, else the model's current total. weighting: "newton" (rows H^-1 r: the one-step error to
    first order, H at the current iterate) or "jacobi" (rows r_i / |H_ii| with H at the start, fixed: a
    linear problem). iterations: LM Jacobians at most (0: the least-squares start only). epsilon: when
    given and no total mass was, every parameter is then scaled by one factor (no prediction changes:
    the DEL equations are homogeneous when nothing else is learned) so that every body's mixed-Hessian
    block has log|det| >= epsilon + 1 on the triplets (the regularity term inactive where training
    continues). Returns an `IdentificationResult`."""
    if weighting not in ("newton", "jacobi"):
        raise ValueError(f"weighting={weighting!r}: 'newton' or 'jacobi'")
    say = log if log is not None else (lambda s: None)
    res = IdentificationResult()
    t0 = time.perf_counter()
    if total_mass is None:
        total_mass = getattr(model, "total_mass", None)
    prob, pi0 = linear_problem(model, triplets, total_mass, max_triplets)
    res.n_params = prob.P
    M = prob.scales.M
    with torch.no_grad():
        pi0 = pi0 * (M / float(pi0[0 : 10 * prob.B : 10].sum()))  # the same model at the fit's scale
    if weighting == "jacobi":
        Hd = prob.jacobian(pi0).diagonal(dim1=-2, dim2=-1).abs().clamp_min(1e-300)  # (N, n)
        w = prob.unit / Hd
        eye = torch.eye(Hd.shape[-1], dtype=Hd.dtype, device=Hd.device)
        # H := diag(1 / w) exactly, so x = w r: the same code with a constant Jacobian
        prob = LinearProblem(
            prob.Y,
            prob.r0,
            torch.zeros_like(prob.Hb[..., :1]).expand_as(prob.Hb),
            eye / w[:, None, :] * 1.0,
            torch.ones_like(prob.unit),
            prob.B,
            prob.damped,
            prob.scales,
        )
    res.seconds["regressor"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    start_rms = _rms(prob.prediction_error(pi0))
    res.start_rms = start_rms
    say(
        f"identification: {prob.P} parameters, {prob.Y.shape[0]} triplets x {prob.Y.shape[1]} rows; "
        f"start {start_rms:.4g}"
    )
    # weighted least squares, reweighted from the (consistent) start
    best_pi, best_rms, best_from = pi0, start_rms, "the model's parameters"
    pi_w = pi0
    for k in range(passes):
        pi_ls = _weighted_ls(prob, pi_w, pi0)
        pi_c, changed = _consistent_pi(prob, pi_ls)
        rms = _rms(prob.prediction_error(pi_c))
        res.ls_rms.append(rms)
        say(f"  least squares pass {k + 1}: {rms:.4g} (projected bodies {changed})")
        if rms < best_rms:
            best_pi, best_rms, best_from = pi_c, rms, f"least-squares pass {k + 1}"
            res.projected = changed
        pi_w = pi_c
    res.started_from = best_from
    res.seconds["least_squares"] = time.perf_counter() - t1
    # rank of the regressor at the start point (columns in the tree's units, unit norm)
    H = prob.jacobian(best_pi)
    X = (prob.unit[:, None] * torch.linalg.solve(H, prob.Y)).reshape(-1, prob.P) * _column_units(prob, prob.Y)
    X = _normalise_columns(X)[0]
    res.rank = int(torch.linalg.matrix_rank(X, rtol=1e-9))
    t2 = time.perf_counter()
    tp = _Theta(prob, pi0)
    theta = tp.theta(best_pi)
    if iterations > 0:
        jac_pi = torch.func.jacfwd(tp.pi)

        def f(th: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            pi = tp.pi(th)
            x, Jx = prob.error_and_jacobian(pi)
            return x, Jx @ jac_pi(th)

        # LM from the best least-squares pass and from the model's own (interior) start: a projected
        # least-squares point can sit near the consistent set's boundary, where LM may stall (pinned trees)
        starts = [(best_from, best_pi)] + (
            [("the model's parameters", pi0)] if best_from != "the model's parameters" else []
        )
        best_final = float("inf")
        for name, pi_s in starts:
            th, hist, evals, stop = levenberg_marquardt(f, tp.theta(pi_s), iterations, log=say)
            final = hist[-1] if hist else _rms(prob.prediction_error(pi_s))
            say(f"  LM from {name}: {final:.4g} ({evals} Jacobians, {stop})")
            if final < best_final:
                best_final, theta = final, th
                res.lm_rms, res.lm_iterations, res.stop, res.started_from = hist, evals, stop, name
    res.seconds["levenberg_marquardt"] = time.perf_counter() - t2
    pi = tp.pi(theta)
    pi = torch.cat(
        (
            pi[: 10 * prob.B] * (M / float(pi[0 : 10 * prob.B : 10].sum())),
            pi[10 * prob.B :] * (M / float(pi[0 : 10 * prob.B : 10].sum())),
        )
    )
    Jd, m, rho, d = prob.split(pi)
    write_parameters(model, Jd, m, rho, d)
    if epsilon is not None and total_mass is None:
        with torch.no_grad():
            logdet = model.world_slogdet(
                triplets.inc_next.index(_strided(triplets.n, max_triplets, triplets.cur.R.device))
            )[0]
        low = float(logdet.min())
        if low < epsilon + 1.0:
            grow = math.exp((epsilon + 1.0 - low) / 6.0)
            Jd, m, d = grow * Jd, grow * m, None if d is None else grow * d
            write_parameters(model, Jd, m, rho, d)
    res.Jd, res.m, res.rho, res.d = Jd, m, rho, d
    res.seconds["total"] = time.perf_counter() - t0
    say(res.line())
    return res


# ---------------------------------------------------------------------------------------------- measures
def one_step_ratio(model: Any, truth: Any, tol: float = 1e-5) -> float:
    """Mean geodesic rotation error of the model's teacher-forced one-step predictions over constant
    velocity's, on truth R (T, N+1, B, 3, 3), p (T, N+1, m, 3). tol: the Newton step tolerance (an
    absolute one: 1e-12 makes the figure independent of the length unit)."""
    geodesic_error = _geodesic
    from ...solvers.one_step import constant_velocity_one_step, one_step_predictions
    from ...solvers.options import SolverOptions

    pred, _ = one_step_predictions(model, truth, SolverOptions(tol=tol))
    cv = constant_velocity_one_step(model.G, truth)
    target = truth.index((slice(None), slice(2, None)))
    return float(geodesic_error(pred.R, target.R).mean() / geodesic_error(cv.R, target.R).mean())


def rollout_ratio(model: Any, truth: Any, steps: int = 50) -> float:
    """Mean geodesic rotation error of the model's rollout of `steps` steps from the first two true poses
    over the constant-velocity rollout's (every trajectory of truth, its first steps + 1 poses)."""
    geodesic_error = _geodesic
    from ...solvers.one_step import constant_velocity_rollout
    from ...solvers.options import SolverOptions

    steps = min(steps, truth.R.shape[1] - 1)
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    ro = model.rollout(g0, g1, steps, SolverOptions())
    cv = constant_velocity_rollout(model.G, g0, g1, steps)
    tgt = truth.R[:, 2 : steps + 1]
    return float(geodesic_error(ro.pose.R[:, 2 : steps + 1], tgt).mean() / geodesic_error(cv.R[:, 2:], tgt).mean())


__all__ = [
    "IdentificationResult",
    "LinearProblem",
    "Scales",
    "base_parameters",
    "explicit_parameters",
    "expected_gauge",
    "from_pi",
    "identifiability",
    "identify",
    "levenberg_marquardt",
    "linear_problem",
    "log_cholesky_to_pi",
    "one_step_ratio",
    "pi_to_log_cholesky",
    "project_consistent",
    "pseudo_inertia",
    "rollout_ratio",
    "to_pi",
    "write_parameters",
]
