"""`models.liedflnn.engines.native`: the rollout of a single rigid body (SO(3), SE(3)) or a product of bodies
(SE(3)^m x SO(3)^n) in C++ takes the same Newton steps as the row layout and the reference path (flags,
iteration counts, poses to the Newton tolerance; to rounding at a tight tolerance), on every potential it
serves (MLP with GELU or tanh, declared and learned gravity, their sum, none) and in the branches of its Newton
loop (backtracking, steps that do not converge, an exactly singular Jacobian, a non-finite start), and is
taken only where it serves and pays."""

from __future__ import annotations

import pytest
import torch
from test_fused_columns import PHYS, TOL, H, assert_same_steps, model_named, start

from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, so3
from liedfl_cli.mechanics.forces import NNForce
from liedfl_cli.models.liedflnn.engines import choose
from liedfl_cli.models.liedflnn.engines import native as fused_native
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers import compile as compile_cache
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import rollout_implicit

needs_compiler = pytest.mark.skipif(compile_cache.cxx() is None, reason="no C++ compiler on this machine")
pytestmark = needs_compiler
SERVED = ["mlp_rayleigh", "mlp_no_force", "free_rayleigh", "gravity_and_mlp", "true_scheme", "tanh_mlp", "gravity"]
SE3_PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.05] * 6}
SE3_MODELS = {
    "se3_free": dict(potential="none", forces=["rayleigh"]),
    "se3_mlp": dict(potential="mlp", forces=["rayleigh"], mlp_width=10, mlp_depth=2),
    "se3_gravity_and_mlp": dict(potential=["uniform_gravity", "mlp"], forces=["rayleigh"], mlp_width=8),
    "se3_mlp_no_force": dict(potential="mlp", forces=[], mlp_width=8, mlp_depth=3),
}
PRODUCTS = {  # (n_se3, n_so3, options): the two-body scene's group, rotations only, two free bodies, a chain's
    "se3_so3_mlp_gravity": (1, 1, dict(potential=["mlp", "uniform_gravity"], forces=["rayleigh"], mlp_width=8)),
    "so3_so3_mlp": (0, 2, dict(potential="mlp", forces=["rayleigh"], mlp_width=8, mlp_depth=2)),
    "se3_se3_gravity": (2, 0, dict(potential="uniform_gravity", forces=["rayleigh"])),
    "se3_so3x3_mlp": (1, 3, dict(potential="mlp", forces=[], mlp_width=6)),
    # a learned force F(g, xi~) (`NNForce`): its value and Jacobian in xi~ at every Newton iteration
    "so3_nn": (0, 1, dict(potential="mlp", forces={"rayleigh": {}, "nn": {"width": 8, "depth": 2}}, mlp_width=6)),
    "se3_nn": (1, 0, dict(potential="none", forces={"rayleigh": {}, "nn": {"width": 8, "depth": 3}})),
    "se3_so3_nn": (1, 1, dict(potential="mlp", forces={"rayleigh": {}, "nn": {"width": 6, "depth": 2}}, mlp_width=6)),
}
SE3_SERVED = [*SE3_MODELS, "se3_true_scheme", "se3_tanh_mlp", *PRODUCTS]


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    """Every test builds into (or reads) one cache folder of this session, not the user's; one thread."""
    monkeypatch.setenv("LIEDFL_NATIVE_CACHE", str(tmp_path_factory.getbasetemp() / "native_cache"))
    torch.set_num_threads(1)


