"""The fused engine computes what the reference paths compute: residuals to <= 1e-12 relative,
rollouts to the Newton tolerance with the same convergence flags and iteration counts, the same
training losses; and the runtime switches (threads, fused, compile) behave. No timings here
(scripts/bench.py measures speed)."""

from __future__ import annotations

import os

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, batched, so3
from liedfl_cli.mechanics import kinetic
from liedfl_cli.models.base import LossOptions
from liedfl_cli.models.del_loss import regularity_penalty
from liedfl_cli.models.liedflnn.engines import core as fused
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers import compile as compile_cache
from liedfl_cli.solvers import runtime
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.newton import NewtonProblem, solve
from liedfl_cli.solvers.options import SolverOptions

PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0]}
TWO_BODY = ProductGroup(1, 1)
THREE_BODY = ProductGroup(1, 2)

MODELS = {
    "free_so3_rayleigh": (SO3, dict(potential="none", forces=["rayleigh"])),
    "se3_mlp_rayleigh": (SE3, dict(potential="mlp", forces=["rayleigh"], mlp_width=16)),
    "se3xso3_mlp": (TWO_BODY, dict(potential="mlp", forces=["rayleigh"], mlp_width=16)),
    "se3xso3x2_nonlinear_nn": (
        THREE_BODY,
        dict(
            potential="mlp",
            forces={"rayleigh_nonlinear": {"width": 8, "depth": 2}, "nn": {"width": 8, "depth": 2}},
            mlp_width=8,
        ),
    ),
    "se3xso3x2_coupled_nonlinear": (
        THREE_BODY,
        dict(
            potential="mlp",
            forces={"rayleigh_nonlinear": {"width": 8, "depth": 2, "coupling": "coupled"}},
            mlp_width=8,
        ),
    ),
    "se3xso3_per_body_rayleigh": (TWO_BODY, dict(potential="none", forces={"rayleigh": {"coupling": "per_body"}})),
    "se3_uniform_gravity": (SE3, dict(potential="uniform_gravity", forces=["rayleigh"])),
    "so3_uniform_gravity_and_mlp": (SO3, dict(potential=["uniform_gravity", "mlp"], forces=["rayleigh"], mlp_width=8)),
    "so3_control": (SO3, dict(potential="mlp", forces={"control": {"width": 8}}, mlp_width=8)),
    "so3_no_force": (SO3, dict(potential="none", forces=[])),
}


def trajectories(G: ProductGroup, T: int = 5, N: int = 12, h: float = 0.1, seed: int = 0) -> Pose:
    """Smooth-ish random trajectories (T, N+1, ...) on G."""
    gen = torch.Generator().manual_seed(seed)
    k = torch.arange(N + 1, dtype=torch.float64)[None, :, None, None]
    w0 = torch.randn(T, 1, G.n_bodies, 3, generator=gen, dtype=torch.float64)
    w1 = torch.randn(T, 1, G.n_bodies, 3, generator=gen, dtype=torch.float64)
    p0 = torch.randn(T, 1, G.n_se3, 3, generator=gen, dtype=torch.float64)
    p1 = torch.randn(T, 1, G.n_se3, 3, generator=gen, dtype=torch.float64)
    return Pose(so3.exp(w0 + h * k * w1), p0 + h * k * p1)


def make(name: str, seed: int = 0) -> LieDFLNN:
    G, kw = MODELS[name]
    return LieDFLNN(G, 0.1, init_jitter=0.3, seed=seed, **kw)


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


def both_batches(model, data: Pose, steps: int = 10, reg_points: int = 10):
    ref_set = model.with_path("reference").training_set(data, steps)
    fused_set = model.training_set(data, steps)
    assert isinstance(fused_set, fused.IncrementSet) and not isinstance(ref_set, fused.IncrementSet)
    idx = torch.randperm(ref_set.n, generator=torch.Generator().manual_seed(3))
    ref = ref_set.batch(idx, torch.Generator().manual_seed(1), reg_points)
    fus = fused_set.batch(idx, torch.Generator().manual_seed(1), reg_points)
    return ref, fus


