"""The articulated model's compiled training loss (`runtime.compile`): when the plan asks for it the
paper's DEL loss of a precomputed batch goes through `torch.compile` (`ArticulatedLieDFLNN.loss`), and
the compiled loss and its gradients equal the eager ones to rounding (slow tier: compiling takes a
minute or more on 2 cores)."""

from __future__ import annotations

import pytest
import torch
from test_articulated import EXP4_FORCES, _model, _trajectories, _tree

from liedfl_cli.models.articulated import model as articulated_model
from liedfl_cli.models.articulated.model import ArticulatedTriplets
from liedfl_cli.models.base import LossOptions
from liedfl_cli.solvers import compile as compile_cache
from liedfl_cli.solvers.execution import ExecutionPlan


def _setup():
    tree = _tree("parent", True)
    m = _model(tree, "fast", EXP4_FORCES)
    data = _trajectories(tree, T=3, N=6)
    ts = m.training_set(data, 6)
    assert isinstance(ts, ArticulatedTriplets)
    return m, ts.batch(torch.arange(6), torch.Generator().manual_seed(0), 0)


def _loss_and_grads(m, batch, opts):
    loss, _ = m.loss(batch, opts)
    params = [p for p in m.parameters() if p.requires_grad]
    return loss.detach(), [g for g in torch.autograd.grad(loss, params, allow_unused=True) if g is not None]


def test_the_plan_decides_whether_the_del_loss_is_compiled(monkeypatch):
    calls: list = []

    def record(fn, key=None):  # stands in for torch.compile: records the request, runs fn eagerly
        calls.append((fn, key))
        return fn

    monkeypatch.setattr(compile_cache, "compiled", record)
    monkeypatch.setattr(compile_cache, "compiler_available", lambda: True)
    m, batch = _setup()
    opts = LossOptions(reg_points=0)
    m.set_plan(ExecutionPlan(compile="false"))
    eager = _loss_and_grads(m, batch, opts)
    assert calls == []
    m.set_plan(ExecutionPlan(compile="true"))
    routed = _loss_and_grads(m, batch, opts)
    assert calls == [(articulated_model._articulated_loss, "articulated_train_loss")]
    torch.testing.assert_close(routed[0], eager[0], rtol=0, atol=0)  # the same function, uncompiled here
    with torch.no_grad():  # a check of the weights (no gradient) never compiles a second graph
        m.loss(batch, opts)
    assert len(calls) == 1
    m.set_plan(ExecutionPlan(compile="auto", train_steps=10))  # a short run: auto does not compile
    m.loss(batch, opts)
    assert len(calls) == 1


@pytest.mark.slow
@pytest.mark.skipif(not compile_cache.compiler_available(), reason="torch.compile needs a C++ compiler")
def test_the_compiled_del_loss_and_its_gradients_equal_eager():
    torch.set_num_threads(1)
    m, batch = _setup()
    opts = LossOptions(reg_points=0)
    m.set_plan(ExecutionPlan(compile="false"))
    loss_e, grads_e = _loss_and_grads(m, batch, opts)
    m.set_plan(ExecutionPlan(compile="true"))
    loss_c, grads_c = _loss_and_grads(m, batch, opts)
    # it compiled: a failed compilation would have put the plain function in the cache (and said so)
    assert compile_cache._compiled["articulated_train_loss"] is not articulated_model._articulated_loss
    assert len(grads_c) == len(grads_e) >= 8
    torch.testing.assert_close(loss_c, loss_e, rtol=1e-10, atol=0)
    for c, e in zip(grads_c, grads_e):
        torch.testing.assert_close(c, e, rtol=1e-8, atol=1e-10 * max(1.0, float(e.abs().max())))
