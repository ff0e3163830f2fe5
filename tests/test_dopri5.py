"""`solvers.dopri5` (the whole adaptive solve as one autograd node, the GLNN-RK4 training path) against
torchdiffeq's dopri5 with autograd through every step, over the plain-expression field R' = R hat(w),
w' = J^{-1}((J w) x w - D w): the same outputs (1e-12 relative), the same number of attempted steps,
the same gradients for y0, J, J^{-1} and D (1e-12 of the largest entry) -- also where the first step is
rejected, where several outputs fall in one step, and on the initial-step rule's small-field branch."""

from __future__ import annotations

import pytest
import torch
from torchdiffeq import odeint as torchdiffeq_odeint

from liedfl_cli.lie import so3
from liedfl_cli.models.glnn.engines import fused as fused_glnn
from liedfl_cli.solvers import dopri5

F64 = torch.float64


def _plain_field(y, J, Jinv, D):
    """The field as plain tensor expressions (autograd reference): y (N, 12) -> (N, 12)."""
    n = y.shape[0]
    R, w = y[:, :9].reshape(n, 3, 3), y[:, 9:]
    tau = torch.cross(w @ J.T, w, dim=-1)
    if D is not None:
        tau = tau - w @ D.T
    return torch.cat(((R @ so3.hat(w)).reshape(n, 9), tau @ Jinv.T), -1)


class _Counted(fused_glnn.Dopri5Field):
    """Counts the solver's field evaluations."""

    def __init__(self):
        self.calls = 0

    def forward(self, y, params):
        self.calls += 1
        return super().forward(y, params)


def _odeint(y0, times, params, rtol, atol, limit, field=None):
    """`dopri5.odeint` over GLNN's field, feature major as the model runs it: y0 (N, 12) -> (T, N, 12)."""
    field = field if field is not None else fused_glnn.Dopri5Field()
    return dopri5.odeint(field, y0.T, list(times), params, rtol, atol, limit).transpose(1, 2)


def _first_step(y0, params, rtol, atol):
    """The first step's size as the solver takes it, from rows y0 (N, 12)."""
    return dopri5.first_step(fused_glnn.Dopri5Field(), y0.T.contiguous(), params, rtol, atol)


def _problem(seed: int, n: int, w_scale: float, d_scale: float | None, dtype=F64):
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(3, 3, generator=gen, dtype=F64)
    J = A @ A.T + torch.eye(3, dtype=F64)
    D = None
    if d_scale is not None:
        B = torch.randn(3, 3, generator=gen, dtype=F64)
        D = (d_scale * (B @ B.T)).to(dtype).requires_grad_(True)
    R = so3.exp(torch.randn(n, 3, generator=gen, dtype=F64))
    w = w_scale * torch.randn(n, 3, generator=gen, dtype=F64)
    y0 = torch.cat((R.reshape(n, 9), w), -1).to(dtype).requires_grad_(True)
    Jinv = torch.linalg.inv(J).to(dtype).requires_grad_(True)
    weights = torch.randn(64, n, 12, generator=gen, dtype=F64).to(dtype)
    return y0, (J.to(dtype).requires_grad_(True), Jinv, D), weights


def _grads(loss, y0, params):
    leaves = [y0] + [p for p in params if p is not None]
    return torch.autograd.grad(loss, leaves)


# (seed, trajectories, |w|, damping scale, rtol, atol, h, outputs): what each case covers
CASES = {
    "paper tolerances": (0, 5, 1.0, 0.1, 1e-7, 1e-9, 0.1, 8),
    "many steps per output": (1, 3, 3.0, 1.0, 1e-9, 1e-11, 0.2, 3),
    "several outputs per step": (0, 4, 2.0, 1.0, 1e-5, 1e-8, 0.01, 20),
    "first step rejected": (0, 4, 20.0, 50.0, 1e-7, 1e-9, 0.05, 5),
    "no damping": (2, 6, 1.0, None, 1e-7, 1e-9, 0.1, 6),
    "body at rest (small-field first step)": (3, 2, 0.0, 1.0, 1e-7, 1e-9, 0.1, 5),
}


@pytest.mark.parametrize("case", list(CASES))
def test_solve_and_gradients_equal_torchdiffeq(case):
    seed, n, w_scale, d_scale, rtol, atol, h, T = CASES[case]
    y0, params, weights = _problem(seed, n, w_scale, d_scale)
    t = h * torch.arange(T, dtype=F64)
    calls = [0]

    def ref_f(_t, y):
        calls[0] += 1
        return _plain_field(y, *params)

    Y_ref = torchdiffeq_odeint(ref_f, y0, t, rtol=rtol, atol=atol, method="dopri5")
    field = _Counted()
    Y = _odeint(y0, t.tolist(), params, rtol, atol, 10**5, field)

    assert Y.shape == Y_ref.shape == (T, n, 12)
    assert (Y - Y_ref).abs().max() <= 1e-12 * Y_ref.abs().max()
    # the same evaluations, plus F(y0) once more: the first step's size is computed through its own node
    assert field.calls == calls[0] + 1
    g_ref = _grads((Y_ref * weights[:T]).sum(), y0, params)
    g = _grads((Y * weights[:T]).sum(), y0, params)
    for a, b in zip(g, g_ref, strict=True):
        assert (a - b).abs().max() <= 1e-12 * b.abs().max()


