"""Sub-steps and the fourth-order step (`model.substeps`, `model.order`; models/liedflnn/substeps.py).

References that do not share the sub-step code: scipy's DOP853 at tolerance 1e-13 (the heavy top's
equations of motion, `data.physics`) for the convergence orders of a single body; autodiff for the
internal Jacobian; central differences of the loss (the internal poses re-solved) for the
implicit-function gradient; the wrapped model's own residual where the sub-steps are uniform.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.lie import joints as jt
from liedfl_cli.models.base import LossOptions, TripletBatch
from liedfl_cli.models.liedflnn import substeps as sb
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.options import SolverOptions
from tests.test_articulated_joints import learned_like, mixed_tree, smooth_motion

F64 = torch.float64
TIGHT = SolverOptions(tol=1e-12, max_iter=20)
G_SO3 = ProductGroup(0, 1)
TOP = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1, 0.1, 0.1]}


def top_truth(h: float, horizon: float, n_traj: int = 3) -> Pose:
    """The damped heavy top sampled at h (DOP853, rtol 1e-13): R (n_traj, N+1, 1, 3, 3)."""
    from liedfl_cli.data.physics import RigidBodySO3, simulate_so3

    body = RigidBodySO3(J=np.diag(TOP["J"]), m=TOP["m"], rho=np.array(TOP["rho"]), g=TOP["g"], D=np.diag(TOP["D"]))
    w0 = np.random.default_rng(0).normal(size=(n_traj, 3))
    R0 = np.broadcast_to(np.eye(3), (n_traj, 3, 3)).copy()
    n = round(horizon / h)
    sim = simulate_so3(body, R0, w0, h * np.arange(n + 1), {"method": "DOP853", "rtol": 1e-13, "atol": 1e-14})
    R = torch.from_numpy(sim.R)[:, :, None]
    return Pose(R, R.new_zeros(n_traj, n + 1, 0, 3))


def end_error(model, truth: Pose) -> float:
    n = truth.R.shape[1] - 1
    ro = model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, TIGHT)
    assert ro.n_failed == 0
    return float((ro.pose.R[:, -1] - truth.R[:, -1]).norm(dim=(-1, -2)).max())


def test_fractions_sum_to_one_and_are_symmetric():
    for s in (1, 2, 3, 8):
        for order in (2, 4):
            c = sb.step_fractions(s, order)
            assert len(c) == s * (1 if order == 2 else 3)
            assert math.isclose(sum(c), 1.0, rel_tol=1e-14)
            assert c == tuple(reversed(c))
    g1, g2 = sb.GAMMA1, sb.GAMMA2
    assert g2 < 0 and math.isclose(2 * g1**3 + g2**3, 0.0, abs_tol=1e-14)  # the order-4 condition


@pytest.mark.parametrize("bad", [0, -1, 1.5, "two", True, 65])
def test_bad_substeps_is_one_config_error(bad):
    with pytest.raises(ConfigError, match="model.substeps"):
        sb.check_steps(bad, 2)


@pytest.mark.parametrize("bad", [1, 3, 6, "4", True])
def test_bad_order_is_one_config_error(bad):
    with pytest.raises(ConfigError, match="model.order"):
        sb.check_steps(1, bad)


def test_one_second_order_step_is_the_paper_model_itself():
    m = physics_model(G_SO3, 0.05, TOP)
    assert sb.with_substeps(m, 1, 2) is m
    assert isinstance(sb.with_substeps(m, 2, 2), sb.SubstepModel)


@pytest.mark.parametrize("residual", ["fast", "generic"])
def test_uniform_substep_residual_is_the_models_residual(residual):
    model = LieDFLNN(G_SO3, 0.05, potential=["mlp"], forces=["rayleigh"], residual=residual, seed=1)
    g = top_truth(0.05, 0.15)
    a, b, c = (g.index((slice(None), i)) for i in range(3))
    r = sb.substep_residual(model, model, a, b, c)
    assert torch.allclose(r, model.residual(a, b, c), rtol=1e-12, atol=1e-14)


def test_uniform_substep_residual_is_the_tree_models_reduced_residual():
    tree = mixed_tree("world")
    torch.manual_seed(0)
    model = learned_like(tree, 0.05)
    assert model.reduced
    q = smooth_motion(tree, 2, 2, 0.05, seed=4)
    a, b, c = (q.index((slice(None), i)) for i in range(3))
    assert torch.allclose(sb.substep_residual(model, model, a, b, c), model.residual(a, b, c), rtol=1e-11, atol=1e-13)


def test_symmetric_potential_weight_between_unequal_substeps():
    """A_{ha} + B_{hb} weights V at the pose by (ha + hb) / 2, in both residual modes."""
    h = 0.05
    out = {}
    g = top_truth(h, 0.15)
    a, b, c = (g.index((slice(None), i)) for i in range(3))
    for residual in ("fast", "generic"):
        model = LieDFLNN(G_SO3, h, potential=["mlp"], forces=[], residual=residual, seed=1)
        ma, mb = model.with_path("reference"), model.with_path("reference")
        ma.h, mb.h = 0.03, 0.07
        out[residual] = sb.substep_residual(ma, mb, a, b, c)
        # reference: the kinetic terms at their own steps and -(ha + hb)/2 dV/d eta, by autodiff of V
        eta = torch.zeros(b.R.shape[0], 3, dtype=F64)
        V = model.potential
        dV = torch.func.grad(lambda e, V=V: V(G_SO3.perturb(b, e)).sum())(eta)
        from liedfl_cli.mechanics import kinetic

        Jd = model.inertia.Jd()
        ref = (
            kinetic.kinetic_d2(G_SO3, G_SO3.increment(a, b), Jd, Jd.new_zeros(0), Jd.new_zeros(0, 3), 0.03)
            + kinetic.kinetic_d1(G_SO3, G_SO3.increment(b, c), Jd, Jd.new_zeros(0), Jd.new_zeros(0, 3), 0.07)
            - 0.05 * dV
        )
        assert torch.allclose(out[residual], ref, rtol=1e-10, atol=1e-12), residual


@pytest.mark.parametrize("potential", [["uniform_gravity"], ["mlp"], []])
def test_linear_engine_equals_the_reference_residual(potential):
    """The fused linear maps give the sub-step residual of the reference functions (unequal steps too)."""
    model = sb.SubstepModel(
        LieDFLNN(G_SO3, 0.05, potential=potential, forces=["rayleigh"], seed=3, init_jitter=0.3), 1, 4
    )
    assert sb._LinearEngine.applies(model.inner)
    engine = sb._LinearEngine(model)
    ref = model._models("reference")
    g = top_truth(0.05, 0.15)
    a, b, c = (g.index((slice(None), i)) for i in range(3))
    for ia, ib in ((0, 1), (1, 2), (2, 0)):
        with torch.enable_grad():
            want = sb.substep_residual(ref[ia], ref[ib], a, b, c).detach()
        assert torch.allclose(engine.residual(ia, ib, a, b, c), want, rtol=1e-10, atol=1e-12), (ia, ib)


def test_fused_and_reference_order_four_rollouts_agree():
    kw = {"potential": ["uniform_gravity"], "forces": ["rayleigh"], "seed": 5, "init_jitter": 0.2}
    fused = sb.SubstepModel(LieDFLNN(G_SO3, 0.05, path="fused", **kw), 2, 4)
    ref = sb.SubstepModel(LieDFLNN(G_SO3, 0.05, path="reference", **kw), 2, 4)
    assert sb._LinearEngine.applies(fused.inner) and not sb._LinearEngine.applies(ref.inner)
    g = top_truth(0.05, 0.1)
    # 12 steps: past the 4 cycles the warm start's extrapolation needs; the paths differ by ~1e-14 there
    a, b = (
        fused.rollout(g.index((slice(None), 0)), g.index((slice(None), 1)), 12, TIGHT),
        ref.rollout(g.index((slice(None), 0)), g.index((slice(None), 1)), 12, TIGHT),
    )
    assert a.n_failed == 0 and b.n_failed == 0
    assert torch.allclose(a.pose.R, b.pose.R, atol=1e-10)


def test_column_and_row_order_four_rollouts_agree(monkeypatch):
    from liedfl_cli.models.liedflnn.engines import columns as fused_columns

    model = sb.SubstepModel(
        LieDFLNN(G_SO3, 0.05, potential=["uniform_gravity"], forces=["rayleigh"], seed=5, init_jitter=0.2), 1, 4
    )
    g = top_truth(0.05, 0.1, n_traj=fused_columns.MIN_ROWS)
    start = g.index((slice(None), 0)), g.index((slice(None), 1))
    assert fused_columns.applies(model.inner, start[0])
    cols = model.rollout(*start, 25, TIGHT)
    monkeypatch.setattr(fused_columns, "MIN_ROWS", 10**6)  # the row layout (`_rows_cycle`)
    rows = model.rollout(*start, 25, TIGHT)
    assert cols.n_failed == 0 and rows.n_failed == 0
    assert torch.allclose(cols.pose.R, rows.pose.R, atol=1e-11)


def test_internal_jacobian_matches_autodiff():
    model = sb.SubstepModel(physics_model(G_SO3, 0.05, TOP), 4, 2)
    g = top_truth(0.05, 0.05, n_traj=2)
    q0, q1 = g.index((slice(None), 0)), g.index((slice(None), 1))
    models = model._models("reference")
    z, ok = model.internal_poses(q0, q1)
    assert bool(ok.all())
    J = model._interior_jacobian(models, q0, z, q1)
    zero = torch.zeros(2, len(z), 3, dtype=F64)

    def F(d):
        return model._interior(models, q0, [G_SO3.retract(z[i], d[:, i]) for i in range(len(z))], q1)

    Jad = torch.autograd.functional.jacobian(F, zero).reshape(2, 9, 2, 9)
    Jad = torch.stack([Jad[i, :, i] for i in range(2)])
    assert torch.allclose(J, Jad, rtol=1e-6, atol=1e-6 * float(Jad.abs().max()))


@pytest.mark.parametrize(("s", "order"), [(3, 2), (1, 4)])
def test_internal_poses_solve_the_substep_equations(s, order):
    model = sb.SubstepModel(physics_model(G_SO3, 0.05, TOP), s, order)
    g = top_truth(0.05, 0.05)
    q0, q1 = g.index((slice(None), 0)), g.index((slice(None), 1))
    z, ok = model.internal_poses(q0, q1)
    assert bool(ok.all()) and len(z) == len(model.fractions) - 1
    with torch.enable_grad():
        F = model._interior(model._models("reference"), q0, z, q1)
    assert float(F.abs().max()) < 1e-10
    assert all(float(G_SO3.orthogonality_error(x).max()) < 1e-12 for x in z)


def test_tree_internal_poses_stay_on_the_joints():
    """Damping drawn with seed 2 (seed 1 ran the same code with 3 Newton Jacobians, this one needs 5:
    more moves along the joints to stay on them)."""
    tree = mixed_tree("world")
    torch.manual_seed(2)  # learned_like draws its damping from the global generator
    model = sb.SubstepModel(learned_like(tree, 0.05), 1, 4)
    q = smooth_motion(tree, 2, 1, 0.05, seed=5)
    z, ok = model.internal_poses(q.index((slice(None), 0)), q.index((slice(None), 1)))
    assert bool(ok.all())
    ax = torch.tensor(tree.axes_array(), dtype=F64)
    q0 = jt.to_joint_coordinates(tree, q.index((slice(None), 0)))
    for x in z:
        qx = jt.to_joint_coordinates(tree, x)
        # the hinge keeps its axis, the weld its rotation (as in tests/test_articulated_joints.py)
        assert torch.allclose(qx.R[:, 1] @ ax[1, 0], q0.R[:, 1] @ ax[1, 0], atol=1e-11)
        assert torch.allclose(qx.R[:, 4], q0.R[:, 4], atol=1e-11)


def test_convergence_orders_on_the_heavy_top_against_dop853():
    """Error at t = 0.6 s with the true parameters: / 4 per halving for one second-order step, / s^2 with
    s sub-steps, / 16 for order 4 (the measured slope, not the expected one, is what is asserted)."""
    errs: dict[tuple[int, int], list[float]] = {(1, 2): [], (2, 2): [], (1, 4): []}
    hs = (0.06, 0.03)
    for h in hs:
        truth = top_truth(h, 0.6)
        for s, order in errs:
            errs[(s, order)].append(end_error(sb.with_substeps(physics_model(G_SO3, h, TOP), s, order), truth))
    p2 = sb.measured_order(errs[(1, 2)], hs)
    p4 = sb.measured_order(errs[(1, 4)], hs)
    assert 1.8 < p2 < 2.3, errs
    assert p4 > 3.7, errs
    for e1, e2 in zip(errs[(1, 2)], errs[(2, 2)]):
        assert 3.3 < e1 / e2 < 4.7, errs  # two sub-steps: a quarter of the error


def test_an_unconverged_start_is_reported_as_a_failed_first_step(monkeypatch):
    monkeypatch.setattr(sb, "INTERNAL_MAX_ITER", 1)  # one Newton iteration cannot reach the tolerance
    model = sb.SubstepModel(physics_model(G_SO3, 0.05, TOP), 1, 4)
    g = top_truth(0.05, 0.15)
    ro = model.rollout(g.index((slice(None), 0)), g.index((slice(None), 1)), 3, TIGHT)
    assert not bool(ro.converged[:, 0].any()) and bool(ro.converged[:, 1].all())


@pytest.mark.slow
def test_an_unsolvable_fourth_order_start_is_a_reported_failure():
    """Damping per DoF up to 1.6 (seed 0): the triple jump's negative sub-step leaves one trajectory's
    internal poses without a solution; the rollout flags its first step instead of going on silently."""
    tree = mixed_tree("world")
    torch.manual_seed(0)
    model = sb.SubstepModel(learned_like(tree, 0.05), 1, 4)
    q = smooth_motion(tree, 2, 1, 0.05, seed=5)
    q0, q1 = q.index((slice(None), 0)), q.index((slice(None), 1))
    z, ok = model.internal_poses(q0, q1)
    assert ok.tolist() == [True, False]
    assert all(float(model.G.orthogonality_error(x).max()) < 1e-10 for x in z)  # still on the group
    ro = model.rollout(q0, q1, 2, TIGHT)
    assert not bool(ro.converged[1, 0])
    assert sb.with_substeps(model.inner, 3, 2).internal_poses(q0, q1)[1].all()  # positive sub-steps solve it


@pytest.mark.slow
def test_convergence_order_four_on_a_tree():
    """A reduced tree (free root, hinge, universal, ball, weld) under gravity with per-DoF damping, its
    own parameters: order 4 against the same scheme 8 sub-steps finer (Richardson-style reference)."""
    tree = mixed_tree("world")
    q = smooth_motion(tree, 2, 1, 0.04, seed=6)
    q0, q1 = q.index((slice(None), 0)), q.index((slice(None), 1))
    torch.manual_seed(1)  # damping per DoF where the triple jump's start is solvable (seed 0: see above)
    base = learned_like(tree, 0.04)
    fine = sb.SubstepModel(base, 8, 4)
    ref = fine.rollout(q0, q1, 11)  # default Newton settings: 1e-12 is below a tree's rounding floor  # to t = 0.4 s
    assert ref.n_failed == 0
    errs = []
    for s in (1, 2):
        model = sb.SubstepModel(base, s, 4)
        ro = model.rollout(q0, q1, 11)
        assert ro.n_failed == 0
        errs.append(float((ro.pose.R[:, -1] - ref.pose.R[:, -1]).norm(dim=(-1, -2)).max()))
    assert math.log2(errs[0] / errs[1]) > 3.6, errs


def test_implicit_function_gradient_matches_central_differences():
    torch.manual_seed(0)
    model = sb.SubstepModel(
        LieDFLNN(G_SO3, 0.05, potential=["uniform_gravity"], forces=["rayleigh"], seed=2, init_jitter=0.3), 1, 4
    )
    g = top_truth(0.05, 0.15, n_traj=2)
    batch = TripletBatch(*(g.index((slice(None), i)) for i in range(3)))
    opts = LossOptions(w_reg=0.0)
    param = model.inner.inertia.abc
    loss, _ = model.loss(batch, opts)
    (grad,) = torch.autograd.grad(loss, param)
    eps = 1e-6
    fd = torch.zeros_like(param)
    with torch.no_grad():
        for i in range(param.numel()):
            param.view(-1)[i] += eps
            up = float(model.loss(batch, opts)[0])
            param.view(-1)[i] -= 2 * eps
            down = float(model.loss(batch, opts)[0])
            param.view(-1)[i] += eps
            fd.view(-1)[i] = (up - down) / (2 * eps)
    assert torch.allclose(grad, fd, rtol=1e-4, atol=1e-6 * float(fd.abs().max()))


def test_substep_rollout_starts_and_ends_on_the_samples():
    model = sb.SubstepModel(physics_model(G_SO3, 0.05, TOP), 3, 2)
    g = top_truth(0.05, 0.2)
    ro = model.rollout(g.index((slice(None), 0)), g.index((slice(None), 1)), 4, TIGHT)
    assert ro.pose.R.shape == (3, 5, 1, 3, 3)
    assert ro.converged.shape == (3, 3) and ro.iterations.shape == (3, 3)
    assert torch.equal(ro.pose.R[:, :2], g.R[:, :2])
    assert float((ro.pose.R - g.R).abs().max()) < 1e-3


def test_newton_loss_with_substeps_is_refused():
    model = sb.SubstepModel(physics_model(G_SO3, 0.05, TOP), 2, 2)
    g = top_truth(0.05, 0.1)
    with pytest.raises(ConfigError, match="train.loss=newton"):
        model.loss(TripletBatch(*(g.index((slice(None), i)) for i in range(3))), LossOptions(loss="newton"))


@pytest.mark.parametrize("n_se3", [0, 1])
def test_closed_form_gravity_covector_equals_autodiff(n_se3):
    G = ProductGroup(n_se3, 1 - n_se3)
    model = LieDFLNN(G, 0.05, potential=["uniform_gravity"], forces=[], seed=4, init_jitter=0.3)
    gen = torch.Generator().manual_seed(1)
    g = G.exp(torch.randn(5, G.dim, generator=gen, dtype=F64))
    eta = torch.zeros(5, G.dim, dtype=F64)
    ref = -0.05 * torch.func.grad(lambda e: model.potential(G.perturb(g, e)).sum())(eta)
    assert torch.allclose(model.potential_covector(g), ref, rtol=1e-12, atol=1e-14)
    from liedfl_cli.models.liedflnn.engines import maps as fused_maps

    assert torch.allclose(fused_maps.potential_covector(model, g), ref, rtol=1e-12, atol=1e-14)


def test_random_rotation_guess_is_on_the_group():
    """so3 sanity for the geodesic start of the internal poses (far from the identity)."""
    R = so3.exp(torch.tensor([[3.0, 0.1, 0.0]], dtype=F64))
    z = sb.move(
        physics_model(G_SO3, 0.05, TOP), Pose(R[:, None], R.new_zeros(1, 0, 3)), torch.tensor([[0.1, 0, 0]]).double()
    )
    assert float(G_SO3.orthogonality_error(z).max()) < 1e-13


@pytest.fixture(scope="module")
def heavy_so3_data(tmp_path_factory) -> Path:
    """One data folder for the train commands below: the smoke heavy_so3 dataset is generated once
    (the dataset cache is keyed by its config) instead of once per test."""
    return tmp_path_factory.mktemp("substeps_data")


@pytest.fixture
def short_start(monkeypatch) -> list[str]:
    """The train commands below run the sub-step start (L-BFGS on the one-step loss, then
    Levenberg-Marquardt on the sub-step residual) with a tenth of its iterations: they test the
    command's path through it (the start, the rollout, the files), not how well it fits (which they
    never asserted; the fitting loops have tests of their own in this file). Returns the stages that
    ran, in order, for the tests to check."""
    ran: list[str] = []
    lbfgs, lm = sb.second_order_fit, sb.levenberg_marquardt

    def second_order_fit(model, samples, iterations=sb.START_ITERATIONS):
        ran.append("L-BFGS")
        return lbfgs(model, samples, max(1, iterations // 10))

    def levenberg_marquardt(model, samples, iterations=sb.LM_ITERATIONS):
        ran.append("LM")
        return lm(model, samples, max(1, iterations // 10))

    monkeypatch.setattr(sb, "second_order_fit", second_order_fit)
    monkeypatch.setattr(sb, "levenberg_marquardt", levenberg_marquardt)
    return ran


def _smoke_train_cfg(data: Path, out: Path, *overrides: str):
    from helpers import SMOKE, compose_config

    return compose_config("train", (*SMOKE, f"paths.data_dir={data}", f"paths.output_dir={out}", *overrides))


@pytest.mark.parametrize(("s", "order"), [(2, 2), (1, 4)])
def test_train_command_with_substeps_end_to_end(tmp_path, heavy_so3_data, short_start, s, order):
    """`liedfl train model.substeps/model.order` at a smoke budget: the start, a rollout of the sub-stepped
    model, the true scheme on the same step, every file written."""
    from liedfl_cli.commands.train import run_train

    cfg = _smoke_train_cfg(
        heavy_so3_data, tmp_path / "run", "dataset=heavy_so3", f"model.substeps={s}", f"model.order={order}"
    )
    result = run_train(cfg)
    out = Path(result["run_dir"])
    for name in ("eval.csv", "rollout.h5", "checkpoints/last.pt", "summary.json"):
        assert (out / name).exists(), name
    import json

    components = json.loads((out / "components.json").read_text())
    assert components["model"] == "SubstepModel"
    assert f"step: {s} sub-step(s) of order {order}" in components["components"][-1]
    assert short_start == ["L-BFGS", "LM"]  # the start ran both of its stages


def test_train_epochs_zero_keeps_the_start(tmp_path, heavy_so3_data, short_start):
    """train.epochs=0: the model's start only (here the sub-step fit), checkpointed and evaluated.

    Two second-order sub-steps: the same start (the one-step L-BFGS, then Levenberg-Marquardt on the
    sub-step residual) as order 4 at a third of its cost; order 4's start runs end to end above
    (`test_train_command_with_substeps_end_to_end[1-4]`)."""
    import json

    from liedfl_cli.commands.train import run_train

    cfg = _smoke_train_cfg(heavy_so3_data, tmp_path / "run", "dataset=heavy_so3", "model.substeps=2", "train.epochs=0")
    result = run_train(cfg)
    out = Path(result["run_dir"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["final_loss"] is None and summary["timings"]["epochs"] == 0
    assert (out / "checkpoints" / "last.pt").is_file() and (out / "eval.csv").is_file()
    assert short_start == ["L-BFGS", "LM"]  # the start ran (and was all the training)


# ---------------------------------------------------------------------------- the cycle's warm start
@pytest.mark.parametrize("n_traj", [3, 32])  # the row layout, then the column layout (`fused_columns.MIN_ROWS`)
def test_predicted_warm_start_keeps_the_rollout_and_cuts_the_iterations(monkeypatch, n_traj):
    """The old warm start (the last increment scaled to the sub-step, `PREDICTOR_DEGREE < 0`) and the
    extrapolation of the same sub-step's last cycles converge to the same poses at tol 1e-12; the
    solver's own iteration counts fall from 2 to ~1 per sub-step at the default tolerance, 3 to ~2 at 1e-12."""
    from liedfl_cli.models.liedflnn.engines import columns as fused_columns

    model = sb.SubstepModel(physics_model(G_SO3, 0.02, TOP), 1, 4)
    g = top_truth(0.02, 0.6, n_traj=n_traj)
    start = g.index((slice(None), 0)), g.index((slice(None), 1))
    assert fused_columns.applies(model.inner, start[0]) == (n_traj >= fused_columns.MIN_ROWS)
    runs = {}
    for degree in (-1, sb.PREDICTOR_DEGREE):
        monkeypatch.setattr(sb, "PREDICTOR_DEGREE", degree)
        runs[degree] = model.rollout(*start, 30, TIGHT), model.rollout(*start, 30, SolverOptions())
    (old, old_default), (new, new_default) = runs[-1], runs[sb.PREDICTOR_DEGREE]
    assert old.n_failed == new.n_failed == old_default.n_failed == new_default.n_failed == 0
    scale = float(old.pose.R.abs().max())
    assert float((new.pose.R - old.pose.R).abs().max()) <= 1e-10 * scale
    solves = 3 * 29 * n_traj
    assert int(old.iterations.sum()) >= 2.9 * solves and int(new.iterations.sum()) <= 2.2 * solves
    assert int(old_default.iterations.sum()) >= 1.9 * solves and int(new_default.iterations.sum()) <= 1.2 * solves


