"""Teacher-forced one-step predictions and the zero-parameter references (constant velocity and
constant acceleration).

A one-step prediction predicts g_{k+1} from the *true* pair (g_{k-1}, g_k) for every interior k of
every trajectory; it measures what a model learned about one step without the compounding of a
rollout. The constant-velocity guess g_{k+1} = g_k exp(log(g_{k-1}^{-1} g_k)) (the last increment
repeated) is the reference every learned model must beat: a model no better than it has learned
nothing about the dynamics. It is written with exp(log(.)) so a long constant-velocity rollout stays
on the group to rounding error (composing the raw increment matrices drifts off SO(3)).
"""

from __future__ import annotations

from typing import Any

import torch

from ..lie import Pose, ProductGroup, so3
from .options import SolverOptions


def constant_velocity_step(G: ProductGroup, g_prev: Pose, g: Pose) -> Pose:
    """g exp(log(g_prev^{-1} g)): Pose (..., B, 3, 3), (..., m, 3) twice -> the guess for the next pose."""
    return G.retract(g, G.log(G.increment(g_prev, g)))


def constant_velocity_rollout(G: ProductGroup, g0: Pose, g1: Pose, steps: int) -> Pose:
    """The constant-velocity rollout from (g0, g1): R (T, S+1, B, 3, 3), p (T, S+1, m, 3) starting
    with g0, g1, then g_{k+1} = g_k exp(xi) with xi = log(g0^{-1} g1) for every k (S = steps)."""
    xi = G.log(G.increment(g0, g1))
    Rs, ps = [g0.R, g1.R], [g0.p, g1.p]
    g = g1
    for _ in range(1, steps):
        g = G.retract(g, xi)
        Rs.append(g.R)
        ps.append(g.p)
    return Pose(torch.stack(Rs, 1), torch.stack(ps, 1))


def _pairs(truth: Pose) -> tuple[Pose, Pose, tuple[int, int]]:
    """(g_{k-1}, g_k) for k = 1..N-1 of truth R (T, N+1, B, 3, 3), flattened to (T (N-1), ...)."""
    T, n1 = truth.R.shape[:2]
    if n1 < 3:
        raise ValueError(f"one-step predictions need trajectories of at least 3 poses, got {n1}")
    prev = truth.index((slice(None), slice(0, n1 - 2)))
    cur = truth.index((slice(None), slice(1, n1 - 1)))
    flat = lambda g: Pose(g.R.flatten(0, 1), g.p.flatten(0, 1))  # also with no SE(3) body (p: (T, n, 0, 3))
    return flat(prev), flat(cur), (T, n1 - 2)


def constant_velocity_one_step(G: ProductGroup, truth: Pose) -> Pose:
    """Constant-velocity guesses of g_2..g_N from the true pairs: R (T, N-1, B, 3, 3), p (T, N-1, m, 3)."""
    g_prev, g, (T, n) = _pairs(truth)
    out = constant_velocity_step(G, g_prev, g)
    return Pose(out.R.reshape(T, n, *out.R.shape[1:]), out.p.reshape(T, n, *out.p.shape[1:]))


def constant_acceleration_step(G: ProductGroup, g_pp: Pose, g_prev: Pose, g: Pose) -> Pose:
    """The constant-acceleration guess from three poses: every rotation R exp(2 w_k - w_{k-1}) with
    w_k = log(R_{k-1}^T R_k), every SE(3) position p + 2 dp_k - dp_{k-1} (Euclidean) -> the next pose."""
    w1 = so3.log(g_pp.R.transpose(-1, -2) @ g_prev.R)
    w2 = so3.log(g_prev.R.transpose(-1, -2) @ g.R)
    R = g.R @ so3.exp(2.0 * w2 - w1)
    p = g.p + 2.0 * (g.p - g_prev.p) - (g_prev.p - g_pp.p)
    return Pose(R, p)


def constant_acceleration_one_step(G: ProductGroup, truth: Pose) -> Pose:
    """Constant-acceleration guesses of g_2..g_N from the true poses (`constant_acceleration_step` from
    (g_{k-2}, g_{k-1}, g_k)); g_2, which has only two poses before it, gets the constant-velocity guess.
    R (T, N-1, B, 3, 3), p (T, N-1, m, 3), like `constant_velocity_one_step`."""
    cv = constant_velocity_one_step(G, truth)
    n1 = truth.R.shape[1]
    if n1 < 4:
        return cv
    at = lambda a, b: truth.index((slice(None), slice(a, n1 - b)))
    ca = constant_acceleration_step(G, at(0, 3), at(1, 2), at(2, 1))
    return Pose(torch.cat((cv.R[:, :1], ca.R), 1), torch.cat((cv.p[:, :1], ca.p), 1))


