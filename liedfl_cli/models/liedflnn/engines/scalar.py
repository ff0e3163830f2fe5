"""Fused hot paths of LieDFLNN, part 5 (see `models.liedflnn.engines.core`): the rollout of a *few* trajectories of a
single SO(3) body with a linear Newton residual (no force, or constant Rayleigh damping) in Python
floats.

At batch 1 a step of the row layout runs ~540 torch calls of a few microseconds each on 3x3 arrays
(1.4-1.7 ms per step, almost all dispatch); the same arithmetic on Python floats is a few hundred
multiply-adds and a few dozen `math` calls. What it computes is `fused_columns`' step for one
trajectory, term by term: the residual const + lin_f^T W and its Jacobian lin_J^T W from the same
linear maps (`RolloutMaps.linear`), the 3x3 solve from the adjugate, the retraction W exp(hat(delta))
in closed form, one Newton-Schulz step, g_{k+1} = g_k W; the MLP potential's covector from its
layers (exact GELU or tanh) as `mlp_derivatives.gradient_columns` and `fused_columns.row_cross_sum`
compute it. Its Newton loop is `solvers.newton`'s for one row: the same acceptance test, convergence
test and iteration counts; an iteration that needs care (a singular Jacobian, or a step without
decrease) hands the trajectory to the row layout's loop from that iteration on, as the column layout
does.

    applies(model, g0)                       whether a rollout takes this path
    rollout(model, g0, g1, steps, opts)      `solvers.rollout.rollout_implicit` for those models
"""

from __future__ import annotations

import math
import sys
import time
from operator import mul

import torch
from torch import nn

from ....lie import Pose
from ....lie.batched import HISTORY, TRUST
from ....mechanics.potentials import MLPPotential
from ....solvers import newton
from ....solvers.options import SolverOptions
from ....solvers.rollout import Rollout
from ... import mlp_derivatives
from . import columns as fused_columns
from .rollout import RolloutMaps, rollout_maps

MAX_ROWS = 6
"""Batches up to this many trajectories can take this path: each trajectory is its own Python loop,
and from about 8 on the row layout's batched kernels cost less per trajectory (idle, 2026-11-27, SO(3)
MLP 10x2 + damping, µs per step per trajectory, floats / rows: 181 / 1089 at batch 1, 145 / 296 at 4,
205 / 267 at 6, 199 / 190 at 8; no potential: 79 / 113 at 8, 118 / 116 at 12)."""
STEP_COST = 1000
"""A trajectory's step in floats costs about as much as this many MLP weights (measured above: about
130 µs plus 0.14 µs per weight)."""
BUDGET = 7200
"""The path is taken while trajectories x (weights + STEP_COST) stays within this (measured: a 32x3 MLP,
2368 weights, 515 / 1271 µs at batch 1 and 507 / 601 at 2; a 64x3, 8832 weights, 1401 / 1122 at batch
1: the row layout's)."""

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)


def activation_name(act) -> str | None:
    """ "gelu" (exact) or "tanh" for the activations computed in floats here and natively, else None."""
    if isinstance(act, nn.GELU) and act.approximate == "none":
        return "gelu"
    if isinstance(act, nn.Tanh):
        return "tanh"
    return None


def applies(model, g0: Pose) -> bool:
    """Whether `model`'s rollout from g0 takes this path: `fused_columns.applies` but for at most
    MAX_ROWS trajectories, and a potential that is none or an MLP of Linear layers with exact GELU or
    tanh activations, small enough for the batch (BUDGET)."""
    if not (
        fused_columns.single_linear_so3(model, g0)
        and 1 <= g0.R.shape[0] <= MAX_ROWS
        and _doubles(g0.R.dtype)
        and g0.R.device.type == "cpu"
    ):
        return False
    T = g0.R.shape[0]
    if model.potential is None:
        return T * STEP_COST <= BUDGET
    if not isinstance(model.potential, MLPPotential):
        return False
    lys = mlp_derivatives.layers(model.potential.net)
    if lys is None or any(activation_name(act) is None for _, act in lys[:-1]):
        return False
    return T * (sum(lin.weight.numel() for lin, _ in lys) + STEP_COST) <= BUDGET