def test_the_cases_reach_the_branches_they_name():
    """Each named case exercises its branch (a rejected first step, several outputs in one step, the
    initial-step rule's small-field branch), so the equality above covers them."""

    def steps(case):
        seed, n, w_scale, d_scale, rtol, atol, h, T = CASES[case]
        y0, params, _ = _problem(seed, n, w_scale, d_scale)
        with torch.no_grad():
            dt0 = float(_first_step(y0, params, rtol, atol))
            times = (h * torch.arange(T, dtype=F64)).tolist()
            field = fused_glnn.Dopri5Field()
            return dopri5._solve_forward(field, params, y0.T.contiguous(), dt0, times, rtol, atol, 10**5)[1]

    assert not steps("first step rejected")[0].first
    assert steps("paper tolerances")[0].first
    assert max(len(s.outputs) for s in steps("several outputs per step")) >= 3
    assert min(len(s.outputs) for s in steps("many steps per output")) == 0
    y0, params, _ = _problem(*CASES["body at rest (small-field first step)"][:4])
    assert float(_first_step(y0, params, 1e-7, 1e-9).detach()) == 1e-6


def test_float32_matches_torchdiffeq_to_float32_rounding():
    y0, params, weights = _problem(0, 5, 1.0, 0.1, torch.float32)
    t = 0.1 * torch.arange(6, dtype=torch.float32)
    Y_ref = torchdiffeq_odeint(lambda _t, y: _plain_field(y, *params), y0, t, rtol=1e-5, atol=1e-7, method="dopri5")
    Y = _odeint(y0, t.tolist(), params, 1e-5, 1e-7, 100)
    assert Y.dtype == torch.float32
    assert (Y - Y_ref).abs().max() <= 1e-5 * Y_ref.abs().max()
    g_ref = _grads((Y_ref * weights[:6]).sum(), y0, params)
    g = _grads((Y * weights[:6]).sum(), y0, params)
    for a, b in zip(g, g_ref, strict=True):
        assert a.dtype == torch.float32
        assert (a - b).abs().max() <= 1e-4 * b.abs().max()


def test_step_limit_and_non_finite_start_raise_as_torchdiffeq_does():
    """Too few steps allowed, and a NaN in the start (its first step size is NaN, so both solvers stop on
    a zero step): the same exception and message as torchdiffeq's."""
    y0, params, _ = _problem(1, 3, 3.0, 1.0)
    bad = y0.detach().clone()
    bad[0, 9] = float("nan")
    for start, rtol, limit, message in ((y0, 1e-10, 3, "max_num_steps exceeded"), (bad, 1e-7, 100, "underflow in dt")):
        with pytest.raises(AssertionError, match=message):
            torchdiffeq_odeint(
                lambda _t, y: _plain_field(y, *params),
                start,
                torch.tensor([0.0, 1.0], dtype=F64),
                rtol=rtol,
                atol=1e-12,
                method="dopri5",
                options={"max_num_steps": limit},
            )
        with pytest.raises(AssertionError, match=message):
            _odeint(start, [0.0, 1.0], params, rtol, 1e-12, limit)


def test_a_second_backward_raises():
    """One node per solve, differentiable once (training needs one backward)."""
    y0, params, _ = _problem(0, 2, 1.0, 0.1)
    Y = _odeint(y0, [0.0, 0.1], params, 1e-7, 1e-9, 100)
    (g,) = torch.autograd.grad(Y.sum(), params[0], create_graph=True)
    with pytest.raises(RuntimeError, match="twice"):
        g.sum().backward()


def _tableau():
    A = torch.zeros(7, 7, dtype=F64)
    for i, row in enumerate(dopri5._A):
        A[i, : len(row)] = torch.tensor(row, dtype=F64)
    return A, A.sum(1)


def _order_conditions(w: torch.Tensor, theta: float) -> dict[int, float]:
    """Largest violation of the Runge-Kutta order conditions of each order 1..5 (all 17 rooted trees) for
    weights w (7,) of a solution at theta (1: the step's end)."""
    A, c = _tableau()
    Ac = A @ c
    trees = {
        1: [(w.sum(), theta)],
        2: [(w @ c, theta**2 / 2)],
        3: [(w @ c**2, theta**3 / 3), (w @ Ac, theta**3 / 6)],
        4: [(w @ c**3, theta**4 / 4), (w @ (c * Ac), theta**4 / 8), (w @ (A @ c**2), theta**4 / 12)]
        + [(w @ (A @ Ac), theta**4 / 24)],
        5: [(w @ c**4, theta**5 / 5), (w @ (c**2 * Ac), theta**5 / 10), (w @ Ac**2, theta**5 / 20)]
        + [(w @ (c * (A @ c**2)), theta**5 / 15), (w @ (A @ c**3), theta**5 / 20), (w @ (c * (A @ Ac)), theta**5 / 30)]
        + [
            (w @ (A @ (c * Ac)), theta**5 / 40),
            (w @ (A @ A @ c**2), theta**5 / 60),
            (w @ (A @ A @ Ac), theta**5 / 120),
        ],
    }
    return {p: max(abs(float(a) - b) for a, b in conds) for p, conds in trees.items()}


