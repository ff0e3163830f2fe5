"""`models.liedflnn.engines.scalar`: one or a few trajectories of a single SO(3) body rolled out in Python floats
take the same Newton steps as the row layout and the reference path (flags, iteration counts, poses to
the Newton tolerance), hand careful iterations to the row layout's loop, and are taken only where they
pay (batch size, MLP size, activations, dtype, compilation)."""

from __future__ import annotations

import pytest
import torch
from test_fused_columns import MODELS, PHYS, TOL, H, assert_same_steps, model_named, start

from liedfl_cli.lie import SO3, Pose, so3, tolerances
from liedfl_cli.models.liedflnn.engines import columns as fused_columns
from liedfl_cli.models.liedflnn.engines import scalar as fused_scalar
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit

FLOAT_MODELS = ["mlp_rayleigh", "mlp_no_force", "free_rayleigh"]  # (gravity_and_mlp: not an MLP alone)


@pytest.fixture(autouse=True)
def _torch_engines(monkeypatch):
    """The float path, not the native step that would otherwise take these rollouts (tests/test_native_so3.py)."""
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)


def rows_floats_reference(model, g0, g1, steps, opts=None):
    """(row-layout fused rollout, rollout in floats, reference-path rollout)."""
    opts = opts or SolverOptions()
    assert fused_scalar.applies(model, g0)
    rows = rollout_implicit(model, g0, g1, steps, opts)
    floats = model.rollout(g0, g1, steps, opts)
    ref = model.with_path("reference").rollout(g0, g1, steps, opts)
    return rows, floats, ref


@pytest.mark.parametrize("name", FLOAT_MODELS + ["tanh_mlp"])
@pytest.mark.parametrize("n", [1, 2, 5])
def test_rollout_in_floats_takes_the_same_steps_as_the_row_layout_and_the_reference(name, n):
    if name == "tanh_mlp":
        model = LieDFLNN(SO3, H, init_jitter=0.3, seed=2, potential="mlp", forces=["rayleigh"], mlp_width=6)
        model.potential.net[1] = torch.nn.Tanh()
        model.requires_grad_(False)
    else:
        model = model_named(name)
    g0, g1 = start(n, seed=n)
    rows, floats, ref = rows_floats_reference(model, g0, g1, 25)
    assert_same_steps(rows, floats)
    assert_same_steps(ref, floats)
    assert torch.equal(floats.pose.R[:, 0], g0.R) and torch.equal(floats.pose.R[:, 1], g1.R)
    assert float(floats.residual_norm.max()) < 1e-8
    torch.testing.assert_close(floats.residual_norm, rows.residual_norm, rtol=0, atol=1e-10)


def test_irregular_iterations_go_to_the_row_layouts_careful_loop(monkeypatch):
    """Huge rotations per step: full steps without decrease, handed over (spied) and finished by the
    row layout's careful iterations: the same flags, counts and poses as the row layout."""
    handed = []
    real = fused_columns.ColumnStep.hand_over

    def spy(self, rows, W, *args):
        handed.append(W.shape)
        return real(self, rows, W, *args)

    model = physics_model(SO3, H, {**PHYS, "g": 0.0})  # no potential: the float path applies
    g0, g1 = start(40, scale=8.0, seed=1)
    rows = rollout_implicit(model, g0, g1, 12, SolverOptions())
    monkeypatch.setattr(fused_columns.ColumnStep, "hand_over", spy)
    got = []
    for t in range(40):  # one trajectory at a time: each through the float path
        one = Pose(g0.R[t : t + 1], g0.p[t : t + 1]), Pose(g1.R[t : t + 1], g1.p[t : t + 1])
        assert fused_scalar.applies(model, one[0])
        got.append(model.rollout(*one, 12, SolverOptions()))
    assert handed, "no iteration was handed over: the case no longer exercises the branch"
    assert all(shape == (9, 1) for shape in handed)
    assert rows.n_failed == 0
    assert torch.equal(torch.cat([r.iterations for r in got]), rows.iterations)
    assert torch.equal(torch.cat([r.converged for r in got]), rows.converged)
    assert float((torch.cat([r.pose.R for r in got]) - rows.pose.R).abs().max()) <= TOL


