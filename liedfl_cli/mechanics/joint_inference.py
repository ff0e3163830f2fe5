"""Which joint each body of a kinematic tree has -- weld, hinge, universal or ball -- inferred from poses.

Input: coordinates R (T, N+1, B, 3, 3) of a `Tree` (`tree.rotations` "world" or "parent"). Per joint,
the relative rotations R_rel = R_parent^T R_b over every sample (a pinned root: its world attitude;
a free root is "free" and only reported). Method (docs/joints.md):

1. Clouds (body frame), pooled over all trajectories:
   increments    w = log(R_rel,k^T R_rel,k+1), (T N, 3), not centred: their RMS singular values
                 s1 >= s2 >= s3 (singular values / sqrt(count)) and right singular vectors;
   displacements d = log(Rbar^T R_rel,k), (T (N+1), 3), centred, with Rbar the chordal mean of R_rel:
                 the same for the pose itself. A slow joint (its increments at the noise) still moves
                 many noise levels away from its mean pose, so this cloud sees small motions that the
                 increments cannot; for a hinge R_rel = C exp(t a) both clouds lie exactly on the line a.
2. Noise level sigma (rad, per sample and axis of the rotation noise R exp(n), n ~ N(0, sigma^2 I)):
   given (`noise=`), or estimated per joint from the third difference of the poses, the second difference
   of the increments e_k = w_k+2 - 2 w_k+1 + w_k: white noise gives it 20 sigma^2 per axis (1+9+9+1) and
   a smooth motion only h^3 |d^3 theta/dt^3|; robustly, sigma^2 = median_k |e_k|^2 / (20 * 2.366)
   (2.366 = the median of a chi-square with 3 degrees of freedom). A smooth signal makes this an upper
   bound on the noise (the verdict then errs towards fewer degrees of freedom). Never below `FLOOR`.
3. Tolerances, with K = `K_SIGMA` = 3:  increments K sqrt(2) sigma (the noise of a difference of two
   samples), displacements K sigma, the hinge's axis drift K sqrt(2) sigma (two perpendicular
   components), the universal fit K sigma (one angle).
4. A direction i moves when s_i > tolerance in either cloud: z_i = max(s_i,inc / tol_inc,
   s_i,disp / tol_disp) > 1; rank = the number of such directions.
   rank 0                                   -> weld;
   rank 1 and the axis fixed in the parent frame (RMS angle of R_rel a from its mean direction at most
     its tolerance) -> hinge, a = the first right singular vector of the cloud with the larger z_1
     (body frame; sign: largest |component| positive);
   otherwise the universal fit: a1 (parent frame), a2 (body frame), c with a1^T R_rel a2 = c for every
     sample: the smallest right singular vector of the (samples x 10) rows [vec(R_rel)^T, -1]
     (vec row-major, so <K, R_rel> = a1^T R_rel a2 for K = a1 a2^T), its 3x3 part K reduced to its
     rank-one part (first singular pair), refined by Levenberg-Marquardt on the same algebraic residual
     (the linear fit alone can be far off when the motion is small or not exactly universal: the CMU
     feet after smoothing, 0.15 rad instead of 1.2e-3; a 0.05 rad universal joint at 1e-4 noise,
     0.04 rad instead of 1e-4); unit a1, a2, each signed like a hinge axis; residual = the RMS
     over samples of phi_k - mean(phi), phi_k = angle(a1, R_rel,k a2). At most its tolerance ->
     universal, else ball. (A universal joint's increments span 3-D in general: the rank cannot tell
     it from a ball, the fit can.)
5. margin: how clearly the verdict holds, the smallest ratio (>= 1) of the decisive comparisons
   (weld 1/z1; hinge min(z1, 1/z2, tol/drift); universal min(z2 or drift/tol, tol/residual);
   ball min(z2 or drift/tol, residual/tol)). Near 1: borderline; set `noise=` to decide otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..lie import so3
from ..lie.tree import Tree, relative_rotations

K_SIGMA = 3.0
"""Tolerances are K_SIGMA times the noise of the compared quantity (module docstring, step 3)."""
FLOOR = 1e-12
"""The smallest noise level used (rad): float64 poses of exact joint motion are exact to ~1e-15."""
CHI2_3_MEDIAN = 2.365974
"""The median of a chi-square distribution with 3 degrees of freedom (noise estimate, step 2)."""
LM_ITERATIONS = 100
"""Most Levenberg-Marquardt steps of the universal fit (it stops when the residual stalls)."""
MAX_FIT_ROWS = 20000
"""Samples used by the universal fit (evenly strided beyond this; the residual uses every sample)."""
DIFF3_VARIANCE = 20.0
"""Variance, per axis and in units of sigma^2, of a third difference of white noise: 1 + 9 + 9 + 1."""


@dataclass(frozen=True)
class JointEvidence:
    """One body's verdict and its evidence (angles in rad).

    kind: "free", "weld", "hinge", "universal" or "ball"; axes (2, 3) as in `Tree.axes` (hinge: row 0 in
    the body frame; universal: row 0 in the parent frame, row 1 in the body frame; zeros otherwise).
    increment_sv, displacement_sv (3,): RMS singular values of the two clouds, largest first.
    universal_residual: RMS angle residual of the universal fit (computed for every joint).
    axis_drift: RMS angle of R_rel a (a the best single axis) from its mean direction, parent frame.
    noise: the sigma used; tol_increment, tol_displacement, tol_axis, tol_universal: the tolerances.
    rank: directions that move (step 4); margin: step 5 (nan for a free root)."""

    kind: str
    axes: tuple[tuple[float, float, float], tuple[float, float, float]]
    increment_sv: tuple[float, float, float]
    displacement_sv: tuple[float, float, float]
    universal_residual: float
    axis_drift: float
    noise: float
    tol_increment: float
    tol_displacement: float
    tol_axis: float
    tol_universal: float
    rank: int
    margin: float


@dataclass(frozen=True)
class JointInference:
    """The inferred joints of a tree of B bodies.

    joints: one `JointEvidence` per body; kinds (B,) and axes (B, 2, 3) (nested floats) in `Tree`'s
    layout; tree: the input tree with these joints (`Tree.with_joints`); noise_source: "given" or
    "estimated"."""

    joints: tuple[JointEvidence, ...]
    tree: Tree
    noise_source: str

    @property
    def kinds(self) -> tuple[str, ...]:
        """(B,) joint kinds."""
        return tuple(j.kind for j in self.joints)

    @property
    def axes(self) -> list[list[list[float]]]:
        """(B, 2, 3) axes as nested lists."""
        return [[list(r) for r in j.axes] for j in self.joints]


def _signed(v: torch.Tensor) -> torch.Tensor:
    """The unit vector of v (3,) with its largest-magnitude component positive."""
    v = v / v.norm().clamp_min(1e-300)
    return v if float(v[v.abs().argmax()]) >= 0 else -v


def _triple(v: torch.Tensor) -> tuple[float, float, float]:
    """A (3,) tensor as a tuple of floats."""
    return (float(v[0]), float(v[1]), float(v[2]))


def _rms_sv(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """RMS singular values (3,) and right singular vectors (rows of Vh, (3, 3)) of a cloud X (M, 3)."""
    if X.shape[0] == 0:
        return X.new_zeros(3), torch.eye(3, dtype=X.dtype, device=X.device)
    M = X.shape[0]
    if M < 3:  # zero rows change neither the singular values nor the vectors
        X = torch.cat((X, X.new_zeros(3 - M, 3)))
    _, s, Vh = torch.linalg.svd(X, full_matrices=False)
    return s / math.sqrt(M), Vh


def _angles(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Angles (...,) between vectors u, v (..., 3), accurate for small angles."""
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(u, v, dim=-1), dim=-1), (u * v).sum(-1))


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt()) if x.numel() else 0.0