@pytest.mark.parametrize("columns", [False, True])
def test_sine_rotations_invert_and_stay_on_the_group(columns):
    torch.manual_seed(0)
    w = torch.randn(50, 3, dtype=F64)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(50, 1, dtype=F64) * 1.5  # angles below pi/2
    W = so3.exp(w)
    rot = sb._SineRotations(columns, W)
    x = W.reshape(50, 9).T.contiguous() if columns else W
    back = rot.rotation(rot.sine(x))
    back = back.T.reshape(50, 3, 3) if columns else back
    assert torch.allclose(back, W, atol=1e-14)
    v = rot.sine(x)
    v = v.T if columns else v
    assert torch.allclose(v, torch.sin(w.norm(dim=-1, keepdim=True)) * w / w.norm(dim=-1, keepdim=True), atol=1e-15)


def test_predictor_extrapolates_polynomials_exactly():
    """Sine vectors on a cubic in the cycle index: the guess from the last four cycles is the next value
    (the weights of `EXTRAPOLATION` are those of a degree-3 polynomial), lower degrees before that."""
    rot = sb._SineRotations(False, torch.zeros(1, dtype=F64))

    def v(k: float) -> torch.Tensor:
        return torch.tensor([[0.01 + 0.002 * k - 3e-4 * k**2 + 2e-5 * k**3, -0.03 + 0.001 * k, 0.02]], dtype=F64)

    pred = sb._Predictor(1, rot)
    for k in range(6):
        if k >= 4:
            assert torch.allclose(rot.sine(pred.guess(0)), v(k), atol=1e-15)
        pred.record(0, rot.rotation(v(k)))
    assert len(pred.hist[0]) == sb.PREDICTOR_DEGREE + 1
    assert sb.cycle_period(sb.step_fractions(2, 4)) == 3 and sb.cycle_period(sb.step_fractions(4, 2)) == 1


