"""The articulated model on trees with hinge, universal and weld joints (reduced coordinates).

Checked against references that do not share its closed forms: the reduced residual against autodiff
of the discrete Lagrangian through the joints' own exact motion (`lie.joints.advance`), its Newton
Jacobian against autodiff of the residual, and MuJoCo hinge chains against the true-parameter scheme
(one step and rollouts far better than constant velocity, where the ball-joint scheme is worse than
constant velocity) with every hinge kept a hinge to rounding error.
"""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.evaluation.metrics import geodesic_error
from liedfl_cli.lie import Pose, so3
from liedfl_cli.lie import joints as jt
from liedfl_cli.lie.tree import Tree
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedTriplets, articulated_true_model
from liedfl_cli.solvers.one_step import constant_velocity_one_step, one_step_predictions
from liedfl_cli.solvers.options import SolverOptions

F64 = torch.float64
TIGHT = SolverOptions(tol=1e-12, max_iter=20)


def _unit(v):
    v = torch.as_tensor(v, dtype=F64)
    return (v / v.norm()).tolist()


def mixed_tree(rotations: str, free_root: bool = True) -> Tree:
    z = [0.0, 0.0, 0.0]
    kinds = ["free" if free_root else "universal", "hinge", "universal", "ball", "weld"]
    axes = [
        [_unit([0.3, -0.2, 1.0]), _unit([1.0, 0.1, 0.0])] if not free_root else [z, z],
        [_unit([1.0, 2.0, -0.5]), z],
        [_unit([0.2, 1.0, 0.1]), _unit([1.0, 0.3, 0.4])],
        [z, z],
        [z, z],
    ]
    offsets = [z if free_root else [0.1, 0.2, 0.3], [0.4, 0.0, 0.1], [0.0, 0.3, 0.0], [0.2, 0.2, 0.0], [0.0, 0.0, 0.5]]
    return Tree.from_lists([-1, 0, 0, 2, 1], offsets, rotations, free_root, kinds, axes)


def smooth_motion(tree: Tree, n_traj: int, steps: int, h: float, seed: int = 0) -> Pose:
    """Coordinates (n_traj, steps+1, ...) of a smooth motion that obeys the joints: DoF angles as sums
    of sines, applied with `advance` from random reference rotations."""
    gen = torch.Generator().manual_seed(seed)
    G = tree.group
    C = so3.exp(0.7 * torch.randn(tree.n_bodies, 3, generator=gen, dtype=F64))
    t = h * torch.arange(steps + 1, dtype=F64)
    amp = torch.randn(n_traj, 1, tree.n_dof, generator=gen, dtype=F64)
    freq = 1.0 + torch.rand(n_traj, 1, tree.n_dof, generator=gen, dtype=F64)
    d = amp * torch.sin(freq * t[None, :, None])
    q0 = Pose(C.expand(n_traj, steps + 1, -1, -1, -1).clone(), torch.zeros(n_traj, steps + 1, G.n_se3, 3, dtype=F64))
    return jt.from_joint_coordinates(tree, jt.advance(tree, q0, d))


def learned_like(tree: Tree, h: float) -> ArticulatedLieDFLNN:
    """An untrained model with jittered parameters and damping per DoF (not the truth of anything)."""
    m = ArticulatedLieDFLNN(tree, h, potential=("uniform_gravity",), forces=("rayleigh",), init_jitter=0.3, seed=3)
    assert m.dof_damper is not None
    with torch.no_grad():
        m.dof_damper.lam.copy_(0.3 + torch.rand(m.dof_damper.lam.shape, dtype=F64))
    return m


def reference_residual(model: ArticulatedLieDFLNN, g0: Pose, g1: Pose, g2: Pose) -> torch.Tensor:
    """d/d delta [L_d(g0, g1(delta)) + L_d(g1(delta), g2)] + damping, with g1(delta) moved along the
    joints by `advance` (autodiff; no basis T involved)."""
    tree = model.tree
    q1 = jt.to_joint_coordinates(tree, g1)

    def L(delta):
        moved = jt.from_joint_coordinates(tree, jt.advance(tree, q1, delta))
        return (model.lagrangian(g0, moved) + model.lagrangian(moved, g2)).sum()

    zero = g1.R.new_zeros(*g1.R.shape[:-3], tree.n_dof)
    return torch.func.grad(L)(zero) + model.dof_torques(g0, g1, g2)


@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("free_root", [True, False])
def test_reduced_residual_equals_autodiff_through_the_joints(rotations, free_root):
    tree = mixed_tree(rotations, free_root)
    model = learned_like(tree, 0.05)
    data = smooth_motion(tree, 2, 4, 0.05)
    g0, g1, g2 = (data.index((slice(None), k)) for k in (0, 1, 2))
    ref = reference_residual(model, g0, g1, g2)
    fast = model.residual(g0, g1, g2)
    assert fast.shape == (2, tree.n_dof)
    scale = float(ref.detach().abs().max())
    assert torch.allclose(fast, ref, atol=1e-10 * scale), (fast - ref).abs().max()
    trip = ArticulatedTriplets(model, data, 4)
    b = trip.batch(torch.arange(trip.n), torch.Generator().manual_seed(0), 0)
    batch = model._batch_residual(b)
    assert torch.allclose(batch, model.residual(trip.prev, trip.cur, trip.nxt), atol=1e-10 * scale)