def test_the_tableau_meets_the_order_conditions():
    """The constants are what they claim: nodes (0, 1/5, 3/10, 4/5, 8/9, 1, 1); a 5th-order solution, an
    embedded 4th-order one (so the error estimate is of 5th order), a 4th-order midpoint."""
    A, c = _tableau()
    assert torch.allclose(c, torch.tensor([0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1, 1], dtype=F64), rtol=0, atol=1e-15)
    b = A[6]
    assert max(_order_conditions(b, 1.0).values()) < 1e-14
    low = _order_conditions(b - torch.tensor(dopri5._E, dtype=F64), 1.0)
    assert max(low[p] for p in range(1, 5)) < 1e-14 and low[5] > 1e-4
    mid = _order_conditions(torch.tensor(dopri5._MID, dtype=F64), 0.5)
    assert max(mid[p] for p in range(1, 5)) < 1e-14 and mid[5] > 1e-4


def test_the_dense_output_is_the_quartic_through_the_five_conditions():
    """_FIT maps (y0, y1, ymid, dt f0, dt f1) to the coefficients of p(x) = sum_p C_p x^p with p(0) = y0,
    p(1) = y1, p(1/2) = ymid, p'(0) = dt f0, p'(1) = dt f1: the inverse of that conditions matrix."""
    x = torch.tensor([0.0, 1.0, 0.5], dtype=F64)
    values = x[:, None] ** torch.arange(5, dtype=F64)  # p(x) rows
    slopes = torch.tensor([[0, 1, 0, 0, 0], [0, 1, 2, 3, 4]], dtype=F64)  # p'(0), p'(1) rows
    conditions = torch.cat((values, slopes))
    assert torch.allclose(torch.tensor(dopri5._FIT, dtype=F64), torch.linalg.inv(conditions), rtol=0, atol=1e-13)


def test_the_error_follows_the_tolerance_against_scipy():
    """A damped free body over 5 s against scipy's DOP853 at rtol 1e-13: the error is within a small multiple
    of the tolerance and falls ~ with it (1e-5 -> 1e-9: at least 1,000x)."""
    from scipy.integrate import solve_ivp

    y0, params, _ = _problem(4, 3, 1.5, 0.2)
    y0, params = y0.detach(), tuple(p.detach() for p in params)
    times = [0.5 * k for k in range(11)]

    def rhs(_t, flat):
        y = torch.from_numpy(flat).reshape(3, 12)
        return _plain_field(y, *params).reshape(-1).numpy()

    exact = solve_ivp(rhs, (0, 5), y0.reshape(-1).numpy(), method="DOP853", rtol=1e-13, atol=1e-14, t_eval=times)
    truth = torch.from_numpy(exact.y.T).reshape(11, 3, 12)
    errors = {}
    for rtol in (1e-5, 1e-9):
        Y = _odeint(y0, times, params, rtol, rtol * 1e-2, 10**5)
        errors[rtol] = float((Y - truth).abs().max())
    assert errors[1e-5] < 1e-3 and errors[1e-9] < 1e-7
    assert errors[1e-9] < errors[1e-5] / 1e3


def test_a_solve_nothing_differentiates_keeps_no_step_and_gives_the_same_outputs():
    """Rollouts (no gradient) hold only the current step, not the whole solve: same outputs."""
    y0, params, _ = _problem(0, 4, 1.0, 0.1)
    times = [0.1 * k for k in range(8)]
    Y = _odeint(y0, times, params, 1e-7, 1e-9, 100)
    with torch.no_grad():
        Y_free = _odeint(y0, times, params, 1e-7, 1e-9, 100)
        dt0 = float(_first_step(y0, params, 1e-7, 1e-9))
        field, cols = fused_glnn.Dopri5Field(), y0.T.contiguous()
        kept = dopri5._solve_forward(field, params, cols, dt0, times, 1e-7, 1e-9, 100, keep=True)
        free = dopri5._solve_forward(field, params, cols, dt0, times, 1e-7, 1e-9, 100, keep=False)
    assert Y.requires_grad and not Y_free.requires_grad
    assert torch.equal(Y.detach(), Y_free) and torch.equal(kept[0], free[0])
    assert len(kept[1]) > 7 and free[1] == []
