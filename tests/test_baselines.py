"""The paper's baselines: conversions, correctness with true parameters, training and rollout.

Fast tier (< 90 s): tiny scenes generated once per session; every baseline goes through
`run_train` (train -> checkpoint -> rollout -> eval) with the smoke budget.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import pytest
import torch
from omegaconf import OmegaConf

from helpers import SMOKE, compose_config, single_body_models
from liedfl_cli.commands.train import fit, run_train
from liedfl_cli.config.factory import build_model
from liedfl_cli.data.scenes import generate
from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import SE3, SO3, Pose, euler, so3
from liedfl_cli.mechanics.potentials import GravityPotential
from liedfl_cli.models.euclidean_dflnn.model import EuclideanDFLNN
from liedfl_cli.models.euler_dflnn.model import EulerDFLNN
from liedfl_cli.models.glnn.model import GLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.options import SolverOptions
from liedfl_cli.solvers.rollout import Rollout

CONF = str(Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf")
# every model config except LieDFLNN's own and those needing a kinematic tree (the articulated one:
# tests/test_articulated_config.py): a new model file + config is covered without editing this list
NAMES = single_body_models()
J_TRUE = torch.diag(torch.tensor([1.521, 1.362, 1.211], dtype=torch.float64))
D_TRUE = 0.05 * torch.eye(3, dtype=torch.float64)
F64 = torch.float64


def _cfg(tmp, name, extra=()):
    paths = (f"paths.data_dir={tmp}/data", f"paths.output_dir={tmp}/run_{name}")
    return compose_config("train", (f"baseline={name}", *SMOKE, *paths, *extra))


def _scene(name="free_rigid_body", **kw):
    base = dict(
        name=name,
        h=0.1,
        n_trajectories=4,
        steps=12,
        train_steps=12,
        rollout_steps=12,
        test_fraction=0.5,
        n_test=None,
        seed=0,
        solver={"method": "RK45", "rtol": 1e-10, "atol": 1e-12},
    )
    if name == "free_rigid_body":
        base.update(
            physics={"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [1.2, 0.5, 1.0], "g": 0.0, "D": [0.05] * 3},
            initial={"omega_std": 1.0},
        )
    else:
        base.update(
            h=0.05,
            physics={
                "J": [1.521, 1.362, 1.211],
                "m": 0.5,
                "rho": [0.0, 0.5, 1.0],
                "g": 9.81,
                "D": [0.1] * 3 + [0.0] * 3,
            },
            initial={"p_std": 1.0, "omega_std": 1.0, "v_std": 1.0},
        )
    base.update(kw)
    return generate(base)


@pytest.fixture(scope="module")
def free_body():
    return _scene()


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("baselines")


def _true_glnn(integrator, h=0.1):
    m = GLNN(SO3, h, integrator=integrator, init_jitter=0.0)
    m.inertia.set_J(J_TRUE[None])
    m.damping.set_matrix(D_TRUE)
    return m


# ----------------------------------------------------------------------------- Euler angles
def test_euler_round_trip_random_rotations():
    R = so3.random((500,), generator=torch.Generator().manual_seed(1))
    q = euler.from_matrix(R)
    assert torch.allclose(euler.to_matrix(q), R, atol=1e-13)
    assert (q[:, 1].abs() <= math.pi / 2).all() and (q[:, [0, 2]].abs() <= math.pi).all()
    assert torch.allclose(euler.from_matrix(euler.to_matrix(q)), q, atol=1e-10)


@pytest.mark.parametrize(
    "theta", [math.pi / 2, -math.pi / 2, math.pi / 2 - 1e-9, -math.pi / 2 + 1e-7, math.pi / 2 - 1e-4, 1.0]
)
def test_euler_round_trip_through_gimbal_lock(theta):
    q = torch.tensor([[0.3, theta, -1.2], [2.9, theta, 3.0], [-3.0, theta, 0.0]], dtype=F64)
    R = euler.to_matrix(q)
    q2 = euler.from_matrix(R)
    assert torch.isfinite(q2).all()
    assert torch.allclose(euler.to_matrix(q2), R, atol=1e-13)
    assert torch.allclose(q2[:, 1], q[:, 1], atol=1e-7)
    # only phi - psi (theta = pi/2) or phi + psi (theta = -pi/2) is determined at the lock
    s = 1.0 if theta > 0 else -1.0
    comb = lambda a: euler.wrap(a[:, 0] - s * a[:, 2])
    assert torch.allclose(euler.wrap(comb(q2) - comb(q)), torch.zeros(3, dtype=F64), atol=1e-7)
    if abs(theta) == math.pi / 2:
        assert (q2[:, 2] == 0).all()  # convention at the exact lock


def test_euler_sequence_through_gimbal_lock_jumps_and_unwraps():
    # pitch sweeps 0 -> 180 deg with a little roll: the paper's figure. R is smooth, the angles jump.
    t = torch.linspace(0, math.pi, 181, dtype=F64)
    R = so3.exp(torch.stack((0.2 * torch.ones_like(t), t, torch.zeros_like(t)), -1))
    q = euler.from_matrix(R)
    assert torch.allclose(euler.to_matrix(q), R, atol=1e-13)
    jumps = torch.diff(q, dim=0).abs().amax(-1)
    assert jumps.max() > 1.0  # a coordinate discontinuity near theta = pi/2 ...
    assert (torch.diff(R, dim=0).abs().amax((-1, -2)) < 0.05).all()  # ... where R moves smoothly
    # unwrap removes 2 pi jumps and nothing else
    a = torch.cumsum(torch.full((50, 3), 0.4, dtype=F64), 0)
    assert torch.allclose(euler.unwrap(euler.wrap(a), dim=0), a - (a[0] - euler.wrap(a[0])))


def test_euler_rate_matrix_gives_body_angular_velocity():
    g = torch.Generator().manual_seed(2)
    q, qd, e = torch.randn(20, 3, generator=g, dtype=F64), torch.randn(20, 3, generator=g, dtype=F64), 1e-6
    Rdot = (euler.to_matrix(q + e * qd) - euler.to_matrix(q - e * qd)) / (2 * e)
    w = so3.vee(euler.to_matrix(q).transpose(-1, -2) @ Rdot)
    assert torch.allclose(w, (euler.rate_matrix(q) @ qd[..., None])[..., 0], atol=1e-8)
    assert torch.allclose(torch.linalg.det(euler.rate_matrix(q)), torch.cos(q[:, 1]), atol=1e-14)


# ----------------------------------------------------------------------------- correctness with true parameters
def test_glnn_dopri5_with_true_parameters_reproduces_the_simulator(free_body):
    R = free_body.pose().R[:, :, 0]
    w0 = torch.as_tensor(free_body.extras["omega"][:, 0, 0])
    with torch.no_grad():
        pred = _true_glnn("dopri5").integrate_rotations(R[:, 0], w0, R.shape[1] - 1)
    assert (pred - R).abs().max() < 1e-5


def test_glnn_potential_torque_with_the_true_gravity_reproduces_the_heavy_body():
    ds = _scene(
        "heavy_so3",
        h=0.05,
        n_trajectories=3,
        steps=20,
        train_steps=20,
        rollout_steps=20,
        physics={"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1] * 3},
        initial={"omega_scale": 1.0, "omega_radius": 2.0},
    )
    truth = ds.pose()
    R, w0 = truth.R[:, :, 0], torch.as_tensor(ds.extras["omega"][:, 0, 0])
    models = {}
    for integrator in ("dopri5", "midpoint"):
        m = _true_glnn(integrator, 0.05)
        m.damping.set_matrix(0.1 * torch.eye(3, dtype=F64))
        m.potential = GravityPotential(SO3, [0.5], [[0.0, 0.5, 1.0]], 9.81)
        models[integrator] = m
    with torch.no_grad():
        pred = models["dopri5"].integrate_rotations(R[:, 0], w0, 20)
    assert (pred - R).abs().max() < 1e-5
    g = lambda k: truth.index((slice(None), k))
    ro = models["midpoint"].rollout(g(0), g(1), 20, SolverOptions(tol=1e-10, max_iter=10))
    assert ro.converged.all() and (ro.pose.R - truth.R).abs().max() < 0.1


@pytest.mark.parametrize("integrator", ["heun", "midpoint"])
def test_lie_integrators_are_second_order_and_stay_on_so3(integrator):
    R0 = so3.random((3,), generator=torch.Generator().manual_seed(3))
    w0 = torch.tensor([[1.0, -0.5, 0.8], [0.2, 1.5, -0.3], [-1.2, 0.4, 0.9]], dtype=F64)
    with torch.no_grad():
        ref = _true_glnn("dopri5", 0.2).integrate_rotations(R0, w0, 5)[:, -1]
        errs = [
            (_true_glnn(integrator, 0.2 / k).integrate_rotations(R0, w0, 5 * k)[:, -1] - ref).abs().max()
            for k in (1, 2, 4)
        ]
        R = _true_glnn(integrator, 0.05).integrate_rotations(R0, w0, 20)
    assert 3.0 < errs[0] / errs[1] < 5.5 and 3.0 < errs[1] / errs[2] < 5.5, errs
    assert so3.orthogonality_error(R).max() < 1e-12


def test_euler_dflnn_with_true_parameters_tracks_the_motion():
    R0 = so3.identity((2,))
    w0 = torch.tensor([[0.5, 0.3, -0.4], [-0.2, 0.4, 0.6]], dtype=F64)
    with torch.no_grad():
        truth = _true_glnn("dopri5").integrate_rotations(R0, w0, 20)
    e = EulerDFLNN(SO3, 0.1, init_jitter=0.0)
    e.inertia.set_J(J_TRUE[None])
    e.damping.set_matrix(D_TRUE)
    g = lambda k: Pose(truth[:, k, None], truth.new_zeros(2, 0, 3))
    ro = e.rollout(g(0), g(1), 20, SolverOptions(tol=1e-10, max_iter=20))
    assert ro.converged.all()
    # the observed start is w0-free: the error is the O(h) start-up plus the scheme's O(h^2)
    assert (ro.pose.R[:, :, 0] - truth).abs().max() < 2e-2


@pytest.mark.parametrize("G", [SO3, SE3], ids=["so3", "se3"])
def test_euclidean_residual_along_the_group_equals_liedflnn(G):
    """On group data, the Euclidean residual paired with the tangent directions of the left
    perturbation g exp(eta) equals LieDFLNN's residual with the same parameters."""
    gen = torch.Generator().manual_seed(4)
    T = 5
    Rs = so3.random((T,), generator=gen)
    poses, R, p = [], Rs, torch.randn(T, 3, generator=gen, dtype=F64)
    for _ in range(3):
        poses.append(Pose(R[:, None], p[:, None][:, : G.n_se3]))
        R = R @ so3.exp(0.1 * torch.randn(T, 3, generator=gen, dtype=F64))
        p = p + 0.1 * torch.randn(T, 3, generator=gen, dtype=F64)
    physics = {
        "J": [1.521, 1.362, 1.211],
        "m": 0.5,
        "rho": [0.1, 0.5, 1.0],
        "D": [0.05, 0.07, 0.1] + [0.0] * (3 * G.n_se3),
    }
    ref = physics_model(G, 0.1, physics)
    eu = EuclideanDFLNN(G, 0.1, potential=False, init_jitter=0.0)
    eu.inertia.set_J(J_TRUE[None])
    eu.damping.set_matrix(torch.diag(torch.tensor(physics["D"], dtype=F64)))
    if G.n_se3:
        eu.mass.set_value(torch.tensor([0.5]))
        with torch.no_grad():
            eu.rho.copy_(torch.tensor(physics["rho"]))
    r = eu.residual(*(eu.to_x(g) for g in poses))
    Rk = poses[1].R[:, 0]
    E = so3.hat(torch.eye(3, dtype=F64))
    rw = torch.stack([(r[:, :9].reshape(T, 3, 3) * (Rk @ E[i])).sum((-1, -2)) for i in range(3)], -1)
    parts = [rw] + ([(r[:, 9:, None] * Rk).sum(-2)] if G.n_se3 else [])  # (R_k e_i) . r_p
    assert torch.allclose(torch.cat(parts, -1), ref.residual(*poses), atol=1e-12)
    assert torch.allclose(
        eu.lagrangian(eu.to_x(poses[0]), eu.to_x(poses[1])), ref.lagrangian(poses[0], poses[1]), atol=1e-12
    )


