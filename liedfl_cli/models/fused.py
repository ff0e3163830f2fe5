"""Fused hot paths of LieDFLNN: the same residual, regularity and Newton step as the reference
methods of `models.liedflnn`, computed once and with few kernel calls.

Compute once
    `derive(model)` builds the derived parameters (J_d, m, rho, the constant Rayleigh D) once per
    optimiser step and once per rollout; the reference path rebuilds them in every residual call.
    `IncrementSet` stores the training triplets as what the loss needs, once at load: the summed
    rotational increments A = W_1 + W_2^T (the kinetic residual of a rotation block is linear in
    it), the SE(3) bodies' increments, the velocity estimates, and only the poses that a
    configuration-dependent part (a potential network, a configuration-dependent force) reads.
    Parts without trainable parameters (a known potential or force) are evaluated at load.

Fewer kernels
    Every rotational quantity that is linear in a rotation-like matrix (the kinetic residual
    vee(J_d W^T - W J_d)/h, the mixed Hessian block, the velocity estimate and its Jacobian) is a
    linear map of the 9 entries, built once from J_d (and D) by evaluating the reference formula
    on the 9 basis matrices, then applied to the whole batch as one matrix product. For SO(3)
    bodies with constant Rayleigh damping, the Newton residual and its Jacobian are one product
    each; the Newton step solves 3x3 systems in closed form.

Numbers: equal to the reference path to rounding (tests/test_fused.py checks <= 1e-12 relative).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ..lie import Pose, ProductGroup, so3
from ..lie.tolerances import projects_poses, tol
from ..mechanics import kinetic
from ..mechanics.damping import PerBodySPSD
from ..mechanics.forces import PDControl, RayleighForce, RayleighNonlinearForce, force_jacobian_xi
from ..mechanics.parameterizations import Inertia, SPSDMatrix
from ..mechanics.potentials import left_gradient
from ..solvers import runtime
from ..solvers.newton import NewtonProblem
from . import mlp_derivatives
from .base import TripletSet, oriented_logdet

AFFINE_FORCES = (RayleighNonlinearForce, PDControl)
"""Forces known to be affine in the velocity estimate: F(g, xi) = F(g, 0) + dF/dxi(g) xi."""


# ---------------------------------------------------------------------------- small closed forms
_EXP_TAYLOR = (
    (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880),  # sinc
    (0.5, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),  # cosc
    (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),  # sinc3
)


_CONSTANTS: dict[tuple, dict[str, Any]] = {}


def _constants(dtype: torch.dtype, device: torch.device | None = None) -> dict[str, Any]:
    """Constant tensors of the fused paths, built once per dtype/device."""
    key = (dtype, device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = _build_constants(dtype, device)
    return _CONSTANTS[key]


def _build_constants(dtype: torch.dtype, device: torch.device | None) -> dict[str, Any]:
    eye = torch.eye(3, dtype=dtype, device=device)
    return {
        "eye": eye,
        "basis": torch.eye(9, dtype=dtype, device=device).reshape(9, 3, 3),  # matrix units E_(ij)
        "hat": so3.hat(eye).reshape(3, 9),  # w @ hat = hat(w).flatten(): entries +-1, exact
        "taylor_by_degree": tuple(torch.tensor(_EXP_TAYLOR, dtype=dtype, device=device).T.contiguous()),
        "pair_sums": torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], dtype=dtype, device=device),
    }


def _basis(dtype, device=None) -> torch.Tensor:
    """The 9 matrix units E_(ij), shape (9, 3, 3)."""
    return _constants(dtype, device)["basis"]


def vee2(M: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3): vee(M - M^T) = (M21 - M12, M02 - M20, M10 - M01)."""
    return torch.stack((M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]), -1)


def exp_coefficients(t2: torch.Tensor) -> torch.Tensor:
    """(sinc, cosc, sinc3) of `lie.series` as functions of t^2, stacked on a new last axis.

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


def _split_tangent(G: ProductGroup, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`G.split`, a plain view for SO(3)-only groups."""
    if not G.n_se3:
        return xi.unflatten(-1, (G.n_bodies, 3)), xi.new_zeros(*xi.shape[:-1], 0, 3)
    return G.split(xi)


def group_exp(G: ProductGroup, xi: torch.Tensor) -> Pose:
    """`G.exp` with shared coefficients: R = I + sinc W + cosc W^2, p = (I + cosc W + sinc3 W^2) v."""
    w, v = _split_tangent(G, xi)
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
    """`G.compose` (g h body by body); for SO(3)-only groups just the rotation product."""
    if not G.n_se3:
        return Pose(g.R @ h.R, g.p)
    return G.compose(g, h)


def group_retract(G: ProductGroup, g: Pose, xi: torch.Tensor) -> Pose:
    """g exp(xi) (`G.retract` with `group_exp`)."""
    return compose(G, g, group_exp(G, xi))


def solve_small(J: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(J^{-1} r, singular) for (T, n, n), (T, n): closed-form inverse for n = 3, LU otherwise.

    `singular` marks rows the reference solver (LU) would call singular: exactly zero determinant
    for n = 3 (a zero pivot), LAPACK's info > 0 otherwise."""
    if J.shape[-1] != 3:
        sol, info = torch.linalg.solve_ex(J, r[..., None])
        return sol[..., 0], info > 0
    a, b, c = J[..., 0, :], J[..., 1, :], J[..., 2, :]
    bc, ca, ab = torch.linalg.cross(b, c), torch.linalg.cross(c, a), torch.linalg.cross(a, b)
    det = (a * bc).sum(-1)
    x = (bc * r[..., 0:1] + ca * r[..., 1:2] + ab * r[..., 2:3]) / det[..., None]
    return x, det == 0


# ---------------------------------------------------------------------------- derived parameters
@dataclass
class Derived:
    """Parameters of a LieDFLNN built once: J_d (B, 3, 3), mass (m,), rho (m, 3) and D, the sum
    of the constant Rayleigh matrices (dim, dim), or None without a Rayleigh force."""

    Jd: torch.Tensor
    mass: torch.Tensor
    rho: torch.Tensor
    D: torch.Tensor | None


def inertia_jd(inertia: Inertia) -> torch.Tensor:
    """`Inertia.Jd()` with a hand-written gradient: in scalar arithmetic for a few bodies
    (`_InertiaJdScalar`: a handful of tensor calls instead of ~70), else `_InertiaJd`."""
    if inertia.r.shape[0] <= SCALAR_BODIES and inertia.r.device.type == "cpu":
        return _InertiaJdScalar.apply(inertia.r, inertia.abc)
    return _InertiaJd.apply(inertia.r, inertia.abc)


SCALAR_BODIES = 4  # up to this many bodies J_d is built in Python scalars (per-call cost ~ a few kernels)


def _exp_coefficients_scalar(t2: float) -> tuple[float, float, float]:
    """(sinc, cosc, sinc3) of t^2 as Python floats: `exp_coefficients` for one angle."""
    if t2 < tol(torch.float64, "taylor") ** 2:
        out = []
        for coeffs in _EXP_TAYLOR:
            acc = coeffs[4]
            for c in coeffs[3::-1]:
                acc = acc * t2 + c
            out.append(acc)
        return out[0], out[1], out[2]
    if not math.isfinite(t2):  # huge weights: a non-finite result (reported by the caller), as torch.sin gives
        return math.nan, math.nan, math.nan
    t = math.sqrt(t2)
    sin_t, half = math.sin(t), math.sin(0.5 * t)
    return sin_t / t, 2.0 * (half * half) / t2, (t - sin_t) / (t2 * t)


def _exp(x: float) -> float:
    """math.exp, but inf past float64's range (as torch.exp): huge weights give a non-finite loss or
    prediction that the caller reports, not an OverflowError."""
    return math.exp(x) if x < 709.0 else math.inf


def _matmul3(A, B):
    return [[A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j] for j in range(3)] for i in range(3)]


