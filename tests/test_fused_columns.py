"""The column-layout rollout (`models.liedflnn.engines.columns`) steps exactly as the row layout does: the same
Newton iterations, flags and poses to the Newton tolerance (and to the reference path), its
pieces equal to independent references, and every branch of its Newton loop (compaction to the
rows still iterating, the hand-over of a singular or non-decreasing iteration) taken and checked."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, so3
from liedfl_cli.models.liedflnn.engines import columns as fused_columns
from liedfl_cli.models.liedflnn.engines import scalar as fused_scalar
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers import newton
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit

H = 0.1
PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.05] * 3}
TOL = SolverOptions().tol

MODELS = {
    "mlp_rayleigh": dict(potential="mlp", forces=["rayleigh"], mlp_width=10, mlp_depth=2),
    "mlp_no_force": dict(potential="mlp", forces=[], mlp_width=8, mlp_depth=3),
    "free_rayleigh": dict(potential="none", forces=["rayleigh"]),
    "gravity_and_mlp": dict(potential=["uniform_gravity", "mlp"], forces=["rayleigh"], mlp_width=8),
}


@pytest.fixture(autouse=True)
def _columns_at_every_batch_size(monkeypatch):
    """The column path at every batch size here (in use it starts at `MIN_ROWS` trajectories, and a
    few trajectories take `fused_scalar`)."""
    monkeypatch.setattr(fused_columns, "MIN_ROWS", 1)
    monkeypatch.setattr(fused_scalar, "MAX_ROWS", 0)
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)  # the torch engine (native: its own tests)


def model_named(name: str) -> LieDFLNN:
    """The model `name`, its networks from a fixed seed (the same model in every process)."""
    torch.manual_seed(0)
    if name == "true_scheme":
        return physics_model(SO3, H, PHYS)
    return LieDFLNN(SO3, H, init_jitter=0.3, seed=1, **MODELS[name]).requires_grad_(False)


def start(n: int, scale: float = 1.0, seed: int = 0) -> tuple[Pose, Pose]:
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, 1, 3, generator=gen, dtype=torch.float64)), torch.zeros(n, 0, 3, dtype=torch.float64)
    )
    return g0, SO3.retract(g0, H * scale * torch.randn(n, 3, generator=gen, dtype=torch.float64))


def rows_and_columns(model, g0, g1, steps, opts=None):
    """(row-layout fused rollout, column rollout, reference-path rollout)."""
    opts = opts or SolverOptions()
    assert fused_columns.applies(model, g0)
    rows = rollout_implicit(model, g0, g1, steps, opts)
    cols = model.rollout(g0, g1, steps, opts)
    ref = model.with_path("reference").rollout(g0, g1, steps, opts)
    return rows, cols, ref


def assert_same_steps(a, b, tol: float = TOL) -> None:
    assert a.pose.R.shape == b.pose.R.shape and a.pose.p.shape == b.pose.p.shape
    assert torch.equal(a.converged, b.converged)
    assert torch.equal(a.iterations, b.iterations)
    assert float((a.pose.R - b.pose.R).abs().max()) <= tol


@pytest.mark.parametrize("name", [*sorted(MODELS), "true_scheme"])
@pytest.mark.parametrize("n", [1, 7, 150])
def test_column_rollout_takes_the_same_steps_as_the_row_layout_and_the_reference(name, n):
    model = model_named(name)
    g0, g1 = start(n, seed=n)
    rows, cols, ref = rows_and_columns(model, g0, g1, 25)
    assert_same_steps(rows, cols)
    assert_same_steps(ref, cols)
    assert torch.equal(cols.pose.R[:, 0], g0.R) and torch.equal(cols.pose.R[:, 1], g1.R)
    assert float(cols.residual_norm.max()) < 1e-8  # converged steps: a residual far below the data scale


def test_compaction_to_the_rows_still_iterating_is_taken_and_keeps_the_counts(monkeypatch):
    """>= 64 rows with different iteration counts: the loop restarts on the rows still iterating."""
    calls = []
    loop = newton._newton_rows

    def counting(problem, x, r, *args):
        if problem.layout is fused_columns.COLUMNS:  # (the row layout's rollout runs too)
            calls.append(r.shape[1])
        return loop(problem, x, r, *args)

    monkeypatch.setattr(newton, "_newton_rows", counting)
    model = physics_model(SO3, H, {**PHYS, "g": 0.0})
    g0, g1 = start(300, scale=3.0)
    rows, cols, _ = rows_and_columns(model, g0, g1, 12)
    assert len(torch.unique(rows.iterations)) > 1
    assert any(k < 300 for k in calls)  # some solves ran on a subset of the rows
    assert_same_steps(rows, cols)


def test_irregular_iterations_hand_the_rows_to_the_row_layouts_careful_loop(monkeypatch):
    """Huge rotations per step: full Newton steps that do not decrease the residual, found by the
    column loop and finished by the row layout's careful iterations (same flags, counts, poses)."""
    handed = []
    rows_loop = newton._newton_rows

    def spy(problem, x, *args):
        if problem.layout is newton.ROWS:
            handed.append(x.R.shape[0])
        return rows_loop(problem, x, *args)

    model = physics_model(SO3, H, PHYS)
    # large enough for a full step without decrease, small enough that every step converges (with
    # failures, rounding decides among chaotic outcomes: rows and the reference path differ there too)
    g0, g1 = start(40, scale=5.0, seed=1)
    rows = rollout_implicit(model, g0, g1, 12, SolverOptions())
    ref = model.with_path("reference").rollout(g0, g1, 12, SolverOptions())
    monkeypatch.setattr(newton, "_newton_rows", spy)
    cols = model.rollout(g0, g1, 12, SolverOptions())
    assert handed, "no iteration was handed over: the case no longer exercises the branch"
    assert rows.n_failed == 0
    assert_same_steps(rows, cols)
    assert_same_steps(ref, cols)