def test_predictor_leaves_a_turn_too_large_to_the_fallback_guess():
    """Sine vectors growing fast: the extrapolation would pass |v| = sin(angle) = 1, where no rotation has
    that sine vector (c = sqrt(1 - |v|^2) would be NaN); beyond 45 degrees the predictor gives no guess."""
    rot = sb._SineRotations(False, torch.zeros(1, dtype=F64))
    pred = sb._Predictor(1, rot)
    for a in (0.1, 0.3, 0.5, 0.65):  # angles of one sub-step, rad: cubic extrapolation ~0.71 rad in sine
        pred.record(0, so3.exp(torch.tensor([[0.0, 0.0, a]], dtype=F64)))
    small = pred.guess(0)
    assert small is not None and torch.isfinite(small).all()
    pred.record(0, so3.exp(torch.tensor([[0.0, 0.0, 1.2]], dtype=F64)))
    assert pred.guess(0) is None  # extrapolated sine 1.25 or so: no rotation


# ---------------------------------------------------------------------------- the rollout refinement
def test_levenberg_marquardt_loop_fits_and_never_raises_the_cost():
    t = torch.linspace(0.0, 2.0, 40, dtype=F64)
    data = 1.5 * torch.exp(-0.7 * t) + 0.2
    costs = []

    def res(theta):
        r = theta[0] * torch.exp(-theta[1] * t) + theta[2] - data
        costs.append(float(r @ r))
        return r

    theta, first, last = sb._lm(torch.tensor([1.0, 0.1, 0.0], dtype=F64), res, 50)
    assert last <= first and last < 1e-20
    assert torch.allclose(theta, torch.tensor([1.5, 0.7, 0.2], dtype=F64), atol=1e-8)