@pytest.mark.parametrize("opts", [SolverOptions(tol=1e-30, max_iter=1), SolverOptions(tol=1e-13, max_iter=3)])
def test_non_converged_steps_are_flagged_alike(opts):
    model = model_named("mlp_rayleigh")
    g0, g1 = start(3, scale=4.0)
    rows, floats, ref = rows_floats_reference(model, g0, g1, 15, opts)
    assert torch.equal(rows.converged, floats.converged) and torch.equal(ref.converged, floats.converged)
    assert torch.equal(rows.iterations, floats.iterations)
    if opts.max_iter == 1:
        assert floats.n_failed == 3 * 14


@pytest.mark.parametrize("steps", [0, 1, 2])
def test_short_rollouts_have_the_row_layouts_shapes(steps):
    model = model_named("free_rayleigh")
    g0, g1 = start(2)
    rows, floats, _ = rows_floats_reference(model, g0, g1, steps)
    assert_same_steps(rows, floats)
    assert floats.residual_norm.shape == rows.residual_norm.shape
    assert floats.iterations.dtype == rows.iterations.dtype and floats.converged.dtype == torch.bool


def test_long_rollout_stays_on_so3():
    model = model_named("mlp_rayleigh")
    g0, g1 = start(1, seed=5)
    floats = model.rollout(g0, g1, 1000)
    rows = rollout_implicit(model, g0, g1, 1000, SolverOptions())
    R = floats.pose.R
    assert float((R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-12
    assert torch.equal(rows.converged, floats.converged)
    assert float((rows.pose.R - floats.pose.R).abs().max()) < 1e-9  # rounding, grown over 1,000 steps


def test_progress_is_called_once_per_step():
    seen: list[int] = []
    g0, g1 = start(1)
    model_named("mlp_rayleigh").rollout(g0, g1, 6, progress=seen.append)
    assert seen == [1, 2, 3, 4, 5]


def test_which_rollouts_take_the_float_path():
    g1_, _ = start(1)
    mlp = model_named("mlp_rayleigh")  # 200 weights
    assert fused_scalar.applies(mlp, g1_) and fused_scalar.applies(mlp, start(6)[0])
    assert not fused_scalar.applies(mlp, start(7)[0])  # MAX_ROWS
    assert fused_scalar.applies(model_named("free_rayleigh"), start(6)[0])
    big = LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3)
    assert not fused_scalar.applies(big, g1_)  # 8,832 weights: the row layout is faster
    mid = LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=32, mlp_depth=3)
    assert fused_scalar.applies(mid, start(2)[0]) and not fused_scalar.applies(mid, start(3)[0])
    silu = LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=4)
    silu.potential.net[1] = torch.nn.SiLU()
    assert not fused_scalar.applies(silu, g1_)
    assert not fused_scalar.applies(model_named("gravity_and_mlp"), g1_)
    assert not fused_scalar.applies(physics_model(SO3, H, PHYS), g1_)  # gravity: not an MLP potential
    assert not fused_scalar.applies(mlp.with_path("reference"), g1_)
    assert not fused_scalar.applies(mlp, Pose(g1_.R.float(), g1_.p.float()))
    with pytest.MonkeyPatch.context() as mp:  # float32 unprojected: still not doubles
        mp.setitem(tolerances.PROJECT_POSES, torch.float32, False)
        assert not fused_scalar.applies(mlp, Pose(g1_.R.float(), g1_.p.float()))
    control = LieDFLNN(SO3, H, potential="mlp", forces={"control": {"width": 4}}, mlp_width=4)
    assert not fused_scalar.applies(control, g1_)
    assert set(FLOAT_MODELS) < set(MODELS)


def test_a_compiled_rollout_takes_the_row_layouts_compiled_step(monkeypatch):
    taken = []
    monkeypatch.setattr(ExecutionPlan, "wants_compile", lambda self, kind, work=None: True)
    monkeypatch.setattr(LieDFLNN, "rollout_rows", lambda self, *a, **k: taken.append(a) or "rows")
    g0, g1 = start(1)
    assert model_named("free_rayleigh").rollout(g0, g1, 4) == "rows"
    assert len(taken) == 1


def test_the_float_covector_equals_the_column_layouts():
    """The MLP potential's covector in floats against `gradient_columns` + `row_cross_sum`."""
    model = model_named("mlp_no_force")
    maps = fused_columns.rollout_maps(model)
    R = so3.exp(torch.randn(4, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    cols = R.reshape(4, 9).T.contiguous()
    want = fused_columns.potential_columns(model, maps, cols).T
    pot = fused_scalar._Potential(maps.potential_layers, -float(model.h))
    got = torch.tensor([pot.covector(r) for r in R.reshape(4, 9).tolist()], dtype=torch.float64)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-15)