def gap(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| (0 for empty tensors: the positions of SO(3) poses)."""
    return float((a - b).abs().max()) if a.numel() else 0.0


def se3_start(n: int, scale: float = 1.0, seed: int = 0, G: ProductGroup = SE3) -> tuple[Pose, Pose]:
    """n starts on G (default one SE(3) body): random attitudes and positions of order one, a twist of order
    `scale` per unit time."""
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )
    return g0, G.retract(g0, H * scale * torch.randn(n, G.dim, generator=gen, dtype=torch.float64))


def served(name: str) -> LieDFLNN:
    """The model `name` (its networks initialised from a fixed seed: the same model in every process)."""
    torch.manual_seed(0)
    if name in PRODUCTS:
        n_se3, n_so3, options = PRODUCTS[name]
        G = ProductGroup(n_se3, n_so3)
        model = LieDFLNN(G, H, init_jitter=0.3, seed=4, **options).requires_grad_(False)
        if model.mass is not None:  # bodies of different masses (gravity's translational part is per body)
            model.mass.set_value(torch.linspace(0.7, 1.6, G.n_se3, dtype=torch.float64))
        for force in model.forces:
            if isinstance(force, NNForce):  # a force that matters (the default start is near zero)
                with torch.no_grad():
                    for p in force.net.parameters():
                        p.mul_(3.0)
        return model
    if name == "se3_true_scheme":
        return physics_model(SE3, H, SE3_PHYS)
    if name == "se3_tanh_mlp":
        model = LieDFLNN(SE3, H, init_jitter=0.3, seed=2, potential="mlp", forces=["rayleigh"], mlp_width=6)
        model.potential.net[1] = torch.nn.Tanh()
        return model.requires_grad_(False)
    if name in SE3_MODELS:
        return LieDFLNN(SE3, H, init_jitter=0.3, seed=1, **SE3_MODELS[name]).requires_grad_(False)
    if name == "tanh_mlp":
        model = LieDFLNN(SO3, H, init_jitter=0.3, seed=2, potential="mlp", forces=["rayleigh"], mlp_width=6)
        model.potential.net[1] = torch.nn.Tanh()
        return model.requires_grad_(False)
    if name == "gravity":  # learned uniform gravity alone, with a moment that matters
        model = LieDFLNN(SO3, H, init_jitter=0.3, seed=3, potential="uniform_gravity", forces=["rayleigh"])
        with torch.no_grad():
            model.potential.moment.copy_(torch.tensor([[0.2, -0.4, 0.7]], dtype=torch.float64))
        return model.requires_grad_(False)
    return model_named(name)


def starts(name: str, n: int, scale: float = 1.0, seed: int = 0) -> tuple[Pose, Pose]:
    if name in PRODUCTS:
        return se3_start(n, scale, seed, ProductGroup(*PRODUCTS[name][:2]))
    return se3_start(n, scale, seed) if name.startswith("se3") else start(n, scale=scale, seed=seed)


def three_ways(model, g0, g1, steps, opts=None):
    """(native rollout, row-layout fused rollout, reference-path rollout)."""
    opts = opts or SolverOptions()
    with torch.no_grad():
        assert fused_native.applies(model, g0)
        assert choose.choose_rollout_engine(model, g0, steps) is choose.NATIVE
        nat = model.rollout(g0, g1, steps, opts)
        rows = rollout_implicit(model, g0, g1, steps, opts)
        ref = model.with_path("reference").rollout(g0, g1, steps, opts)
    return nat, rows, ref


@pytest.mark.parametrize("name", SERVED + SE3_SERVED)
@pytest.mark.parametrize("n", [1, 5, 40])
def test_the_native_rollout_takes_the_same_steps_as_the_row_layout_and_the_reference(name, n):
    model = served(name)
    g0, g1 = starts(name, n, seed=n)
    nat, rows, ref = three_ways(model, g0, g1, 25)
    assert_same_steps(rows, nat)
    assert_same_steps(ref, nat)
    assert torch.equal(nat.pose.R[:, 0], g0.R) and torch.equal(nat.pose.R[:, 1], g1.R)
    assert torch.equal(nat.pose.p[:, :2], torch.stack((g0.p, g1.p), 1))
    assert gap(nat.pose.p, rows.pose.p) <= TOL and gap(nat.pose.p, ref.pose.p) <= TOL
    assert float(nat.residual_norm.max()) < 1e-8
    torch.testing.assert_close(nat.residual_norm, rows.residual_norm, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "name",
    ["mlp_rayleigh", "gravity_and_mlp", "true_scheme", "se3_mlp", "se3_gravity_and_mlp", "se3_true_scheme", *PRODUCTS],
)
def test_at_a_tight_tolerance_the_poses_agree_to_rounding(name):
    """Newton to 1e-12: the native poses are the row layout's to rounding after 60 steps (what the looser
    tolerance of the test above cannot tell from a slightly wrong covector, damping or warm start)."""
    model = served(name)
    g0, g1 = starts(name, 6, seed=4)
    nat, rows, _ = three_ways(model, g0, g1, 60, SolverOptions(tol=1e-12))
    assert torch.equal(nat.converged, rows.converged)
    assert float((nat.pose.R - rows.pose.R).abs().max()) < 1e-11
    assert gap(nat.pose.p, rows.pose.p) < 1e-11


@pytest.mark.parametrize("group", ["so3", "se3"])
def test_steps_without_decrease_backtrack_as_the_row_layout(group):
    """Huge rotations per step: full steps without decrease, halved as the row layout's careful iterations
    halve them: the same flags, counts and poses."""
    if group == "so3":
        model = physics_model(SO3, H, {**PHYS, "g": 0.0})
        g0, g1 = start(40, scale=8.0, seed=1)
    else:
        model = physics_model(SE3, H, {**SE3_PHYS, "g": 0.0})
        g0, g1 = se3_start(40, scale=8.0, seed=1)
    nat, rows, _ = three_ways(model, g0, g1, 12)
    assert rows.n_failed == 0
    assert int(rows.iterations.max()) >= 4  # the case still exercises the careful iterations
    assert_same_steps(rows, nat)
    assert gap(nat.pose.p, rows.pose.p) <= TOL


@pytest.mark.parametrize("G, scale, seed", [(SO3, 8.0, 4), (SE3, 7.0, 8)], ids=["so3", "se3"])
def test_the_line_search_accepts_a_step_where_the_row_layout_does(G, scale, seed):
    """Starts (found by search) where some full Newton step lowers ||r|| by less than 10 % but more than the
    sufficient decrease 1e-4 asks: accepted there, as the row layout accepts it; a line search that asked for
    more (a constant of 1e-1) halves that step and takes another iteration."""
    phys = {**PHYS, "g": 0.0} if G is SO3 else {**SE3_PHYS, "g": 0.0}
    model = physics_model(G, H, phys)
    g0, g1 = se3_start(20, scale, seed, G)
    nat, rows, _ = three_ways(model, g0, g1, 12)
    assert rows.n_failed == 0
    assert_same_steps(rows, nat)


@pytest.mark.parametrize("n_se3, n_so3", [(0, 1), (1, 0), (0, 2), (1, 1)])
def test_stiff_damping_refuses_the_extrapolation_as_the_row_layout_does(n_se3, n_so3):
    """D = 150 at h 0.1: the spin reverses every step and the extrapolated warm start is refused (its move
    exceeds TRUST times the last increment's, summed over the bodies): the same iterations and poses as the
    row layout."""
    G = ProductGroup(n_se3, n_so3)
    J = [[1.521, 1.362, 1.211], [0.9, 0.8, 0.6]][: G.n_bodies]
    physics = {"J": J, "m": [0.5, 1.0][: G.n_bodies], "rho": [[0.0, 0.5, 1.0], [0.0, 0.0, -0.8]][: G.n_bodies]}
    model = physics_model(G, H, {**physics, "g": 0.0, "D": [150.0] * G.dim})
    g0, g1 = se3_start(3, 1.0, 2, G)
    nat, rows, _ = three_ways(model, g0, g1, 20)
    assert rows.n_failed == 0
    assert_same_steps(rows, nat)
    assert gap(nat.pose.p, rows.pose.p) <= TOL


@pytest.mark.parametrize("name", ["mlp_rayleigh", "se3_mlp"])
@pytest.mark.parametrize("opts", [SolverOptions(tol=1e-30, max_iter=1), SolverOptions(tol=1e-13, max_iter=3)])
def test_non_converged_steps_are_flagged_alike(name, opts):
    model = served(name)
    g0, g1 = starts(name, 3, scale=4.0)
    nat, rows, ref = three_ways(model, g0, g1, 15, opts)
    assert torch.equal(rows.converged, nat.converged) and torch.equal(ref.converged, nat.converged)
    assert torch.equal(rows.iterations, nat.iterations)
    if opts.max_iter == 1:
        assert nat.n_failed == 3 * 14


@pytest.mark.parametrize("name", ["free_rayleigh", "se3_free"])
@pytest.mark.parametrize("steps", [0, 1, 2])
def test_short_rollouts_have_the_row_layouts_shapes(name, steps):
    model = served(name)
    g0, g1 = starts(name, 2)
    nat, rows, _ = three_ways(model, g0, g1, steps)
    assert_same_steps(rows, nat)
    assert nat.residual_norm.shape == rows.residual_norm.shape
    assert nat.iterations.dtype == rows.iterations.dtype and nat.converged.dtype == torch.bool


@pytest.mark.parametrize("name", ["mlp_rayleigh", "se3_gravity_and_mlp"])
def test_long_rollout_stays_on_the_group(name):
    model = served(name)
    g0, g1 = starts(name, 1, seed=5)
    with torch.no_grad():
        nat = model.rollout(g0, g1, 1000)
        rows = rollout_implicit(model, g0, g1, 1000, SolverOptions())
    R = nat.pose.R
    assert float((R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-12
    assert torch.equal(rows.converged, nat.converged)
    # rounding, grown over 1,000 steps (2e-10 here; up to 5e-9 over other draws of the MLP, and another CPU
    # rounds the torch engine's products otherwise)
    assert float((rows.pose.R - nat.pose.R).abs().max()) < 1e-8
    assert gap(rows.pose.p, nat.pose.p) < 1e-9 * max(1.0, gap(rows.pose.p, 0 * rows.pose.p))


def test_progress_is_called_once_per_step_across_chunks(monkeypatch):
    monkeypatch.setattr(fused_native, "CHUNK_ROW_STEPS", 6)  # 2 steps per call for 3 trajectories
    seen: list[int] = []
    g0, g1 = start(3)
    model = model_named("mlp_rayleigh")
    with torch.no_grad():
        chunked = model.rollout(g0, g1, 8, progress=seen.append)
        monkeypatch.setattr(fused_native, "CHUNK_ROW_STEPS", 10**6)
        whole = model.rollout(g0, g1, 8)
    assert seen == [1, 2, 3, 4, 5, 6, 7]
    assert torch.equal(chunked.pose.R, whole.pose.R) and torch.equal(chunked.iterations, whole.iterations)


@pytest.mark.parametrize("name", ["mlp_rayleigh", "se3_mlp"])
def test_two_threads_give_the_same_bits(name):
    model = served(name)
    g0, g1 = starts(name, 64, seed=7)
    with torch.no_grad():
        one = model.rollout(g0, g1, 20)
        torch.set_num_threads(2)
        two = model.rollout(g0, g1, 20)
    assert torch.equal(one.pose.R, two.pose.R) and torch.equal(one.iterations, two.iterations)
    assert torch.equal(one.pose.p, two.pose.p)


@pytest.mark.parametrize("name", ["mlp_rayleigh", "se3_mlp"])
def test_a_non_finite_start_fails_its_row_alone(name):
    model = served(name)
    g0, g1 = starts(name, 3, seed=2)
    bad = g1.R.clone()
    bad[1, 0, 0, 0] = float("nan")
    g1b = Pose(bad, g1.p)
    with torch.no_grad():
        nat = model.rollout(g0, g1b, 6)
        good = model.rollout(Pose(g0.R[[0, 2]], g0.p[[0, 2]]), Pose(g1.R[[0, 2]], g1.p[[0, 2]]), 6)
    assert not bool(nat.converged[1].any())
    assert torch.equal(nat.pose.R[[0, 2]], good.pose.R)


def test_an_exactly_singular_jacobian_takes_no_step_and_fails():
    """The documented difference from the reference (which takes a least-squares step): a zero Jacobian ends
    every iteration without a step, and every step is flagged, with its iterations used up."""
    model = model_named("mlp_rayleigh")
    g0, g1 = start(2)
    engine = fused_native.NativeSO3(model, g0.R)
    engine.JT.zero_()
    hist = torch.zeros(2, 3, 9, dtype=torch.float64)
    hist[:, 0] = SO3.increment(g0, g1).R.reshape(2, 9)
    state = {"R": g1.R.reshape(2, 9).clone(), "hist": hist, "hist_len": torch.ones(2, dtype=torch.int64)}
    out = engine.run(state, 3, SolverOptions(max_iter=4))
    assert not bool(out["converged"].any())
    assert bool((out["iterations"] == 4).all())
    assert bool(torch.isfinite(out["R"]).all())


def test_the_constants_follow_the_parameters():
    """The native constants are kept on the model between rollouts and rebuilt after an in-place change (an
    edit through `.data` too): the rollout after the change is the row layout's with the new potential."""
    model = model_named("mlp_rayleigh")
    g0, g1 = start(2, seed=3)
    with torch.no_grad():
        model.rollout(g0, g1, 5)
        first = model.__dict__["_native_body"][1]
        model.rollout(g0, g1, 5)
        assert model.__dict__["_native_body"][1] is first
        model.potential.net[0].weight.data.mul_(1.5)
        nat = model.rollout(g0, g1, 12)
        rows = rollout_implicit(model, g0, g1, 12, SolverOptions())
    assert model.__dict__["_native_body"][1] is not first
    assert_same_steps(rows, nat)


def test_which_rollouts_take_the_native_step():
    g1_, _ = start(1)
    mlp = model_named("mlp_rayleigh")  # 200 weights
    with torch.no_grad():
        assert fused_native.applies(mlp, g1_) and fused_native.applies(mlp, start(1000)[0])
        assert not fused_native.applies(mlp, start(3000)[0])  # MLP_ROWS on one thread: the columns
        assert fused_native.applies(model_named("free_rayleigh"), start(20000)[0])  # no MLP: any batch
        big = LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3).requires_grad_(False)
        assert fused_native.applies(big, start(100)[0]) and not fused_native.applies(big, start(400)[0])
        silu = LieDFLNN(SO3, H, potential="mlp", forces=["rayleigh"], mlp_width=4)
        silu.potential.net[1] = torch.nn.SiLU()
        assert not fused_native.applies(silu, g1_)
        assert not fused_native.applies(mlp.with_path("reference"), g1_)
        assert not fused_native.applies(mlp, Pose(g1_.R.float(), g1_.p.float()))
        eager = model_named("mlp_rayleigh")
        eager.set_plan(ExecutionPlan(compile="false"))
        assert not fused_native.applies(eager, g1_)  # runtime.compile=false: eager torch everywhere
        control = LieDFLNN(SO3, H, potential="mlp", forces={"control": {"width": 4}}, mlp_width=4)
        assert not fused_native.applies(control, g1_)
        se3 = LieDFLNN(SE3, H, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3)
        assert fused_native.applies(se3, se3_start(20000)[0])  # SE(3): the torch engine is slower at any batch
        se3_control = LieDFLNN(SE3, H, potential="none", forces={"control": {"width": 4}})
        assert not fused_native.applies(se3_control, se3_start(1)[0])
        nn = LieDFLNN(SE3, H, potential="none", forces={"rayleigh": {}, "nn": {"width": 32, "depth": 3}})
        assert fused_native.applies(nn, se3_start(1)[0]) and fused_native.applies(nn, se3_start(200)[0])
        assert not fused_native.applies(nn, se3_start(400)[0])  # FORCE_ROWS: the row layout's batches win
        nn.forces[1].net[1] = torch.nn.SiLU()  # an activation the native step does not compute
        assert not fused_native.applies(nn, se3_start(1)[0])
        two = LieDFLNN(SO3, H, potential="none", forces={"nn": {"width": 4}})
        two.forces.append(NNForce(SO3, width=4, depth=2))
        assert not fused_native.applies(two, g1_)  # (one learned force at most)
        pair = LieDFLNN(ProductGroup(1, 1), H, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3)
        assert fused_native.applies(pair, se3_start(20000, G=pair.G)[0])  # products: any batch
        scene = {**SE3_PHYS, "D": [0.05] * 9, "interaction": {"kind": "spring", "mu": 1.0}}
        two_body = physics_model(ProductGroup(1, 1), H, scene)
        assert not fused_native.applies(two_body, se3_start(1, G=two_body.G)[0])  # an interaction potential
    assert fused_native.applies(mlp, g1_)  # with grad mode on too: no rollout engine records a graph


