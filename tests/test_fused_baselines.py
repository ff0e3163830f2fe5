"""The baselines' fused training paths (`runtime.fused`: models/glnn/engines/fused.py,
models/euclidean_dflnn/engines/fused.py, models/euler_dflnn/engines/fused.py) against their reference
paths (`runtime.fused=false`): the same loss (to 1e-12 relative) and the same gradients (to 1e-12 of the
gradient's largest entry), on the same parameters and batches."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.lie import SE3, SO3, Pose, so3
from liedfl_cli.models.base import LossOptions, TrajectorySet, TripletBatch, TripletSet
from liedfl_cli.models.euclidean_dflnn.model import EuclideanDFLNN
from liedfl_cli.models.euler_dflnn.engines import fused as fused_dflnn
from liedfl_cli.models.euler_dflnn.model import EulerDFLNN
from liedfl_cli.models.glnn.model import GLNN
from liedfl_cli.models.neural_ode.model import NeuralODE
from liedfl_cli.solvers.newton import jacobian

F64 = torch.float64
RTOL = 1e-12


def _trajectories(n: int, steps: int, h: float, seed: int = 0) -> Pose:
    """Free damped rigid-body windows R (n, steps + 1, 1, 3, 3) from a Lie-Heun model with other J, D."""
    gen = torch.Generator().manual_seed(seed)
    truth = GLNN(SO3, h, integrator="heun", init_jitter=0.3, seed=seed + 1)
    R0 = so3.exp(torch.randn(n, 3, generator=gen, dtype=F64))
    w0 = torch.randn(n, 3, generator=gen, dtype=F64)
    with torch.no_grad():
        R = truth.with_path("reference").integrate_rotations(R0, w0, steps)
    return Pose(R[:, :, None], torch.zeros(n, steps + 1, 0, 3, dtype=F64))


def _loss_and_grads(model, batch, fused: bool):
    """The loss and gradients of `model` on its `fused` or reference path (a twin sharing its parameters)."""
    model.zero_grad(set_to_none=True)
    twin = model.with_path("fused" if fused else "reference")
    loss, _ = twin.loss(batch, LossOptions())
    loss.backward()
    grads = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
    return loss.detach(), grads


def _assert_same(model, batch):
    loss_f, grads_f = _loss_and_grads(model, batch, True)
    loss_r, grads_r = _loss_and_grads(model, batch, False)
    assert loss_r > 0
    assert abs(loss_f - loss_r) <= RTOL * abs(loss_r)
    assert grads_f.keys() == grads_r.keys() and grads_r
    # relative to the whole gradient's largest entry: a parameter whose gradient is a near-cancelling
    # sum keeps only the rounding of its terms, which are of the whole gradient's size
    scale = max(g.abs().max() for g in grads_r.values())
    for k in grads_r:
        assert grads_r[k].abs().max() > 0, k
        assert (grads_f[k] - grads_r[k]).abs().max() <= RTOL * scale, k


@pytest.mark.parametrize(
    ("integrator", "window", "steps", "damping"),
    [
        ("dopri5", "trajectory", 6, True),  # 14 dopri5 steps, 2 of them rejected: both branches
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
    assert model.with_path("fused").fused_training() and not model.with_path("reference").fused_training()
    _assert_same(model, batch)


def test_glnn_dopri5_fused_rollout_equals_the_reference():
    """GLNN-RK4's rollout (`integrate`, no graph) through `solvers.dopri5` against torchdiffeq's."""
    data = _trajectories(4, 3, 0.1)
    model = GLNN(SO3, 0.1, integrator="dopri5", init_jitter=0.2, seed=3)
    g0, g1 = (Pose(data.R[:, k], data.p[:, k]) for k in (0, 1))
    with torch.no_grad():
        fused, ref = (
            m.integrate(m.initial_state(g0, g1), 40).R for m in (model.with_path(p) for p in ("fused", "reference"))
        )
    assert model.with_path("fused").fused_training()
    assert fused.shape == ref.shape == (4, 41, 1, 3, 3)
    assert (fused - ref).abs().max() <= 1e-12


@pytest.mark.parametrize("G", [SO3, SE3])
def test_neural_ode_fused_loss_gradients_and_rollout_equal_the_reference(G):
    """The Neural ODE's dopri5 through `solvers.dopri5` with the MLP field of `models.neural_ode.engines.fused`
    against torchdiffeq over the module: loss, every weight's and bias's gradient, and a rollout."""
    steps, h = 6, 0.1
    rot = _trajectories(5, steps, h)
    gen = torch.Generator().manual_seed(7)
    p = torch.cumsum(0.05 * torch.randn(5, steps + 1, 1, 3, generator=gen, dtype=F64), 1)
    data = rot if G is SO3 else Pose(rot.R, p)
    model = NeuralODE(G, h, mlp_width=16, mlp_depth=2, seed=3)
    assert model.with_path("fused").fused_solve() and not model.with_path("reference").fused_solve()
    batch = TrajectorySet(data, steps).batch(torch.arange(5), torch.Generator(), 0)
    _assert_same(model, batch)
    g0, g1 = (Pose(data.R[:, k], data.p[:, k]) for k in (0, 1))
    with torch.no_grad():
        fused, ref = (
            m.integrate(m.initial_state(g0, g1), 30) for m in (model.with_path(q) for q in ("fused", "reference"))
        )
    assert fused.R.shape == (5, 31, 1, 3, 3) and (fused.R - ref.R).abs().max() <= 1e-12
    assert fused.p.shape == ref.p.shape and torch.allclose(fused.p, ref.p, rtol=0, atol=1e-12)


def test_glnn_with_a_potential_keeps_the_reference_path():
    model = GLNN(SO3, 0.1, integrator="heun", potential=True)
    assert model.path == "fused" and not model.fused_training()


def _heavy_triplets(n: int, h: float, seed: int = 0) -> TripletBatch:
    """Triplets of smooth rotations R exp(k h w) with varied w, plus 10 regularity pairs."""
    gen = torch.Generator().manual_seed(seed)
    R0 = so3.exp(torch.randn(n, 3, generator=gen, dtype=F64))
    w = 2.0 * torch.randn(n, 3, generator=gen, dtype=F64)
    w2 = w + 0.3 * torch.randn(n, 3, generator=gen, dtype=F64)
    R1 = R0 @ so3.exp(h * w)
    R2 = R1 @ so3.exp(h * w2)
    pose = lambda R: Pose(R[:, None], torch.zeros(R.shape[0], 0, 3, dtype=F64))
    g0, g1, g2 = pose(R0), pose(R1), pose(R2)
    reg = (g1.index(torch.arange(10)), g2.index(torch.arange(10)))
    return TripletBatch(g0, g1, g2, reg)


@pytest.mark.parametrize(("G", "potential", "damping"), [(SE3, True, True), (SO3, True, True), (SE3, False, False)])
def test_euclidean_dflnn_fused_loss_and_gradients_equal_the_reference(G, potential, damping):
    model = EuclideanDFLNN(G, 0.05, potential=potential, damping=damping, mlp_width=16, mlp_depth=2, seed=2)
    if damping:
        with torch.no_grad():
            model.damping.L_entries.add_(0.02 * torch.arange(model.damping.L_entries.numel(), dtype=F64))
    batch = _heavy_triplets(64, 0.05)
    if G is SE3:  # positions moving with the rotations, so that the kinetic p and rho terms are exercised
        gen = torch.Generator().manual_seed(5)
        p0, v = torch.randn(64, 1, 3, generator=gen, dtype=F64), torch.randn(64, 1, 3, generator=gen, dtype=F64)
        ps = [p0, p0 + 0.05 * v, p0 + 0.1 * v + 0.01]
        poses = [Pose(g.R, p) for g, p in zip(batch.poses(), ps)]
        batch = TripletBatch(*poses, (poses[1].index(torch.arange(10)), poses[2].index(torch.arange(10))))
    _assert_same(model, batch)


def test_glnn_fused_dopri5_in_float32_matches_the_reference_to_float32_rounding():
    data = _trajectories(6, 6, 0.1)
    data = Pose(data.R.float(), data.p.float())
    model = GLNN(SO3, 0.1, integrator="dopri5", init_jitter=0.2, seed=3).to(torch.float32)
    batch = TrajectorySet(data, 6).batch(torch.arange(6), torch.Generator(), 0)
    loss_f, grads_f = _loss_and_grads(model, batch, True)
    loss_r, grads_r = _loss_and_grads(model, batch, False)
    assert loss_f.dtype == torch.float32
    assert abs(loss_f - loss_r) <= 1e-5 * abs(loss_r)
    scale = max(g.abs().max() for g in grads_r.values())
    for k in grads_r:  # float32 rounding through an adaptive solve: ~1e-6 of the largest entry
        assert (grads_f[k] - grads_r[k]).abs().max() <= 1e-4 * scale, k


@pytest.mark.parametrize(("potential", "damping"), [(True, True), (False, True), (True, False)])
def test_euler_dflnn_fused_loss_and_gradients_equal_the_reference(potential, damping):
    model = EulerDFLNN(SO3, 0.05, potential=potential, damping=damping, mlp_width=16, mlp_depth=2, seed=2)
    with torch.no_grad():  # a non-diagonal J, so that every term of the closed-form Hessian is exercised
        model.inertia.abc.add_(0.1 * torch.arange(model.inertia.abc.numel(), dtype=F64).reshape_as(model.inertia.abc))
    _assert_same(model, _heavy_triplets(64, 0.05))
    a, b = model.angles(*_heavy_triplets(64, 0.05).reg)
    H = fused_dflnn.euler_mixed_hessian(model, a, b)
    H_ref = model.mixed_hessian(a, b)
    assert (H - H_ref).abs().max() <= 1e-12 * H_ref.abs().max()


@pytest.mark.parametrize(("potential", "damping"), [(True, True), (False, False)])
def test_euler_dflnn_closed_form_residual_and_its_jacobian_equal_autograd(potential, damping):
    """The closed-form residual (`fused_dflnn.euler_residual`) against autograd of `lagrangian`, and its
    Jacobian in q_next (what Newton uses in rollouts) against the reference residual's, near gimbal lock
    too (theta = pi/2 - 1e-3, where E is nearly singular)."""
    model = EulerDFLNN(SO3, 0.05, potential=potential, damping=damping, mlp_width=16, mlp_depth=2, seed=3)
    with torch.no_grad():
        model.inertia.abc.add_(0.1 * torch.arange(model.inertia.abc.numel(), dtype=F64).reshape_as(model.inertia.abc))
    q_prev, q, q_next = model.angles(*_heavy_triplets(32, 0.05, seed=4).poses())
    q = q.clone()
    q[:4, 1] = torch.pi / 2 - 1e-3
    fused, ref = model.with_path("fused"), model.with_path("reference")
    r_f, r_r = fused.residual(q_prev, q, q_next), ref.residual(q_prev, q, q_next)
    assert r_r.abs().max() > 0
    assert (r_f - r_r).abs().max() <= 1e-12 * r_r.abs().max()
    with torch.no_grad():
        J_f = jacobian(lambda x: fused.residual(q_prev, q, x), q_next)
        J_r = jacobian(lambda x: ref.residual(q_prev, q, x), q_next)
    assert (J_f - J_r).abs().max() <= 1e-12 * J_r.abs().max()
