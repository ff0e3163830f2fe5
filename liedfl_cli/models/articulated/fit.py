"""A start for the articulated model that does not care about units or mass ratios: the prediction-
weighted least-squares fit of its physical parameters, made physically consistent.

The DEL residual of a tree is linear in each body's ten inertial parameters
    pi_b = (m_b, c_b = m_b rho_b, Q_b = J_d,b + m_b rho_b rho_b^T)
(the kinetic term K = tr((I - W)(J_d + m rho rho^T))/h + m |z|^2/(2h) + z^T (W - I) m rho / h; uniform
gravity gamma.(m p + R m rho)) and in the per-DoF damping d: r = Y pi + r0 over the training triplets
(r0: the parts with no such parameter, e.g. an MLP potential, held at their current values). Y is
exact by forward-mode autodiff of the model's own batch residual (`ArticulatedLieDFLNN._batch_residual`
with explicit parameters). Rows are weighted by H^{-1} (H: the Newton Jacobian of the residual in the
next pose), so the fit minimises the first-order one-step prediction error sum |H^{-1} r|^2 rather than
the residual's mixed units; columns are scaled to unit norm (the fit is the same in metres and in
millimetres). The scale the data cannot see is fixed by sum_b m_b = M (dataset.total_mass, else the
model's current total), and the other gauge directions (a child's mass sliding onto its parent) by a
small pull towards the current parameters. H depends on pi: the fit is repeated `passes` times with H
from the last one. Each body is then projected onto physical consistency (m > 0; the inertia about the
centre of mass positive definite with the triangle inequality, its principal moments raised where they
fail) and written into the model, so first-order epochs continue from there.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import torch

RIDGE = 1e-6
"""Weight of the pull towards the current parameters (in column-normalised units): picks a point in the
gauge's null space and keeps poorly determined combinations near the geometric start."""
MAX_TRIPLETS = 1500
"""Triplets the regressor is built on (evenly strided): enough rows for a few hundred parameters."""


@dataclass
class FitReport:
    """What the start did: passes, seconds, the weighted residual norm before and after each pass, the
    regressor's numerical rank against its column count, and the bodies whose inertia was projected."""

    passes: int = 0
    seconds: float = 0.0
    weighted_rms: list[float] = field(default_factory=list)
    rank: int = 0
    n_params: int = 0
    projected: list[int] = field(default_factory=list)
    scale: float = 1.0

    def line(self) -> str:
        rms = " -> ".join(f"{x:.3g}" for x in self.weighted_rms)
        proj = f"; inertia projected for bodies {self.projected}" if self.projected else ""
        proj += f"; scaled x{self.scale:.3g} for regularity" if self.scale != 1.0 else ""
        return (
            f"least-squares start: {self.passes} passes in {self.seconds:.1f} s, one-step error (first order) "
            f"{rms}; regressor rank {self.rank} of {self.n_params} parameters{proj}"
        )


def _sym6(Q: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) symmetric -> (B, 6): xx, yy, zz, xy, xz, yz."""
    return torch.stack((Q[:, 0, 0], Q[:, 1, 1], Q[:, 2, 2], Q[:, 0, 1], Q[:, 0, 2], Q[:, 1, 2]), -1)


def _unsym6(q: torch.Tensor) -> torch.Tensor:
    """(B, 6) -> (B, 3, 3) symmetric."""
    xx, yy, zz, xy, xz, yz = q.unbind(-1)
    return torch.stack(
        (torch.stack((xx, xy, xz), -1), torch.stack((xy, yy, yz), -1), torch.stack((xz, yz, zz), -1)), -2
    )


def pack(Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor, d: torch.Tensor | None) -> torch.Tensor:
    """(J_d (B, 3, 3), m (B,), rho (B, 3), d (k,) or None) -> pi (10 B + k,): per body m, m rho, Q."""
    c = m[:, None] * rho
    Q = Jd + m[:, None, None] * rho[:, :, None] * rho[:, None, :]
    body = torch.cat((m[:, None], c, _sym6(Q)), -1).reshape(-1)
    return body if d is None else torch.cat((body, d))


def unpack(pi: torch.Tensor, B: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Inverse of `pack`: pi -> (J_d, m, rho, d or None)."""
    body = pi[: 10 * B].reshape(B, 10)
    m, c, Q = body[:, 0], body[:, 1:4], _unsym6(body[:, 4:])
    rho = c / m[:, None]
    Jd = Q - c[:, :, None] * c[:, None, :] / m[:, None, None]
    d = pi[10 * B :] if pi.shape[0] > 10 * B else None
    return Jd, m, rho, d