# ----------------------------------------------------------------------------- training
@pytest.mark.parametrize("name", sorted(MODELS))
def test_fused_residual_regularity_and_loss_equal_the_reference(name):
    model = make(name)
    ref, fus = both_batches(model, trajectories(model.G))
    opts = LossOptions()
    r_ref = model.residual(*ref.poses())
    ld_ref = model.regularity_logdet(*ref.reg)
    r_fus, ld_fus = fused.residual_and_logdet(model, fus, opts)
    assert rel(r_fus, r_ref) <= 1e-12
    assert rel(ld_fus, ld_ref) <= 1e-12
    params = [p for p in model.parameters() if p.requires_grad]
    loss_ref, parts_ref = model.loss(ref, opts)
    loss_fus, parts_fus = model.loss(fus, opts)
    assert abs(float(loss_fus - loss_ref)) <= 1e-12 * abs(float(loss_ref))
    assert set(parts_fus) == set(parts_ref)
    g_ref = torch.autograd.grad(loss_ref, params, allow_unused=True)
    g_fus = torch.autograd.grad(loss_fus, params, allow_unused=True)
    scale = max(float(g.abs().max()) for g in g_ref if g is not None)
    for a, b in zip(g_fus, g_ref):
        a = torch.zeros(()) if a is None else a
        b = torch.zeros(()) if b is None else b
        assert float((a - b).abs().max()) <= 1e-10 * scale


def big_step_trajectories(G: ProductGroup, T: int = 8, N: int = 6, seed: int = 0) -> Pose:
    """Trajectories (T, N+1, ...) turning by 0.5 to 3 rad per step (one angle per trajectory) about
    a random axis per body: the larger increments turn the orientation of some mixed-Hessian
    blocks (det(-H_b) < 0)."""
    gen = torch.Generator().manual_seed(seed)
    axis = torch.randn(T, 1, G.n_bodies, 3, generator=gen, dtype=torch.float64)
    angle = torch.linspace(0.5, 3.0, T, dtype=torch.float64)[:, None, None, None]
    axis = angle * axis / axis.norm(dim=-1, keepdim=True)
    k = torch.arange(N + 1, dtype=torch.float64)[None, :, None, None]
    R0 = so3.exp(torch.randn(T, 1, G.n_bodies, 3, generator=gen, dtype=torch.float64))
    p0 = torch.randn(T, 1, G.n_se3, 3, generator=gen, dtype=torch.float64)
    v = 0.1 * torch.randn(T, 1, G.n_se3, 3, generator=gen, dtype=torch.float64)
    return Pose(R0 @ so3.exp(k * axis), p0 + k * v)


def block_orientations(model: LieDFLNN, g: Pose, g_next: Pose) -> torch.Tensor:
    """sign det(-H_b) of each body's mixed-Hessian block (+1: the normal orientation), (..., B)."""
    Jd, m, rho = model._params()
    blocks = kinetic.mixed_hessian_blocks(model.G, model.G.increment(g, g_next), Jd, m, rho, model.h)
    return torch.stack([torch.linalg.slogdet(-b).sign for b in blocks], -1)


@pytest.mark.parametrize("name", ["free_so3_rayleigh", "se3xso3_mlp", "se3_mlp_rayleigh"])
def test_wrong_orientation_of_the_mixed_hessian_is_penalised_alike_in_both_paths(name):
    """A block with det(-H_b) <= 0 is penalised however large |det H_b| is (log|det| alone does
    not see the sign), and the fused loss (the hand-written gradient for free_so3_rayleigh) equals
    the reference loss and gradients to rounding."""
    model = make(name)
    ref, fus = both_batches(model, big_step_trajectories(model.G), steps=6, reg_points=24)
    orientation = block_orientations(model, *ref.reg)
    assert (orientation < 0).any() and (orientation > 0).any()  # the case this test is about
    opts = LossOptions(epsilon=-50.0)  # every block's |det H_b| is far above e^epsilon
    assert float(model.regularity_logdet(*ref.reg).min()) > opts.epsilon + 10
    params = [p for p in model.parameters() if p.requires_grad]
    loss_ref, parts_ref = model.loss(ref, opts)
    loss_fus, parts_fus = model.loss(fus, opts)
    assert float(parts_ref["reg_loss"]) >= float((orientation < 0).double().mean())  # >= 1 per wrong block
    assert abs(float(parts_fus["reg_loss"] - parts_ref["reg_loss"])) <= 1e-12 * float(parts_ref["reg_loss"])
    assert abs(float(loss_fus - loss_ref)) <= 1e-12 * abs(float(loss_ref))
    g_ref = torch.autograd.grad(loss_ref, params, allow_unused=True)
    g_fus = torch.autograd.grad(loss_fus, params, allow_unused=True)
    scale = max(float(g.abs().max()) for g in g_ref if g is not None)
    assert scale > 0
    for a, b in zip(g_fus, g_ref):
        a = torch.zeros(()) if a is None else a
        b = torch.zeros(()) if b is None else b
        assert float((a - b).abs().max()) <= 1e-10 * scale