# ----------------------------------------------------------------------------- protocol and rollout shapes
def _cfg_obj(**train):
    base = {
        "w_del": 0.5,
        "w_reg": 0.5,
        "reg_points": 4,
        "reg_form": "relu",
        "epsilon": 10.0,
        "epochs": 30,
        "batch_size": 1024,
        "optimizer": {"name": "adam", "lr": 1e-2, "weight_decay": 0.0},
    }
    return OmegaConf.create({**base, **train})


@pytest.mark.parametrize("name", NAMES)
def test_rollout_shapes_and_fields(name, free_body, data_dir):
    ds = free_body
    model = build_model(_cfg(data_dir, name), ds)
    assert ds.group == model.G and model.h == ds.h and model.window in ("triplet", "trajectory")
    assert model.components()
    truth = ds.pose()
    steps = 6
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    seen = []
    ro = model.rollout(g0, g1, steps, SolverOptions(tol=1e-5, max_iter=10), progress=seen.append)
    T = truth.R.shape[0]
    assert isinstance(ro, Rollout)
    assert ro.pose.R.shape == (T, steps + 1, 1, 3, 3) and ro.pose.p.shape == (T, steps + 1, 0, 3)
    assert ro.converged.shape == ro.iterations.shape == ro.residual_norm.shape == (T, steps - 1)
    assert ro.converged.dtype == torch.bool and ro.iterations.dtype == torch.long
    assert torch.equal(ro.pose.R[:, 0], g0.R) and torch.equal(ro.pose.R[:, 1], g1.R)
    assert torch.isfinite(ro.pose.R).all() and ro.seconds > 0 and seen and seen[-1] == steps - 1
    if name in ("glnn_rk4", "glnn_lie_heun", "neural_ode"):
        assert ro.converged.all() and (ro.iterations == 0).all()
    if name in ("glnn_lie_midpoint", "euler_dflnn", "euclidean_dflnn"):
        assert (ro.iterations > 0).all()