@pytest.mark.parametrize("opts", [SolverOptions(tol=1e-30, max_iter=1), SolverOptions(tol=1e-13, max_iter=3)])
def test_non_converged_steps_are_flagged_alike(opts):
    model = physics_model(SO3, H, PHYS)
    g0, g1 = start(5, scale=4.0)
    rows, cols, ref = rows_and_columns(model, g0, g1, 15, opts)
    assert torch.equal(rows.converged, cols.converged) and torch.equal(ref.converged, cols.converged)
    assert torch.equal(rows.iterations, cols.iterations)
    if opts.max_iter == 1:
        assert cols.n_failed == 5 * 14


@pytest.mark.parametrize("steps", [0, 1, 2])
def test_short_rollouts_have_the_row_layouts_shapes(steps):
    model = model_named("mlp_rayleigh")
    g0, g1 = start(3)
    rows, cols, _ = rows_and_columns(model, g0, g1, steps)
    assert_same_steps(rows, cols)
    assert cols.residual_norm.shape == rows.residual_norm.shape


def test_progress_is_called_once_per_step():
    seen: list[int] = []
    g0, g1 = start(2)
    model_named("free_rayleigh").rollout(g0, g1, 6, progress=seen.append)
    assert seen == [1, 2, 3, 4, 5]


def test_small_batches_keep_the_row_layout(monkeypatch):
    monkeypatch.setattr(fused_columns, "MIN_ROWS", 32)
    model = model_named("mlp_rayleigh")
    assert not fused_columns.applies(model, start(31)[0]) and fused_columns.applies(model, start(32)[0])
    taken = []
    monkeypatch.setattr(fused_columns, "rollout", lambda *a, **k: taken.append(a))
    g0, g1 = start(5)
    model.rollout(g0, g1, 4)
    assert not taken


def test_which_models_take_the_column_path():
    g0, _ = start(2)
    assert fused_columns.applies(model_named("mlp_rayleigh"), g0)
    assert not fused_columns.applies(model_named("mlp_rayleigh").with_path("reference"), g0)
    control = LieDFLNN(SO3, H, potential="mlp", forces={"control": {"width": 4}}, mlp_width=4)
    assert not fused_columns.applies(control, g0)
    assert not fused_columns.applies(model_named("mlp_rayleigh"), Pose(g0.R.float(), g0.p.float()))
    se3 = LieDFLNN(SE3, H, potential="none", forces=["rayleigh"])
    assert not fused_columns.applies(se3, Pose(g0.R, torch.zeros(2, 1, 3, dtype=torch.float64)))
    two = LieDFLNN(ProductGroup(0, 2), H, potential="none", forces=["rayleigh"])
    assert not fused_columns.applies(two, Pose(g0.R.expand(2, 2, 3, 3), g0.p))


