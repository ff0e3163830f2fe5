"""Dormand-Prince 5(4) with adaptive steps and dense output, the whole solve as ONE autograd node.

    y' = F(y),   y(t_0) = y_0,   returns y(t_j) for every requested time t_j   (T, N, D)

The GLNN-RK4 baseline trains by back-propagating through an unrolled adaptive solve (the Neural ODE too;
it still goes through torchdiffeq). Through torchdiffeq (`runtime.fused=false`) every step leaves ~100 autograd
nodes and ~30 Python-level tensor checks; at the paper's batch sizes (8-32 trajectories of 12 numbers)
that bookkeeping, not arithmetic, is the cost. Here the forward runs without a graph and the backward is
the exact discrete adjoint of the same computation, written out stage by stage.

The method is the textbook one, written here from the references, and its constants are the ones
torchdiffeq's `dopri5` uses (its defaults), so both accept and reject the same steps and their outputs
agree to rounding (tests/test_dopri5.py checks it against torchdiffeq; no code of it is used here):
- the Dormand-Prince 5(4) pair (Dormand & Prince, J. Comput. Appl. Math. 6, 1980), 5th-order solution
  propagated, FSAL; the midpoint weights of Shampine's dense output (Math. Comp. 46, 1986);
- first step: Hairer, Norsett & Wanner, *Solving ODEs I*, II.4 (`initial_step`), computed with autograd
  outside the node: the first step's size depends on F, and when that step is accepted every later step
  boundary moves with it, so its gradient is part of the reference's (and of this node's);
- error: RMS over every entry of the batch of err / (atol + rtol max(|y_0|, |y_1|)), one step size for the
  whole batch; accept iff <= 1; next step dt min(10, max(0.9 ratio^(-1/5), 0.2, or 1 after an accepted
  step)) (HNW II.4, safety 0.9, facmax 10, facmin 0.2);
- output at t in [t_0, t_1]: the quartic p(x), x = (t - t_0)/(t_1 - t_0), with p(0) = y_0, p(1) = y_1,
  p(1/2) = the midpoint estimate, p'(0) = dt F(y_0), p'(1) = dt F(y_1) (`_FIT` is that interpolation
  problem solved once; a test re-derives it).
Step-size control after the first step carries no gradient (the reference's does not either).

A vector field is an object with `forward(y, params) -> (F(y), saved)` (no graph) and
`vjp(saved, g, params, acc) -> g_y`, which adds its parameters' pieces to `acc`;
`param_grads(acc, params)` turns them into one gradient per parameter tensor (`models.glnn.engines.fused`).
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import torch
from torch.autograd.function import once_differentiable

# Dormand-Prince tableau (stages 1..6 from k_0..k_{i-1}); row 6 is the 5th-order solution (FSAL).
_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
# 5th minus 4th order solution weights (the error estimate), over k_0..k_6
_E = (
    35 / 384 - 1951 / 21600,
    0.0,
    500 / 1113 - 22642 / 50085,
    125 / 192 - 451 / 720,
    -2187 / 6784 - -12231 / 42400,
    11 / 84 - 649 / 6300,
    -1.0 / 60.0,
)
# the solution at the step's midpoint (Shampine's dense output), over k_0..k_6
_MID = (
    6025192743 / 30085553152 / 2,
    0.0,
    51252292925 / 65400821598 / 2,
    -2691868925 / 45128329728 / 2,
    187940372067 / 1594534317056 / 2,
    -1776094331 / 19743644256 / 2,
    11237099 / 235043384 / 2,
)
# dense-output polynomial: coefficients (x^0..x^4) = _FIT @ (y_0, y_1, y_mid, dt k_0, dt k_6)
_FIT = (
    (1.0, 0.0, 0.0, 0.0, 0.0),
    (0.0, 0.0, 0.0, 1.0, 0.0),
    (-11.0, -5.0, 16.0, -4.0, 1.0),
    (18.0, 14.0, -32.0, 5.0, -3.0),
    (-8.0, -8.0, 16.0, -2.0, 2.0),
)
ORDER = 5
SAFETY, IFACTOR, DFACTOR = 0.9, 10.0, 0.2


class Field(Protocol):
    """A vector field with a hand-written vector-Jacobian product (module docstring)."""

    def forward(self, y: torch.Tensor, params: tuple) -> tuple[torch.Tensor, Any]: ...

    def vjp(self, saved: Any, g: torch.Tensor, params: tuple, acc: list) -> torch.Tensor: ...

    def param_grads(self, acc: list, params: tuple) -> tuple: ...


def _rms(x: torch.Tensor) -> torch.Tensor:
    return x.abs().pow(2).mean().sqrt()


def initial_step(f, y0: torch.Tensor, f0: torch.Tensor, rtol: float, atol: float) -> torch.Tensor:
    """The first step size (Hairer-Norsett-Wanner II.4, as torchdiffeq picks it), differentiable:
    f: y (N, D) -> F(y) (autograd); y0, f0 = F(y0) (N, D) -> () tensor."""
    scale = atol + y0.abs() * rtol
    d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = torch.tensor(1e-6, dtype=y0.dtype, device=y0.device)
    else:
        h0 = 0.01 * d0 / d1
    f1 = f(y0 + h0 * f0)
    d2 = _rms((f1 - f0) / scale) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = torch.clamp(h0 * 1e-3, min=1e-6)
    else:
        h1 = (0.01 / torch.maximum(d1, d2)) ** (1.0 / ORDER)
    return torch.minimum(100 * h0, h1)


def next_step(dt: float, ratio: float) -> float:
    """The step after one of size dt with error ratio `ratio` (accepted or not)."""
    if ratio == 0:
        return dt * IFACTOR
    dfactor = 1.0 if ratio < 1 else DFACTOR
    return dt * min(IFACTOR, max(SAFETY / ratio ** (1.0 / ORDER), dfactor))


class _Step:
    """An accepted step: stages K (7, N, D), their fields' saved values, size dt, interval [t0, t1],
    dense-output coefficients C (5, N, D), whether it is the first step (whose size carries a gradient),
    and the outputs it produced: [(j, x)]."""

    __slots__ = ("K", "saved", "dt", "t0", "t1", "C", "first", "outputs")

    def __init__(self, K, saved, dt, t0, t1, C, first):
        self.K, self.saved, self.dt, self.t0, self.t1, self.C, self.first = K, saved, dt, t0, t1, C, first
        self.outputs: list[tuple[int, float]] = []


class _Tableau:
    """The coefficients as tensors of one dtype and device (stage rows, error, midpoint, fit)."""

    def __init__(self, like: torch.Tensor):
        self.A = [like.new_tensor(a) for a in _A]
        self.E, self.MID, self.FIT = like.new_tensor(_E), like.new_tensor(_MID), like.new_tensor(_FIT)
        self.powers = like.new_tensor([0.0, 1.0, 2.0, 3.0, 4.0])


def _combine(y: torch.Tensor, dt: float, w: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """y + dt sum_l w_l K[l] over the first len(w) stages, one kernel: y (N, D), K (7, N, D) -> (N, D)."""
    n = w.shape[0]
    return torch.addmv(y.reshape(-1), K[:n].reshape(n, -1).T, w, alpha=dt).view_as(y)


def _solve_forward(field: Field, params, y0, dt0, times, rtol, atol, max_num_steps, keep: bool = True):
    """The solve without a graph: -> (Y (T, N, D), accepted steps, f0's saved values). keep=False: keep no
    step (a solve nothing differentiates, e.g. a long rollout, holds only the current step)."""
    tab = _Tableau(y0)
    T = len(times)
    Y = y0.new_empty(T, *y0.shape)
    Y[0] = y0
    f, saved0 = field.forward(y0, params)
    zero = torch.zeros_like(y0)
    y, t, dt = y0, times[0], dt0
    steps: list[_Step] = []
    first = True  # the next attempted step is the first (its size carries dt0's gradient)
    last: _Step | None = None
    for j in range(1, T):
        n = 0
        while times[j] > t:
            if n >= max_num_steps:
                raise AssertionError(f"max_num_steps exceeded ({n}>={max_num_steps})")
            if not math.isfinite(dt):
                dt = 0.0
            if not t + dt > t:
                raise AssertionError(f"underflow in dt {dt}")
            if not bool(torch.isfinite(y).all()):
                raise AssertionError(f"non-finite values in state `y`: {y}")
            K = y.new_empty(7, *y.shape)
            K[0] = f
            saved = [None] * 7
            for i in range(1, 7):
                Yi = _combine(y, dt, tab.A[i], K)
                K[i], saved[i] = field.forward(Yi, params)
            y1 = Yi
            tol = torch.maximum(y.abs(), y1.abs()).mul_(rtol).add_(atol)
            ratio = float(_rms(_combine(zero, dt, tab.E, K).div_(tol)))
            if ratio <= 1:
                basis = torch.stack((y, y1, _combine(y, dt, tab.MID, K), dt * K[0], dt * K[6]))
                C = torch.tensordot(tab.FIT, basis, 1)
                last = _Step(K, saved, dt, t, t + dt, C, first)
                if keep:
                    steps.append(last)
                y, f, t = y1, K[6], t + dt
            first = False
            dt = next_step(dt, ratio)
            n += 1
        assert last is not None  # times increase, so at least one step was accepted
        x = (times[j] - last.t0) / (last.t1 - last.t0)
        C = last.C
        total, xp = C[0] + x * C[1], x
        for p in range(2, 5):
            xp = xp * x
            total = total + xp * C[p]
        Y[j] = total
        last.outputs.append((j, x))
    return Y, steps, saved0


def _solve_backward(field: Field, params, steps: list[_Step], saved0, G: torch.Tensor):
    """The discrete adjoint of `_solve_forward`: G = dL/dY (T, N, D) -> (dL/dy0, dL/d dt0 (), param grads)."""
    tab = _Tableau(G)
    acc: list = []
    g_y = torch.zeros_like(G[0])  # adjoint of the state after the step being processed
    g_f = torch.zeros_like(G[0])  # adjoint of F at that state (the next step's k_0)
    g_dt0 = G.new_zeros(())
    shift = bool(steps) and steps[0].first  # every later t0, t1 move with the first step's size
    for s in reversed(steps):
        dt, K, C = s.dt, s.K, s.C
        js = [j for j, _ in s.outputs]
        gC = C.new_zeros(C.shape)
        if js:
            xs = C.new_tensor([x for _, x in s.outputs])
            Gm = G[js].reshape(len(js), -1)
            gC = (xs[:, None] ** tab.powers).T.mm(Gm).view_as(C)
            if shift:  # d output / dx (x^p -> p x^(p-1)), times dx / d(first step's size)
                slope = torch.cat((torch.zeros_like(xs[:, None]), tab.powers[1:] * xs[:, None] ** tab.powers[:4]), 1)
                g_x = (slope.mm(C.reshape(5, -1)) * Gm).sum(1)
                g_dt0 = g_dt0 - (g_x * (xs if s.first else 1.0)).sum() / (s.t1 - s.t0)
        gB = torch.tensordot(tab.FIT.T, gC, 1)  # adjoints of (y0, y1, ymid, dt k0, dt k6)
        g_y1 = gB[1] + g_y
        g_ymid = gB[2]
        g_y0 = gB[0] + g_ymid
        gK = (dt * tab.MID)[:, None, None] * g_ymid
        gK[0] += dt * gB[3]
        gK[6] += dt * gB[4] + g_f
        if s.first:
            g_dt0 = g_dt0 + (gB[3] * K[0]).sum() + (gB[4] * K[6]).sum()
            g_dt0 = g_dt0 + (g_ymid * _combine(torch.zeros_like(g_y), 1.0, tab.MID, K)).sum()
        gKf = gK.view(7, -1)
        for i in range(6, 0, -1):
            g_Yi = field.vjp(s.saved[i], gK[i], params, acc)
            if i == 6:
                g_Yi = g_Yi + g_y1
            gKf[:i].addr_(tab.A[i], g_Yi.reshape(-1), alpha=dt)
            g_y0 = g_y0 + g_Yi
            if s.first:
                g_dt0 = g_dt0 + (g_Yi * _combine(torch.zeros_like(g_y), 1.0, tab.A[i], K)).sum()
        g_y, g_f = g_y0, gK[0]
    g_y = g_y + field.vjp(saved0, g_f, params, acc) + G[0]
    return g_y, g_dt0, field.param_grads(acc, params)


class _Dopri5(torch.autograd.Function):
    """(y0 (N, D), dt0 (), field, times, rtol, atol, max_num_steps, *params) -> Y (T, N, D)."""

    @staticmethod
    def forward(ctx, y0, dt0, field, times, rtol, atol, max_num_steps, *params):
        with torch.no_grad():
            Y, steps, saved0 = _solve_forward(field, params, y0, float(dt0), times, rtol, atol, max_num_steps)
        ctx.field, ctx.steps, ctx.saved0 = field, steps, saved0
        ctx.save_for_backward(*params)
        return Y

    @staticmethod
    @once_differentiable
    def backward(ctx, G):
        params = ctx.saved_tensors
        g_y0, g_dt0, g_params = _solve_backward(ctx.field, params, ctx.steps, ctx.saved0, G.contiguous())
        ctx.steps = ctx.saved0 = None
        return (g_y0, g_dt0, None, None, None, None, None, *g_params)


class _FieldNode(torch.autograd.Function):
    """F(y) of a `Field` as an autograd node (its own vjp): y (N, D), field, *params -> (N, D). For the first
    step's size, which the reference differentiates."""

    @staticmethod
    def forward(ctx, y, field, *params):
        with torch.no_grad():
            out, saved = field.forward(y, params)
        ctx.field, ctx.saved = field, saved
        ctx.save_for_backward(*params)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        params = ctx.saved_tensors
        acc: list = []
        g_y = ctx.field.vjp(ctx.saved, g.contiguous(), params, acc)
        return (g_y, None, *ctx.field.param_grads(acc, params))


def first_step(field: Field, y0: torch.Tensor, params: tuple, rtol: float, atol: float) -> torch.Tensor:
    """`initial_step` with `field` (differentiable in y0 and params when grad mode is on): -> () tensor."""

    def f(y: torch.Tensor) -> torch.Tensor:
        return _FieldNode.apply(y, field, *params)

    return initial_step(f, y0, f(y0), rtol, atol)


def odeint(
    field: Field,
    y0: torch.Tensor,
    times: list[float],
    params: tuple,
    rtol: float,
    atol: float,
    max_num_steps: int,
) -> torch.Tensor:
    """y(t_j) for the increasing `times` (T floats, y(times[0]) = y0 (N, D)) -> (T, N, D), differentiable
    in y0 and `params` (tensors; None entries allowed)."""
    y0 = y0.contiguous()  # fields view their state's rows
    tensors = [y0, *(p for p in params if p is not None)]
    args = (float(rtol), float(atol), int(max_num_steps))
    if not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors)):
        with torch.no_grad():
            dt0 = float(first_step(field, y0, params, rtol, atol))
            return _solve_forward(field, params, y0, dt0, list(times), *args, keep=False)[0]
    dt0_t = first_step(field, y0, params, rtol, atol)
    return _Dopri5.apply(y0, dt0_t, field, list(times), *args, *params)