@pytest.mark.parametrize("form", ["relu", "gaussian"])
def test_normally_oriented_blocks_keep_the_log_abs_det_penalty_exactly(form):
    """Where every block has det(-H_b) > 0 (all the shipped scenes) the regularity loss is the
    penalty of log|det H_b|, bit for bit, on both paths."""
    model = make("se3xso3_mlp")
    ref, fus = both_batches(model, trajectories(model.G))
    assert (block_orientations(model, *ref.reg) > 0).all()
    opts = LossOptions(epsilon=30.0, reg_form=form)  # the penalty is active
    expected = regularity_penalty(model.regularity_logdet(*ref.reg), opts.epsilon, form).mean()
    assert float(expected.detach()) > 0
    assert torch.equal(model.loss(ref, opts)[1]["reg_loss"], expected)
    _, ld_fus = fused.residual_and_logdet(model, fus, opts)
    assert torch.equal(model.loss(fus, opts)[1]["reg_loss"], regularity_penalty(ld_fus, opts.epsilon, form).mean())


def test_known_parts_are_evaluated_once_at_load_and_still_equal():
    physics = {**PHYS, "g": 9.81, "D": [0.1, 0.1, 0.1, 0.0, 0.0, 0.0]}
    model = LieDFLNN(SE3, 0.05, potential="none", forces=["rayleigh"], known=["potential"], physics=physics)
    ref, fus = both_batches(model, trajectories(SE3, h=0.05))
    assert "static" in fus.fields and not fus.potential  # the frozen gravity covector is stored
    r_fus, _ = fused.residual_and_logdet(model, fus, LossOptions())
    assert rel(r_fus, model.residual(*ref.poses())) <= 1e-12


def test_increment_set_draws_the_same_random_pairs_as_the_triplet_set():
    model = make("free_so3_rayleigh")
    data = trajectories(SO3)
    ref_set = model.with_path("reference").training_set(data, 10)
    fused_set = model.training_set(data, 10)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    idx = torch.arange(7)
    a, b = ref_set.batch(idx, g1, 10), fused_set.batch(idx, g2, 10)
    inc = SO3.increment(*a.reg)
    torch.testing.assert_close(b.reg_W, inc.R.flatten(-2), rtol=0, atol=0)
    assert torch.equal(g1.get_state(), g2.get_state())


def test_generic_residual_mode_keeps_the_reference_path():
    G, kw = MODELS["se3_mlp_rayleigh"]
    model = LieDFLNN(G, 0.1, residual="generic", **kw)
    assert not isinstance(model.training_set(trajectories(G), 10), fused.IncrementSet)


# ----------------------------------------------------------------------------- rollouts
def _start(G: ProductGroup, n: int, h: float, seed: int = 0, scale: float = 1.0):
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )
    xi = h * scale * torch.randn(n, G.dim, generator=gen, dtype=torch.float64)
    return g0, G.retract(g0, xi)


def _both_rollouts(model, g0, g1, steps, opts=None):
    ref = model.with_path("reference").rollout(g0, g1, steps, opts)
    return ref, model.rollout(g0, g1, steps, opts)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_fused_rollout_equals_the_reference_to_the_newton_tolerance(name):
    model = make(name)
    model.requires_grad_(False)
    g0, g1 = _start(model.G, 6, 0.1)
    ref, fus = _both_rollouts(model, g0, g1, 12)
    assert torch.equal(ref.converged, fus.converged)
    assert torch.equal(ref.iterations, fus.iterations)
    tol = SolverOptions().tol
    assert float((ref.pose.R - fus.pose.R).abs().max()) <= tol
    if ref.pose.p.numel():
        assert float((ref.pose.p - fus.pose.p).abs().max()) <= tol * max(1.0, float(ref.pose.p.abs().max()))


