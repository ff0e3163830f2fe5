"""Fused training loss of the Euler-angle DFLNN baseline (`model.py` beside this folder; the fused path).

The forced DEL residual in closed form (`euler_residual`: both pairs of a triplet in one batch, so the
potential MLP runs once on 2N midpoints, its input gradient from `mlp_derivatives`), so that the loss's
backward is one pass instead of a double backward through `autograd.grad(..., create_graph=True)`; and
the regularity term's mixed Hessian (`euler_mixed_hessian`: E(q)'s first and second derivatives written
out, the potential's Hessian by `mlp_derivatives.gradient_and_hvp`) instead of four autograd passes.

Same numbers as the reference (the reference path: autograd of `lagrangian`) to rounding;
tests/test_fused_baselines.py checks losses and gradients to 1e-12 relative.
"""

from __future__ import annotations

import torch

from ....lie import euler
from ... import mlp_derivatives


def _mat(*rows: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def _rate_matrix_first_derivatives(qm: torch.Tensor) -> torch.Tensor:
    """dE (P, 3, 3, 3) of the ZYX rate matrix E(q) (`euler.rate_matrix`, a function of phi = q_0 and
    theta = q_1 only) at qm (P, 3): dE[:, a] = dE/dq_a."""
    phi, theta = qm[..., 0], qm[..., 1]
    cf, sf, ct, st = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    o = torch.zeros_like(phi)
    d_phi = _mat((o, o, o), (o, -sf, cf * ct), (o, -cf, -sf * ct))
    d_theta = _mat((o, o, -ct), (o, o, -sf * st), (o, o, -cf * st))
    return torch.stack((d_phi, d_theta, torch.zeros_like(d_phi)), 1)


def _rate_matrix_derivatives(qm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and second derivatives of E(q): qm (P, 3) -> (dE (P, 3, 3, 3), d2E (P, 3, 3, 3, 3)),
    d2E[:, a, b] = d^2 E/dq_a dq_b."""
    phi, theta = qm[..., 0], qm[..., 1]
    cf, sf, ct, st = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    o = torch.zeros_like(phi)
    d_pp = _mat((o, o, o), (o, -cf, -sf * ct), (o, sf, -cf * ct))
    d_pt = _mat((o, o, o), (o, o, -cf * st), (o, o, sf * st))
    d_tt = _mat((o, o, st), (o, o, -sf * ct), (o, o, -cf * ct))
    z = torch.zeros_like(d_pp)
    d2E = torch.stack((torch.stack((d_pp, d_pt, z), 1), torch.stack((d_pt, d_tt, z), 1), torch.stack((z, z, z), 1)), 1)
    return _rate_matrix_first_derivatives(qm), d2E


def euler_mixed_hessian(model, q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor | None:
    """d^2 L_d / dq0 dq1 of `EulerDFLNN.lagrangian` in closed form: q0, q1 (P, 3) -> (P, 3, 3) (None when
    the potential network is not one `mlp_derivatives` supports).

    With w = E(qm) qd, p = J w, W0 = dw/dq0 = -E/h + M/2, W1 = dw/dq1 = E/h + M/2 (M = d(E qd)/dqm at fixed
    qd), Pd[a] = p^T dE/dq_a and Q_ab = p^T (d^2 E/dq_a dq_b) qd:
        H = h [W0^T J W1 + (Pd - Pd^T)/(2h) + Q/4] - h/4 d^2 V(qm)."""
    h = model.h
    qd, qm = (q1 - q0) / h, 0.5 * (q0 + q1)
    E = euler.rate_matrix(qm)
    dE, d2E = _rate_matrix_derivatives(qm)
    J = model.inertia.J()[0]
    w = (E @ qd[..., None])[..., 0]
    p = w @ J.T
    M = (dE @ qd[:, None, :, None])[..., 0].transpose(-1, -2)  # columns dw/dq_a
    W0, W1 = -E / h + 0.5 * M, E / h + 0.5 * M
    Pd = (p[:, None, None, :] @ dE)[..., 0, :]  # (P, a, 3)
    Q = (p[:, None, None, None, :] @ d2E @ qd[:, None, None, :, None])[..., 0, 0]
    H = h * (W0.transpose(-1, -2) @ J @ W1 + (Pd - Pd.transpose(-1, -2)) / (2 * h) + 0.25 * Q)
    if model.potential is not None:
        n = qm.shape[0]
        eye = torch.eye(3, dtype=qm.dtype, device=qm.device)
        gh = mlp_derivatives.gradient_and_hvp(model.potential, qm.repeat(3, 1), eye.repeat_interleave(n, 0))
        if gh is None:
            return None
        H = H - 0.25 * h * gh[1].reshape(3, n, 3).transpose(0, 1)
    return H


def euler_residual(model, q_prev: torch.Tensor, q: torch.Tensor, q_next: torch.Tensor) -> torch.Tensor:
    """`EulerDFLNN.residual` in closed form: q_prev, q, q_next (N, 3) -> r (N, 3), differentiable in the
    inputs and the parameters.

    For a pair (q0, q1) with qd = (q1 - q0)/h, qm = (q0 + q1)/2, w = E(qm) qd, p = J w and
    c_a = p^T (dE/dq_a) qd:
        D1 L_d = -E^T p + h/2 (c - dV(qm)),   D2 L_d = E^T p + h/2 (c - dV(qm)),
        h/2 Q = -h/2 E^T D w.
    With X = h/2 (c - dV(qm) - E^T D w) and Y = E^T p of the pairs (q_prev, q) [first] and (q, q_next)
    [second]: r = Y_first - Y_second + X_first + X_second. Both pairs go through the potential MLP as
    one batch of 2N midpoints."""
    h, n = model.h, q.shape[0]
    q0, q1 = torch.cat((q_prev, q), 0), torch.cat((q, q_next), 0)
    qd, qm = (q1 - q0) / h, 0.5 * (q0 + q1)
    E = euler.rate_matrix(qm)
    Et = E.transpose(-1, -2)
    w = (E @ qd[..., None])[..., 0]
    p = w @ model.inertia.J()[0].T
    c = (p[:, None, None, :] @ _rate_matrix_first_derivatives(qm) @ qd[:, None, :, None])[..., 0, 0]
    X = c
    if model.potential is not None:
        X = X - mlp_derivatives.potential_input_gradient(model.potential, qm)
    if model.damping is not None:
        X = X - (Et @ (w @ model.damping().T)[..., None])[..., 0]
    X = (0.5 * h) * X
    Y = (Et @ p[..., None])[..., 0]
    return Y[:n] - Y[n:] + X[:n] + X[n:]
