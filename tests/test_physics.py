"""Ground-truth rigid-body simulators: conservation laws, dissipation, signs and the paper's formulas."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from liedfl_cli.data import physics
from liedfl_cli.data.physics import RigidBodySE3, RigidBodySO3, SolverOptions, hat, simulate_se3, simulate_so3
from liedfl_cli.errors import SimulationError
from liedfl_cli.lie import so3

J_PAPER = [1.521, 1.362, 1.211]
RHO = [0.0, 0.5, 1.0]


def rand_rot(rng, n):
    return so3.from_quaternion(torch.from_numpy(rng.standard_normal((n, 4)))).numpy()


def rand_spd(rng, n, shift=0.5):
    A = rng.standard_normal((n, n))
    return A @ A.T / n + shift * np.eye(n)


def so3_exp(w):
    return so3.exp(torch.as_tensor(w, dtype=torch.float64)).numpy()


def times(h, n):
    return h * np.arange(n + 1)


# ------------------------------------------------------------------ structural checks (no integration)
def test_so3_gravity_torque_is_minus_left_trivialised_gradient():
    rng = np.random.default_rng(0)
    body = RigidBodySO3(J=J_PAPER, m=0.5, rho=RHO, g=9.81)
    R = rand_rot(rng, 5)
    eps = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = eps
        dV = (body.potential(R @ so3_exp(e)) - body.potential(R @ so3_exp(-e))) / (2 * eps)
        np.testing.assert_allclose(dV, -body.gravity_torque(R)[:, i], atol=1e-8)


def test_se3_gravity_wrench_is_minus_left_trivialised_gradient():
    rng = np.random.default_rng(1)
    body = RigidBodySE3(J=J_PAPER, m=0.5, rho=RHO, g=9.81)
    R, p = rand_rot(rng, 5), rng.standard_normal((5, 3))
    tau, f = body.gravity_wrench(R)
    eps = 1e-6
    for i in range(6):
        eta = np.zeros(6)
        eta[i] = eps
        # (R, p) exp(eta) to first order: (R exp(eta_w), p + R eta_v)
        Vp = body.potential(R @ so3_exp(eta[:3]), p + R @ eta[3:])
        Vm = body.potential(R @ so3_exp(-eta[:3]), p - R @ eta[3:])
        expected = -(tau if i < 3 else f)[:, i % 3]
        np.testing.assert_allclose((Vp - Vm) / (2 * eps), expected, atol=1e-8)


def test_mass_matrix_matches_kinetic_energy_and_momenta():
    rng = np.random.default_rng(2)
    body = RigidBodySE3(J=rand_spd(rng, 3), m=0.7, rho=rng.standard_normal(3), g=0.0)
    M = body.mass_matrix()
    np.testing.assert_allclose(M, M.T, atol=0)
    assert np.linalg.eigvalsh(M).min() > 0
    w, v = rng.standard_normal((8, 3)), rng.standard_normal((8, 3))
    xi = np.concatenate((w, v), -1)
    np.testing.assert_allclose(body.kinetic(w, v), 0.5 * np.einsum("bi,ij,bj->b", xi, M, xi), rtol=1e-13)
    Pi, P = body.momenta(w, v)
    np.testing.assert_allclose(np.concatenate((Pi, P), -1), xi @ M.T, rtol=1e-12, atol=1e-13)


def paper_se3_accelerations(J, m, rho, w, v, tau, f):
    """The paper's explicit (w', v') for the SE(3) body, written independently of physics.py."""
    P = m * (v + np.cross(w, rho))
    rhs = tau - np.cross(w, w @ J.T + np.cross(rho, P)) - np.cross(v, P) - np.cross(rho, f - np.cross(w, P))
    wdot = np.linalg.solve(J, rhs[..., None])[..., 0]
    vdot = (f - np.cross(w, P)) / m - np.cross(wdot, rho)
    return wdot, vdot


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_se3_rhs_matches_paper_explicit_formula(seed):
    rng = np.random.default_rng(seed)
    J, rho, m = rand_spd(rng, 3), rng.standard_normal(3), 0.3 + rng.random()
    D = rand_spd(rng, 6, shift=0.0)
    body = RigidBodySE3(J=J, m=m, rho=rho, g=9.81, D=D)
    n = 16
    R, p = rand_rot(rng, n), rng.standard_normal((n, 3))
    w, v = 2 * rng.standard_normal((n, 3)), 2 * rng.standard_normal((n, 3))
    y = body.pack(R, p, w, v)
    dy = body.rhs(0.0, y.reshape(-1)).reshape(n, 18)
    tg, fg = body.gravity_wrench(R)
    te, fe = body.external_wrench(R, p, w, v)
    wdot, vdot = paper_se3_accelerations(J, m, rho, w, v, tg + te, fg + fe)
    np.testing.assert_allclose(dy[:, 12:15], wdot, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(dy[:, 15:18], vdot, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(dy[:, :9].reshape(n, 3, 3), R @ hat(w), atol=1e-14)
    np.testing.assert_allclose(dy[:, 9:12], (R @ v[..., None])[..., 0], atol=1e-14)


def test_se3_centre_of_mass_falls_freely_from_rhs():
    """D = 0: c'' = -g e3 for any state (c = p + R rho), computed from the ODE right-hand side."""
    rng = np.random.default_rng(3)
    body = RigidBodySE3(J=rand_spd(rng, 3), m=0.5, rho=RHO, g=9.81)
    n = 16
    R, p, w, v = (
        rand_rot(rng, n),
        rng.standard_normal((n, 3)),
        3 * rng.standard_normal((n, 3)),
        rng.standard_normal((n, 3)),
    )
    wdot, vdot = body.accelerations(R, p, w, v)
    rho = np.asarray(RHO)
    inner = np.cross(w, np.cross(w, rho) + v) + np.cross(wdot, rho) + vdot
    cdd = (R @ inner[..., None])[..., 0]
    np.testing.assert_allclose(cdd, np.broadcast_to([0, 0, -9.81], (n, 3)), atol=1e-12)


@pytest.mark.parametrize("kind", ["so3", "se3"])
def test_energy_rate_equals_power(kind):
    """dE/dt along the vector field (finite difference in state space) = w.tau_ext (+ v.f_ext)."""
    rng = np.random.default_rng(4)
    n = 8
    R, w = rand_rot(rng, n), rng.standard_normal((n, 3))
    K = rng.standard_normal(3)
    if kind == "so3":
        body = RigidBodySO3(
            J=rand_spd(rng, 3),
            m=0.5,
            rho=RHO,
            g=9.81,
            D=rand_spd(rng, 3, 0.0),
            tau_extra=lambda R, w: np.cross(R[..., 2, :], K),
        )
        y = body.pack(R, w)

        def E(Y):
            s = body.unpack(Y)
            return body.energy(s["R"], s["w"])

        power = body.power(R, w)
    else:
        body = RigidBodySE3(J=rand_spd(rng, 3), m=0.5, rho=RHO, g=9.81, D=rand_spd(rng, 6, 0.0))
        p, v = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
        y = body.pack(R, p, w, v)

        def E(Y):
            s = body.unpack(Y)
            return body.energy(s["R"], s["p"], s["w"], s["v"])

        power = body.power(R, p, w, v)
    f = body.rhs(0.0, y.reshape(-1)).reshape(y.shape)
    eps = 1e-5
    dE = (E(y + eps * f) - E(y - eps * f)) / (2 * eps)
    np.testing.assert_allclose(dE, power, rtol=1e-7, atol=1e-8)


def test_tau_extra_callback_enters_the_dynamics():
    """J = I, g = 0, D = 0, w0 = 0 and a constant torque k: w(t) = k t."""
    k = np.array([0.3, -0.2, 0.1])
    body = RigidBodySO3(J=[1.0, 1.0, 1.0], tau_extra=lambda R, w: np.broadcast_to(k, w.shape))
    t = times(0.1, 10)
    sim = simulate_so3(body, np.eye(3)[None], np.zeros((1, 3)), t)
    np.testing.assert_allclose(sim.w[0], t[:, None] * k, atol=1e-10)
    # rotation about a fixed axis by the angle |k| t^2 / 2
    np.testing.assert_allclose(sim.R[0, -1], so3_exp(k * t[-1] ** 2 / 2), atol=1e-9)


# ------------------------------------------------------------------ integrated trajectories
def test_one_solve_ivp_call_for_all_trajectories(monkeypatch):
    calls = []
    real = physics.solve_ivp

    def counting(*a, **kw):
        calls.append(a[2].shape)
        return real(*a, **kw)

    monkeypatch.setattr(physics, "solve_ivp", counting)
    rng = np.random.default_rng(5)
    body = RigidBodySO3(J=J_PAPER, m=0.5, rho=RHO, g=9.81, D=[0.1] * 3)
    sim = simulate_so3(body, rand_rot(rng, 7), rng.standard_normal((7, 3)), times(0.05, 20))
    assert calls == [(7 * 12,)]
    assert sim.R.shape == (7, 21, 3, 3) and sim.w.shape == (7, 21, 3)


def test_stacked_integration_matches_single_trajectories():
    rng = np.random.default_rng(6)
    body = RigidBodySO3(J=J_PAPER, m=0.5, rho=RHO, g=9.81, D=[0.1] * 3)
    R0, w0, t = rand_rot(rng, 4), 2 * rng.standard_normal((4, 3)), times(0.05, 40)
    both = simulate_so3(body, R0, w0, t)
    for i in range(4):
        one = simulate_so3(body, R0[i : i + 1], w0[i : i + 1], t)
        np.testing.assert_allclose(one.R[0], both.R[i], atol=1e-8)


@pytest.mark.parametrize("g", [9.81, 0.0], ids=["heavy", "free"])
def test_so3_energy_conserved_without_damping(g):
    rng = np.random.default_rng(7)
    body = RigidBodySO3(J=J_PAPER, m=0.5, rho=RHO, g=g)
    sim = simulate_so3(body, rand_rot(rng, 6), 2 * rng.standard_normal((6, 3)), times(0.05, 100))
    E = body.energy(sim.R, sim.w)
    scale = np.abs(E).max() + body.kinetic(sim.w).max()
    assert np.abs(E - E[:, :1]).max() < 1e-8 * scale
    assert sim.max_drift < 1e-8
    np.testing.assert_allclose(physics.orthogonality_drift(sim.R), 0, atol=1e-13)  # projected


def test_free_so3_body_conserves_angular_momentum():
    rng = np.random.default_rng(8)
    body = RigidBodySO3(J=J_PAPER)
    sim = simulate_so3(body, rand_rot(rng, 6), 2 * rng.standard_normal((6, 3)), times(0.1, 100))
    L_body = sim.w * np.asarray(J_PAPER)  # J w in the body frame
    L_space = (sim.R @ L_body[..., None])[..., 0]  # R J w in the world frame
    np.testing.assert_allclose(
        np.linalg.norm(L_body, axis=-1), np.linalg.norm(L_body[:, :1], axis=-1).repeat(101, 1), rtol=1e-8
    )
    np.testing.assert_allclose(L_space, np.broadcast_to(L_space[:, :1], L_space.shape), atol=1e-8)


def test_se3_energy_conserved_and_centre_of_mass_parabola_without_damping():
    rng = np.random.default_rng(9)
    body = RigidBodySE3(J=J_PAPER, m=0.5, rho=RHO, g=9.81)
    n, h = 6, 0.05
    sim = simulate_se3(
        body,
        rand_rot(rng, n),
        rng.standard_normal((n, 3)),
        rng.standard_normal((n, 3)),
        rng.standard_normal((n, 3)),
        times(h, 60),
    )
    E = body.energy(sim.R, sim.p, sim.w, sim.v)
    assert np.abs(E - E[:, :1]).max() < 1e-8 * (np.abs(E).max() + 1.0)
    c = body.centre_of_mass(sim.R, sim.p)
    acc = (c[:, 2:] - 2 * c[:, 1:-1] + c[:, :-2]) / h**2  # exact for a parabola up to rounding
    np.testing.assert_allclose(acc, np.broadcast_to([0, 0, -9.81], acc.shape), atol=1e-5)


def test_energy_strictly_decreases_with_damping_so3():
    rng = np.random.default_rng(10)
    for g in (9.81, 0.0):
        body = RigidBodySO3(J=J_PAPER, m=0.5, rho=RHO, g=g, D=[0.1] * 3)
        sim = simulate_so3(body, rand_rot(rng, 6), 1 + rng.standard_normal((6, 3)), times(0.05, 100))
        assert (np.diff(body.energy(sim.R, sim.w), axis=1) < 0).all()


def test_energy_strictly_decreases_with_damping_se3():
    rng = np.random.default_rng(11)
    body = RigidBodySE3(J=J_PAPER, m=0.5, rho=RHO, g=9.81, D=[0.1, 0.1, 0.1, 0.0, 0.0, 0.0])
    sim = simulate_se3(
        body,
        rand_rot(rng, 6),
        rng.standard_normal((6, 3)),
        1 + rng.standard_normal((6, 3)),
        rng.standard_normal((6, 3)),
        times(0.05, 100),
    )
    assert (np.diff(body.energy(sim.R, sim.p, sim.w, sim.v), axis=1) < 0).all()


def test_rk45_and_dop853_agree():
    rng = np.random.default_rng(12)
    body = RigidBodySE3(J=J_PAPER, m=0.5, rho=RHO, g=9.81, D=[0.1, 0.1, 0.1, 0, 0, 0])
    args = (
        rand_rot(rng, 4),
        rng.standard_normal((4, 3)),
        rng.standard_normal((4, 3)),
        rng.standard_normal((4, 3)),
        times(0.05, 40),
    )
    a = simulate_se3(body, *args, solver={"method": "RK45", "rtol": 1e-10, "atol": 1e-12})
    b = simulate_se3(body, *args, solver=SolverOptions("DOP853", 1e-12, 1e-13))
    np.testing.assert_allclose(a.R, b.R, atol=1e-8)
    np.testing.assert_allclose(a.p, b.p, atol=1e-7)


def test_drift_beyond_threshold_raises():
    rng = np.random.default_rng(13)
    body = RigidBodySO3(J=J_PAPER)
    with pytest.raises(SimulationError, match="drifted off SO"):
        simulate_so3(
            body,
            rand_rot(rng, 2),
            3 * rng.standard_normal((2, 3)),
            times(0.1, 100),
            solver={"method": "RK45", "rtol": 1e-3, "atol": 1e-6},
        )
