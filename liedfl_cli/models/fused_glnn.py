"""Fused training path of the GLNN baselines (`models.glnn`, `runtime.fused`): the vector field

    R' = R hat(w),   w' = A(w) = J^{-1} ((J w) x w - D w)

(no potential: the Exp 2 scenes) as one autograd node per evaluation with a hand-written
vector-Jacobian product, instead of the ~15 small autograd nodes of the reference `GLNN.accel`
and `R @ so3.hat(w)`. Training unrolls the integrator over 100-step windows at batch 8-32, so
the cost is the number of small kernels and autograd nodes (docs/benchmarks.md, "Baselines"),
not arithmetic. The rows of R hat(w) are the cross products R_i x w, one kernel.

Same numbers as the reference to rounding (tests/test_fused_baselines.py: losses and gradients
to 1e-12 relative). Only first derivatives (the training loss's backward); rollouts and models
with a learned potential keep the reference path.
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


class _Field(torch.autograd.Function):
    """y' = (R hat(w) entries, A(w)) (N, 12) from y = (R entries, w) (N, 12)."""

    @staticmethod
    def forward(ctx, y, J, Jinv, D):
        n = y.shape[0]
        R, w = y[:, :9].reshape(n, 3, 3), y[:, 9:]
        Rdot = torch.linalg.cross(R, w[:, None, :].expand(n, 3, 3))  # row i of R hat(w) = R_i x w
        u, tau, A = _accel(w, J, Jinv, D)
        ctx.save_for_backward(R, w, u, tau, J, Jinv, D)
        return torch.cat((Rdot.reshape(n, 9), A), -1)

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        R, w, u, tau, J, Jinv, D = ctx.saved_tensors
        n = g.shape[0]
        gRd = g[:, :9].reshape(n, 3, 3)
        gw, gJ, gJinv, gD = _accel_backward(g[:, 9:], w, u, tau, J, Jinv, D)
        # <gRd_i, R_i x w> = <R_i, w x gRd_i> = <w, gRd_i x R_i>
        gR = torch.linalg.cross(w[:, None, :].expand(n, 3, 3), gRd)
        gw = gw + torch.linalg.cross(gRd, R).sum(1)
        return torch.cat((gR.reshape(n, 9), gw), -1), gJ, gJinv, gD


def accel(w: torch.Tensor, J: torch.Tensor, Jinv: torch.Tensor, D: torch.Tensor | None) -> torch.Tensor:
    """A(w) = J^{-1}((J w) x w - D w): w (N, 3), J, J^{-1}, D (3, 3) -> (N, 3), one autograd node."""
    return _Accel.apply(w, J, Jinv, D)


def field(y: torch.Tensor, J: torch.Tensor, Jinv: torch.Tensor, D: torch.Tensor | None) -> torch.Tensor:
    """The dopri5 state's derivative: y = (R entries, w) (N, 12) -> (R hat(w) entries, A(w)) (N, 12)."""
    return _Field.apply(y, J, Jinv, D)