def _transpose3(A):
    return [[A[j][i] for j in range(3)] for i in range(3)]


def _hat3(w):
    x, y, z = w
    return [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]


class _InertiaJdScalar(torch.autograd.Function):
    """`_InertiaJd` computed body by body in Python floats (same formulas, float64 rounding)."""

    @staticmethod
    def forward(ctx, r, abc):
        rs, abcs = r.tolist(), abc.tolist()
        saved, out = [], []
        for w, (a, b, c) in zip(rs, abcs):
            e = (_exp(a), _exp(b), _exp(c))
            d = (e[0] + e[1], e[0] + e[2], e[1] + e[2])
            s1, s2, s3 = _exp_coefficients_scalar(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
            K = _hat3(w)
            K2 = _matmul3(K, K)
            R = [[(i == j) + s1 * K[i][j] + s2 * K2[i][j] for j in range(3)] for i in range(3)]
            half = 0.5 * (d[0] + d[1] + d[2])
            J = [[sum(R[i][k] * d[k] * R[j][k] for k in range(3)) for j in range(3)] for i in range(3)]
            out.append([[half * (i == j) - J[i][j] for j in range(3)] for i in range(3)])
            saved.append((e, d, s2, s3, K, K2, R))
        ctx.saved = saved
        return torch.tensor(out, dtype=r.dtype, device=r.device)

    @staticmethod
    def backward(ctx, G):
        dr_all, dabc_all = [], []
        for (e, d, s2, s3, K, K2, R), Gb in zip(ctx.saved, G.tolist()):
            trG = Gb[0][0] + Gb[1][1] + Gb[2][2]
            RtGR = _matmul3(_transpose3(R), _matmul3(Gb, R))
            dd = [0.5 * trG - RtGR[k][k] for k in range(3)]
            dabc_all.append([(dd[0] + dd[1]) * e[0], (dd[0] + dd[2]) * e[1], (dd[1] + dd[2]) * e[2]])
            S = [[Gb[i][j] + Gb[j][i] for j in range(3)] for i in range(3)]
            SR = _matmul3(S, R)
            M = _matmul3(_transpose3(R), [[-SR[i][k] * d[k] for k in range(3)] for i in range(3)])
            v = (M[2][1] - M[1][2], M[0][2] - M[2][0], M[1][0] - M[0][1])
            Jl = [[(i == j) + s2 * K[i][j] + s3 * K2[i][j] for j in range(3)] for i in range(3)]
            dr_all.append([Jl[i][0] * v[0] + Jl[i][1] * v[1] + Jl[i][2] * v[2] for i in range(3)])
        opts = {"dtype": G.dtype, "device": G.device}
        return torch.tensor(dr_all, **opts), torch.tensor(dabc_all, **opts)


class _InertiaJd(torch.autograd.Function):
    """J_d(r, abc) = tr(J)/2 I - J, J = R diag(d) R^T, R = exp(hat(r)), d = (e^a + e^b, e^a + e^c,
    e^b + e^c) (`Inertia`), with shared exp coefficients. Gradient, for G = dL/dJ_d:
    dL/dd_k = tr(G)/2 - (R^T G R)_kk, dL/dR = -(G + G^T) R diag(d), and through R = exp(hat(r)),
    dL/dr = J_l(r) vee(R^T dL/dR - (R^T dL/dR)^T) with J_l = I + cosc hat(r) + sinc3 hat(r)^2."""

    @staticmethod
    def forward(ctx, r, abc):
        const = _constants(r.dtype, r.device)
        eye = const["eye"]
        e = torch.exp(abc)
        d = e @ const["pair_sums"]  # (B, 3)
        # c and K saved as fresh tensors, not views: torch.compile refuses to save a view of
        # an intermediate from an autograd.Function (InternalTorchDynamoError on Exp 4's loss)
        c = exp_coefficients((r * r).sum(-1)).unsqueeze(-2).unsqueeze(-2).clone()
        K = (r @ const["hat"]).unflatten(-1, (3, 3)).clone()
        K2 = K @ K
        Rt = eye + c[..., 0] * K + c[..., 1] * K2
        J = (Rt * d[..., None, :]) @ Rt.transpose(-1, -2)
        ctx.save_for_backward(e, d, c, K, K2, Rt)
        return (0.5 * d.sum(-1))[..., None, None] * eye - J

    @staticmethod
    def backward(ctx, G):
        e, d, c, K, K2, Rt = ctx.saved_tensors
        const = _constants(G.dtype, G.device)
        trG = G.diagonal(dim1=-2, dim2=-1).sum(-1)
        RtGR = Rt.transpose(-1, -2) @ G @ Rt
        dd = 0.5 * trG[..., None] - RtGR.diagonal(dim1=-2, dim2=-1)
        dabc = (dd @ const["pair_sums"].T) * e
        dR = -((G + G.transpose(-1, -2)) @ Rt) * d[..., None, :]
        M = Rt.transpose(-1, -2) @ dR
        Jl = const["eye"] + c[..., 1] * K + c[..., 2] * K2
        dr = (Jl @ vee2(M)[..., None])[..., 0]
        return dr, dabc


def derive(model) -> Derived:
    if isinstance(model.inertia, Inertia):
        Jd = inertia_jd(model.inertia)
        if model.G.n_se3:
            mass, rho = model.mass(), model.rho
        else:
            mass, rho = Jd.new_zeros(0), Jd.new_zeros(0, 3)
    else:
        Jd, mass, rho = model._params()
    D = None
    for f in model.forces:
        if isinstance(f, RayleighForce):
            Df = spsd_matrix(f.D)
            D = Df if D is None else D + Df
    return Derived(Jd, mass, rho, D)


SCALAR_DIM = 6  # SPSD matrices up to this size are built in Python scalars


def spsd_matrix(module: SPSDMatrix | PerBodySPSD) -> torch.Tensor:
    """`SPSDMatrix()` (D = sym(L L^T) + diag(lambda^2)); small ones in Python scalars with a
    hand-written gradient (`_SPSDScalar`)."""
    if type(module) is SPSDMatrix and module.dim <= SCALAR_DIM and module.lam.device.type == "cpu":
        return _SPSDScalar.apply(module.L_entries, module.lam, module.dim)
    out = module()
    assert isinstance(out, torch.Tensor)
    return out


class _SPSDScalar(torch.autograd.Function):
    """D = (M + M^T)/2 + diag(lambda^2), M = L L^T, L lower triangular from its row-major entries.
    Gradient for G = dL/dD: dL/dL = (G + G^T) L (lower part), dL/dlambda = 2 lambda diag(G)."""

    @staticmethod
    def forward(ctx, entries, lam, n):
        L = [[0.0] * n for _ in range(n)]
        flat = entries.tolist()
        k = 0
        for i in range(n):
            for j in range(i + 1):
                L[i][j] = flat[k]
                k += 1
        lams = lam.tolist()
        M = [[sum(L[i][t] * L[j][t] for t in range(n)) for j in range(n)] for i in range(n)]
        D = [[0.5 * (M[i][j] + M[j][i]) + (lams[i] * lams[i] if i == j else 0.0) for j in range(n)] for i in range(n)]
        ctx.saved = (L, lams, n)
        return torch.tensor(D, dtype=lam.dtype, device=lam.device)

    @staticmethod
    def backward(ctx, G):
        L, lams, n = ctx.saved
        g = G.tolist()
        S = [[g[i][j] + g[j][i] for j in range(n)] for i in range(n)]
        d_entries = [sum(S[i][t] * L[t][j] for t in range(n)) for i in range(n) for j in range(i + 1)]
        d_lam = [2.0 * lams[i] * g[i][i] for i in range(n)]
        opts = {"dtype": G.dtype, "device": G.device}
        return torch.tensor(d_entries, **opts), torch.tensor(d_lam, **opts), None


def kinetic_residual_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 3): A.flatten() @ map = vee(J_d A - A^T J_d) / h, the rotational kinetic residual of
    a triplet with A = W_1 + W_2^T (d2 of W_1 plus d1 of W_2, `kinetic.kinetic_d1/d2`)."""
    E = _basis(Jd.dtype, Jd.device)[:, None]  # (9, 1, 3, 3)
    out = so3.vee(Jd @ E - E.transpose(-1, -2) @ Jd) / h  # (9, B, 3)
    return out.transpose(0, 1)


def hessian_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 9): W.flatten() @ map = H_rot(W).flatten(), H_ij = tr(hat(e_i) W hat(e_j) J_d) / h
    (`kinetic.mixed_hessian_blocks`), i.e. h H = (<W, J_d> - tr W tr J_d) I - W^T J_d - J_d W^T
    + tr(J_d) W^T + tr(W) J_d."""
    E = _basis(Jd.dtype, Jd.device)[:, None]  # (9, 1, 3, 3)
    trN = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    trW = E.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    inner = (E * Jd).sum((-1, -2))[..., None, None]
    eye = torch.eye(3, dtype=Jd.dtype, device=Jd.device)
    Et = E.transpose(-1, -2)
    H = (inner - trW * trN) * eye - Et @ Jd - Jd @ Et + trN * Et + trW * Jd  # (9, B, 3, 3)
    return (H / h).flatten(-2).transpose(0, 1)