def _doubles(dtype: torch.dtype) -> bool:
    """Whether dtype is what Python floats are (IEEE doubles): only there is this path the same
    arithmetic as the tensors'."""
    return dtype.is_floating_point and not dtype.is_complex and dtype.itemsize == 8


# ---------------------------------------------------------------------------- float arithmetic
def _mat(A: torch.Tensor) -> list[list[float]]:
    return A.tolist()


def _mul3(A: list[float], B: list[float]) -> list[float]:
    """A B of 3x3 matrices as row-major lists of 9 (unrolled: each entry summed left to right)."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return [
        a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
        a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
        a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8,
    ]  # fmt: skip


def _mul3_tn(A: list[float], B: list[float]) -> list[float]:
    """A^T B of 3x3 matrices as row-major lists of 9 (unrolled)."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return [
        a0 * b0 + a3 * b3 + a6 * b6, a0 * b1 + a3 * b4 + a6 * b7, a0 * b2 + a3 * b5 + a6 * b8,
        a1 * b0 + a4 * b3 + a7 * b6, a1 * b1 + a4 * b4 + a7 * b7, a1 * b2 + a4 * b5 + a7 * b8,
        a2 * b0 + a5 * b3 + a8 * b6, a2 * b1 + a5 * b4 + a8 * b7, a2 * b2 + a5 * b5 + a8 * b8,
    ]  # fmt: skip


def _mul3_nt(A: list[float], B: list[float]) -> list[float]:
    """A B^T of 3x3 matrices as row-major lists of 9 (unrolled)."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return [
        a0 * b0 + a1 * b1 + a2 * b2, a0 * b3 + a1 * b4 + a2 * b5, a0 * b6 + a1 * b7 + a2 * b8,
        a3 * b0 + a4 * b1 + a5 * b2, a3 * b3 + a4 * b4 + a5 * b5, a3 * b6 + a4 * b7 + a5 * b8,
        a6 * b0 + a7 * b1 + a8 * b2, a6 * b3 + a7 * b4 + a8 * b5, a6 * b6 + a7 * b7 + a8 * b8,
    ]  # fmt: skip


def _extrapolate(incs: list[list[float]]) -> list[float]:
    """`lie.batched.extrapolate_increments` in floats, increments oldest first: W, or E W with E = D
    (two increments) or D D'^T D (three; D = W W_1^T, D' = W_1 W_2^T); W where E is further from the
    identity than `TRUST` times W (3 - tr, as |M - I|^2 / 2 of a rotation) or is not finite."""
    W = incs[-1]
    if len(incs) == 1:
        return W
    E = _mul3_nt(W, incs[-2])
    if len(incs) == 3:
        E = _mul3(_mul3_nt(E, _mul3_nt(incs[-2], incs[-3])), E)
    ok = 3.0 - (E[0] + E[4] + E[8]) <= TRUST * TRUST * (3.0 - (W[0] + W[4] + W[8]))  # NaN compares false
    return _mul3(E, W) if ok else W


def _apply(M: list[list[float]], x: list[float]) -> list[float]:
    """M x for M (k, n) as nested lists, x of n."""
    return [sum(map(mul, row, x)) for row in M]  # map: the same sum, in the same order, without a generator


def _retract(W: list[float], d: list[float]) -> list[float]:
    """W exp(hat(d)): `fused_columns.retract`'s closed form."""
    t = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    t = max(t, _TINY)
    sinc = math.sin(t) / t
    s = math.sin(0.5 * t) / t
    cosc = 2.0 * s * s
    c = math.cos(t)
    x, y, z = d
    E = [
        c + cosc * x * x, cosc * x * y - sinc * z, cosc * x * z + sinc * y,
        cosc * y * x + sinc * z, c + cosc * y * y, cosc * y * z - sinc * x,
        cosc * z * x - sinc * y, cosc * z * y + sinc * x, c + cosc * z * z,
    ]  # fmt: skip
    return _mul3(W, E)


_TINY = sys.float_info.min  # Python floats are IEEE doubles: float64's tiny, eps and max


