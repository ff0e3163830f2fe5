"""The baselines' fused training paths (`runtime.fused`, models/fused_glnn.py) against their
reference paths (`runtime.fused=false`): the same loss and the same gradients, to 1e-12 relative,
on the same parameters and batches."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.lie import SO3, Pose, so3
from liedfl_cli.models.base import LossOptions, TrajectorySet, TripletSet
from liedfl_cli.models.glnn import GLNN
from liedfl_cli.solvers import runtime

F64 = torch.float64
RTOL = 1e-12


def _trajectories(n: int, steps: int, h: float, seed: int = 0) -> Pose:
    """Free damped rigid-body windows R (n, steps + 1, 1, 3, 3) from a Lie-Heun model with other J, D."""
    gen = torch.Generator().manual_seed(seed)
    truth = GLNN(SO3, h, integrator="heun", init_jitter=0.3, seed=seed + 1)
    R0 = so3.exp(torch.randn(n, 3, generator=gen, dtype=F64))
    w0 = torch.randn(n, 3, generator=gen, dtype=F64)
    with torch.no_grad(), runtime.using(fused=False):
        R = truth.integrate_rotations(R0, w0, steps)
    return Pose(R[:, :, None], torch.zeros(n, steps + 1, 0, 3, dtype=F64))


def _loss_and_grads(model, batch, fused: bool):
    model.zero_grad(set_to_none=True)
    with runtime.using(fused=fused):
        loss, _ = model.loss(batch, LossOptions())
    loss.backward()
    grads = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
    return loss.detach(), grads


def _assert_same(model, batch):
    loss_f, grads_f = _loss_and_grads(model, batch, True)
    loss_r, grads_r = _loss_and_grads(model, batch, False)
    assert loss_r > 0
    assert abs(loss_f - loss_r) <= RTOL * abs(loss_r)
    assert grads_f.keys() == grads_r.keys() and grads_r
    for k in grads_r:
        scale = grads_r[k].abs().max()
        assert scale > 0, k
        assert (grads_f[k] - grads_r[k]).abs().max() <= RTOL * scale, k


@pytest.mark.parametrize(
    ("integrator", "window", "steps", "damping"),
    [
        ("dopri5", "trajectory", 6, True),
        ("heun", "trajectory", 20, True),
        ("heun", "trajectory", 8, False),
        ("midpoint", "triplet", 20, True),
    ],
)
def test_glnn_fused_loss_and_gradients_equal_the_reference(integrator, window, steps, damping):
    h = 0.1
    data = _trajectories(6, steps, h)
    model = GLNN(SO3, h, integrator=integrator, window=window, damping=damping, init_jitter=0.2, seed=3)
    if damping:  # off-diagonal damping too, so that every entry's gradient path is exercised
        with torch.no_grad():
            model.damping.L_entries.add_(0.05 * torch.arange(6, dtype=F64))
    samples = (TrajectorySet if window == "trajectory" else TripletSet)(data, steps)
    batch = samples.batch(torch.arange(min(samples.n, 40)), torch.Generator(), 0)
    with runtime.using(fused=True):
        assert model.fused_training()
    _assert_same(model, batch)


def test_glnn_with_a_potential_keeps_the_reference_path():
    model = GLNN(SO3, 0.1, integrator="heun", potential=True)
    with runtime.using(fused=True):
        assert not model.fused_training()