def test_se3_baselines_and_group_errors(data_dir):
    ds = _scene("heavy_se3", n_trajectories=3, steps=6, train_steps=6, rollout_steps=6)
    truth = ds.pose()
    for name in ("euclidean_dflnn", "neural_ode"):
        model = build_model(_cfg(data_dir, name, ["dataset=heavy_se3"]), ds)
        ro = model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), 4, SolverOptions())
        assert ro.pose.R.shape == (3, 5, 1, 3, 3) and ro.pose.p.shape == (3, 5, 1, 3)
        assert torch.equal(ro.pose.p[:, 1], truth.p[:, 1])
    for name in ("glnn_rk4", "glnn_lie_midpoint", "glnn_lie_heun", "euler_dflnn"):
        with pytest.raises(ConfigError, match="SO\\(3\\)"):
            build_model(_cfg(data_dir, name, ["dataset=heavy_se3"]), ds)


def test_unknown_baseline_key_is_a_config_error(free_body, data_dir):
    with pytest.raises(ConfigError, match="mlp_widht"):
        build_model(_cfg(data_dir, "glnn_rk4", ["+model.mlp_widht=3"]), free_body)


# ----------------------------------------------------------------------------- training
@pytest.mark.parametrize("name", ["glnn_rk4", "glnn_lie_midpoint", "glnn_lie_heun", "euclidean_dflnn"])
def test_loss_decreases_on_a_tiny_problem(name, free_body, data_dir):
    torch.manual_seed(0)
    model = build_model(_cfg(data_dir, name), free_body)
    res = fit(model, free_body.pose(free_body.train_idx), _cfg_obj(), 8)
    first, last = res["history"][0]["loss"], res["history"][-1]["loss"]
    # Lie-midpoint on triplets starts close to its floor (two steps from a finite-difference
    # velocity carry little signal -- the paper's explanation of its failure): only ask for progress.
    assert last < (0.9 if name == "glnn_lie_midpoint" else 0.5) * first, (first, last)


@pytest.mark.parametrize("name", NAMES)
def test_every_baseline_runs_end_to_end(name, data_dir):
    s = run_train(_cfg(data_dir, name))
    run = Path(s["run_dir"])
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "eval.csv").is_file()
    with h5py.File(run / "rollout.h5") as f:
        assert f["model/R"].shape == (2, 13, 1, 3, 3)
        assert f["model/converged"].shape == (2, 11)
    row = next(r for r in s["eval"] if r["model"] == "model")
    assert math.isfinite(row["rel_rot_error_mean"])
    if name in ("glnn_lie_midpoint", "glnn_lie_heun", "euler_dflnn"):
        assert row["max_orth_drift"] < 1e-10  # these predict rotations (Euler: via the angle map)
    # the checkpoint reloads into the same model
    from liedfl_cli.config.runs import load_run

    _, model, _, _ = load_run(run)
    assert type(model).__name__ == json.loads((run / "components.json").read_text())["model"]