# ---------------------------------------------------------------------------- dopri5
# The Dormand-Prince tableau of torchdiffeq 0.2.5 (`_impl/dopri5.py`), as Python floats.
_BETA = (
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
_C_ERROR = (
    35 / 384 - 1951 / 21600,
    0,
    500 / 1113 - 22642 / 50085,
    125 / 192 - 451 / 720,
    -2187 / 6784 - -12231 / 42400,
    11 / 84 - 649 / 6300,
    -1.0 / 60.0,
)
_C_MID = (
    6025192743 / 30085553152 / 2,
    0,
    51252292925 / 65400821598 / 2,
    -2691868925 / 45128329728 / 2,
    187940372067 / 1594534317056 / 2,
    -1776094331 / 19743644256 / 2,
    11237099 / 235043384 / 2,
)
_SAFETY, _IFACTOR, _DFACTOR, _ORDER = 0.9, 10.0, 0.2, 5


def _field_forward(y, J, Jinv, D):
    """(y' (N, 12), what `_field_vjp` needs) for y = (R entries, w) (N, 12), no autograd."""
    n = y.shape[0]
    R, w = y[:, :9].reshape(n, 3, 3), y[:, 9:]
    Rdot = torch.linalg.cross(R, w[:, None, :].expand(n, 3, 3))
    u, tau, A = _accel(w, J, Jinv, D)
    return torch.cat((Rdot.reshape(n, 9), A), -1), (R, w, u, tau)


def _field_vjp(g, saved, J, Jinv, D):
    """Vector-Jacobian product of the field at the saved point: g (N, 12) -> (gy (N, 12), gJ, gJinv, gD)."""
    R, w, u, tau = saved
    n = g.shape[0]
    gRd = g[:, :9].reshape(n, 3, 3)
    gw, gJ, gJinv, gD = _accel_backward(g[:, 9:], w, u, tau, J, Jinv, D)
    gR = torch.linalg.cross(w[:, None, :].expand(n, 3, 3), gRd)
    gw = gw + torch.linalg.cross(gRd, R).sum(1)
    return torch.cat((gR.reshape(n, 9), gw), -1), gJ, gJinv, gD


class _Dopri5Step(torch.autograd.Function):
    """The six new stages of one Dormand-Prince step as one autograd node.

    y0, f0 = field(y0) (N, 12), dt (), betas (the tableau rows as tensors) -> (k (N, 12, 7) with
    k[..., 0] = f0, y1 = the 7th stage's input (N, 12)); the backward runs the stages in reverse
    with `_field_vjp` and sums the parameters' gradients over the stages in one product each."""

    @staticmethod
    def forward(ctx, y0, f0, dt, J, Jinv, D, betas):
        k = y0.new_empty(*y0.shape, len(betas) + 1)
        k[..., 0] = f0
        saved, incs = [], []
        yi = y0
        for i, beta in enumerate(betas):
            inc = k[..., : i + 1] @ beta  # y_i = y0 + dt sum_j beta_j k_j
            yi = torch.addcmul(y0, inc, dt)
            k[..., i + 1], s = _field_forward(yi, J, Jinv, D)
            saved.append(s)
            incs.append(inc)
        ctx.saved, ctx.incs, ctx.betas = saved, incs, betas
        ctx.save_for_backward(dt, J, Jinv, D)
        return k, yi

    @staticmethod
    @once_differentiable
    def backward(ctx, gk, gy1):
        dt, J, Jinv, D = ctx.saved_tensors
        a = gk.clone()
        gy0 = torch.zeros_like(gy1)
        n = gy1.shape[0]
        gys: list[torch.Tensor] = []
        cols: dict[str, list[torch.Tensor]] = {"w": [], "tau": [], "gA": [], "gu": [], "gtau": []}
        for i in range(len(ctx.betas), 0, -1):  # stage i: k_i = field(y_i)
            R, w, u, tau = ctx.saved[i - 1]
            g = a[..., i]
            gRd, gA = g[:, :9].reshape(n, 3, 3), g[:, 9:]
            gtau = gA @ Jinv
            gu = torch.linalg.cross(w, gtau)
            gw = torch.linalg.cross(gtau, u) + gu @ J + torch.linalg.cross(gRd, R).sum(1)
            if D is not None:
                gw = gw - gtau @ D
            gR = torch.linalg.cross(w[:, None, :].expand(n, 3, 3), gRd)
            gyi = torch.cat((gR.reshape(n, 9), gw), -1)
            if i == len(ctx.betas):  # y1 is the last stage's input
                gyi = gyi + gy1
            gy0 = gy0 + gyi
            a[..., :i] += gyi[..., None] * (ctx.betas[i - 1] * dt)
            gys.append(gyi)
            for key, v in zip(cols, (w, tau, gA, gu, gtau)):
                cols[key].append(v)
        c = {key: torch.cat(v) for key, v in cols.items()}
        gdt = (torch.stack(gys[::-1]) * torch.stack(ctx.incs)).sum().reshape(dt.shape)
        gD = None if D is None else -(c["gtau"].T @ c["w"])
        del ctx.saved, ctx.incs
        return gy0, a[..., 0], gdt, c["gu"].T @ c["w"], c["gA"].T @ c["tau"], gD, None


def _rms(x: torch.Tensor) -> torch.Tensor:
    return x.abs().pow(2).mean().sqrt()


def _first_step(f, y0, f0, rtol: float, atol: float):
    """torchdiffeq's `_select_initial_step` (Hairer-Norsett-Wanner II.4) for order 4, differentiable
    as there (the first step size carries a gradient in torchdiffeq; later ones do not)."""
    scale = atol + torch.abs(y0) * rtol
    d0, d1 = _rms(y0 / scale).abs(), _rms(f0 / scale).abs()
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = torch.tensor(1e-6, dtype=y0.dtype, device=y0.device)
    else:
        h0 = 0.01 * d0 / d1
    h0 = h0.abs()
    f1 = f(y0 + h0 * f0)
    d2 = torch.abs(_rms((f1 - f0) / scale) / h0)
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = torch.max(torch.tensor(1e-6, dtype=y0.dtype, device=y0.device), h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1.0 / float(_ORDER))
    return torch.min(100 * h0, h1.abs())


def dopri5(
    y0: torch.Tensor,
    t: torch.Tensor,
    params: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None],
    rtol: float,
    atol: float,
    max_num_steps: int,
) -> torch.Tensor:
    """torchdiffeq's `odeint(field, y0, t, method="dopri5")` for the GLNN field, the same steps,
    step-size control, interpolation and gradients (first step size included) with each RK step one
    autograd node: y0 (N, 12), increasing t (T,) -> y (T, N, 12)."""
    J, Jinv, D = params

    def f(y):
        return _Field.apply(y, J, Jinv, D)

    # time-like quantities in float64 at least, the state's arithmetic in its own dtype (as torchdiffeq)
    t = t.to(torch.promote_types(torch.float64, y0.dtype))
    f0 = f(y0)
    dt = _first_step(f, y0, f0, rtol, atol).to(t.dtype)
    betas = [torch.tensor(b, dtype=y0.dtype, device=y0.device) for b in _BETA]
    mid = torch.tensor(_C_MID, dtype=y0.dtype, device=y0.device)
    c_err = torch.tensor(_C_ERROR, dtype=y0.dtype, device=y0.device)
    y, t0, t1 = y0, t[0], t[0]
    coeff = [y0] * 5
    out = [y0]
    for next_t in t[1:]:
        n_steps = 0
        while next_t > t1:
            assert n_steps < max_num_steps, f"max_num_steps exceeded ({n_steps}>={max_num_steps})"
            if not torch.isfinite(dt):
                dt = torch.zeros_like(dt)
            dt = dt.clamp(min=0.0)
            t0 = t1
            assert t0 + dt > t0, f"underflow in dt {dt.item()}"
            assert torch.isfinite(y).all(), f"non-finite values in state `y`: {y}"
            dty = dt.to(y.dtype)
            k, y1 = _Dopri5Step.apply(y, f0, dty, J, Jinv, D, betas)
            with torch.no_grad():  # the error only decides acceptance and the next (gradient-free) step size
                err = torch.sum(k * (dty * c_err), dim=-1)
                ratio = _rms(err / (atol + rtol * torch.max(y.abs(), y1.abs()))).abs().to(t.dtype)
            accept = bool(ratio <= 1) or bool(dt <= 0)
            if accept:
                dtc = dty
                y_mid = y + torch.sum(k * (dtc * mid), dim=-1)
                ka, kb = k[..., 0], k[..., -1]
                a = 2 * dtc * (kb - ka) - 8 * (y1 + y) + 16 * y_mid
                b = dtc * (5 * ka - 3 * kb) + 18 * y + 14 * y1 - 32 * y_mid
                c = dtc * (kb - 4 * ka) - 11 * y - 5 * y1 + 16 * y_mid
                coeff = [y, dtc * ka, c, b, a]
                t1 = t0 + dt
                y, f0 = y1, kb
            else:
                t1 = t0
            with torch.no_grad():
                if ratio == 0:
                    dt = dt * _IFACTOR
                else:
                    dfactor = 1.0 if ratio < 1 else _DFACTOR
                    factor = torch.clamp(_SAFETY / ratio ** (1.0 / _ORDER), min=dfactor, max=_IFACTOR)
                    dt = dt * factor
            n_steps += 1
        x = ((next_t - t0) / (t1 - t0)).to(y.dtype)
        total, xp = coeff[0] + x * coeff[1], x
        for cf in coeff[2:]:
            xp = xp * x
            total = total + xp * cf
        out.append(total)
    return torch.stack(out, 0)