def test_rollout_windows_cover_the_trajectories():
    g = top_truth(0.05, 1.0, n_traj=2)  # 21 samples
    w = sb.rollout_windows(g, 20, length=5, most=8)
    assert w is not None and w.R.shape == (8, 6, 1, 3, 3)  # starts 0, 4, 8, 12 per trajectory
    assert torch.equal(w.R[1], g.R[1, 0:6]) and torch.equal(w.R[2], g.R[0, 4:10])
    assert sb.rollout_windows(g, 4, length=5) is None


def test_rollout_refinement_lowers_the_objective_it_minimises(monkeypatch):
    """A free rotor's order-4 model started by the one-step fit to its exact poses (L-BFGS on the one-step
    DEL loss: parameters off by that scheme's O(h^2) bias): one reweighted pass of two Levenberg-Marquardt
    iterations lowers the mean log square error of the windows (majorise-minimise: it cannot raise it)."""
    from liedfl_cli.data.physics import RigidBodySO3, simulate_so3

    body = RigidBodySO3(J=np.diag(TOP["J"]), m=0.5, rho=np.zeros(3), g=0.0, D=np.diag([0.05] * 3))
    w0 = np.random.default_rng(4).normal(size=(4, 3))
    R0 = np.broadcast_to(np.eye(3), (4, 3, 3)).copy()
    sim = simulate_so3(body, R0, w0, 0.05 * np.arange(31), {"method": "DOP853", "rtol": 1e-13, "atol": 1e-14})
    R = torch.from_numpy(sim.R)[:, :, None]
    train = Pose(R, R.new_zeros(4, 31, 0, 3))
    model = sb.SubstepModel(LieDFLNN(G_SO3, 0.05, forces=["rayleigh"], seed=0), 1, 4)
    assert sb.second_order_fit(model.inner, model.inner.training_set(train, 30), iterations=100) is not None
    monkeypatch.setattr(sb, "ROLLOUT_FIT_WINDOWS", 16)
    monkeypatch.setattr(sb, "ROLLOUT_FIT_ITERATIONS", 2)
    windows = sb.rollout_windows(train, 30)
    assert windows is not None and windows.R.shape[:2] == (16, 11)
    before = sb.WindowErrors(model, windows).log_mean_square()
    note = sb.rollout_refinement(model, train, 30, passes=1)
    assert note is not None and "16 windows of 10 steps" in note
    after = sb.WindowErrors(model, windows).log_mean_square()
    assert after < before - 0.1, (before, after)  # a factor > 1.05 on the geometric mean of the RMS errors