_CONTRACTIONS: dict[tuple, torch.Tensor] = {}


def _map_contraction(dtype: torch.dtype, h: float, device: torch.device | None = None) -> torch.Tensor:
    """(9, 27 + 81): J_d.flatten() @ C = (kinetic_residual_map, hessian_map) flattened; both maps
    are linear in J_d, so C is built once (per dtype, h and device: no copy per step) from the 9
    basis matrices."""
    key = (dtype, h, device)
    if key not in _CONTRACTIONS:
        E = _basis(dtype)
        C = torch.cat((kinetic_residual_map(E, h).flatten(-2), hessian_map(E, h).flatten(-2)), -1)
        _CONTRACTIONS[key] = C if device is None else C.to(device)
    return _CONTRACTIONS[key]


def warm_caches(dtype: torch.dtype, device: torch.device, h: float) -> None:
    """Build the module's constant caches eagerly: a compiled function must not fill a global
    cache while it is traced (torch.compile refuses tensors created in a traced region that
    outlive it, e.g. the Exp 4 loss: InternalTorchDynamoError)."""
    _constants(dtype, device)
    _constants(dtype, None)
    _map_contraction(dtype, float(h), device)


def training_maps(Jd: torch.Tensor, h: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(kinetic_residual_map (B, 9, 3), hessian_map (B, 9, 9)) of J_d (B, 3, 3) in one product."""
    maps = Jd.flatten(-2) @ _map_contraction(Jd.dtype, float(h), Jd.device)
    return maps[..., :27].unflatten(-1, (9, 3)), maps[..., 27:].unflatten(-1, (9, 9))


def _apply_map(X: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """X (..., B, 9) with per-body maps M (B, 9, k) -> (..., B, k)."""
    if M.shape[0] == 1:
        return X @ M[0]
    return (X.unsqueeze(-2) @ M).squeeze(-2)


def _trainable(module: nn.Module | None) -> bool:
    return module is not None and any(p.requires_grad for p in module.parameters())


# ---------------------------------------------------------------------------- potential gradient
def potential_covector(model, g: Pose, create_graph: bool = False) -> torch.Tensor:
    """-h dV(g exp(eta))/d eta at 0 (`LieDFLNN.potential_covector`), shape (..., dim).

    MLP potentials: the input gradient in closed form (`mlp_derivatives`); others: autograd over
    the matrices."""
    out = mlp_derivatives.potential_covector(model, g)
    if out is not None:
        return out
    if create_graph and not (g.R.requires_grad or g.p.requires_grad):  # data poses: leaves of the graph
        g = Pose(g.R.detach().requires_grad_(True), g.p.detach().requires_grad_(True))
    return -model.h * left_gradient(model.potential, model.G, g, create_graph=create_graph)


# ---------------------------------------------------------------------------- training samples
@dataclass
class IncrementBatch:
    """A batch of `IncrementSet`: the stored fields of the triplets `idx` and of the regularity
    pairs (`reg_W`, `reg_logdetW`), or None where the loss does not need them."""

    fields: dict[str, Any]
    reg_W: torch.Tensor | None
    reg_logdetW: torch.Tensor | None
    forces: list[nn.Module]  # trainable forces other than Rayleigh, evaluated per batch
    potential: bool  # the potential has trainable parameters: evaluated per batch


class IncrementSet(TripletSet):
    """Training triplets of a LieDFLNN stored as precomputed increments (see the module docstring).

    Fields (N triplets, B bodies, m SE(3) bodies, dim the tangent dimension):
      A (N, B, 9)             W_1 + W_2^T flattened (rotational kinetic residual)
      W1, u1, z2 (N, m, ...)  SE(3) bodies only: W_1, W_1^T z_1, z_2
      W2 (N, B, 9)            W_2 flattened (SE(3) residual terms and regularity pairs)
      s (N, dim)              xi~_1 + xi~_2 (constant Rayleigh damping)
      xi (2, N, dim)          velocity estimates of both time levels (configuration-dependent forces)
      levels (L, N, ...)      poses of both levels (L = 2) for those forces, or of the current
                              one (L = 1) where only the potential network reads them
      static (N, dim)         the residual terms without trainable parameters (known parts)
    """

    def __init__(self, model, data: Pose, steps: int):
        super().__init__(data, steps)
        G, h = model.G, model.h
        m = G.n_se3
        inc1 = G.increment(self.prev, self.cur)
        inc2 = G.increment(self.cur, self.nxt)
        xi1 = kinetic.velocity_estimate(G, inc1, h)
        xi2 = kinetic.velocity_estimate(G, inc2, h)
        f: dict[str, Any] = {"A": (inc1.R + inc2.R.transpose(-1, -2)).flatten(-2)}
        W2 = inc2.R.flatten(-2)
        if m:
            f["W1"] = inc1.R[:, :m]
            f["u1"] = (inc1.R[:, :m].transpose(-1, -2) @ inc1.p[..., None])[..., 0]
            f["z2"] = inc2.p
            f["W2"] = W2[:, :m]
        self.reg_W = W2
        self.reg_logdetW = torch.linalg.slogdet(inc2.R[:, :m]).logabsdet if m else None
        rayleigh = [x for x in model.forces if isinstance(x, RayleighForce)]
        others = [x for x in model.forces if not isinstance(x, RayleighForce)]
        if rayleigh:
            f["s"] = xi1 + xi2
        self.dynamic_forces = [x for x in others if _trainable(x)]
        self.potential_trainable = _trainable(model.potential)
        if self.dynamic_forces:  # both time levels, stacked: (2, N, ...)
            f["xi"] = torch.stack((xi1, xi2))
            f["levels"] = Pose(torch.stack((self.prev.R, self.cur.R)), torch.stack((self.prev.p, self.cur.p)))
        elif self.potential_trainable:  # the current level only: (1, N, ...)
            f["levels"] = Pose(self.cur.R[None], self.cur.p[None])
        static = torch.zeros_like(xi1)
        with torch.no_grad():
            for x in others:
                if not _trainable(x):
                    static = static + 0.5 * h * (x(self.prev, xi1) + x(self.cur, xi2))
            if model.potential is not None and not self.potential_trainable:
                static = static + potential_covector(model, self.cur)
        if any(not _trainable(x) for x in others) or (model.potential is not None and not self.potential_trainable):
            f["static"] = static
        self.static_jac: torch.Tensor | None = None  # dF/dxi~ of the frozen forces at (g_k, xi~_k), N x dim x dim
        frozen = [x for x in others if not _trainable(x)]
        if frozen:
            with torch.no_grad():
                self.static_jac = sum(force_jacobian_xi(x, self.cur, xi2) for x in frozen)  # type: ignore[assignment]
        self.fields = f
        del self.prev, self.cur, self.nxt  # everything needed is in `fields`

    def enable_jacobian(self) -> None:
        """Also give every batch what the step Jacobian at (g_k, W_k) needs (`models.losses`, loss
        newton): W2r, W_k of every body flattened (N, B, 9), and static_jac for frozen forces."""
        self.fields["W2r"] = self.reg_W
        if self.static_jac is not None:
            self.fields["static_jac"] = self.static_jac

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> IncrementBatch:  # type: ignore[override]
        """Triplets `idx` plus `reg_points` random pairs from `generator` (the draws of `TripletSet`)."""
        reg_W = reg_ld = None
        idx = idx.to(self.reg_W.device)  # indices drawn on the training loop's CPU generator
        if reg_points > 0:
            reg_idx = torch.randint(0, self.n, (int(reg_points),), generator=generator).to(idx.device)
            reg_W = self.reg_W.index_select(0, reg_idx)
            reg_ld = self.reg_logdetW.index_select(0, reg_idx) if self.reg_logdetW is not None else None
        fields: dict[str, Any] = {}  # tensors, and the Pose of "levels"
        for k, v in self.fields.items():
            if k == "levels":
                fields[k] = Pose(v.R.index_select(1, idx), v.p.index_select(1, idx))
            else:
                fields[k] = v.index_select(1 if k == "xi" else 0, idx)
        return IncrementBatch(fields, reg_W, reg_ld, self.dynamic_forces, self.potential_trainable)


def training_residual(model, batch: IncrementBatch, P: Derived, kin_map: torch.Tensor) -> torch.Tensor:
    """The forced DEL residual of the batch's triplets (`LieDFLNN.residual`), shape (N, dim);
    kin_map = `kinetic_residual_map(P.Jd, h)`."""
    G, h = model.G, model.h
    m = G.n_se3
    f = batch.fields
    w = _apply_map(f["A"], kin_map)  # (N, B, 3)
    if m:
        rho = P.rho
        W1 = f["W1"]
        W2 = f["W2"].unflatten(-1, (3, 3))
        W2rho = (W2 @ rho[..., None])[..., 0]
        X2 = f["z2"] + W2rho - rho
        a2 = f["z2"] + W2rho
        WtX1 = f["u1"] + rho - (W1.transpose(-1, -2) @ rho[..., None])[..., 0]
        scale = (P.mass / h)[..., None]
        extra = scale * (torch.linalg.cross(X2, a2) + torch.linalg.cross(rho.expand_as(WtX1), WtX1))
        w = torch.cat((w[..., :m, :] + extra, w[..., m:, :]), -2)
        v = scale * (WtX1 - X2)
    else:
        v = w[..., :0, :]
    r = G.join(w, v)
    if P.D is not None:
        r = r - (0.5 * h) * (f["s"] @ P.D.T)
    if batch.forces:
        r = r + batch_forces(model, batch.forces, f)
    if "static" in f:
        r = r + f["static"]
    if batch.potential:
        levels = f["levels"]
        r = r + potential_covector(model, Pose(levels.R[-1], levels.p[-1]), create_graph=True)
    return r


def batch_forces(model, forces: list[nn.Module], f: dict) -> torch.Tensor:
    """(h/2)(F(g_prev, xi~_1) + F(g, xi~_2)) summed over `forces`, each evaluated once on both
    time levels stacked."""
    levels = f["levels"]
    both = Pose(levels.R.flatten(0, 1), levels.p.flatten(0, 1))
    xi = f["xi"].flatten(0, 1)
    n = f["xi"].shape[1]
    out = None
    for x in forces:
        F = force_value(x, both, xi)
        out = F if out is None else out + F
    assert out is not None
    return 0.5 * model.h * (out[:n] + out[n:])


def force_value(force: nn.Module, g: Pose, xi: torch.Tensor) -> torch.Tensor:
    """F(g, xi~); the coupled configuration-dependent Rayleigh force D(g) xi~ = L (L^T xi~) as two
    matrix-vector products instead of forming the dim x dim matrix L L^T per sample (the per-body
    one applies its blocks itself)."""
    if type(force) is RayleighNonlinearForce and getattr(force, "per_body", None) is None:
        L = force.L(g)
        return -(L @ (L.transpose(-1, -2) @ xi[..., None]))[..., 0]
    return force(g, xi)


def regularity_slogdet(
    model, batch: IncrementBatch, P: Derived, hess_map: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(log|det H_b|, sign det(-H_b)) of each body's mixed-Hessian block at the regularity pairs,
    both (P, B) (`LieDFLNN.regularity_slogdet`).

    SE(3) blocks [[H + s P W P, -s P W], [s W P, -s W]] (s = m/h) have the Schur complement H, so
    log|det| = log|det H| + 3 log s + log|det W| and det(-block) = -s^3 det W det H: with W a
    rotation, sign det(-H_b) = -sign det H for SE(3) and SO(3) bodies alike."""
    assert batch.reg_W is not None
    Hflat = _apply_map(batch.reg_W, hess_map)
    sl = torch.linalg.slogdet(Hflat.unflatten(-1, (3, 3)))
    logdet = sl.logabsdet
    m = model.G.n_se3
    if m:
        assert batch.reg_logdetW is not None
        se = logdet[..., :m] + 3.0 * torch.log(P.mass / model.h) + batch.reg_logdetW
        logdet = torch.cat((se, logdet[..., m:]), -1)
    return logdet, -sl.sign


def residual_and_logdet(model, batch: IncrementBatch, opts) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(residual (N, dim), regularity log|det| (P, B) or None) of a batch, with the derived
    parameters built once (`LieDFLNN.loss` turns them into the loss); blocks of the wrong
    orientation carry `base.oriented_logdet`'s value."""
    P = derive(model)
    kin_map, hess_map = training_maps(P.Jd, model.h)
    use_reg = batch.reg_W is not None and opts.w_reg > 0
    logdet = oriented_logdet(*regularity_slogdet(model, batch, P, hess_map), opts.epsilon) if use_reg else None
    return training_residual(model, batch, P, kin_map), logdet


def rotational_only(model, batch: IncrementBatch) -> bool:
    """Whether `rotational_loss` applies: SO(3) bodies only, and nothing trainable besides J_d and
    the constant Rayleigh D (frozen parts are in the batch's `static` field)."""
    return not model.G.n_se3 and not batch.forces and not batch.potential


def rotational_loss(model, batch: IncrementBatch, opts) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of an SO(3)-only model whose trainable parts are J_d and D, with its gradient
    with respect to (J_d, D) written by hand (`_RotationalLoss`): the batch-sized part of the
    graph is a handful of kernels each way; autograd only sees J_d's and D's parameterisations."""
    P = derive(model)
    reg = batch.reg_W if batch.reg_W is not None and opts.w_reg > 0 else None
    static = batch.fields.get("static")
    s = batch.fields.get("s")
    C = _map_contraction(P.Jd.dtype, float(model.h), P.Jd.device)
    settings = (float(model.h), float(opts.w_del), float(opts.w_reg), float(opts.epsilon), str(opts.reg_form))
    A = batch.fields["A"]
    loss, del_loss, reg_loss = _RotationalLoss.apply(P.Jd.flatten(-2), P.D, A, s, static, reg, C, settings)
    return loss, {"del_loss": del_loss, "reg_loss": reg_loss}


def _penalty_and_slope(logdet: torch.Tensor, epsilon: float, form: str) -> tuple[torch.Tensor, torch.Tensor]:
    """`del_loss.regularity_penalty` and its derivative with respect to logdet."""
    if form == "relu":
        gap = epsilon - logdet
        return torch.relu(gap), -(gap > 0).to(logdet.dtype)
    if form == "gaussian":
        x = logdet - epsilon
        u = torch.exp(torch.clamp(x, max=50.0))
        pen = torch.exp(-0.5 * (u - 1.0) ** 2) / math.sqrt(2 * math.pi)
        return pen, -pen * (u - 1.0) * u * (x <= 50.0).to(logdet.dtype)
    raise ValueError(f"train.reg_form must be 'relu' or 'gaussian', got {form!r}")


def _oriented_penalty_and_slope(sl, epsilon: float, form: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The penalty of `base.oriented_logdet` of SO(3) blocks (sign det(-H) = -sign det H) from
    their `slogdet` and its derivative with respect to log|det H| (unchanged where det(-H) > 0)."""
    right = sl.sign < 0
    pen, slope = _penalty_and_slope(oriented_logdet(sl.logabsdet, -sl.sign, epsilon), epsilon, form)
    return pen, torch.where(right, slope, -torch.sign(sl.logabsdet - epsilon) * slope)


class _RotationalLoss(torch.autograd.Function):
    """(loss, del_loss, reg_loss) of `rotational_loss` from J_d.flatten() (B, 9) and D (dim, dim):

        r = A @ kinetic_residual_map(J_d) - (h/2) s D^T + static,    del_loss = mean r^2
        H = W_2 @ hessian_map(J_d),                                   reg_loss = mean penalty(log|det H|)

    Both maps are J_d.flatten() @ C (`_map_contraction`), so the gradient is
    dJ_d = (A^T dr) C_r^T + (W_2^T dH) C_H^T with dH = dlogdet H^-T, and dD = -(h/2) dr^T s."""

    @staticmethod
    def forward(ctx, Jd_flat, D, A, s, static, reg_W, C, settings):
        h, w_del, w_reg, epsilon, form = settings
        B = Jd_flat.shape[0]
        maps = Jd_flat @ C
        kin = maps[:, :27].unflatten(-1, (9, 3))
        r = _apply_map(A, kin).flatten(-2)
        if D is not None:
            r = r - (0.5 * h) * (s @ D.T)
        if static is not None:
            r = r + static
        del_loss = (r * r).mean()
        reg_loss = torch.zeros((), dtype=r.dtype, device=r.device)
        H = slope = None
        if reg_W is not None:
            H = _apply_map(reg_W, maps[:, 27:].unflatten(-1, (9, 9))).unflatten(-1, (3, 3))
            pen, slope = _oriented_penalty_and_slope(torch.linalg.slogdet(H), epsilon, form)
            reg_loss = pen.mean()
        ctx.save_for_backward(r, A, s, reg_W, H, slope, C)
        ctx.settings = (h, w_del, w_reg, B, D is not None)
        return w_del * del_loss + w_reg * reg_loss, del_loss, reg_loss

    @staticmethod
    def backward(ctx, g_loss, g_del, g_reg):
        r, A, s, reg_W, H, slope, C = ctx.saved_tensors
        h, w_del, w_reg, B, has_D = ctx.settings
        g_del = g_loss * w_del + (g_del if g_del is not None else 0.0)
        g_reg = g_loss * w_reg + (g_reg if g_reg is not None else 0.0)
        dr = (2.0 * g_del / r.numel()) * r
        dkin = A.permute(1, 2, 0) @ dr.unflatten(-1, (B, 3)).transpose(0, 1)  # (B, 9, N) @ (B, N, 3)
        dJd = dkin.flatten(-2) @ C[:, :27].T
        dD = -(0.5 * h) * (dr.T @ s) if has_D else None
        if reg_W is not None:
            dlogdet = (g_reg / slope.numel()) * slope  # (P, B)
            dH = dlogdet[..., None, None] * torch.linalg.inv(H).transpose(-1, -2)
            dhess = reg_W.permute(1, 2, 0) @ dH.flatten(-2).transpose(0, 1)  # (B, 9, P) @ (B, P, 9)
            dJd = dJd + dhess.flatten(-2) @ C[:, 27:].T
        return dJd, dD, None, None, None, None, None, None


# ---------------------------------------------------------------------------- rollout
@dataclass
class RolloutMaps:
    """What a rollout builds once from the model's parameters (all detached).

    P: derived parameters. d1, d2, hess (B, 9, k): the rotational kinetic d1 / d2 residuals and
    mixed-Hessian blocks as linear maps of W.flatten(). rho_map (m, 9, 3): W.flatten() @ map =
    W rho. se3_block (m, 9, 36): the SE(3) bodies' 6x6 kinetic blocks. linear: for SO(3)-only
    groups whose forces are constant Rayleigh matrices, (lin_f, lin_J, lin_const) with
    W.flatten() @ lin_f = residual_var, @ lin_J = its Jacobian, and W_prev.flatten() @ lin_const
    = d2 + (h/2) F(g_prev, xi~_prev); None otherwise. kin_index / dxi_index: flat positions of
    the block-diagonal entries in a (dim, dim) matrix (several bodies)."""

    P: Derived
    d1: torch.Tensor
    d2: torch.Tensor
    hess: torch.Tensor
    rho_map: torch.Tensor | None
    se3_block: torch.Tensor | None
    linear: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None
    block_index: torch.Tensor | None


@dataclass
class RolloutState:
    """State of a fused rollout: poses g_{k-1}, g_k, the increment W_{k-1} (warm start) and the
    maps built once per rollout."""

    g_prev: Pose
    g: Pose
    inc: Pose
    maps: RolloutMaps
    compile: bool = False


def _d2_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 3): W.flatten() @ map = vee(J_d W - W^T J_d) / h (`kinetic.kinetic_d2`, rotation)."""
    E = _basis(Jd.dtype, Jd.device)[:, None]
    return (so3.vee(Jd @ E - E.transpose(-1, -2) @ Jd) / h).transpose(0, 1)


def _d1_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 3): W.flatten() @ map = vee(J_d W^T - W J_d) / h (`kinetic.kinetic_d1`, rotation)."""
    E = _basis(Jd.dtype, Jd.device)[:, None]
    return (so3.vee(Jd @ E.transpose(-1, -2) - E @ Jd) / h).transpose(0, 1)