def consistent(Jd: torch.Tensor, m: torch.Tensor, floor: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """(J about the COM (B, 3, 3) positive definite with the triangle inequality, m (B,) > 0, the bodies
    changed) from a least-squares J_d (B, 3, 3) and m (B,): J = tr(J_d) I - J_d, its principal moments
    raised to floor * their largest and so that each is at most the sum of the other two (plus 1e-3)."""
    m_out = m.clamp_min(floor * float(m.abs().max()))
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=Jd.dtype, device=Jd.device) - Jd
    J = 0.5 * (J + J.transpose(-1, -2))
    lam, V = torch.linalg.eigh(J)
    big = lam.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    lam2 = lam.clamp_min(floor * big)
    # triangle: the largest at most (1 - 1e-3) (the sum of the others), else raise the two smaller ones
    short = lam2[:, 2] - (1 - 1e-3) * (lam2[:, 0] + lam2[:, 1])
    lift = (short.clamp_min(0) / (2 * (1 - 1e-3)))[:, None] * torch.tensor(
        [1.0, 1.0, 0.0], dtype=J.dtype, device=J.device
    )
    lam2 = lam2 + lift
    changed = [int(b) for b in torch.nonzero(((lam2 - lam).abs() > 1e-9 * big).any(-1) | (m_out != m)).flatten()]
    return V @ torch.diag_embed(lam2) @ V.transpose(-1, -2), m_out, changed


def regressor(model: Any, batch: Any, pi0: torch.Tensor) -> torch.Tensor:
    """d r / d pi (N k, P) of the batch's residual (`ArticulatedLieDFLNN._batch_residual` with the
    parameters `unpack(pi)`), exact: r is linear in pi. Body b's world covector depends on body b's ten
    numbers only, so one forward-mode pass in ten colours (the k-th number of every body at once) gives
    every body's 6 x 10 block; the FK Jacobian A (and T on a reduced tree) then maps the blocks, and the
    per-DoF damping enters as -(h/2) diag(nu~_{k-1} + nu~_k). (The same matrix as
    `torch.func.jacfwd` of the residual in P directions, which pushes each of them through A: tested.)"""
    B = model.tree.n_bodies
    P = pi0.shape[0]
    colours = torch.zeros(P, 10, dtype=pi0.dtype, device=pi0.device)
    colours[torch.arange(10 * B, device=pi0.device), torch.arange(10 * B, device=pi0.device) % 10] = 1.0

    def covectors(t: torch.Tensor) -> torch.Tensor:
        Jd, m, rho, _ = unpack(pi0 + colours @ t, B)
        return model.body_covectors(batch, (Jd, m, rho, None))[0]

    zero = pi0.new_zeros(10)
    N = batch.A.shape[0]
    Phi = torch.func.jacfwd(covectors)(zero).detach().reshape(N, B, 6, 10)
    Yb = torch.einsum("Nbsd,Nbsk->Ndbk", batch.A, Phi).reshape(N, -1, 10 * B)  # (N, dim, 10 B)
    if not model.reduced:
        return (
            Yb.reshape(-1, P)
            if P == 10 * B
            else torch.cat((Yb, Yb.new_zeros(N, Yb.shape[1], P - 10 * B)), -1).reshape(-1, P)
        )
    Yb = batch.T.transpose(-1, -2) @ Yb  # (N, n, 10 B)
    n = Yb.shape[1]
    if P == 10 * B:
        return Yb.reshape(-1, P)
    nu = batch.nu_red_prev + batch.nu_red_next  # (N, n)
    Yd = torch.diag_embed(-0.5 * model.h * nu)  # (N, n, n): d enters the reduced residual per DoF
    return torch.cat((Yb, Yd), -1).reshape(N * n, P)


