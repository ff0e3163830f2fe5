"""An implicit model's path ("fused" | "reference") is its execution plan's: the fused paths by default,
the command's `runtime.fused` when the pipeline builds it (`factory.build_model`), or explicitly with
`with_path` / `set_plan`; the process runtime changed afterwards does not switch it (no model reads
it). Both paths give the same loss (1e-12 relative) and rollouts (Newton tolerance)."""

from __future__ import annotations

import pytest
import torch
from test_fused import _start, make, rel, trajectories

from liedfl_cli.models.base import LossOptions
from liedfl_cli.models.liedflnn.engines import core as fused
from liedfl_cli.solvers import rollout as rollout_loop
from liedfl_cli.solvers import runtime
from liedfl_cli.solvers.execution import ExecutionPlan, check_path
from liedfl_cli.solvers.options import SolverOptions


@pytest.fixture
def solver_calls(monkeypatch):
    """Which Newton loop ("fused" | "reference") each call of the rollout loop's one entry point ran."""
    calls: list[str] = []
    real = rollout_loop.solve

    def spy(problem, opts, *, reference=False):
        calls.append("reference" if reference else "fused")
        return real(problem, opts, reference=reference)

    monkeypatch.setattr(rollout_loop, "solve", spy)
    return calls


def _path_taken(model, solver_calls: list[str]) -> tuple[bool, bool, set[str]]:
    """(training set fused, rollout state fused, Newton loops run) of one short rollout."""
    G = model.G
    data = trajectories(G)
    g0, g1 = _start(G, 2, 0.1)
    solver_calls.clear()
    model.rollout(g0, g1, 3)
    is_fused_set = isinstance(model.training_set(data, 10), fused.IncrementSet)
    is_fused_state = isinstance(model.implicit_start(g0, g1), fused.RolloutState)
    return is_fused_set, is_fused_state, set(solver_calls)


def test_the_path_is_the_models_plan_whatever_the_runtime_says(solver_calls, monkeypatch):
    # the torch Newton loops (the native step, which would take the fused model's rollout, runs none of them;
    # its own routing: tests/test_native_body.py)
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)
    with runtime.using(fused=False):  # a model built outside the pipeline does not read the runtime
        fus = make("se3xso3_mlp")
    ref = make("se3xso3_mlp")
    ref.set_plan(ExecutionPlan(path="reference"))
    assert (ref.path, fus.path) == ("reference", "fused")
    for later in (True, False):
        with runtime.using(fused=later):
            assert _path_taken(ref, solver_calls) == (False, False, {"reference"})
            assert _path_taken(fus, solver_calls) == (True, True, {"fused"})


def test_with_path_shares_the_parameters_and_leaves_the_original_alone():
    model = make("se3_mlp_rayleigh")
    twin = model.with_path("reference")
    assert model.path == "fused" and twin.path == "reference"
    assert all(a is b for a, b in zip(model.parameters(), twin.parameters()))
    with torch.no_grad():
        next(model.parameters()).add_(1.0)  # an optimiser step on one moves the other
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), twin.state_dict().values()))
    with pytest.raises(ValueError, match="model path must be one of"):
        model.with_path("fast")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="got 'nope'"):
        check_path("nope")


@pytest.mark.parametrize("name", ["free_so3_rayleigh", "se3xso3_mlp"])
def test_fused_and_reference_models_give_the_same_loss_and_rollout(name):
    fus = make(name)
    ref = fus.with_path("reference")
    data = trajectories(fus.G)
    idx = torch.randperm(40, generator=torch.Generator().manual_seed(3))
    losses = [
        m.loss(m.training_set(data, 10).batch(idx, torch.Generator().manual_seed(1), 10), LossOptions())[0]
        for m in (ref, fus)
    ]
    assert rel(losses[1].detach(), losses[0].detach()) <= 1e-12
    fus.requires_grad_(False)
    g0, g1 = _start(fus.G, 4, 0.1)
    a, b = ref.rollout(g0, g1, 10), fus.rollout(g0, g1, 10)
    tol = SolverOptions().tol
    assert bool(a.converged.all()) and torch.equal(a.converged, b.converged)
    assert float((a.pose.R - b.pose.R).abs().max()) <= tol
    if a.pose.p.numel():  # SE(3) bodies
        assert float((a.pose.p - b.pose.p).abs().max()) <= tol * max(1.0, float(a.pose.p.abs().max()))