def _block_index(G: ProductGroup, device: torch.device) -> torch.Tensor:
    """Flat positions in a (dim, dim) matrix of the block-diagonal entries, body by body
    (6x6 for SE(3) bodies, 3x3 for SO(3) bodies, row-major within a block), on `device`."""
    out = []
    for s in G.body_slices():
        rows = torch.arange(s.start, s.stop, device=device)
        out.append((rows[:, None] * G.dim + rows[None, :]).flatten())
    return torch.cat(out)


def rollout_maps(model) -> RolloutMaps:
    G, h = model.G, model.h
    P = derive(model)
    P = Derived(P.Jd.detach(), P.mass.detach(), P.rho.detach(), None if P.D is None else P.D.detach())
    m = G.n_se3
    d1, d2, hess = _d1_map(P.Jd, h), _d2_map(P.Jd, h), hessian_map(P.Jd, h)
    rho_map = se3_block = None
    if m:
        E = _basis(P.Jd.dtype, P.Jd.device)
        rho_map = (E[None] @ P.rho[:, None, :, None])[..., 0]  # (m, 9, 3)
        se3_block = torch.stack(
            [
                kinetic.mixed_hessian_blocks(
                    ProductGroup(1, 0),
                    Pose(E[:, None], E.new_zeros(9, 1, 3)),
                    P.Jd[i : i + 1],
                    P.mass[i : i + 1],
                    P.rho[i : i + 1],
                    h,
                )[0].flatten(-2)
                for i in range(m)
            ]
        )
    linear = None
    if not m and all(isinstance(f, RayleighForce) for f in model.forces):
        linear = _linear_maps(model, P)
    block_index = _block_index(G, P.Jd.device) if G.n_bodies > 1 else None
    return RolloutMaps(P, d1, d2, hess, rho_map, se3_block, linear, block_index)


