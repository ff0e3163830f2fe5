"""The rollout loops: one for implicit (DEL) models, one for explicit integrators.

Both predict g_2..g_S from the observed pair (g_0, g_1) for a batch of T trajectories and
return a `Rollout` whose pose sequence starts with g_0, g_1 as given. Implicit steps are
solved by damped Newton (`solvers.newton`) and every step's convergence flag, iteration
count and residual norm are kept; a step that does not converge keeps its last iterate and
is flagged, never silently accepted. The models say what one step is (`models.base`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from ..lie import Pose
from .newton import NewtonResult, solve
from .options import SolverOptions


@dataclass
class Rollout:
    """Predicted trajectory and solver diagnostics.

    pose: R (T, S+1, B, 3, 3), p (T, S+1, m, 3); converged, iterations: (T, S-1) per step to
    g_2..g_S; residual_norm: (T, S-1); seconds: wall time of the whole rollout.
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
        """Index of the first pose (any trajectory) whose solve did not converge, or None.

        converged[:, j] is the solve for pose g_{j+2} (the pose sequence starts with g_0, g_1)."""
        bad = (~self.converged).any(0).nonzero()
        return int(bad[0]) + 2 if len(bad) else None


def with_data_start(pred: Pose, g0: Pose, g1: Pose) -> Pose:
    """Predicted sequence (T, S+1, ...) with its first two entries replaced by g0, g1 (every
    model's rollout starts with the observed pair)."""
    R, p = pred.R.clone(), pred.p.clone()
    R[:, 0], R[:, 1] = g0.R, g1.R
    p[:, 0], p[:, 1] = g0.p, g1.p
    return Pose(R, p)


def _stack(xs: list[torch.Tensor], like: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The per-step values (T,) stacked to (T, S-1); (T, 0) on `like`'s device without steps."""
    return torch.stack(xs, 1) if xs else torch.zeros(like.shape[0], 0, dtype=dtype, device=like.device)


@torch.no_grad()
def rollout_implicit(
    model: Any, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None, start: Callable | None = None
) -> Rollout:
    """Roll an `ImplicitModel` forward: for k = 1..steps-1 solve the model's Newton problem
    for g_{k+1} given its state (built from g_{k-1}, g_k). `progress`: optional callable(k);
    `start(g0, g1)`: the first state (default `model.implicit_start`). Where the model's
    `native_rollout(g0, g1, steps, opts, progress)` returns a `Rollout` (not None) that is the rollout
    (the articulated model's native step), unless `start` is given."""
    if start is None:  # a model whose whole rollout runs in native code (`ImplicitModel.native_rollout`)
        ro = model.native_rollout(g0, g1, steps, opts, progress)
        if ro is not None:
            return ro
    t0 = time.perf_counter()
    state = (start or model.implicit_start)(g0, g1)
    reference = model.path != "fused"  # fixed when the model was built
    Rs, ps = [g0.R, g1.R], [g0.p, g1.p]
    conv, its, res = [], [], []
    for k in range(1, steps):
        sol = solve(model.implicit_problem(state), opts, reference=reference)
        state, g_next = model.implicit_advance(state, sol.x)
        Rs.append(g_next.R)
        ps.append(g_next.p)
        conv.append(sol.converged)
        its.append(sol.iterations)
        res.append(sol.residual_norm.detach())
        if progress is not None:
            progress(k)
    return Rollout(
        Pose(torch.stack(Rs, 1), torch.stack(ps, 1)),
        _stack(conv, g0.R, torch.bool),
        _stack(its, g0.R, torch.long),
        _stack(res, g0.R, g0.R.dtype),
        time.perf_counter() - t0,
    )


@torch.no_grad()
def rollout_explicit(model: Any, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout:
    """Roll an `ExplicitModel` forward from its initial state (g0 and a velocity from g0, g1).

    Adaptive integrators give the whole grid t = 0..steps h at once; fixed-step ones are
    stepped `steps` times. The prediction of g1 is replaced by the observed g1 (it still feeds
    the next steps), so the diagnostics of an implicit first step are folded into those of the
    step to g_2. Explicit steps count as converged with 0 iterations.
    """
    t0 = time.perf_counter()
    T = g0.R.shape[0]
    state = model.initial_state(g0, g1)
    sols: list[NewtonResult | None] = []
    if model.adaptive:
        seq = model.integrate(state, steps)
        if progress is not None:
            progress(steps - 1)
    else:
        poses = [model.state_pose(state)]
        for k in range(steps):
            state, sol = model.step(state, opts)
            poses.append(model.state_pose(state))
            sols.append(sol)
            if progress is not None and k >= 1:
                progress(k)
        seq = Pose(torch.stack([g.R for g in poses], 1), torch.stack([g.p for g in poses], 1))
    pose = with_data_start(seq, g0, g1)
    n = max(steps - 1, 0)
    if not sols or sols[0] is None or n == 0:
        converged = torch.ones(T, n, dtype=torch.bool, device=g0.R.device)
        iterations = torch.zeros(T, n, dtype=torch.long, device=g0.R.device)
        residual = torch.zeros(T, n, dtype=g0.R.dtype, device=g0.R.device)
        return Rollout(pose, converged, iterations, residual, time.perf_counter() - t0)
    conv = torch.stack([s.converged for s in sols], 1)  # type: ignore[union-attr]
    its = torch.stack([s.iterations for s in sols], 1)  # type: ignore[union-attr]
    res = torch.stack([s.residual_norm.detach() for s in sols], 1)  # type: ignore[union-attr]
    converged, iterations, residual = conv[:, 1:].clone(), its[:, 1:].clone(), res[:, 1:].clone()
    converged[:, 0] &= conv[:, 0]
    iterations[:, 0] += its[:, 0]
    residual[:, 0] = torch.maximum(residual[:, 0], res[:, 0])
    return Rollout(pose, converged, iterations, residual, time.perf_counter() - t0)