def test_a_compiled_plan_still_takes_the_native_step(monkeypatch):
    """Native code is faster than the compiled row layout at every size: `compile: true` takes it too."""
    monkeypatch.setattr(ExecutionPlan, "wants_compile", lambda self, kind, work=None: True)
    g0, _ = start(1)
    with torch.no_grad():
        assert choose.choose_rollout_engine(model_named("free_rayleigh"), g0, 4) is choose.NATIVE


def test_without_a_compiler_the_torch_engines_serve(monkeypatch, capsys):
    monkeypatch.setattr(compile_cache, "cxx", lambda: None)
    monkeypatch.setattr(compile_cache, "_said", set())
    fused_native.library.cache_clear()
    try:
        model = model_named("mlp_rayleigh")
        g0, g1 = start(2)
        with torch.no_grad():
            assert not fused_native.applies(model, g0)
            assert choose.choose_rollout_engine(model, g0, 4).name == "scalar"
            ro = model.rollout(g0, g1, 4)
        assert "no C++ compiler" in capsys.readouterr().err
        assert bool(ro.converged.all())
    finally:
        fused_native.library.cache_clear()


def test_the_benchmark_script_writes_its_record(tmp_path, monkeypatch):
    """scripts/bench_native_body.py on a tiny budget: one row per group and potential, the ratio its two timings
    give, and whether the native step takes the batch as `applies` says."""
    import importlib.util
    import json
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_native_body.py"
    spec = importlib.util.spec_from_file_location("bench_native_body", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "record.json"
    monkeypatch.setattr(module, "MLPS", {"none": None, "mlp_10x2": (10, 2)})  # two of each: seconds, not tens
    monkeypatch.setattr(module, "GROUPS", {g: module.GROUPS[g] for g in ("SO3", "SE3xSO3")})
    monkeypatch.setattr(sys, "argv", ["bench_native_body.py", "--json", str(out), "--threads", "1", "--batches", "3"])
    module.main()
    rows = json.loads(out.read_text())["rows"]
    assert [(r["group"], r["potential"]) for r in rows] == [(g, p) for g in module.GROUPS for p in module.MLPS]
    for r in rows:
        assert r["native_applies"] and r["torch_engine"] in ("scalar", "rows")  # three trajectories
        assert r["torch_over_native"] == pytest.approx(r["torch_us_per_step_traj"] / r["native_us_per_step_traj"])


@pytest.mark.parametrize("name", ["mlp_rayleigh", "se3_mlp", "se3_so3_mlp_gravity"])
def test_an_empty_batch_rolls_out_to_empty_poses_on_every_engine(name):
    """No trajectories: empty poses and diagnostics of the right shapes, natively and in the row layout (whose
    MLP input, `ProductGroup.flatten`, once failed to reshape an empty batch)."""
    model = served(name)
    g0, g1 = starts(name, 0)
    with torch.no_grad():
        nat = model.rollout(g0, g1, 5)
        rows = rollout_implicit(model, g0, g1, 5, SolverOptions())
    assert nat.pose.R.shape == rows.pose.R.shape == (0, 6, model.G.n_bodies, 3, 3)
    assert nat.pose.p.shape == rows.pose.p.shape and nat.iterations.shape == rows.iterations.shape == (0, 4)


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_units_and_mass_ratios_the_generator_does_not_vary(unit):
    """Two free bodies of 25 kg and 0.5 kg beside a pivoted one, in metres or millimetres (positions and lengths
    x 1000, inertia x 1e6, g 9,810 mm/s^2, rotational damping x 1e6): the true scheme's native rollout takes the
    row layout's steps, its positions within the Newton tolerance scaled by their magnitude (the step test's
    rounding floor is)."""
    k = 1000.0 if unit == "mm" else 1.0
    G = ProductGroup(2, 1)
    J = [[2.1, 1.7, 0.9], [0.02, 0.015, 0.01], [0.9, 0.8, 0.6]]  # principal moments per body
    physics = {
        "J": [torch.diag(torch.tensor(row, dtype=torch.float64) * k * k).tolist() for row in J],  # (3 bodies, 3 x 3)
        "m": [25.0, 0.5, 1.0],
        "rho": [[0.0, 0.0, 0.1 * k], [0.02 * k, 0.0, 0.0], [0.0, 0.0, -0.8 * k]],
        "g": 9.81 * k,
        "D": [0.05 * k * k] * 3 + [0.05] * 3 + [0.05 * k * k] * 3 + [0.05] * 3 + [0.05 * k * k] * 3,
    }
    model = physics_model(G, H, physics)
    gen = torch.Generator().manual_seed(3)
    R0 = so3.exp(torch.randn(4, 3, 3, generator=gen, dtype=torch.float64))
    g0 = Pose(R0, k * torch.randn(4, 2, 3, generator=gen, dtype=torch.float64))
    xi = H * torch.randn(4, G.dim, generator=gen, dtype=torch.float64)
    xi[:, 3:6] *= k
    xi[:, 9:12] *= k
    g1 = G.retract(g0, xi)
    nat, rows, _ = three_ways(model, g0, g1, 30)
    assert rows.n_failed == 0
    assert_same_steps(rows, nat)
    assert gap(nat.pose.p, rows.pose.p) <= TOL * max(1.0, gap(rows.pose.p, 0 * rows.pose.p))
    assert gap(nat.pose.p[:, -1], nat.pose.p[:, 1]) > 0.01 * k  # the bodies moved