def _newton_schulz(W: list[float]) -> list[float]:
    """W (3 I - W^T W) / 2."""
    M = _mul3_tn(W, W)
    M = [(3.0 if i % 4 == 0 else 0.0) - m for i, m in enumerate(M)]
    return [0.5 * v for v in _mul3(W, M)]


def _norm(v: list[float]) -> float:
    return math.sqrt(sum(x * x for x in v))


class _Potential:
    """-h dV(g exp(eta))/d eta at 0 of an MLP potential, in floats (`gradient_columns` +
    `row_cross_sum`)."""

    def __init__(self, lys, scale: float):
        self.hidden = []
        for lin, act in lys[:-1]:
            b = lin.bias.tolist() if lin.bias is not None else [0.0] * lin.out_features
            self.hidden.append((lin.weight.tolist(), lin.weight.T.tolist(), b, activation_name(act)))
        self.out = [scale * w for w in lys[-1][0].weight[0].tolist()]

    def covector(self, g: list[float]) -> list[float]:
        a, slopes = g, []
        for Wt, _, b, act in self.hidden:
            z = [sum(map(mul, row, a)) + bi for row, bi in zip(Wt, b)]
            if act == "gelu":
                cdf = [0.5 * math.erf(v * _INV_SQRT2) + 0.5 for v in z]
                a = [v * p for v, p in zip(z, cdf)]
                slopes.append([p + v * math.exp(-0.5 * v * v) * _INV_SQRT2PI for v, p in zip(z, cdf)])
            else:  # tanh
                a = [math.tanh(v) for v in z]
                slopes.append([1.0 - u * u for u in a])
        gr = self.out
        for (_, WT, _, _), s in zip(reversed(self.hidden), reversed(slopes)):
            gs = [si * gi for si, gi in zip(s, gr)]
            gr = [sum(map(mul, row, gs)) for row in WT]
        dx = gr  # (9,): d(scale V)/dR entries, row major
        # sum over rows k of dR_k x R_k
        c = [0.0, 0.0, 0.0]
        for k in range(3):
            a0, a1, a2 = dx[3 * k], dx[3 * k + 1], dx[3 * k + 2]
            b0, b1, b2 = g[3 * k], g[3 * k + 1], g[3 * k + 2]
            c[0] += a1 * b2 - a2 * b1
            c[1] += a2 * b0 - a0 * b2
            c[2] += a0 * b1 - a1 * b0
        return c


# ---------------------------------------------------------------------------- one trajectory
class _Maps:
    """The linear maps of `RolloutMaps.linear` as nested lists: f (3, 9), J (9, 9), c (3, 9)."""

    def __init__(self, maps: RolloutMaps):
        assert maps.linear is not None
        lin_f, lin_J, lin_c = maps.linear
        self.f, self.J, self.c = _mat(lin_f.T), _mat(lin_J.T), _mat(lin_c.T)


def _solve(
    maps: _Maps, const: list[float], W: list[float], opts: SolverOptions, step_tol: float, hand_over
) -> tuple[list[float], list[float], bool, int]:
    """`solvers.newton`'s loop for one row from W -> (W, r, converged, iterations)."""
    r = [a + b for a, b in zip(const, _apply(maps.f, W))]
    rn = _norm(r)
    big = sys.float_info.max
    for it in range(opts.max_iter):
        J = _apply(maps.J, W)  # the 3x3 Jacobian, row major
        a, b, c = J[0:3], J[3:6], J[6:9]
        adj = [  # rows: b x c, c x a, a x b (the adjugate's columns, `fused_maps.solve_small`)
            b[1] * c[2] - b[2] * c[1], b[2] * c[0] - b[0] * c[2], b[0] * c[1] - b[1] * c[0],
            c[1] * a[2] - c[2] * a[1], c[2] * a[0] - c[0] * a[2], c[0] * a[1] - c[1] * a[0],
            a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0],
        ]  # fmt: skip
        det = a[0] * adj[0] + a[1] * adj[1] + a[2] * adj[2]
        if det == 0.0:
            return hand_over(W, r, rn, opts.max_iter - it, it)
        delta = [-(adj[i] * r[0] + adj[3 + i] * r[1] + adj[6 + i] * r[2]) / det for i in range(3)]
        cand = _retract(W, delta)
        rc = [x + y for x, y in zip(const, _apply(maps.f, cand))]
        rcn = _norm(rc)
        full_step = max(abs(delta[0]), abs(delta[1]), abs(delta[2]))
        if not (rcn <= min(rn * (1 - 1e-4) + 1e-300, big) and full_step <= big):  # NaN fails too
            return hand_over(W, r, rn, opts.max_iter - it, it)
        W, r, rn = cand, rc, rcn
        if full_step <= step_tol:
            return W, r, True, it + 1
    return W, r, False, opts.max_iter