@pytest.mark.parametrize("G", [SO3, SE3], ids=["so3", "se3"])
def test_true_scheme_rollout_with_failures_has_the_same_flags_and_counts(G):
    physics = {**PHYS, "g": 9.81, "D": [0.1] * 3 + [0.0] * 3 * G.n_se3}
    model = physics_model(G, 0.1, physics)
    g0, g1 = _start(G, 5, 0.1, scale=4.0)
    for opts in (SolverOptions(tol=1e-30, max_iter=1), SolverOptions(tol=1e-13, max_iter=3), SolverOptions()):
        ref, fus = _both_rollouts(model, g0, g1, 15, opts)
        assert torch.equal(ref.converged, fus.converged)
        assert torch.equal(ref.iterations, fus.iterations)
    ref, fus = _both_rollouts(model, g0, g1, 15, SolverOptions(tol=1e-30, max_iter=1))
    assert fus.n_failed == ref.n_failed == 5 * 14


def test_large_batch_finishes_the_last_rows_apart_with_the_same_counts():
    """Batches of >= 64 rows iterate only the rows still iterating once few are left."""
    model = physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.05] * 3})
    g0, g1 = _start(SO3, 300, 0.1, scale=3.0)
    ref, fus = _both_rollouts(model, g0, g1, 12)
    assert len(torch.unique(ref.iterations)) > 1  # rows need different numbers of iterations
    assert torch.equal(ref.converged, fus.converged)
    assert torch.equal(ref.iterations, fus.iterations)
    assert float((ref.pose.R - fus.pose.R).abs().max()) <= SolverOptions().tol


@pytest.mark.parametrize("G", [SO3, ProductGroup(0, 2), SE3], ids=["so3", "so3x2", "se3"])
def test_rollout_retraction_equals_the_group_exponential_to_rounding(G):
    """The rollout's few-kernel rotation retraction (closed forms at every angle) against `G.retract`
    (Taylor polynomials below the threshold), from a zero step through tiny ones to large angles."""
    angles = torch.tensor([0.0, 1e-200, 1e-12, 1e-6, 1e-3, 0.05, 0.5, 2.0, 3.1], dtype=torch.float64)
    n = len(angles)
    gen = torch.Generator().manual_seed(7)
    x = Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )
    axes = torch.nn.functional.normalize(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64), dim=-1)
    w = axes * angles[:, None, None]
    delta = G.join(w, torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64))
    got = batched.retract_increment(G, x, delta)
    ref = G.retract(x, delta)
    assert float((got.R - ref.R).abs().max()) <= 1e-14
    assert float((got.R[0] - x.R[0]).abs().max()) == 0.0  # a zero step leaves the rotation as it is
    torch.testing.assert_close(got.p, ref.p, rtol=1e-13, atol=1e-13)


# ----------------------------------------------------------------------------- the Newton loop itself
def _cubic(c):
    return lambda x: x**3 + x - c


NEWTON_CASES = {
    "converging": (_cubic(torch.tensor([[0.0, 1.0], [10.0, -3.0], [1e-3, 2.0]], dtype=torch.float64)), 0.0, 1e-12, 50),
    "iteration_limit": (_cubic(torch.tensor([[100.0], [0.5]], dtype=torch.float64)), 0.0, 1e-14, 2),
    "no_root_line_search": (lambda x: torch.cat((x[:1] ** 2 + 1.0, x[1:] - 2.0)), 1.0, 1e-10, 10),
    "singular_jacobian": (lambda x: torch.cat((x[:1] ** 2, x[1:] ** 3 - 8.0)), 0.0, 1e-10, 8),
}


