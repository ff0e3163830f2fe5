"""Two-body scene (SE(3) x SO(3)): ground-truth physics, invariants, data layout and the discrete
scheme with the true parameters (fast == generic residual, O(h^3) residual, O(h^2) rollout)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from liedfl_cli.data import ConfigError, generate, load_dataset, save_dataset
from liedfl_cli.data.physics_multibody import MultiBodySystem, simulate_multibody
from liedfl_cli.data.scenes_multibody import two_body_physics, two_body_system
from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.mechanics.potentials import INTERACTIONS, InteractionPotential
from liedfl_cli.models.true_scheme import physics_model, true_model
from liedfl_cli.solvers.options import SolverOptions

CONF = Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf" / "dataset"
G = ProductGroup(1, 1)
TIGHT = {"method": "DOP853", "rtol": 1e-12, "atol": 1e-12}
J2 = [[1.521, 1.362, 1.211], [0.9, 0.8, 0.6]]
RHO2 = [[0.0, 0.5, 1.0], [0.0, 0.0, -0.8]]


def config(**over) -> dict:
    c = OmegaConf.to_container(OmegaConf.load(CONF / "two_body.yaml"))
    c.pop("defaults", None)
    c.update(n_trajectories=4, steps=8, train_steps=6, rollout_steps=8, n_test=1)
    c.update(over)
    return c


def physics(kind: str, g: float = 9.81, D: float = 0.0) -> dict:
    """Physics of the two_body scene with interaction `kind` (geometry kept apart from singularities)."""
    c = config()
    c["interaction"].update(
        kind=kind, mu={"spring": 10.0, "newton": 2.0, "dipole": 0.05}.get(kind, 3.0), moment2=[1.0, 0.0, 0.0]
    )
    c["physics"]["g"], c["physics"]["D"] = g, [D] * 9
    return two_body_physics(c)


def initial(system: MultiBodySystem, T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    R0 = so3.exp(torch.from_numpy(0.4 * rng.standard_normal((T, system.G.n_bodies, 3)))).numpy()
    p0 = np.array([0.0, 0.0, -2.6]) + 0.2 * rng.standard_normal((T, system.G.n_se3, 3))
    if system.G.n_se3 == 2:
        p0[:, 1] = np.array([0.0, 0.0, 0.6]) + 0.2 * rng.standard_normal((T, 3))
    xi0 = 0.6 * rng.standard_normal((T, system.G.dim))
    return R0, p0, xi0


# ------------------------------------------------------------------ continuous ground truth
@pytest.mark.parametrize("kind", INTERACTIONS)
def test_conservative_wrench_is_minus_left_gradient(kind):
    """The autodiff wrench (-2 vee(R^T dV/dR), -R^T dV/dp) equals finite differences of V(g exp(eta))."""
    system = two_body_system(physics(kind))
    R0, p0, _ = initial(system, 3)
    F = system.conservative_covector(R0, p0)
    g = Pose(torch.from_numpy(R0), torch.from_numpy(p0))
    eps = 1e-6
    for i in range(G.dim):
        e = torch.zeros(3, G.dim, dtype=torch.float64)
        e[:, i] = eps
        gp, gm = G.retract(g, e), G.retract(g, -e)
        fd = -(system.potential(gp.R.numpy(), gp.p.numpy()) - system.potential(gm.R.numpy(), gm.p.numpy())) / (2 * eps)
        np.testing.assert_allclose(F[:, i], fd, rtol=1e-6, atol=1e-7)


def test_interaction_values_by_hand():
    """Each potential at a configuration where it can be evaluated on paper."""
    Gp = ProductGroup(1, 1)
    R = torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3).clone()
    Rz = so3.exp(torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
    R[0, 1] = Rz
    g = Pose(R, torch.tensor([[[0.0, 0.0, -2.0]]], dtype=torch.float64))
    kw = dict(
        r1=[0, 0, 0.5],
        r2=[0, 0, -1.0],
        moment1=[0, 0, 1.0],
        moment2=[0, 0, 1.0],
        masses=[2.0, 3.0],
        rhos=[[0, 0, 0], [0, 0, -1.0]],
    )
    V = lambda kind, mu=1.5: float(InteractionPotential(Gp, kind, mu, **kw)(g))
    assert V("spring") == pytest.approx(0.5 * 1.5 * 0.5**2)  # X1 = (0,0,-1.5), X2 = (0,0,-1)
    assert V("relative_rotation") == pytest.approx(0.5 * 1.5 * 0.25)
    assert V("relative_rotation_trace") == pytest.approx(1.5 * (3 - (1 + 2 * np.cos(0.5))))
    assert V("newton") == pytest.approx(-1.5 * 6.0 / 1.0)  # c1 = (0,0,-2), c2 = (0,0,-1)
    # coaxial dipoles along e3 at distance 0.5: mu/r^3 (1 - 3) = -2 mu / r^3
    assert V("dipole") == pytest.approx(-2 * 1.5 / 0.5**3)


@pytest.mark.parametrize("kind", INTERACTIONS)
def test_energy_conserved_without_damping(kind):
    system = two_body_system(physics(kind))
    R0, p0, xi0 = initial(system, 2)
    # DOP853 (8th order) reaches rtol 1e-10 in 2-4x fewer evaluations than RK45; both stay ~1e-10 from E(0)
    sim = simulate_multibody(
        system, R0, p0, xi0, 0.05 * np.arange(41), {"method": "DOP853", "rtol": 1e-10, "atol": 1e-12}
    )
    E = system.energy(sim.R, sim.p, sim.w)
    assert np.ptp(system.kinetic(sim.w)) > 1e-2  # the bodies do exchange energy with the potential
    np.testing.assert_allclose(E, E[:, :1] * np.ones_like(E), rtol=0, atol=1e-8 * np.abs(E).max())


def test_damping_dissipates_at_the_rate_of_its_power():
    system = two_body_system(physics("spring", D=0.1))
    R0, p0, xi0 = initial(system, 2, seed=1)
    t = 0.02 * np.arange(51)
    sim = simulate_multibody(system, R0, p0, xi0, t, TIGHT)
    E = system.energy(sim.R, sim.p, sim.w)
    P = system.power(sim.R, sim.p, sim.w)
    assert (P <= 0).all() and (np.diff(E, axis=1) < 0).all()
    # E(t_end) - E(0) = int P dt (Simpson's rule on the samples)
    from scipy.integrate import simpson

    np.testing.assert_allclose(E[:, -1] - E[:, 0], simpson(P, x=t, axis=1), rtol=1e-5)


@pytest.mark.parametrize("kind", ["spring", "relative_rotation", "newton", "dipole"])
def test_linear_momentum_of_an_isolated_se3_pair(kind):
    """SE(3) x SE(3), g = 0, no damping: every interaction depends on relative positions only,
    so the total linear momentum sum_i R_i P_i is conserved exactly."""
    inter = physics(kind)["interaction"]
    system = MultiBodySystem(("se3", "se3"), J2, [0.5, 1.0], RHO2, 0.0, None, inter)
    R0, p0, xi0 = initial(system, 2, seed=2)
    sim = simulate_multibody(system, R0, p0, xi0, 0.05 * np.arange(31), TIGHT)
    lin, ang = system.world_momentum(sim.R, sim.p, sim.w)
    assert np.abs(np.diff(lin[:, [0, -1]], axis=1)).max() < 1e-9 * max(1.0, np.abs(lin).max())
    assert np.ptp(sim.p[:, :, 0, 0]) > 1e-2  # the bodies move
    np.testing.assert_allclose(ang, ang[:, :1] * np.ones_like(ang), atol=1e-8)  # and angular momentum too


@pytest.mark.parametrize("kind", INTERACTIONS)
def test_angular_momentum_about_the_pivot(kind):
    """Scene layout SE(3) x SO(3) with g = 0, no damping: V_int is invariant under a rotation of the
    whole system about the pivot (R_i -> Q R_i, p_1 -> Q p_1), so the total angular momentum about
    the pivot is conserved (linear momentum is not: the pivot pushes)."""
    system = two_body_system(physics(kind, g=0.0))
    R0, p0, xi0 = initial(system, 2, seed=3)
    sim = simulate_multibody(system, R0, p0, xi0, 0.05 * np.arange(16), TIGHT)  # before any close encounter
    _, ang = system.world_momentum(sim.R, sim.p, sim.w)
    np.testing.assert_allclose(ang, ang[:, :1] * np.ones_like(ang), atol=1e-8 * max(1.0, np.abs(ang).max()))


# ------------------------------------------------------------------ scene and data file
def test_two_body_scene_layout_and_roundtrip(tmp_path):
    ds = generate(config())
    assert ds.R.shape == (4, 9, 2, 3, 3) and ds.p.shape == (4, 9, 1, 3)
    assert ds.body_kinds == ["se3", "so3"] and (ds.n_se3, ds.n_so3) == (1, 1)
    assert ds.extras["omega"].shape == (4, 9, 2, 3) and ds.extras["v"].shape == (4, 9, 1, 3)
    ph = ds.params["physics"]
    assert ph["interaction"]["kind"] == "spring" and ph["bodies"] == ["se3", "so3"]
    path = save_dataset(ds, tmp_path / "tb.h5")
    back = load_dataset(path)
    assert (back.n_se3, back.n_so3) == (1, 1) and back.params["physics"] == ph
    import h5py

    with h5py.File(path) as f:
        assert (int(f.attrs["n_se3"]), int(f.attrs["n_so3"])) == (1, 1)
    # the true-parameter scheme is built from the file alone and nearly solves the data
    ref = true_model(back)
    traj = back.pose()
    r = ref.residual(
        traj.index((slice(None), slice(0, -2))),
        traj.index((slice(None), slice(1, -1))),
        traj.index((slice(None), slice(2, None))),
    )
    assert r.abs().max() < 5e-3


def test_two_body_config_errors():
    with pytest.raises(ConfigError, match="interaction.kind"):
        generate(config(interaction=dict(config()["interaction"], kind="glue")))
    with pytest.raises(ConfigError, match="dataset.interaction"):
        c = config()
        del c["interaction"]["r2"]
        generate(c)
    with pytest.raises(ConfigError, match="physics.D"):
        c = config()
        c["physics"]["D"] = [0.1] * 6
        generate(c)


# ------------------------------------------------------------------ discrete scheme, true parameters
def random_triplet(n=5, step=0.08, seed=0):
    gen = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.randn(*s, generator=gen, dtype=torch.float64)
    g0 = Pose(so3.exp(0.5 * rnd(n, 2, 3)), torch.tensor([0.0, 0.0, -2.6], dtype=torch.float64) + 0.2 * rnd(n, 1, 3))
    g1 = G.retract(g0, step * rnd(n, G.dim))
    return g0, g1, G.retract(g1, step * rnd(n, G.dim))


@pytest.mark.parametrize("kind", INTERACTIONS)
def test_fast_residual_equals_generic_on_two_body(kind):
    model = physics_model(G, 0.05, physics(kind, D=0.07))
    assert len(model.forces) == 1 and model.potential is not None
    g0, g1, g2 = random_triplet()
    fast = model.residual(g0, g1, g2)
    model.residual_mode = "generic"
    generic = model.residual(g0, g1, g2)
    assert fast.abs().max() > 1e-3
    torch.testing.assert_close(fast, generic, rtol=0, atol=1e-10)


_EXACT: dict[str, Pose] = {}


def exact(ph: dict, h: float, final_time: float, T: int = 2, seed: int = 4) -> Pose:
    """The two-body system sampled at h up to final_time (DOP853, tolerance 1e-13): computed once per
    argument set in a test process (the order tests below share their trajectories; nothing changes them)."""
    key = repr((ph, h, final_time, T, seed))
    if key not in _EXACT:
        _EXACT[key] = _exact(ph, h, final_time, T, seed)
    return _EXACT[key]


def _exact(ph: dict, h: float, final_time: float, T: int, seed: int) -> Pose:
    system = two_body_system(ph)
    R0, p0, xi0 = initial(system, T, seed)
    t = h * np.arange(round(final_time / h) + 1)
    sim = simulate_multibody(system, R0, p0, xi0, t, {"method": "DOP853", "rtol": 1e-13, "atol": 1e-13})
    return Pose(torch.from_numpy(sim.R), torch.from_numpy(sim.p))


def test_residual_is_third_order_on_two_body():
    ph = physics("spring", D=0.1)
    hs, res = (0.04, 0.02, 0.01), []
    for h in hs:
        traj = exact(ph, h, 0.4)
        r = physics_model(G, h, ph).residual(
            traj.index((slice(None), slice(0, -2))),
            traj.index((slice(None), slice(1, -1))),
            traj.index((slice(None), slice(2, None))),
        )
        res.append(float(r.abs().max()))
    order = np.polyfit(np.log(hs), np.log(res), 1)[0]
    assert 2.7 < order < 3.3, (res, order)


def test_rollout_is_second_order_on_two_body():
    """Over 0.4 s (the trajectories of the residual test above): measured order 1.97 (1.98 over 0.8 s)."""
    ph = physics("spring", D=0.1)
    hs, errs = (0.04, 0.02, 0.01), []
    for h in hs:
        traj = exact(ph, h, 0.4)
        ro = physics_model(G, h, ph).rollout(
            traj.index((slice(None), 0)),
            traj.index((slice(None), 1)),
            traj.R.shape[1] - 1,
            SolverOptions(tol=1e-12, max_iter=20),
        )
        assert ro.n_failed == 0
        e = torch.linalg.matrix_norm(ro.pose.R[:, -1] - traj.R[:, -1]).max()
        e = max(float(e), float(torch.linalg.vector_norm(ro.pose.p[:, -1] - traj.p[:, -1], dim=-1).max()))
        errs.append(e)
        assert float(so3.orthogonality_error(ro.pose.R).max()) < 1e-12
    order = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert 1.8 < order < 2.2, (errs, order)