# ---------------------------------------------------------------------------- the rollout
@torch.no_grad()
def rollout(model, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout:
    """`rollout_implicit(model, ...)` in Python floats (`applies(model, g0)` must hold); a rollout that
    the plan compiles takes the rows engine instead (`engines/choose.py`)."""
    t0 = time.perf_counter()
    T = g0.R.shape[0]
    maps = rollout_maps(model)
    cols: list[fused_columns.ColumnMaps] = []  # the column maps, built by the first hand-over only
    fmaps = _Maps(maps)
    potential = _Potential(maps.potential_layers, -float(model.h)) if model.potential is not None else None
    step_tol = max(opts.tol, newton.ROUNDING_ULPS * sys.float_info.epsilon)  # rotations: entries <= 1
    n = max(steps - 1, 0)
    n_poses = max(steps, 1) + 1
    # per trajectory the last increments, oldest first: the last one fixes the step's constant part, all of
    # them its warm start
    history = [[W] for W in model.G.increment(g0, g1).R.reshape(T, 9).tolist()]
    poses = [[R0, R1] for R0, R1 in zip(g0.R.reshape(T, 9).tolist(), g1.R.reshape(T, 9).tolist())]
    conv = [[True] * n for _ in range(T)]
    its = [[0] * n for _ in range(T)]
    res = [[0.0] * n for _ in range(T)]

    for k in range(1, steps):
        for t in range(T):
            g, W_prev = poses[t][-1], history[t][-1]
            cov = potential.covector(g) if potential is not None else [0.0, 0.0, 0.0]
            const = [x + y for x, y in zip(_apply(fmaps.c, W_prev), cov)]

            def hand_over(W, r, rn, left, done, g=g, const=const):
                """The row layout's loop (careful iterations) from this iteration on."""
                like = g0.R
                if not cols:
                    cols.append(fused_columns.ColumnMaps(model, maps))
                step = fused_columns.ColumnStep(cols[0], _col(like, const), _col(like, g))
                rows = like.new_zeros(1, dtype=torch.long)
                Ws, rs, cs, n_it = step.hand_over(rows, _col(like, W), _col(like, r), like.new_tensor([rn]), opts, left)
                return Ws[:, 0].tolist(), rs[:, 0].tolist(), bool(cs[0]), done + int(n_it[0])

            W, r, ok, n_it = _solve(fmaps, const, _extrapolate(history[t]), opts, step_tol, hand_over)
            W_next = _newton_schulz(W)
            history[t] = [*history[t], W_next][-HISTORY:]
            poses[t].append(_mul3(g, W_next))
            conv[t][k - 1], its[t][k - 1], res[t][k - 1] = ok, n_it, max(abs(x) for x in r)
        if progress is not None:
            progress(k)
    like = g0.R
    return Rollout(
        Pose(like.new_tensor(poses).reshape(T, n_poses, 1, 3, 3), g0.p.new_zeros(T, n_poses, 0, 3)),
        like.new_tensor(conv, dtype=torch.bool).reshape(T, n),
        like.new_tensor(its, dtype=torch.long).reshape(T, n),
        like.new_tensor(res).reshape(T, n),
        time.perf_counter() - t0,
    )


def _col(like: torch.Tensor, values: list[float]) -> torch.Tensor:
    """A column (n, 1) of the column layout, of like's dtype and device."""
    return like.new_tensor(values)[:, None]