@pytest.mark.parametrize("case", sorted(NEWTON_CASES))
def test_lean_newton_equals_the_reference_loop(case):
    f, x0, tol, max_iter = NEWTON_CASES[case]
    n = 3 if case == "converging" else 2
    width = 2 if case == "converging" else 1
    x0 = torch.full((n, width), float(x0), dtype=torch.float64)
    problem = NewtonProblem.euclidean(f, x0)
    opts = SolverOptions(tol=tol, max_iter=max_iter)
    a = solve(problem, opts)
    b = solve(problem, opts, reference=True)
    assert torch.equal(a.converged, b.converged)
    assert torch.equal(a.iterations, b.iterations)
    torch.testing.assert_close(a.x, b.x, rtol=0, atol=0, equal_nan=True)


# ----------------------------------------------------------------------------- a default run, smoke-sized
def _smoke_config(tmp_path, *overrides: str):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            "train",
            overrides=[
                "budget=smoke",
                f"paths.data_dir={tmp_path / 'data'}",
                f"paths.output_dir={tmp_path / 'run'}",
                "train.epochs=4",
                "train.batch_size=16",
                *overrides,
            ],
        )


def _smoke_fit(tmp_path, optimizer: str):
    from liedfl_cli.commands.train import fit
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.config.recovery import parameter_recovery
    from liedfl_cli.data.scenes import get_dataset

    cfg = _smoke_config(tmp_path, f"train.optimizer.name={optimizer}")
    ds, _ = get_dataset(cfg.dataset, cfg.paths.data_dir)
    data = ds.pose(ds.train_idx)
    out = {}
    for use_fused in (False, True):
        with runtime.using(fused=use_fused):  # decides the path of the model built here
            model = build_model(cfg, ds)
        assert model.path == ("fused" if use_fused else "reference")
        result = fit(model, data, cfg.train, int(cfg.dataset.train_steps))
        out[use_fused] = (result["history"], parameter_recovery(model, ds))
    return out


def _close(a: float, b: float, bound: float) -> bool:
    return abs(a - b) <= max(bound * abs(b), 1e-300)


def test_smoke_training_gives_the_same_losses_and_recovered_parameters(tmp_path):
    """With Adam, fused and reference training agree to rounding: every epoch's losses and the
    recovered parameters."""
    out = _smoke_fit(tmp_path, "adam")
    for a, b in zip(out[True][0], out[False][0]):
        for key in ("loss", "del_loss", "reg_loss"):
            assert _close(a[key], b[key], 1e-12), (key, a[key], b[key])
    rec_a, rec_b = out[True][1], out[False][1]
    assert rec_a is not None and rec_b is not None and set(rec_a) == set(rec_b)
    for key in rec_b:
        assert _close(rec_a[key], rec_b[key], 1e-10), key


def test_smoke_training_with_soap_agrees_until_soaps_first_update(tmp_path):
    """SOAP's first eigenbasis is that of a rank-one gradient statistic (its null space is
    arbitrary), so a rounding-level difference in the gradient changes its first update at the
    1e-3 level: fused and reference runs agree to rounding until that update (the first epoch
    here), then stay close, as two reference runs with gradients one ulp apart do
    (docs/benchmarks.md)."""
    out = _smoke_fit(tmp_path, "soap")
    first_a, first_b = out[True][0][0], out[False][0][0]
    for key in ("loss", "del_loss", "reg_loss"):
        assert _close(first_a[key], first_b[key], 1e-12), key
    last_a, last_b = out[True][0][-1], out[False][0][-1]
    assert _close(last_a["loss"], last_b["loss"], 0.2)


def test_full_batch_and_precondition_frequency_options(tmp_path):
    from liedfl_cli.commands.train import fit, make_optimizer
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.data.scenes import get_dataset

    cfg = _smoke_config(tmp_path, "train.full_batch=true", "train.optimizer.precondition_frequency=3")
    ds, _ = get_dataset(cfg.dataset, cfg.paths.data_dir)
    model = build_model(cfg, ds)
    result = fit(model, ds.pose(ds.train_idx), cfg.train, int(cfg.dataset.train_steps))
    assert result["batches_per_epoch"] == 1
    opt = make_optimizer([p for p in model.parameters() if p.requires_grad], cfg.train.optimizer)
    assert opt.param_groups[0]["precondition_frequency"] == 3


