"""Fused training path of the GLNN baselines (`models.glnn`, `runtime.fused`): the vector field

    R' = R hat(w),   w' = A(w) = J^{-1} ((J w) x w - D w)

(no potential: the Exp 2 scenes) with hand-written vector-Jacobian products: A(w) as one autograd
node (`accel`, Heun and Midpoint) instead of the ~15 small autograd nodes of the reference
`GLNN.accel`, and the whole field for the one-node dopri5 (`Dopri5Field`). Training unrolls the
integrator over 100-step windows at batch 8-32, so the cost is the number of small kernels and
autograd nodes (docs/benchmarks.md, "Baselines"), not arithmetic. The rows of R hat(w) are the cross
products R_i x w, one kernel.

`solvers.dopri5` runs a whole adaptive solve as one autograd node (GLNN-RK4's training and rollouts).

Same numbers as the reference to rounding (tests/test_fused_baselines.py, tests/test_dopri5.py:
losses and gradients to 1e-12 relative). Only first derivatives (the training loss's backward);
models with a learned potential, and the Heun / Midpoint rollouts, keep the reference path.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable


def _accel(w: torch.Tensor, J: torch.Tensor, Jinv: torch.Tensor, D: torch.Tensor | None):
    """(u = J w, tau = (J w) x w - D w, A = J^{-1} tau), each (N, 3), from w (N, 3)."""
    u = w @ J.T
    tau = torch.linalg.cross(u, w)
    if D is not None:
        tau = tau - w @ D.T
    return u, tau, tau @ Jinv.T


def _accel_backward(gA, w, u, tau, J, Jinv, D):
    """Vector-Jacobian product of `_accel`: gA (N, 3) -> (gw (N, 3), gJ, gJinv, gD (3, 3) or None)."""
    gtau = gA @ Jinv
    gJinv = gA.T @ tau
    gu = torch.linalg.cross(w, gtau)  # <gtau, u x w> = <u, w x gtau> = <w, gtau x u>
    gw = torch.linalg.cross(gtau, u) + gu @ J
    gJ = gu.T @ w
    gD = None
    if D is not None:
        gw = gw - gtau @ D
        gD = -(gtau.T @ w)
    return gw, gJ, gJinv, gD


class _Accel(torch.autograd.Function):
    """A(w) (N, 3) from w (N, 3) and J, J^{-1}, D (3, 3) (D optional)."""

    @staticmethod
    def forward(ctx, w, J, Jinv, D):
        u, tau, A = _accel(w, J, Jinv, D)
        ctx.save_for_backward(w, u, tau, J, Jinv, D)
        return A

    @staticmethod
    @once_differentiable
    def backward(ctx, gA):
        w, u, tau, J, Jinv, D = ctx.saved_tensors
        return _accel_backward(gA, w, u, tau, J, Jinv, D)


def accel(w: torch.Tensor, J: torch.Tensor, Jinv: torch.Tensor, D: torch.Tensor | None) -> torch.Tensor:
    """A(w) = J^{-1}((J w) x w - D w): w (N, 3), J, J^{-1}, D (3, 3) -> (N, 3), one autograd node."""
    return _Accel.apply(w, J, Jinv, D)


class Dopri5Field:
    """The dopri5 state's derivative y' = (R hat(w) entries, A(w)) for `solvers.dopri5` (one autograd
    node per solve), feature major: y = (R entries, w) as columns, (12, N), R_i. = y[3i:3i+3],
    w = y[9:]; params (J, J^{-1}, D or None). Feature major because every operand is then contiguous:
    at N = 32 a field evaluation and its vector-Jacobian product take ~30 % / ~15 % less time than in
    rows (per-call cost). `vjp` keeps each stage's pieces of the parameters' gradients and
    `param_grads` sums them with one product per parameter."""

    def forward(self, y: torch.Tensor, params) -> tuple[torch.Tensor, tuple]:
        """y (12, N) -> (y' (12, N), what `vjp` needs); no graph."""
        J, Jinv, D = params
        n = y.shape[1]
        R, w = y[:9].view(3, 3, n), y[9:]
        Rdot = torch.linalg.cross(R, w.expand(3, 3, n), dim=1)  # row i of R hat(w) = R_i x w
        u = torch.mm(J, w)
        tau = torch.linalg.cross(u, w, dim=0)
        if D is not None:
            tau = torch.addmm(tau, D, w, alpha=-1)
        return torch.cat((Rdot.view(9, n), torch.mm(Jinv, tau))), (R, w, u, tau)

    def vjp(self, saved: tuple, g: torch.Tensor, params, acc: list) -> torch.Tensor:
        """g = dL/dy' (12, N) -> dL/dy (12, N); appends this evaluation's parameter pieces to acc."""
        R, w, u, tau = saved
        J, Jinv, D = params
        n = g.shape[1]
        gRd, gA = g[:9].view(3, 3, n), g[9:]
        gtau = torch.mm(Jinv.T, gA)
        gu = torch.linalg.cross(w, gtau, dim=0)
        gw = torch.addmm(torch.linalg.cross(gtau, u, dim=0), J.T, gu)
        if D is not None:
            gw = torch.addmm(gw, D.T, gtau, alpha=-1)
        gR = torch.linalg.cross(w.expand(3, 3, n), gRd, dim=1)
        gw = gw + torch.linalg.cross(gRd, R, dim=1).sum(0)
        acc.append((gA, tau, gu, w, gtau))
        return torch.cat((gR.view(9, n), gw))

    def param_grads(self, acc: list, params) -> tuple:
        """(dL/dJ, dL/dJ^{-1}, dL/dD or None), each (3, 3), from every evaluation's pieces."""
        D = params[2]
        gA, tau, gu, w, gtau = (torch.cat(parts, 1) for parts in zip(*acc))
        return gu @ w.T, gA @ tau.T, (-(gtau @ w.T) if D is not None else None)