def test_a_compiled_rollout_takes_the_row_layouts_compiled_step(monkeypatch):
    taken = []
    monkeypatch.setattr(ExecutionPlan, "wants_compile", lambda self, kind, work=None: True)
    monkeypatch.setattr(LieDFLNN, "rollout_rows", lambda self, *a, **k: taken.append(a) or "rows")
    g0, g1 = start(2)
    assert model_named("free_rayleigh").rollout(g0, g1, 4) == "rows"
    assert len(taken) == 1


# ----------------------------------------------------------------------------- the pieces
def cols_of(R: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) -> (9, T)."""
    return R.reshape(-1, 9).T.contiguous()


def test_column_matmul_and_newton_schulz_equal_batched_matmul():
    gen = torch.Generator().manual_seed(0)
    A, B = (torch.randn(5, 3, 3, generator=gen, dtype=torch.float64) for _ in range(2))
    got = fused_columns.matmul(cols_of(A).view(3, 3, -1), cols_of(B).view(3, 3, -1)).view(9, -1)
    torch.testing.assert_close(got, cols_of(A @ B), rtol=0, atol=1e-15)
    NS = 0.5 * A @ (3 * torch.eye(3, dtype=torch.float64) - A.transpose(-1, -2) @ A)
    torch.testing.assert_close(fused_columns.newton_schulz(cols_of(A)), cols_of(NS), rtol=1e-15, atol=1e-13)


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-3, 1.0, 3.1])
def test_column_retraction_equals_the_matrix_exponential(scale):
    """W exp(hat(delta)) against torch.linalg.matrix_exp, down to delta = 0 and near pi."""
    gen = torch.Generator().manual_seed(1)
    W = so3.exp(torch.randn(6, 3, generator=gen, dtype=torch.float64))
    d = torch.nn.functional.normalize(torch.randn(6, 3, generator=gen, dtype=torch.float64), dim=-1) * scale
    model = model_named("free_rayleigh")
    cols = fused_columns.ColumnMaps(model, fused_columns.rollout_maps(model))
    got = fused_columns.retract(cols_of(W), d.T.contiguous(), cols)
    torch.testing.assert_close(got, cols_of(W @ torch.linalg.matrix_exp(so3.hat(d))), rtol=0, atol=1e-14)


def test_adjugate_solve_equals_lu_and_row_cross_sum_equals_its_definition():
    gen = torch.Generator().manual_seed(2)
    J = torch.randn(8, 3, 3, generator=gen, dtype=torch.float64)
    r = torch.randn(8, 3, generator=gen, dtype=torch.float64)
    adj = fused_columns.adjugate_rows(cols_of(J)[fused_columns.adjugate_index()]).view(3, 3, -1)  # [slot, i, t]
    det = (cols_of(J)[0:3] * adj[0]).sum(0)
    x = ((adj * r.T[:, None]).sum(0) / det).T
    torch.testing.assert_close(x, torch.linalg.solve(J, r), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(det, torch.linalg.det(J), rtol=1e-12, atol=1e-12)
    A, B = (torch.randn(8, 3, 3, generator=gen, dtype=torch.float64) for _ in range(2))
    want = torch.linalg.cross(A, B, dim=-1).sum(-2)  # sum over rows k of A_k x B_k
    torch.testing.assert_close(fused_columns.row_cross_sum(cols_of(A), cols_of(B)).T, want, rtol=1e-14, atol=1e-14)
    # a non-contiguous batch (a column view) gives the same
    wide = torch.cat((cols_of(A), cols_of(B)), 1)
    got = fused_columns.row_cross_sum(wide[:, :8], wide[:, 8:])
    torch.testing.assert_close(got.T, want, rtol=1e-14, atol=1e-14)


def test_long_rollout_stays_on_so3_and_with_the_row_layout():
    """1,000 steps: the Newton-Schulz cleaning keeps the poses orthonormal to rounding, as in rows."""
    model = model_named("mlp_rayleigh")
    g0, g1 = start(4, seed=5)
    rows = rollout_implicit(model, g0, g1, 1000, SolverOptions())
    cols = model.rollout(g0, g1, 1000)
    R = cols.pose.R
    drift = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype)).abs().max()
    assert float(drift) < 1e-12
    assert torch.equal(rows.converged, cols.converged)
    assert (
        float((rows.pose.R - cols.pose.R).abs().max()) < 1e-9
    )  # rounding differences, grown over 1,000 steps (6e-13 here)