# ----------------------------------------------------------------------------- runtime switches
def test_runtime_options_are_checked_with_one_line_errors():
    from liedfl_cli.config.typed import runtime_options

    assert runtime_options({"threads": 2, "compile": True}).compile == "true"
    assert runtime_options(None) == runtime.RuntimeOptions()
    for bad in ({"threads": 0}, {"threads": "many"}, {"compile": "sometimes"}, {"fused": "yes"}, {"speed": 1}):
        with pytest.raises(ConfigError) as e:
            runtime_options(bad)
        assert "\n" not in str(e.value)


def test_threads_default_and_one_thread_per_parallel_job():
    assert runtime.resolve_threads("auto") == runtime.DEFAULT_THREADS
    assert runtime.resolve_threads(4, parallel_job=True) == 1
    assert runtime.resolve_threads(1000) == (os.cpu_count() or 1)


def test_configure_runtime_from_the_train_config(tmp_path):
    from liedfl_cli.config.factory import configure_runtime

    before = torch.get_num_threads()
    try:
        opts = configure_runtime(_smoke_config(tmp_path, "runtime.threads=1", "runtime.compile=false"))
        assert opts.compile == "false" and torch.get_num_threads() == 1 and runtime.current() == opts
    finally:
        runtime.configure(None)
        torch.set_num_threads(before)


@pytest.fixture
def torch_rollouts(monkeypatch):
    """The torch engines of a rollout, not the native step (which `compile: auto | true` would take: these
    tests are about torch.compile; tests/test_native_body.py has the native step's)."""
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)


@pytest.mark.compile_auto
@pytest.mark.parametrize("setting", ["false", "auto"])
def test_compile_false_and_auto_roll_out_the_same(setting, torch_rollouts):
    model = physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.05] * 3})
    g0, g1 = _start(SO3, 4, 0.1)
    model.set_plan(ExecutionPlan(compile="false"))
    a = model.rollout(g0, g1, 10)
    model.set_plan(ExecutionPlan(compile=setting))
    b = model.rollout(g0, g1, 10)
    assert not model.plan.wants_compile("rollout", 4 * 9)  # a small rollout: auto does not compile
    torch.testing.assert_close(a.pose.R, b.pose.R, rtol=0, atol=0)


def test_compile_without_a_compiler_falls_back_saying_so_once(monkeypatch, capsys, torch_rollouts):
    monkeypatch.setattr(compile_cache, "compiler_available", lambda: False)
    monkeypatch.setattr(compile_cache, "_said", set())
    model = physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.05] * 3})
    g0, g1 = _start(SO3, 3, 0.1)
    model.set_plan(ExecutionPlan(compile="false"))
    a = model.rollout(g0, g1, 8)
    model.set_plan(ExecutionPlan(compile="true"))
    b = model.rollout(g0, g1, 8)
    model.rollout(g0, g1, 8)
    err = capsys.readouterr().err
    assert err.count("no C++ compiler") == 1 and err.count("\n") == 1
    torch.testing.assert_close(a.pose.R, b.pose.R, rtol=0, atol=0)


def test_a_failing_compilation_falls_back_to_eager(monkeypatch, capsys, torch_rollouts):
    def broken(fn, **kwargs):
        def run(*args, **kw):
            raise RuntimeError("no toolchain")

        return run

    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setattr(compile_cache, "_compiled", {})
    monkeypatch.setattr(compile_cache, "_said", set())
    monkeypatch.setattr(compile_cache, "compiler_available", lambda: True)
    model = physics_model(SE3, 0.05, {**PHYS, "g": 9.81, "D": [0.1, 0.1, 0.1, 0.0, 0.0, 0.0]})
    g0, g1 = _start(SE3, 3, 0.05)
    model.set_plan(ExecutionPlan(compile="false"))
    a = model.rollout(g0, g1, 8)
    model.set_plan(ExecutionPlan(compile="true"))
    b = model.rollout(g0, g1, 8)
    assert "compilation failed" in capsys.readouterr().err
    torch.testing.assert_close(a.pose.R, b.pose.R, rtol=0, atol=0)
    assert torch.equal(a.iterations, b.iterations)


