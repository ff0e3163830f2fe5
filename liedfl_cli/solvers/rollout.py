"""Roll a discrete model forward from (g_0, g_1) by solving its DEL residual for each increment."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from ..lie import Pose
from .newton import newton_solve


@dataclass
class Rollout:
    """Predicted trajectory and solver diagnostics.

    pose: R (T, S+1, B, 3, 3), p (T, S+1, m, 3); converged, iterations: (T, S-1) per implicit step;
    residual_norm: (T, S-1); seconds: wall time of the whole rollout.
    """

    pose: Pose
    converged: torch.Tensor
    iterations: torch.Tensor
    residual_norm: torch.Tensor
    seconds: float

    @property
    def n_failed(self) -> int:
        return int((~self.converged).sum())

    def first_failure(self) -> int | None:
        bad = (~self.converged).any(0).nonzero()
        return int(bad[0]) + 1 if len(bad) else None  # step index k+1 that was not solved


@torch.no_grad()
def rollout_discrete(
    model, g0: Pose, g1: Pose, steps: int, tol: float = 1e-5, max_iter: int = 10, max_halvings: int = 6, progress=None
) -> Rollout:
    """Predict g_2..g_steps from g0, g1 (each with leading batch dim T).

    Newton works on the increment W_k = g_k^{-1} g_{k+1} (updated by W exp(delta), so it stays
    on the group exactly) and is warm-started from W_{k-1}. A step whose Newton solve does
    not converge is kept (last iterate) and flagged in `converged`; nothing is silently accepted.
    `progress`: optional callable(k) for progress bars.
    """
    G = model.G
    t0 = time.perf_counter()
    Rs, ps = [g0.R, g1.R], [g0.p, g1.p]
    g_prev, g = g0, g1
    inc = G.increment(g0, g1)  # warm start: the previous increment
    conv, its, res = [], [], []
    for k in range(1, steps):
        with torch.enable_grad():  # potential gradients and autodiff Jacobians need autograd
            const = model.residual_const(g_prev, g).detach()
            f = lambda x, g=g, const=const: const + model.residual_var(g, G.compose(g, x))
            jac = lambda x, g=g: model.jacobian_var(g, x)
            sol = newton_solve(f, jac, inc, G.retract, tol=tol, max_iter=max_iter, max_halvings=max_halvings)
        # Newton-Schulz step on the increment: its retractions would otherwise accumulate
        # rounding drift off SO(3) across the warm-started steps (O(k eps) instead of O(sqrt(k) eps)).
        W = sol.x.R.detach()
        W = 0.5 * W @ (3.0 * torch.eye(3, dtype=W.dtype) - W.transpose(-1, -2) @ W)
        inc = Pose(W, sol.x.p.detach())
        g_next = G.compose(g, inc)
        Rs.append(g_next.R)
        ps.append(g_next.p)
        conv.append(sol.converged)
        its.append(sol.iterations)
        res.append(sol.residual_norm.detach())
        g_prev, g = g, g_next
        if progress is not None:
            progress(k)
    T = g0.R.shape[0]
    empty = lambda dt: torch.zeros(T, 0, dtype=dt)
    return Rollout(
        Pose(torch.stack(Rs, 1), torch.stack(ps, 1)),
        torch.stack(conv, 1) if conv else empty(torch.bool),
        torch.stack(its, 1) if its else empty(torch.long),
        torch.stack(res, 1) if res else empty(torch.float64),
        time.perf_counter() - t0,
    )