def least_squares_start(
    model: Any, samples: Any, total_mass: float | None = None, passes: int = 3, epsilon: float | None = None
) -> FitReport:
    """Fit `model`'s inertial parameters and per-DoF damping to the triplets `samples`
    (`ArticulatedTriplets`) by prediction-weighted least squares (module docstring) and write the
    consistent result into the model. epsilon: the regularity threshold; when given, every parameter is
    then scaled by one factor (which changes no prediction: the DEL equations are homogeneous) so that
    every body's mixed-Hessian block has log|det| >= epsilon + 1 on the samples (the regularity term is
    then inactive where training starts). Returns a `FitReport`."""
    t0 = time.perf_counter()
    report = FitReport()
    B = model.tree.n_bodies
    n = samples.n
    dev = samples.cur.R.device
    idx = torch.linspace(0, n - 1, min(n, MAX_TRIPLETS), dtype=samples.cur.R.dtype, device=dev).round().long().unique()
    if samples.A_next is None:
        samples.enable_jacobian()
    batch = samples.batch(idx, torch.Generator().manual_seed(0), 0)
    damper = model.dof_damper
    with torch.no_grad():
        Jd0, m0, rho0 = (t.detach() for t in model._params())
        d0 = None if damper is None else damper.coefficients().detach()
    M = float(m0.sum()) if total_mass is None else float(total_mass)
    pi0 = pack(Jd0, m0, rho0, d0)
    pi0 = torch.cat((pi0[: 10 * B] * (M / float(m0.sum())), pi0[10 * B :] * (M / float(m0.sum()))))

    def residual(pi: torch.Tensor) -> torch.Tensor:
        Jd, m, rho, d = unpack(pi, B)
        return model._batch_residual(batch, (Jd, m, rho, d)).reshape(-1)

    with torch.no_grad():
        r_at = residual(pi0)
    Y = regressor(model, batch, pi0)  # (rows, P): exact, r is linear in pi
    r0 = r_at - Y @ pi0
    P = Y.shape[1]
    e = torch.zeros(P, dtype=Y.dtype, device=Y.device)
    e[0 : 10 * B : 10] = 1.0  # sum of masses
    # the rows of H^-1 r are a step's errors: radians, and a free root's translation in the file's length
    # unit; dividing the translation by the tree's own length makes every row unit-free
    offsets = torch.tensor(model.tree.offsets, dtype=Y.dtype, device=Y.device).norm(dim=-1)
    L = float(offsets[offsets > 0].median()) if bool((offsets > 0).any()) else 1.0
    unit = torch.ones(Y.shape[0] // max(batch.A.shape[0], 1), dtype=Y.dtype, device=Y.device)
    if model.tree.free_root:
        unit[3:6] = 1.0 / L
    # a uniform field of known strength (model.gravity) makes the overall scale visible in the data
    from ...mechanics.potentials import UniformGravityPotential

    V = model.potential_world
    scale_seen = isinstance(V, UniformGravityPotential) and float(V.gravity) > 0
    pi = pi0
    best_pi, best_rms = None, float("inf")
    for _ in range(passes):
        Jd, m, rho, d = unpack(pi, B)
        _set(model, Jd, m, rho, d)
        with torch.no_grad():
            H = model.newton_jacobian_batch(batch).detach()  # (N, n, n)
        N, k = H.shape[0], H.shape[-1]
        Hinv = torch.linalg.pinv(H)
        X = (unit[:, None] * (Hinv @ Y.reshape(N, k, P))).reshape(N * k, P)
        x0 = (unit[:, None] * (Hinv @ r0.reshape(N, k, 1))).reshape(-1)
        report.weighted_rms.append(float((X @ pi + x0).pow(2).mean().sqrt()))
        s = X.norm(dim=0).clamp_min(1e-300)  # column scales: units drop out
        Xs = X / s
        A = Xs.T @ Xs
        lam = RIDGE * float(A.diagonal().mean())
        target = pi0 * s
        rhs = -(Xs.T @ x0) + lam * target
        es = e / s
        if scale_seen:  # gravity of a known strength fixes the scale: no gauge to pin
            pi_new = torch.linalg.solve(A + lam * torch.eye(P, dtype=Y.dtype, device=Y.device), rhs) / s
        else:
            K = torch.zeros(P + 1, P + 1, dtype=Y.dtype, device=Y.device)
            K[:P, :P] = A + lam * torch.eye(P, dtype=Y.dtype, device=Y.device)
            K[:P, P] = es
            K[P, :P] = es
            sol = torch.linalg.solve(K, torch.cat((rhs, torch.tensor([M], dtype=Y.dtype, device=Y.device))))
            pi_new = sol[:P] / s
        pi_new = gauge_repair(pi_new, Xs, s, B)
        Jd, m, rho, d = unpack(pi_new, B)
        J, m_c, changed = consistent(Jd, m)
        Jd_c = (
            J.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] / 2 * torch.eye(3, dtype=J.dtype, device=J.device) - J
        )
        rho_c = (m[:, None] * rho) / m_c[:, None]
        d_c = None if d is None else d.clamp_min(0.0)
        pi = pack(Jd_c, m_c, rho_c, d_c)
        rms = float((X @ pi + x0).pow(2).mean().sqrt())  # with this pass's weights
        if rms < best_rms:
            best_pi, best_rms, report.projected = pi, rms, changed
        report.projected = changed
        report.passes += 1
        report.rank = int(torch.linalg.matrix_rank(Xs).item())
    pi = best_pi if best_pi is not None else pi
    if best_rms >= report.weighted_rms[0]:  # no better than where the model stood: keep that
        pi = pi0
    Jd, m, rho, d = unpack(pi, B)
    _set(model, Jd, m, rho, d)
    with torch.no_grad():
        H = model.newton_jacobian_batch(batch).detach()
        x = unit[:, None] * (torch.linalg.pinv(H) @ residual(pi).reshape(H.shape[0], -1, 1))
    report.weighted_rms.append(float(x.pow(2).mean().sqrt()))
    if epsilon is not None:
        with torch.no_grad():
            logdet = model.world_slogdet(samples.inc_next.index(idx))[0]
        low = float(logdet.min())
        if low < epsilon + 1.0:
            report.scale = float(math.exp((epsilon + 1.0 - low) / 6.0))
            Jd, m, rho, d = unpack(pi, B)
            _set(model, report.scale * Jd, report.scale * m, rho, None if d is None else report.scale * d)
    report.n_params = P
    report.seconds = time.perf_counter() - t0
    return report