def euclidean_velocity_step(g_prev: Pose, g: Pose) -> Pose:
    """The constant-velocity guess with Euclidean positions: every rotation R exp(log(R_prev^T R)),
    every SE(3) position p + (p - p_prev) (the SE(3) guess couples the position to the rotation; on
    data whose positions move independently of the body's own rotation this one is the better guess)."""
    R = g.R @ so3.exp(so3.log(g_prev.R.transpose(-1, -2) @ g.R))
    return Pose(R, g.p + (g.p - g_prev.p))


def euclidean_velocity_one_step(G: ProductGroup, truth: Pose) -> Pose:
    """`euclidean_velocity_step` guesses of g_2..g_N from the true pairs (shapes as
    `constant_velocity_one_step`)."""
    g_prev, g, (T, n) = _pairs(truth)
    out = euclidean_velocity_step(g_prev, g)
    return Pose(out.R.reshape(T, n, *out.R.shape[1:]), out.p.reshape(T, n, *out.p.shape[1:]))


def euclidean_velocity_rollout(g0: Pose, g1: Pose, steps: int) -> Pose:
    """The rollout of `euclidean_velocity_step` from (g0, g1): R (T, S+1, B, 3, 3), p (T, S+1, m, 3),
    the rotations as `constant_velocity_rollout`'s, the positions p0 + k (p1 - p0)."""
    w = so3.log(g0.R.transpose(-1, -2) @ g1.R)
    Rs, ps = [g0.R, g1.R], [g0.p, g1.p]
    R, dp = g1.R, g1.p - g0.p
    for k in range(2, steps + 1):
        R = R @ so3.exp(w)
        Rs.append(R)
        ps.append(g0.p + k * dp)
    return Pose(torch.stack(Rs, 1), torch.stack(ps, 1))


def constant_acceleration_rollout(g0: Pose, g1: Pose, g2: Pose, steps: int) -> Pose:
    """The constant-acceleration rollout from three true poses (g0, g1, g2): R (T, S+1, B, 3, 3),
    p (T, S+1, m, 3) starting with g0, g1, g2, then `constant_acceleration_step` from its own last three
    poses (the body-frame increment grows by the same w_2 - w_1 every step, positions are quadratic in
    k). It needs one true pose more than a model's rollout (from two poses it is constant velocity):
    its sample 2 is the data's."""
    if steps < 2:
        return Pose(torch.stack([g0.R, g1.R], 1)[:, : steps + 1], torch.stack([g0.p, g1.p], 1)[:, : steps + 1])
    w1 = so3.log(g0.R.transpose(-1, -2) @ g1.R)
    w2 = so3.log(g1.R.transpose(-1, -2) @ g2.R)
    dw = w2 - w1
    dp1, dp2 = g1.p - g0.p, g2.p - g1.p
    Rs, ps = [g0.R, g1.R, g2.R], [g0.p, g1.p, g2.p]
    R, p, w, dp = g2.R, g2.p, w2, dp2
    for _ in range(3, steps + 1):
        w = w + dw
        dp = dp + (dp2 - dp1)
        R = R @ so3.exp(w)
        p = p + dp
        Rs.append(R)
        ps.append(p)
    return Pose(torch.stack(Rs, 1), torch.stack(ps, 1))


@torch.no_grad()
def one_step_predictions(
    model: Any, truth: Pose, opts: SolverOptions | None = None, chunk: int = 65536
) -> tuple[Pose, torch.Tensor]:
    """The model's teacher-forced predictions of g_2..g_N from the true pairs (g_{k-1}, g_k).

    truth: R (T, N+1, B, 3, 3), p (T, N+1, m, 3). Every pair is one trajectory of a two-step
    `model.rollout` (any model: implicit, explicit or adaptive), batched `chunk` pairs at a time.
    Returns (Pose R (T, N-1, B, 3, 3), p (T, N-1, m, 3), converged (T, N-1) bool).
    """
    g_prev, g, (T, n) = _pairs(truth)
    Rs, ps, conv = [], [], []
    for a in range(0, T * n, chunk):
        sl = slice(a, min(a + chunk, T * n))
        ro = model.rollout(g_prev.index(sl), g.index(sl), 2, opts or SolverOptions())
        Rs.append(ro.pose.R[:, 2])
        ps.append(ro.pose.p[:, 2])
        conv.append(ro.converged[:, 0] if ro.converged.shape[1] else torch.ones_like(ro.pose.R[:, 0, 0, 0, 0]).bool())
    R, p, c = torch.cat(Rs), torch.cat(ps), torch.cat(conv)
    return Pose(R.reshape(T, n, *R.shape[1:]), p.reshape(T, n, *p.shape[1:])), c.reshape(T, n)