def estimate_noise(w: torch.Tensor) -> float:
    """Rotation noise sigma (rad) from increments w (T, N, 3) of one joint (step 2): median |e|^2 of the
    second differences e of w, over 20 * 2.366, square-rooted; nan with fewer than 3 increments."""
    if w.shape[1] < 3:
        return math.nan
    e = w[:, 2:] - 2.0 * w[:, 1:-1] + w[:, :-2]
    return math.sqrt(float(e.pow(2).sum(-1).median()) / (DIFF3_VARIANCE * CHI2_3_MEDIAN))


def axis_drift(R_rel: torch.Tensor, a: torch.Tensor) -> float:
    """RMS angle (rad) of R_rel a (parent frame) from its mean direction: R_rel (M, 3, 3), a (3,) body frame."""
    p = R_rel @ a
    pbar = p.mean(0)
    pbar = pbar / pbar.norm().clamp_min(1e-300)
    return _rms(_angles(p, pbar.expand_as(p)))


def _tangent_basis(a: torch.Tensor) -> torch.Tensor:
    """(3, 2): an orthonormal basis of the plane perpendicular to the unit vector a (3,)."""
    e = torch.eye(3, dtype=a.dtype, device=a.device)[a.abs().argmin()]
    u = torch.linalg.cross(a, e, dim=-1)
    u = u / u.norm()
    return torch.stack((u, torch.linalg.cross(a, u, dim=-1)), -1)


def _algebraic_cost(R: torch.Tensor, a1: torch.Tensor, a2: torch.Tensor) -> float:
    x = torch.einsum("i,kij,j->k", a1, R, a2)
    return float((x - x.mean()).pow(2).sum())


