"""Fused training residuals of the Euler-angle and Euclidean DFLNN baselines (`runtime.fused`):
the forced DEL residual in closed form, with the potential's input gradient from
`mlp_derivatives.value_and_gradient` (plain tensor expressions), so that the training loss's
backward differentiates one explicit graph instead of a double backward through `autograd.grad(...,
create_graph=True)` of the MLP. Both Lagrangians of a triplet are evaluated in one batch.

Euler angles (`EulerDFLNN`), per pair (q0, q1): qd = (q1 - q0)/h, qm = (q0 + q1)/2, w = E(qm) qd,
p = J w and c_m = p . dw/dq_m at fixed qd, where (ZYX, E depending on phi and theta only)
dw/dphi = (0, w_2, -w_1), dw/dtheta = -qd_2 (cos theta, sin phi sin theta, cos phi sin theta),
dw/dpsi = 0. Then D_1 L_d = -E^T p + h/2 (c - dV(qm)), D_2 L_d = E^T p + h/2 (c - dV(qm)), and

    r_k = E_1^T (p_1 - h/2 D w_1) - E_2^T (p_2 + h/2 D w_2) + h/2 (c_1 + c_2 - dV(qm_1) - dV(qm_2))

for the pairs 1 = (q_{k-1}, q_k) and 2 = (q_k, q_{k+1}) (the Rayleigh terms are h/2 Q = -h/2 E^T D w).

Euclidean coordinates (`EuclideanDFLNN`): L_d(x0, x1) = h/2 xd^T K xd - h V(x0), xd = (x1 - x0)/h,
with the constant kinetic matrix K = [[I3 (x) (J_d + m rho rho^T), m I3 (x) rho], [m I3 (x) rho^T, m I3]]
(the R block alone for an SO(3) body; (x) the Kronecker product over the rows of R). Then

    r_k = K (x_k - x_{k-1})/h - K (x_{k+1} - x_k)/h - h dV(x_k) + F^+(x_{k-1}, x_k) + F^-(x_k, x_{k+1})

and the mixed Hessian is -K/h at every pair: its log-determinant is computed once per batch.

Same numbers as the reference (`runtime.fused=false`: autograd of `lagrangian`) to rounding;
tests/test_fused_baselines.py checks losses and gradients to 1e-12 relative.
"""

from __future__ import annotations

import torch

from ..lie import euler
from . import mlp_derivatives


def potential_gradient(net: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """dV/dx (..., n) of an MLP potential V = net(x)[..., 0], differentiable in the parameters:
    closed form where `mlp_derivatives` supports the network, else autograd."""
    vg = mlp_derivatives.value_and_gradient(net, x)
    if vg is not None:
        return vg[1]
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True) if not x.requires_grad else x
        (g,) = torch.autograd.grad(net(xg)[..., 0].sum(), xg, create_graph=True)
    return g


def euler_residual(model, q_prev: torch.Tensor, q: torch.Tensor, q_next: torch.Tensor) -> torch.Tensor:
    """The forced DEL residual of `EulerDFLNN.residual` in closed form: q_prev, q, q_next (N, 3) -> (N, 3)."""
    h = model.h
    q0 = torch.stack((q_prev, q))  # (2, N, 3): the pairs (q_{k-1}, q_k) and (q_k, q_{k+1})
    q1 = torch.stack((q, q_next))
    qd = (q1 - q0) / h
    qm = 0.5 * (q0 + q1)
    E = euler.rate_matrix(qm)
    w = (E @ qd[..., None])[..., 0]
    p = w @ model.inertia.J()[0].T
    phi, theta = qm[..., 0], qm[..., 1]
    st, ct, sf, cf = torch.sin(theta), torch.cos(theta), torch.sin(phi), torch.cos(phi)
    c_phi = p[..., 1] * w[..., 2] - p[..., 2] * w[..., 1]
    c_theta = -qd[..., 2] * (ct * p[..., 0] + st * (sf * p[..., 1] + cf * p[..., 2]))
    c = torch.stack((c_phi, c_theta, torch.zeros_like(c_phi)), -1)
    if model.damping is not None:  # p_1 - h/2 D w_1 and p_2 + h/2 D w_2 in the E^T terms
        sign = torch.tensor([-1.0, 1.0], dtype=q.dtype, device=q.device)[:, None, None]
        p = p + (0.5 * h) * sign * (w @ model.damping().T)
    Etp = (E.transpose(-1, -2) @ p[..., None])[..., 0]
    extra = c[0] + c[1]
    if model.potential is not None:
        gV = potential_gradient(model.potential, qm)
        extra = extra - gV[0] - gV[1]
    return Etp[0] - Etp[1] + (0.5 * h) * extra


def kinetic_matrix(model) -> torch.Tensor:
    """K (n, n) of `EuclideanDFLNN` (module docstring): h/2 xd^T K xd is its kinetic discrete Lagrangian."""
    Jd = model.inertia.Jd()[0]
    eye = torch.eye(3, dtype=Jd.dtype, device=Jd.device)
    if not model.se3:
        return torch.kron(eye, Jd)
    m, rho = model.mass()[0], model.rho
    KR = torch.kron(eye, Jd + m * rho[:, None] * rho[None, :])
    KRp = m * torch.kron(eye, rho[:, None])  # (9, 3)
    return torch.cat((torch.cat((KR, KRp), 1), torch.cat((KRp.T, m * eye), 1)), 0)


def euclidean_residual_and_logdet(
    model, x_prev: torch.Tensor, x: torch.Tensor, x_next: torch.Tensor, n_reg: int
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(`EuclideanDFLNN.residual` (N, n), log|det| of the mixed Hessian at `n_reg` pairs (n_reg,) or
    None when 0) in closed form from x_prev, x, x_next (N, n)."""
    h = model.h
    K = kinetic_matrix(model)
    r = ((x - x_prev) / h - (x_next - x) / h) @ K.T
    if model.potential is not None:
        r = r - h * potential_gradient(model.potential, x)
    if model.damping is not None:
        r = r + 0.5 * h * (model.forces(x_prev, x)[1] + model.forces(x, x_next)[0])
    logdet = None
    if n_reg > 0:
        logdet = torch.linalg.slogdet(-K / h).logabsdet.expand(n_reg)
    return r, logdet
