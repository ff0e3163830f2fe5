"""Fused training loss of the Euclidean DFLNN baseline (`model.py` beside this folder; the fused path).

The forced DEL residual in closed form, with the potential's input gradient from
`mlp_derivatives.potential_input_gradient` (plain tensor expressions), so that the loss's backward
differentiates one explicit graph instead of a double backward through `autograd.grad(...,
create_graph=True)`, and the regularity term's mixed Hessian (constant here) built once instead of
by 12 autograd passes per batch.

Euclidean coordinates (`EuclideanDFLNN`): L_d(x0, x1) = h/2 xd^T K xd - h V(x0), xd = (x1 - x0)/h,
with the constant kinetic matrix K = [[I3 (x) (J_d + m rho rho^T), m I3 (x) rho], [m I3 (x) rho^T, m I3]]
(the R block alone for an SO(3) body; (x) the Kronecker product over the rows of R). Then

    r_k = K (x_k - x_{k-1})/h - K (x_{k+1} - x_k)/h - h dV(x_k) + F^+(x_{k-1}, x_k) + F^-(x_k, x_{k+1})

and the mixed Hessian is -K/h at every pair: its log-determinant is computed once per batch.

Same numbers as the reference (the reference path: autograd of `lagrangian`) to rounding;
tests/test_fused_baselines.py checks losses and gradients to 1e-12 relative.
"""

from __future__ import annotations

import torch

from ... import mlp_derivatives


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
        r = r - h * mlp_derivatives.potential_input_gradient(model.potential, x)
    if model.damping is not None:
        r = r + 0.5 * h * (model.forces(x_prev, x)[1] + model.forces(x, x_next)[0])
    logdet = None
    if n_reg > 0:
        logdet = torch.linalg.slogdet(-K / h).logabsdet.expand(n_reg)
    return r, logdet


# ---------------------------------------------------------------------------- Euler-angle DFLNN