def _linear_maps(model, P: Derived) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(lin_f (9B, dim), lin_J (9B, dim * dim), lin_const (9B, dim)) of an SO(3)-only model with
    constant forces, built by evaluating the reference formulas on the basis increments."""
    G, h = model.G, model.h
    B, dim = G.n_bodies, G.dim
    E = _basis(P.Jd.dtype, P.Jd.device)
    fs, Js, cs = [], [], []
    for b in range(B):
        W = E.new_zeros(9, B, 3, 3)
        W[:, b] = E
        inc = Pose(W, W.new_zeros(9, 0, 3))
        r = kinetic.kinetic_d1(G, inc, P.Jd, P.mass, P.rho, h)
        c = kinetic.kinetic_d2(G, inc, P.Jd, P.mass, P.rho, h)
        J = W.new_zeros(9, dim, dim)
        for sl, blk in zip(G.body_slices(), kinetic.mixed_hessian_blocks(G, inc, P.Jd, P.mass, P.rho, h)):
            J[:, sl, sl] = blk
        if P.D is not None:
            F = -(kinetic.velocity_estimate(G, inc, h) @ P.D.T)
            r = r + 0.5 * h * F
            c = c + 0.5 * h * F
            J = J + 0.5 * h * (-P.D @ kinetic.velocity_estimate_jacobian(G, inc, h))
        fs.append(r)
        Js.append(J.flatten(-2))
        cs.append(c)
    return torch.cat(fs).contiguous(), torch.cat(Js).contiguous(), torch.cat(cs).contiguous()


def rollout_start(model, g0: Pose, g1: Pose) -> RolloutState:
    """State before the first step; the Newton step is compiled when `runtime.compile` asks for it
    for this rollout's size (`runtime.planned_rollout`)."""
    compile_it = runtime.want_compile("rollout")
    return RolloutState(g0, g1, model.G.increment(g0, g1), rollout_maps(model), compile_it)