@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("damped", [False, True])
def test_reduced_newton_jacobian_equals_autodiff(rotations, damped):
    tree = mixed_tree(rotations)
    model = learned_like(tree, 0.05)
    if not damped:
        assert model.dof_damper is not None
        with torch.no_grad():
            model.dof_damper.lam.zero_()
    data = smooth_motion(tree, 2, 3, 0.05, seed=1)
    trip = ArticulatedTriplets(model, data, 3)
    trip.enable_jacobian()
    b = trip.batch(torch.arange(trip.n), torch.Generator().manual_seed(0), 0)
    H = model.newton_jacobian_batch(b).detach()
    G = tree.group

    def r_of(delta):
        x = jt.retract(tree, trip.cur, trip.inc_coord, delta)
        return model.residual(trip.prev, trip.cur, G.compose(trip.cur, x))

    zero = torch.zeros(trip.n, tree.n_dof, dtype=F64)
    J = torch.func.jacfwd(r_of)(zero).detach()
    J = torch.stack([J[i, :, i, :] for i in range(trip.n)])
    # exact without damping; the damping's Jacobian holds the universal joint's basis fixed over the
    # step (a Newton approximation, measured 1.6e-6 relative), hinges and balls exact
    rel = 1e-12 if not damped else 1e-5
    assert torch.allclose(H, J, atol=rel * float(J.abs().max())), float((H - J).abs().max())


def test_rollout_converges_and_keeps_every_joint():
    tree = mixed_tree("world")
    model = learned_like(tree, 0.05)
    data = smooth_motion(tree, 3, 2, 0.05, seed=2)
    ro = model.rollout(data.index((slice(None), 0)), data.index((slice(None), 1)), 60, TIGHT)
    assert ro.n_failed == 0
    q = jt.to_joint_coordinates(tree, ro.pose)
    q0 = jt.to_joint_coordinates(tree, data.index((slice(None), slice(0, 1))))
    ax = torch.tensor(tree.axes_array(), dtype=F64)
    assert torch.allclose(q.R[..., 1, :, :] @ ax[1, 0], q0.R[..., 1, :, :] @ ax[1, 0], atol=1e-11)
    c = torch.einsum("i,...ij,j->...", ax[2, 0], q.R[..., 2, :, :], ax[2, 1])
    c0 = torch.einsum("i,...ij,j->...", ax[2, 0], q0.R[..., 2, :, :], ax[2, 1])
    assert torch.allclose(c, c0.expand_as(c), atol=1e-11)
    assert torch.allclose(q.R[..., 4, :, :], q0.R[..., 4, :, :].expand_as(q.R[..., 4, :, :]), atol=1e-11)
    assert float(geodesic_error(q.R[:, -1, 2], q0.R[:, 0, 2]).min()) > 1e-3  # the universal joint moved


pytest.importorskip("mujoco")
from liedfl_cli.data.mujoco_chain import chain_dataset  # noqa: E402


@pytest.mark.parametrize(
    "kw",
    [
        {"links": 3, "rotations": "world", "joint_damping": 0.05},
        {
            "links": 3,
            "rotations": "world",
            "root": "pinned",
            "gravity": 9.81,
            "joint_damping": 0.1,
            "h": 0.02,
            "speed": 2.0,
        },
        {
            "links": 4,
            "rotations": "parent",
            "root": "pinned",
            "gravity": 9.81,
            "joint_damping": 0.1,
            "h": 0.02,
            "speed": 2.0,
        },
    ],
)
def test_true_hinge_scheme_beats_constant_velocity_where_ball_joints_cannot(kw):
    ds = chain_dataset(n_trajectories=3, steps=30, seed=7, joint="hinge", **{"h": 0.05, **kw})
    truth = ds.pose()
    cv = constant_velocity_one_step(ds.group, truth)
    target = truth.index((slice(None), slice(2, None)))
    cv_err = geodesic_error(cv.R, target.R).mean()
    ratios = {}
    assert ds.tree.joint_kinds[1:] == ("hinge",) * (len(ds.tree.parents) - 1)  # the file declares its hinges
    for name, tree in (("ball", ds.tree.with_joints(None)), ("hinge", ds.tree)):
        model = articulated_true_model(tree, ds.h, ds.params["physics"])
        pred, conv = one_step_predictions(model, truth, TIGHT)
        assert bool(conv.all())
        ratios[name] = float(geodesic_error(pred.R, target.R).mean() / cv_err)
    assert ratios["hinge"] < 0.1, ratios  # measured 0.002-0.08
    assert ratios["ball"] > 1.0, ratios  # the constraint torque no ball joint has: 1.4-2.1 measured