def test_one_place_chooses_the_rollout_engine(monkeypatch):
    """`engines/choose.py`: the native step for a single SO(3) or SE(3) body where a compiler builds it and
    the plan allows native code; under `compile: false` floats for a few trajectories of a linear single
    SO(3) body, columns for many, rows for everything else, for the reference path and for a rollout the
    plan compiles."""
    from test_fused_columns import model_named
    from test_fused_columns import start as so3_start

    from liedfl_cli.models.liedflnn.engines.choose import choose_rollout_engine
    from liedfl_cli.solvers import compile as compile_cache

    body = model_named("free_rayleigh")
    few, many = so3_start(1)[0], so3_start(64)[0]
    se3 = make("se3_mlp_rayleigh")
    se3_few = _start(se3.G, 4, 0.1)[0]
    native = "native" if compile_cache.cxx() is not None else None
    assert choose_rollout_engine(body, few, 20).name == (native or "scalar")
    assert choose_rollout_engine(body, many, 20).name == (native or "columns")
    assert choose_rollout_engine(se3, se3_few, 20).name == (native or "rows")
    assert choose_rollout_engine(body.with_path("reference"), many, 20).name == "rows"
    for model in (body, se3):
        model.set_plan(ExecutionPlan(compile="false"))  # eager torch everywhere
    assert choose_rollout_engine(body, few, 20).name == "scalar"
    assert choose_rollout_engine(body, many, 20).name == "columns"
    assert choose_rollout_engine(se3, se3_few, 20).name == "rows"
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)
    monkeypatch.setattr(compile_cache, "compiler_available", lambda: True)
    body.set_plan(ExecutionPlan(compile="true"))
    assert choose_rollout_engine(body, many, 20).name == "rows"  # the compiled step lives in rows
    body.set_plan(ExecutionPlan(compile="auto"))
    assert choose_rollout_engine(body, many, 20).name == "columns"  # a small rollout: auto does not compile


def test_one_place_chooses_the_training_engine(monkeypatch):
    """`engines/choose.py`: increments on the fused path with the closed-form residual, triplets for the
    reference path or the autodiff residual; a batch is computed by the engine that built it (a triplet
    batch on a fused model by the reference), with the same loss; the train compile policy lives there."""
    from liedfl_cli.models.base import TripletSet
    from liedfl_cli.models.liedflnn.engines import choose

    fus = make("free_so3_rayleigh")
    generic = make("free_so3_rayleigh")
    generic.residual_mode = "generic"
    assert choose.choose_training_engine(fus).name == "increments"
    assert choose.choose_training_engine(fus.with_path("reference")).name == "triplets"
    assert choose.choose_training_engine(generic).name == "triplets"
    data = trajectories(fus.G)
    idx = torch.arange(12)
    inc = fus.training_set(data, 10).batch(idx, torch.Generator().manual_seed(1), 10)
    tri = TripletSet(data, 10).batch(idx, torch.Generator().manual_seed(1), 10)
    assert choose.choose_training_engine(fus, inc).name == "increments"
    assert choose.choose_training_engine(fus, tri).name == "triplets"
    a, b = fus.loss(inc, LossOptions())[0], fus.loss(tri, LossOptions())[0]
    assert rel(a.detach(), b.detach()) <= 1e-12
    with pytest.raises(TypeError, match="trains on triplets"):
        choose.choose_training_engine(fus, object())
    from liedfl_cli.solvers import compile as compile_cache

    seen: list[str] = []
    monkeypatch.setattr(compile_cache, "compiled", lambda fn, key: seen.append(key) or fn)
    monkeypatch.setattr(type(fus.plan), "wants_compile", lambda self, what, work=0: what == "train")
    assert rel(fus.loss(inc, LossOptions())[0].detach(), a.detach()) <= 1e-12
    assert seen == ["train_loss"]  # the increments engine asked for the compiled loss