def _kinetic_se3_terms(W: torch.Tensor, z: torch.Tensor, maps: RolloutMaps, h: float):
    """SE(3) bodies' kinetic pieces at increments W (T, m, 3, 3), z (T, m, 3): (X, W rho)."""
    assert maps.rho_map is not None
    Wrho = _apply_map(W.flatten(-2), maps.rho_map)
    return z + Wrho - maps.P.rho, Wrho


def kinetic_d1(G: ProductGroup, x: Pose, maps: RolloutMaps, h: float) -> torch.Tensor:
    """`kinetic.kinetic_d1` with the rotational part from its linear map."""
    w = _apply_map(x.R.flatten(-2), maps.d1)
    m = G.n_se3
    if not m:
        return G.join(w, w[..., :0, :])
    X, Wrho = _kinetic_se3_terms(x.R[..., :m, :, :], x.p, maps, h)
    scale = (maps.P.mass / h)[..., None]
    w = torch.cat((w[..., :m, :] + scale * torch.linalg.cross(X, x.p + Wrho), w[..., m:, :]), -2)
    return G.join(w, -scale * X)


def kinetic_d2(G: ProductGroup, x: Pose, maps: RolloutMaps, h: float) -> torch.Tensor:
    """`kinetic.kinetic_d2` with the rotational part from its linear map."""
    w = _apply_map(x.R.flatten(-2), maps.d2)
    m = G.n_se3
    if not m:
        return G.join(w, w[..., :0, :])
    Wm = x.R[..., :m, :, :]
    X, _ = _kinetic_se3_terms(Wm, x.p, maps, h)
    WtX = (Wm.transpose(-1, -2) @ X[..., None])[..., 0]
    scale = (maps.P.mass / h)[..., None]
    rho = maps.P.rho.expand_as(WtX)
    w = torch.cat((w[..., :m, :] + scale * torch.linalg.cross(rho, WtX), w[..., m:, :]), -2)
    return G.join(w, scale * WtX)