def universal_fit(R_rel: torch.Tensor, iterations: int = LM_ITERATIONS) -> tuple[torch.Tensor, torch.Tensor, float]:
    """a1 (3,) parent frame, a2 (3,) body frame (unit, signed) and the RMS angle residual (rad) of the
    fit a1^T R_rel a2 = const over R_rel (M, 3, 3) (module docstring, step 4): the linear fit, then
    Levenberg-Marquardt on sum_k (a1^T R_rel,k a2 - c)^2 (c the mean; a1, a2 moved in their tangent
    planes and renormalised), which is sin(phi)^2 times the angle residual to first order."""
    M = R_rel.shape[0]
    R = R_rel[:: max(1, M // MAX_FIT_ROWS)]
    m = R.shape[0]
    rows = torch.cat((R.reshape(m, 9), -torch.ones(m, 1, dtype=R.dtype, device=R.device)), -1)
    x = torch.linalg.svd(rows, full_matrices=False)[2][-1]
    U, _, Vh = torch.linalg.svd(x[:9].reshape(3, 3))
    a1, a2 = U[:, 0], Vh[0]
    f, lam = _algebraic_cost(R, a1, a2), 1e-3
    ones = -torch.ones(m, 1, dtype=R.dtype, device=R.device)
    for _ in range(iterations):
        if f <= 1e-30:
            break
        B1, B2 = _tangent_basis(a1), _tangent_basis(a2)
        r = torch.einsum("i,kij,j->k", a1, R, a2)
        r = r - r.mean()
        J = torch.cat(((R @ a2) @ B1, (R.transpose(-1, -2) @ a1) @ B2, ones), -1)  # (m, 5)
        A, grad = J.T @ J, J.T @ r
        damp = torch.diagonal(A) + 1e-12 * float(torch.diagonal(A).max())
        while lam < 1e12:
            d = torch.linalg.solve(A + lam * torch.diag(damp), -grad)
            n1, n2 = a1 + B1 @ d[:2], a2 + B2 @ d[2:4]
            n1, n2 = n1 / n1.norm(), n2 / n2.norm()
            fn = _algebraic_cost(R, n1, n2)
            if fn <= f:
                lam = max(lam / 10.0, 1e-12)
                break
            lam *= 10.0
        else:
            break
        done = f - fn <= 1e-14 * f
        a1, a2, f = n1, n2, fn
        if done:
            break
    a1, a2 = _signed(a1), _signed(a2)
    phi = _angles(a1.expand(M, 3), R_rel @ a2)
    return a1, a2, _rms(phi - phi.mean())


def _joint(R_rel: torch.Tensor, sigma: float | None, free: bool) -> JointEvidence:
    """The verdict for one joint: R_rel (T, N+1, 3, 3); sigma None = estimate."""
    T, N1 = R_rel.shape[:2]
    w = so3.log(R_rel[:, :-1].transpose(-1, -2) @ R_rel[:, 1:])  # (T, N, 3)
    flat = R_rel.reshape(-1, 3, 3)
    Rbar = so3.project(flat.sum(0))
    d = so3.log(Rbar.transpose(-1, -2) @ flat)
    d = d - d.mean(0)
    s_inc, V_inc = _rms_sv(w.reshape(-1, 3))
    s_disp, V_disp = _rms_sv(d)
    if sigma is None:
        est = estimate_noise(w)
        if math.isnan(est):
            raise ValueError(
                f"cannot estimate the noise from {N1} samples per trajectory (need at least 4); pass noise="
            )
        sigma = est
    sigma = max(sigma, FLOOR)
    tol_inc = K_SIGMA * math.sqrt(2.0) * sigma
    tol_disp = K_SIGMA * sigma
    tol_axis = K_SIGMA * math.sqrt(2.0) * sigma
    tol_u = K_SIGMA * sigma
    z_inc, z_disp = s_inc / tol_inc, s_disp / tol_disp
    z = torch.maximum(z_inc, z_disp)
    rank = int((z > 1.0).sum())
    a = _signed(V_disp[0] if float(z_disp[0]) >= float(z_inc[0]) else V_inc[0])
    drift = axis_drift(flat, a)
    a1, a2, resid = universal_fit(flat)
    zero = (0.0, 0.0, 0.0)
    axes = (zero, zero)
    z1, z2 = float(z[0]), float(z[1])
    inf = math.inf

    def ratio(num: float, den: float) -> float:
        return num / den if den > 0 else inf

    if free:
        kind, margin = "free", math.nan
    elif rank == 0:
        kind, margin = "weld", ratio(1.0, z1)
    elif rank == 1 and drift <= tol_axis:
        kind, margin = "hinge", min(z1, ratio(1.0, z2), ratio(tol_axis, drift))
        axes = (_triple(a), zero)
    else:
        more = z2 if rank >= 2 else drift / tol_axis  # the evidence of a second degree of freedom
        if resid <= tol_u:
            kind, margin = "universal", min(more, ratio(tol_u, resid))
            axes = (_triple(a1), _triple(a2))
        else:
            kind, margin = "ball", min(more, resid / tol_u)
    return JointEvidence(
        kind,
        axes,
        _triple(s_inc),
        _triple(s_disp),
        resid,
        drift,
        sigma,
        tol_inc,
        tol_disp,
        tol_axis,
        tol_u,
        rank,
        margin,
    )


def infer_joints(tree: Tree, R: torch.Tensor | np.ndarray, noise: float | None = None) -> JointInference:
    """Infer every body's joint from coordinates R (T, N+1, B, 3, 3) (or (N+1, B, 3, 3): one trajectory)
    stored as `tree.rotations` says; computed in float64. `noise`: the rotation noise per sample and
    axis (rad), None to estimate it per joint from the data (module docstring, step 2). A free root
    gets "free" (its evidence is reported all the same). Returns a `JointInference`; its `tree` is
    `tree.with_joints(kinds, axes)`."""
    R = R if isinstance(R, torch.Tensor) else torch.from_numpy(np.asarray(R))
    R = R.to(torch.promote_types(R.dtype, torch.get_default_dtype()) if R.is_floating_point() else R.dtype)
    if R.ndim == 4:
        R = R[None]
    if R.ndim != 5 or R.shape[-2:] != (3, 3) or R.shape[2] != tree.n_bodies:
        raise ValueError(f"R must have shape (T, N+1, {tree.n_bodies}, 3, 3), got {tuple(R.shape)}")
    if R.shape[1] < 2:
        raise ValueError(f"need at least 2 samples per trajectory, got {R.shape[1]}")
    if noise is not None and not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite angle >= 0 (rad), got {noise!r}")
    R_rel = relative_rotations(tree, R) if tree.rotations == "world" else R
    joints = tuple(
        _joint(R_rel[:, :, b], None if noise is None else float(noise), b == 0 and tree.free_root)
        for b in range(tree.n_bodies)
    )
    kinds = [j.kind for j in joints]
    axes = [[list(r) for r in j.axes] for j in joints]
    return JointInference(joints, tree.with_joints(kinds, axes), "estimated" if noise is None else "given")


def _vec(v: Sequence[float]) -> str:
    return "[" + " ".join(f"{x:+.3f}" for x in v) + "]"


def format_inference(result: JointInference, body_names: Sequence[str] | None = None) -> str:
    """A plain-text table, one line per body: name, kind, axis (axes), RMS singular values of the
    increments and of the displacements, the universal fit residual, the noise sigma and the
    increments' tolerance (rad), and the verdict's margin (x: how many times over its tolerance the
    closest decisive comparison is)."""
    names = list(body_names) if body_names is not None else [f"body {b}" for b in range(len(result.joints))]
    w = max([len(n) for n in names] + [4])
    head = (
        f"{'body':<{w}}  {'kind':<9}  {'axis (hinge: body frame; universal: parent; body)':<34}  "
        f"{'increment s1 s2 s3':<26}  {'displacement s1 s2 s3':<26}  {'univ.res':>8}  {'sigma':>8}  "
        f"{'tol':>8}  margin"
    )
    lines = [
        f"joints inferred from the data (noise {result.noise_source}; tol = {K_SIGMA:g} sqrt(2) sigma for "
        "increments, a direction moves above it; docs/joints.md)",
        head,
    ]
    for name, j in zip(names, result.joints):
        if j.kind == "hinge":
            ax = _vec(j.axes[0])
        elif j.kind == "universal":
            ax = _vec(j.axes[0]) + ";" + _vec(j.axes[1])
        else:
            ax = "-"
        si = " ".join(f"{x:.1e}" for x in j.increment_sv)
        sd = " ".join(f"{x:.1e}" for x in j.displacement_sv)
        m = "-" if math.isnan(j.margin) else (">1e6" if j.margin > 1e6 else f"x{j.margin:.3g}")
        lines.append(
            f"{name:<{w}}  {j.kind:<9}  {ax:<34}  {si:<26}  {sd:<26}  {j.universal_residual:8.1e}  "
            f"{j.noise:8.1e}  {j.tol_increment:8.1e}  {m}"
        )
    return "\n".join(lines)


__all__ = [
    "K_SIGMA",
    "FLOOR",
    "JointEvidence",
    "JointInference",
    "infer_joints",
    "estimate_noise",
    "axis_drift",
    "universal_fit",
    "format_inference",
]