@pytest.mark.slow
@pytest.mark.skipif(not compile_cache.compiler_available(), reason="no C++ compiler: the fallback is tested above")
def test_compiled_newton_step_rolls_out_the_same(capsys):
    model = physics_model(SE3, 0.05, {**PHYS, "g": 9.81, "D": [0.1, 0.1, 0.1, 0.0, 0.0, 0.0]})
    g0, g1 = _start(SE3, 5, 0.05)
    model.set_plan(ExecutionPlan(compile="false"))
    a = model.rollout(g0, g1, 20)
    model.set_plan(ExecutionPlan(compile="true"))
    b = model.rollout(g0, g1, 20)
    assert "compilation failed" not in capsys.readouterr().err  # it compiled (a fallback would run eagerly)
    assert torch.equal(a.iterations, b.iterations) and torch.equal(a.converged, b.converged)
    assert float((a.pose.R - b.pose.R).abs().max()) <= SolverOptions().tol


@pytest.mark.slow
@pytest.mark.skipif(not compile_cache.compiler_available(), reason="no C++ compiler: the fallback is tested above")
def test_compiled_training_loss_of_a_many_body_model_equals_eager(monkeypatch, capsys):
    """More than `fused.SCALAR_BODIES` bodies take the tensor J_d path (`_InertiaJd`), which once
    made torch.compile fail on Exp 4's loss (a saved view; a cache filled while tracing)."""
    monkeypatch.setattr(compile_cache, "_compiled", {})
    G = ProductGroup(1, fused.SCALAR_BODIES)
    model = LieDFLNN(G, 0.1, potential="mlp", forces=["rayleigh"], mlp_width=8, init_jitter=0.3, seed=0)
    _, fus = both_batches(model, trajectories(G))
    opts = LossOptions()
    params = [p for p in model.parameters() if p.requires_grad]
    zero = torch.zeros((), dtype=torch.float64)

    def loss_and_grads(setting: str):
        model.set_plan(ExecutionPlan(compile=setting))
        loss, _ = model.loss(fus, opts)
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        return loss, [zero if g is None else g for g in grads]

    eager, g_eager = loss_and_grads("false")
    comp, g_comp = loss_and_grads("true")
    assert "compilation failed" not in capsys.readouterr().err
    assert abs(float(comp - eager)) <= 1e-12 * abs(float(eager))
    scale = max(float(g.abs().max()) for g in g_eager)
    assert max(float((a - b).abs().max()) for a, b in zip(g_comp, g_eager)) <= 1e-10 * scale


def test_train_config_has_the_runtime_section():
    cfg = OmegaConf.load(CONF_DIR / "train.yaml")
    assert set(cfg.runtime) == {"threads", "fused", "compile", "device", "dtype"}
    assert cfg.train.full_batch is False and cfg.train.optimizer.precondition_frequency == 10
    assert cfg.train.optimizer.max_precondition_dim == 10000


@pytest.mark.parametrize("scale", [1e-3, 0.5, 2.0])
def test_hand_written_gradients_pass_gradcheck(scale):
    gen = torch.Generator().manual_seed(0)
    r = (scale * torch.randn(2, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    abc = torch.randn(2, 3, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(fused._InertiaJd.apply, (r, abc))
    assert torch.autograd.gradcheck(fused._InertiaJdScalar.apply, (r, abc))
    entries = torch.randn(6, generator=gen, dtype=torch.float64).requires_grad_()
    lam = torch.randn(3, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda e, lm: fused._SPSDScalar.apply(e, lm, 3), (entries, lam))
    model = make("free_so3_rayleigh")
    _, batch = both_batches(model, trajectories(SO3))
    A, s, W = batch.fields["A"][:6], batch.fields["s"][:6], batch.reg_W[:4]
    C = fused._map_contraction(torch.float64, 0.1)
    for form in ("relu", "gaussian"):
        settings = (0.1, 0.5, 0.5, 10.0 * scale, form)
        Jd = (fused.inertia_jd(model.inertia).detach().flatten(-2) * scale).requires_grad_()
        D = torch.eye(3, dtype=torch.float64).requires_grad_()
        fn = lambda Jd, D, settings=settings: fused._RotationalLoss.apply(Jd, D, A, s, None, W, C, settings)
        assert torch.autograd.gradcheck(fn, (Jd, D))