def _violation(pi: torch.Tensor, B: int) -> torch.Tensor:
    """How far pi is from physical consistency (0 when consistent), differentiable: per body the
    squared shortfalls of m and of the inertia's principal moments below a small margin and of the
    triangle inequality, relative to the body's largest moment."""
    Jd, m, _, _ = unpack(pi, B)
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=Jd.dtype, device=Jd.device) - Jd
    lam = torch.linalg.eigvalsh(0.5 * (J + J.transpose(-1, -2)))
    big = lam.abs().amax(-1).detach().clamp_min(1e-300)
    margin = 1e-3 * big
    pos = torch.relu(margin[:, None] - lam) / big[:, None]
    tri = torch.relu(lam[:, 2] - 0.999 * (lam[:, 0] + lam[:, 1])) / big
    mass = torch.relu(1e-3 * m.abs().max().detach() - m) / m.abs().max().detach()
    return (pos**2).sum() + (tri**2).sum() + (mass**2).sum()


def gauge_repair(pi: torch.Tensor, Xs: torch.Tensor, s: torch.Tensor, B: int, steps: int = 200) -> torch.Tensor:
    """Move pi within the regressor's null space (the gauge the data cannot see: a child's mass sliding
    onto its parent as a point mass at the joint changes no prediction) towards physical consistency,
    before any projection that would change predictions. Xs: the column-scaled weighted regressor, s
    its column scales; the mass-sum direction is excluded (the scale stays fixed)."""
    if float(_violation(pi, B)) == 0.0:
        return pi
    U, S, Vh = torch.linalg.svd(Xs, full_matrices=False)
    null = Vh[1e-7 * S.max() > S]  # (k, P) in scaled coordinates
    if null.shape[0] == 0:
        return pi
    Nmat = (null / s).T  # unscaled directions (P, k)
    e = torch.zeros(pi.shape[0], dtype=pi.dtype, device=pi.device)
    e[0 : 10 * B : 10] = 1.0
    Nmat = Nmat - torch.outer(e, e @ Nmat) / float(e @ e)  # keep the total mass
    t = torch.zeros(Nmat.shape[1], dtype=pi.dtype, device=pi.device, requires_grad=True)
    best, best_v = pi, float(_violation(pi, B))
    for _ in range(4):  # restarts: the eigenvalue penalty is piecewise smooth and LBFGS can stall on a kink
        opt = torch.optim.LBFGS([t], max_iter=steps, line_search_fn="strong_wolfe")

        def closure(opt=opt):
            opt.zero_grad()
            v = _violation(pi + Nmat @ t, B)
            v.backward()
            return v

        try:
            opt.step(closure)
        except (torch.linalg.LinAlgError, RuntimeError):  # a mass through zero: keep the best so far
            break
        cand = (pi + Nmat @ t).detach()
        v = float(_violation(cand, B))
        if v < best_v:
            best, best_v = cand, v
        if best_v < 1e-12:
            break
        with torch.no_grad():
            t.add_(1e-3 * torch.randn_like(t) * (1.0 + t.abs().max()))
    return best


@torch.no_grad()
def _set(model: Any, Jd: torch.Tensor, m: torch.Tensor, rho: torch.Tensor, d: torch.Tensor | None) -> None:
    """Write (J_d, m, rho, d) into the model's parameters (J = tr(J_d)/2 I ... via J = tr(J_d) I - J_d)."""
    J, m, _ = consistent(Jd, m)
    model.inertia.set_J(J)
    model.mass.set_value(m)
    model.rho.copy_(rho)
    if d is not None and model.dof_damper is not None:
        model.dof_damper.set_coefficients(d.clamp_min(0.0))


__all__ = ["FitReport", "pack", "unpack", "consistent", "least_squares_start"]
