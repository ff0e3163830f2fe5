"""The Newton start of a single body's implicit step (`lie.batched.extrapolate_increments`): the last
three increments extrapolated, off the next increment by O(h^4) where the last increment alone is off by
O(h^2); the same guess on every rollout path (reference, rows, columns, floats), a failed step never
seeding it; on a smooth rollout at the default tolerance a step then needs one Newton iteration where
the last increment needs two."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.lie import SO3, Pose, ProductGroup, so3
from liedfl_cli.lie.batched import extrapolate_increments
from liedfl_cli.models.liedflnn import model as liedflnn_model
from liedfl_cli.models.liedflnn.engines import columns as fused_columns
from liedfl_cli.models.liedflnn.engines import scalar as fused_scalar
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit

F64 = torch.float64
G2 = ProductGroup(1, 1)  # an SE(3) body and an SO(3) body
PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 0.0, "D": [0.05] * 3}


def _curve(G: ProductGroup, t: torch.Tensor) -> Pose:
    """A smooth curve g(t) = exp(xi(t)) with xi cubic in t, one pose per time (len(t), ...)."""
    a = torch.tensor([0.3, -1.1, 0.7, 0.2, 0.5, -0.4, 0.9, 0.1, -0.6], dtype=F64)[: G.dim]
    b = torch.tensor([-0.8, 0.4, 0.9, -0.3, 0.6, 0.2, 0.3, -0.7, 0.5], dtype=F64)[: G.dim]
    c = torch.tensor([0.5, 0.2, -0.6, 0.4, -0.1, 0.3, -0.2, 0.4, 0.6], dtype=F64)[: G.dim]
    return G.exp(t[:, None] * a + t[:, None] ** 2 * b + t[:, None] ** 3 * c)


def _guess_errors(G: ProductGroup, h: float) -> list[float]:
    """Max over a unit time of the tangent error of the guess from the last 1, 2 and 3 increments."""
    n = round(1.0 / h)
    g = _curve(G, h * torch.arange(n + 1, dtype=F64))
    inc = G.increment(g.index(slice(None, -1)), g.index(slice(1, None)))  # W_0 .. W_{n-1}
    nxt = inc.index(slice(3, None))
    hist = [inc.index(slice(i, n - 3 + i)) for i in range(3)]  # W_{k-2}, W_{k-1}, W_k for k = 2 .. n-2
    return [float(G.log(G.increment(extrapolate_increments(G, hist[3 - j :]), nxt)).abs().max()) for j in (1, 2, 3)]


@pytest.mark.parametrize("G", [SO3, G2], ids=["SO3", "SE3xSO3"])
def test_the_guess_from_one_two_three_increments_is_off_by_h2_h3_h4(G):
    coarse, fine = _guess_errors(G, 0.02), _guess_errors(G, 0.01)
    assert coarse[2] < 0.1 * coarse[1] < 0.01 * coarse[0]
    for (a, b), order in zip(zip(coarse, fine), (2, 3, 4)):
        assert 0.8 * 2**order < a / b < 1.2 * 2**order, (order, a / b)


def _history(G: ProductGroup, n: int) -> list[Pose]:
    """The increments W_{k-2}, W_{k-1}, W_k of a smooth curve at h 0.05 for n values of k (batch n)."""
    g = _curve(G, 0.05 * torch.arange(n + 3, dtype=F64))
    inc = G.increment(g.index(slice(None, -1)), g.index(slice(1, None)))
    return [Pose(inc.R[i : i + n].clone(), inc.p[i : i + n].clone()) for i in range(3)]  # apart: edited below


def test_the_guess_has_the_closed_forms_of_the_column_and_float_paths():
    Ws = [W.R[:, 0] for W in _history(SO3, 5)]  # W_{k-2}, W_{k-1}, W_k
    T = lambda M: M.transpose(-1, -2)
    D, D_prev = Ws[2] @ T(Ws[1]), Ws[1] @ T(Ws[0])
    expected = {2: Ws[2] @ T(Ws[1]) @ Ws[2], 3: D @ T(D_prev) @ D @ Ws[2]}
    for k in (1, 2, 3):
        hist = Ws[3 - k :]
        ref = extrapolate_increments(SO3, [Pose(W[:, None], W.new_zeros(5, 0, 3)) for W in hist]).R[:, 0]
        torch.testing.assert_close(ref, expected.get(k, Ws[2]), rtol=0, atol=1e-15)
        cols = fused_columns.extrapolate_columns([fused_columns.to_columns(W[:, None]).view(9, 5) for W in hist])
        torch.testing.assert_close(cols.view(3, 3, 5).permute(2, 0, 1), ref, rtol=0, atol=1e-15)
        for i in range(5):
            floats = fused_scalar._extrapolate([W[i].flatten().tolist() for W in hist])
            torch.testing.assert_close(torch.tensor(floats, dtype=F64).view(3, 3), ref[i], rtol=0, atol=1e-15)


def test_a_failed_step_or_a_history_that_is_not_smooth_never_seeds_the_guess():
    """A non-finite earlier increment (a step that failed) or a spin reversed at every step gives the last
    increment back, row by row, on every layout; the other rows keep their extrapolation."""
    hist = _history(G2, 4)
    hist[1].R[1, 0, 0, 0] = float("nan")
    hist[0].p[2, 0, 1] = float("inf")
    w = torch.tensor([0.1, -0.2, 0.05], dtype=F64)
    for j, scale in enumerate((1.0, -2 / 3, 4 / 9)):  # row 3: the stiff damping's reversals
        hist[j].R[3, 1] = so3.exp(scale * w)
    last = hist[2]
    out = extrapolate_increments(G2, hist)
    assert torch.equal(out.R[1:], last.R[1:]) and torch.equal(out.p[1:], last.p[1:])
    assert not torch.allclose(out.R[0], last.R[0]) and bool(torch.isfinite(out.R[0]).all())
    for body in (0, 1):  # the SO(3) layouts, body by body
        Ws = [h.R[:, body : body + 1] for h in hist]
        cols = fused_columns.extrapolate_columns([fused_columns.to_columns(W).view(9, 4) for W in Ws])
        W_last = fused_columns.to_columns(Ws[2]).view(9, 4)
        assert not torch.equal(cols[:, 0], W_last[:, 0])
        for i in range(1, 4):
            expect_last = (i == 3 and body == 1) or (i == 1 and body == 0)  # row 2's inf is a translation
            assert torch.equal(cols[:, i], W_last[:, i]) == expect_last, (body, i)
            floats = fused_scalar._extrapolate([W[i, 0].flatten().tolist() for W in Ws])
            assert (floats == Ws[2][i, 0].flatten().tolist()) == expect_last, (body, i)


def test_stiff_damping_takes_no_more_iterations_than_the_last_increment(monkeypatch):
    """D = 100 J at h 0.1 (tests/test_damping.py): the spin reverses every step, the extrapolation is
    refused on every step, and the rollout is the last-increment start's, iteration for iteration."""
    h = 0.1
    model = physics_model(SO3, h, {**PHYS, "D": [100.0 * j for j in PHYS["J"]]}).requires_grad_(False)
    g0, g1 = _start(3, h, seed=2)
    ref = model.with_path("reference")
    runs = [model.rollout(g0, g1, 20), ref.rollout(g0, g1, 20)]
    monkeypatch.setattr(liedflnn_model, "extrapolate_increments", lambda G, incs: incs[-1])
    last = ref.rollout(g0, g1, 20)
    for r in runs:
        assert r.n_failed == 0 and torch.equal(r.iterations, last.iterations)
        torch.testing.assert_close(r.pose.R, last.pose.R, rtol=0, atol=1e-12)