def kinetic_blocks(G: ProductGroup, x: Pose, maps: RolloutMaps) -> torch.Tensor:
    """Block-diagonal entries of the kinetic mixed Hessian, body by body: (T, 36 m + 9 n)."""
    m = G.n_se3
    Wf = x.R.flatten(-2)
    parts = []
    if m:
        assert maps.se3_block is not None
        parts.append(_apply_map(Wf[..., :m, :], maps.se3_block).flatten(-2))
    if G.n_so3:
        parts.append(_apply_map(Wf[..., m:, :], maps.hess[m:]).flatten(-2))
    return parts[0] if len(parts) == 1 else torch.cat(parts, -1)


def velocity_jacobian_blocks(G: ProductGroup, x: Pose, h: float) -> torch.Tensor:
    """Block-diagonal entries of `kinetic.velocity_estimate_jacobian`, body by body: (T, 36 m + 9 n)."""
    W, z = x.R, x.p
    eye = _constants(W.dtype, W.device)["eye"]
    trW = W.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    dw = (trW * eye - W.transpose(-1, -2)) / (2 * h)  # (T, B, 3, 3)
    m = G.n_se3
    if not m:
        return dw.flatten(-3)
    Wm, dwm = W[..., :m, :, :], dw[..., :m, :, :]
    w_t = so3.vee(Wm) / h
    dvv = (eye - 0.5 * h * so3.hat(w_t)) @ Wm / h
    dvw = 0.5 * so3.hat(z) @ dwm
    top = torch.cat((dwm, torch.zeros_like(dwm)), -1)
    se = torch.cat((top, torch.cat((dvw, dvv), -1)), -2).flatten(-3)
    return se if not G.n_so3 else torch.cat((se, dw[..., m:, :, :].flatten(-3)), -1)


def _block_diagonal(vals: torch.Tensor, index: torch.Tensor | None, dim: int) -> torch.Tensor:
    """(T, nnz) block-diagonal entries -> (T, dim, dim) (one body: the block itself)."""
    if index is None:
        return vals.unflatten(-1, (dim, dim))
    out = vals.new_zeros(*vals.shape[:-1], dim * dim)
    out.index_copy_(-1, index, vals)
    return out.unflatten(-1, (dim, dim))


