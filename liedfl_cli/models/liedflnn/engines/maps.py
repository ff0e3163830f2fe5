"""Fused hot paths of LieDFLNN, part 1 (see `models.liedflnn.engines.core`): the small closed forms (3x3 solves; the
batched group maps live in `lie/batched.py` and are re-exported here), the constants cached per dtype/device,
the derived parameters built once (`Derived`, `derive`: J_d and the SPSD matrices with
hand-written gradients), the rotational kinetic-residual and mixed-Hessian maps linear in W, and the
potential's covector."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ....lie import Pose, so3
from ....lie.batched import EXP_TAYLOR as _EXP_TAYLOR
from ....lie.batched import exp_coefficients, vee2
from ....lie.tolerances import tol
from ....mechanics.damping import PerBodySPSD
from ....mechanics.forces import RayleighForce
from ....mechanics.parameterizations import Inertia, SPSDMatrix
from ....mechanics.potentials import GravityPotential, UniformGravityPotential, left_gradient
from ... import mlp_derivatives

# ---------------------------------------------------------------------------- small closed forms


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
        "three_eye": 3.0 * eye,
        "basis": torch.eye(9, dtype=dtype, device=device).reshape(9, 3, 3),  # matrix units E_(ij)
        "hat": so3.hat(eye).reshape(3, 9),  # w @ hat = hat(w).flatten(): entries +-1, exact
        "taylor_by_degree": tuple(torch.tensor(_EXP_TAYLOR, dtype=dtype, device=device).T.contiguous()),
        "pair_sums": torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], dtype=dtype, device=device),
    }


def _basis(dtype, device=None) -> torch.Tensor:
    """The 9 matrix units E_(ij), shape (9, 3, 3)."""
    return _constants(dtype, device)["basis"]


def solve_small(J: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(J^{-1} r, singular) for (T, n, n), (T, n): closed-form inverse for n = 3, LU otherwise.

    `singular` marks rows the reference solver (LU) would call singular: exactly zero determinant
    for n = 3 (a zero pivot), LAPACK's info > 0 otherwise."""
    if J.shape[-1] != 3:
        sol, info = torch.linalg.solve_ex(J, r[..., None])
        return sol[..., 0], info > 0
    a, b, c = J[..., 0, :], J[..., 1, :], J[..., 2, :]
    bc, ca, ab = torch.linalg.cross(b, c), torch.linalg.cross(c, a), torch.linalg.cross(a, b)
    det = (a[..., None, :] @ bc[..., :, None])[..., 0, 0]  # a batched product: 2x faster than a sum over 3
    x = (bc * r[..., 0:1]).addcmul_(ca, r[..., 1:2]).addcmul_(ab, r[..., 2:3]) / det[..., None]
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


def inertia_jd_lists(rs: list, abcs: list) -> tuple[list, list]:
    """(J_d per body as nested lists (B, 3, 3), what `inertia_jd_grad_lists` needs) from r and abc
    as lists (`_InertiaJdScalar`'s arithmetic)."""
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
    return out, saved


def inertia_jd_grad_lists(saved: list, G: list) -> tuple[list, list]:
    """(dL/dr, dL/dabc) as lists (B, 3) for G = dL/dJ_d as nested lists (`_InertiaJdScalar`)."""
    dr_all, dabc_all = [], []
    for (e, d, s2, s3, K, K2, R), Gb in zip(saved, G):
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
    return dr_all, dabc_all


class _InertiaJdScalar(torch.autograd.Function):
    """`_InertiaJd` computed body by body in Python floats (same formulas, float64 rounding)."""

    @staticmethod
    def forward(ctx, r, abc):
        out, ctx.saved = inertia_jd_lists(r.tolist(), abc.tolist())
        return torch.tensor(out, dtype=r.dtype, device=r.device)

    @staticmethod
    def backward(ctx, G):
        dr_all, dabc_all = inertia_jd_grad_lists(ctx.saved, G.tolist())
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


def spsd_lists(flat: list, lams: list, n: int) -> tuple[list, tuple]:
    """(D as nested lists (n, n), what `spsd_grad_lists` needs) from L's row-major entries and
    lambda as lists (`_SPSDScalar`'s arithmetic)."""
    L = [[0.0] * n for _ in range(n)]
    k = 0
    for i in range(n):
        for j in range(i + 1):
            L[i][j] = flat[k]
            k += 1
    M = [[sum(L[i][t] * L[j][t] for t in range(n)) for j in range(n)] for i in range(n)]
    D = [[0.5 * (M[i][j] + M[j][i]) + (lams[i] * lams[i] if i == j else 0.0) for j in range(n)] for i in range(n)]
    return D, (L, lams, n)


def spsd_grad_lists(saved: tuple, g: list) -> tuple[list, list]:
    """(dL/d entries, dL/d lambda) as lists for g = dL/dD as nested lists (`_SPSDScalar`)."""
    L, lams, n = saved
    S = [[g[i][j] + g[j][i] for j in range(n)] for i in range(n)]
    d_entries = [sum(S[i][t] * L[t][j] for t in range(n)) for i in range(n) for j in range(i + 1)]
    d_lam = [2.0 * lams[i] * g[i][i] for i in range(n)]
    return d_entries, d_lam


class _SPSDScalar(torch.autograd.Function):
    """D = (M + M^T)/2 + diag(lambda^2), M = L L^T, L lower triangular from its row-major entries.
    Gradient for G = dL/dD: dL/dL = (G + G^T) L (lower part), dL/dlambda = 2 lambda diag(G)."""

    @staticmethod
    def forward(ctx, entries, lam, n):
        D, ctx.saved = spsd_lists(entries.tolist(), lam.tolist(), n)
        return torch.tensor(D, dtype=lam.dtype, device=lam.device)

    @staticmethod
    def backward(ctx, G):
        d_entries, d_lam = spsd_grad_lists(ctx.saved, G.tolist())
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
    if isinstance(model.potential, (UniformGravityPotential, GravityPotential)):  # closed form, differentiable
        return -model.h * model.potential.left_gradient(g)
    if create_graph and not (g.R.requires_grad or g.p.requires_grad):  # data poses: leaves of the graph
        g = Pose(g.R.detach().requires_grad_(True), g.p.detach().requires_grad_(True))
    return -model.h * left_gradient(model.potential, model.G, g, create_graph=create_graph)