def _start(n: int, h: float, seed: int) -> tuple[Pose, Pose]:
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(so3.exp(torch.randn(n, 1, 3, generator=gen, dtype=F64)), torch.zeros(n, 0, 3, dtype=F64))
    return g0, SO3.retract(g0, h * torch.randn(n, 3, generator=gen, dtype=F64))


@pytest.mark.parametrize("name", ["free body", "mlp + rayleigh"])
def test_smooth_rollouts_take_one_iteration_a_step_the_same_on_every_path(name, monkeypatch):
    """h 0.05, tolerance 1e-5 (the peer benchmark's settings): started from the last increment every step
    takes two iterations (it misses the next increment by more than the tolerance); from the extrapolated
    guess every step from the third on takes one (the first two have one and two increments behind
    them) — the same counts on the reference, row, column and float paths — and the poses are those of
    the last-increment start to within the tolerance."""
    h = 0.05
    if name == "free body":
        model = physics_model(SO3, h, PHYS)
    else:
        model = LieDFLNN(SO3, h, potential="mlp", forces=["rayleigh"], mlp_width=10, mlp_depth=2, seed=0)
    model.requires_grad_(False)
    g0, g1 = _start(4, h, seed=1)
    opts = SolverOptions()
    monkeypatch.setattr(fused_columns, "MIN_ROWS", 1)
    assert fused_scalar.applies(model, g0)
    floats = model.rollout(g0, g1, 60, opts)
    monkeypatch.setattr(fused_scalar, "MAX_ROWS", 0)
    columns = model.rollout(g0, g1, 60, opts)
    rows = rollout_implicit(model, g0, g1, 60, opts)
    reference = model.with_path("reference")
    ref = reference.rollout(g0, g1, 60, opts)
    monkeypatch.setattr(liedflnn_model, "extrapolate_increments", lambda G, incs: incs[-1])
    last = reference.rollout(g0, g1, 60, opts)
    assert torch.equal(last.iterations, torch.full_like(last.iterations, 2))
    assert torch.equal(ref.iterations[:, 2:], torch.ones_like(ref.iterations[:, 2:]))  # from three increments on
    torch.testing.assert_close(ref.pose.R, last.pose.R, rtol=0, atol=1e-8)
    for r in (floats, columns, rows, ref):
        assert bool(r.converged.all())
        assert torch.equal(r.iterations, ref.iterations)
        torch.testing.assert_close(r.pose.R, ref.pose.R, rtol=0, atol=1e-12)