class FusedStep:
    """One implicit step of a LieDFLNN: the residual, its Jacobian and a full Newton iteration on
    the increment x = (W, z), with the part fixed by (g_{k-1}, g_k) computed once: the kinetic
    d2 term, the forces at (g_{k-1}, xi~_{k-1}), the potential's covector at g_k and, for forces
    affine in xi~ (Rayleigh, configuration-dependent Rayleigh, PD control), their value at
    xi~ = 0 and their Jacobian at g_k. Other forces (`generic`) are evaluated per iteration."""

    def __init__(self, model, state: RolloutState, compiled_iterate=None):
        G, h = model.G, model.h
        self.G, self.h, self.maps, self.g = G, h, state.maps, state.g
        maps, P = state.maps, state.maps.P
        g_prev, g, inc = state.g_prev, state.g, state.inc
        self.generic: list[nn.Module] = []
        self.B: torch.Tensor | None = None
        if maps.linear is not None:
            const = inc.R.flatten(-3) @ maps.linear[2]
        else:
            xi_prev = kinetic.velocity_estimate(G, inc, h)
            const = kinetic_d2(G, inc, maps, h)
            B_aff = None if P.D is None else -P.D
            half = None if P.D is None else -(xi_prev @ P.D.T)
            for f in model.forces:
                if isinstance(f, RayleighForce):
                    continue
                Fp = f(g_prev, xi_prev)
                half = Fp if half is None else half + Fp
                if isinstance(f, AFFINE_FORCES):
                    zero = torch.zeros_like(xi_prev)
                    Bf = force_jacobian_xi(f, g, zero).detach()
                    half = half + f(g, zero)
                    B_aff = Bf if B_aff is None else B_aff + Bf
                else:
                    self.generic.append(f)
            if half is not None:
                const = const + 0.5 * h * half
            self.B = B_aff
        if model.potential is not None:
            const = const + potential_covector(model, g).detach()
        self.const = const
        self.compiled_iterate = compiled_iterate if not self.generic else None
        self.forces_at = mlp_derivatives.ForcesAt(G, self.generic, g) if self.generic else None

    def f(self, x: Pose) -> torch.Tensor:
        """The residual at the increment x, (T, dim)."""
        r = step_residual(self.G, self.h, x, self.const, self.B, self.maps)
        if self.forces_at is not None:
            xi = kinetic.velocity_estimate(self.G, x, self.h)
            r = r + 0.5 * self.h * self.forces_at.value(xi, key=x.R)
        return r

    def jac(self, x: Pose) -> torch.Tensor:
        """d f(x exp(delta)) / d delta at 0, (T, dim, dim)."""
        extra = None
        if self.forces_at is not None:
            extra = self.forces_at.jacobian(kinetic.velocity_estimate(self.G, x, self.h), key=x.R)
        return step_jacobian(self.G, self.h, x, self.B, self.maps, extra)

    def retract(self, x: Pose, delta: torch.Tensor) -> Pose:
        return group_retract(self.G, x, delta)

    def restrict(self, rows: torch.Tensor) -> NewtonProblem:
        """The Newton problem of the rows `rows` (for the last iterations of a few rows)."""
        sub = copy.copy(self)
        sub.const = self.const.index_select(0, rows)
        sub.g = Pose(self.g.R.index_select(0, rows), self.g.p.index_select(0, rows))
        if self.B is not None and self.B.dim() == 3:
            sub.B = self.B.index_select(0, rows)
        if self.forces_at is not None:
            sub.forces_at = self.forces_at.restrict(rows)
        return sub.problem(None)

    def problem(self, x0) -> NewtonProblem:
        return NewtonProblem(self.f, self.jac, x0, self.retract, iterate=self.iterate, restrict=self.restrict)

    def iterate(self, x: Pose, r: torch.Tensor):
        """One full Newton step from x: (delta, singular, candidate x', residual at x')."""
        if self.compiled_iterate is not None:
            return self.compiled_iterate(self.G, self.h, x, r, self.const, self.B, self.maps)
        if not self.generic:
            return step_iterate(self.G, self.h, x, r, self.const, self.B, self.maps)
        sol, singular = solve_small(self.jac(x), r)
        delta = -sol
        cand = self.retract(x, delta)
        return delta, singular, cand, self.f(cand)


def step_residual(G: ProductGroup, h: float, x: Pose, const, B, maps: RolloutMaps) -> torch.Tensor:
    """Residual at the increment x without per-iteration (generic) forces, (T, dim)."""
    if maps.linear is not None:
        return const + x.R.flatten(-3) @ maps.linear[0]
    r = const + kinetic_d1(G, x, maps, h)
    if B is not None:
        xi = kinetic.velocity_estimate(G, x, h)
        Bxi = xi @ B.transpose(-1, -2) if B.dim() == 2 else (B @ xi[..., None])[..., 0]
        r = r + 0.5 * h * Bxi
    return r


def step_jacobian(G: ProductGroup, h: float, x: Pose, B, maps: RolloutMaps, extra=None) -> torch.Tensor:
    """Jacobian of `step_residual` (+ `extra`, the generic forces' dF/dxi~), (T, dim, dim)."""
    dim = G.dim
    if maps.linear is not None:
        return (x.R.flatten(-3) @ maps.linear[1]).unflatten(-1, (dim, dim))
    J = _block_diagonal(kinetic_blocks(G, x, maps), maps.block_index, dim)
    dF = B if extra is None else (extra if B is None else B + extra)
    if dF is not None:
        dxi = _block_diagonal(velocity_jacobian_blocks(G, x, h), maps.block_index, dim)
        J = J + 0.5 * h * (dF @ dxi)
    return J


def step_iterate(G: ProductGroup, h: float, x: Pose, r: torch.Tensor, const, B, maps: RolloutMaps):
    """One full Newton step (no generic forces): (delta, singular, x', residual at x'). Pure
    tensor code: what `runtime.compile` compiles."""
    sol, singular = solve_small(step_jacobian(G, h, x, B, maps), r)
    delta = -sol
    cand = group_retract(G, x, delta)
    return delta, singular, cand, step_residual(G, h, cand, const, B, maps)


def rollout_problem(model, state: RolloutState) -> NewtonProblem:
    compiled = runtime.compiled(step_iterate, "rollout_step") if state.compile else None
    return FusedStep(model, state, compiled).problem(state.inc)


def rollout_advance(model, state: RolloutState, x: Pose) -> tuple[RolloutState, Pose]:
    """Newton-Schulz-cleaned increment, next pose, next state (`LieDFLNN.implicit_advance`)."""
    W = x.R.detach()
    eye = _constants(W.dtype, W.device)["eye"]
    W = 0.5 * W @ (3.0 * eye - W.transpose(-1, -2) @ W)
    inc = Pose(W, x.p.detach())
    g_next = compose(model.G, state.g, inc)
    if projects_poses(W.dtype):  # below float64 the composed poses drift off SO(3) too
        g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
    return RolloutState(state.g, g_next, inc, state.maps, state.compile), g_next
