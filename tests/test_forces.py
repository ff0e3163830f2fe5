"""Learned forces (rayleigh, rayleigh_nonlinear, nn, control): structure, Jacobians, residual paths,
config composition, and the dissipation of structured damping in the discrete scheme."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.mechanics import kinetic
from liedfl_cli.mechanics.forces import FORCES, RayleighForce, RayleighNonlinearForce, build_forces, force_jacobian_xi
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.newton import jacobian
from liedfl_cli.solvers.options import SolverOptions

ROOT = Path(__file__).resolve().parents[1]
GROUPS = [ProductGroup(0, 1), ProductGroup(1, 0), ProductGroup(1, 1), ProductGroup(2, 1)]
PHYS2 = {
    "J": [[1.521, 1.362, 1.211], [0.9, 0.8, 0.6]],
    "m": [0.5, 1.0],
    "rho": [[0.0, 0.5, 1.0], [0.0, 0.0, -0.8]],
    "g": 0.0,
    "D": [0.0] * 9,
}


def random_pose(G, n, seed=0, step=None):
    gen = torch.Generator().manual_seed(seed)
    return Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )


def randomise(module, scale=0.5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen, dtype=p.dtype))


# ------------------------------------------------------------------ structure
def test_registry_keys_are_the_config_option_names():
    confs = {p.stem for p in (ROOT / "liedfl_cli" / "conf" / "force").glob("*.yaml")} - {"none"}
    assert confs == set(FORCES)
    for name in FORCES:
        first = (ROOT / "liedfl_cli" / "conf" / "force" / f"{name}.yaml").read_text().splitlines()[0]
        assert first == f"# @package force.{name}"


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_damping_matrices_are_symmetric_psd(G):
    ray = RayleighForce(G)
    nl = RayleighNonlinearForce(G, init_diag=0.05, width=16, depth=2)
    for seed in range(3):
        randomise(ray, 2.0, seed)
        randomise(nl, 2.0, seed)
        g = random_pose(G, 20, seed)
        for D in (ray.D()[None], nl.D(g)):
            assert torch.equal(D, D.transpose(-1, -2))  # symmetric by construction, on any CPU
            assert torch.linalg.eigvalsh(D).min() >= -1e-10 * D.abs().max()
        xi = torch.randn(20, G.dim, dtype=torch.float64)
        for f in (ray, nl):  # dissipative: F . xi <= 0
            power = (f(g, xi) * xi).sum(-1)
            scale = f(g, xi).norm(dim=-1) * xi.norm(dim=-1)
            assert (power <= 1e-12 * scale).all()


@pytest.mark.parametrize("name", sorted(FORCES))
def test_closed_form_force_jacobians_match_autodiff(name):
    G = ProductGroup(1, 1)
    (force,) = build_forces(G, {name: {"width": 16, "depth": 2}} if name != "rayleigh" else [name], scale=2.0)
    randomise(force, 0.3)
    g = random_pose(G, 5)
    xi = torch.randn(5, G.dim, dtype=torch.float64)
    ref = jacobian(lambda x: force(g, x), xi)
    torch.testing.assert_close(force_jacobian_xi(force, g, xi), ref, rtol=1e-10, atol=1e-12)


def full_model(G, h=0.05, seed=0):
    forces = {
        "rayleigh": {},
        "rayleigh_nonlinear": {"width": 16, "depth": 2},
        "nn": {"width": 16, "depth": 2},
        "control": {"width": 16, "depth": 2},
    }
    torch.manual_seed(seed)
    m = LieDFLNN(G, h, potential="mlp", forces=forces, mlp_width=16, mlp_depth=2, init_jitter=0.3, seed=seed)
    for f in m.forces:
        randomise(f, 0.2, seed)
    return m


@pytest.mark.parametrize("G", [ProductGroup(1, 1), ProductGroup(0, 2)], ids=lambda G: G.name)
def test_fast_residual_and_newton_jacobian_equal_generic_with_every_force(G):
    model = full_model(G)
    g0 = random_pose(G, 4, 1)
    g1 = G.retract(g0, 0.1 * torch.randn(4, G.dim, dtype=torch.float64))
    g2 = G.retract(g1, 0.1 * torch.randn(4, G.dim, dtype=torch.float64))
    fast = model.residual(g0, g1, g2)
    inc = G.increment(g1, g2)
    J_fast = model.jacobian_var(g1, inc)
    model.residual_mode = "generic"
    torch.testing.assert_close(fast, model.residual(g0, g1, g2), rtol=0, atol=1e-10)
    torch.testing.assert_close(J_fast, model.jacobian_var(g1, inc), rtol=0, atol=1e-9)


def test_hydra_force_list_composes_a_sum(tmp_path):
    """`liedfl train 'force=[rayleigh_nonlinear,nn]'` selects both forces; the model adds them."""
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.data import generate

    with initialize_config_dir(config_dir=str(ROOT / "liedfl_cli" / "conf"), version_base="1.3"):
        cfg = compose(
            config_name="train",
            overrides=[
                "experiment=two_body",
                "budget=smoke",
                "force=[rayleigh_nonlinear,nn]",
                f"paths.data_dir={tmp_path}",
                f"paths.output_dir={tmp_path}/run",
            ],
        )
    assert list(cfg.force) == ["rayleigh_nonlinear", "nn"]
    assert cfg.force.nn.width == cfg.model.mlp_width
    c = OmegaConf.to_container(cfg.dataset, resolve=True)
    c.update(n_trajectories=3, steps=4, train_steps=3, rollout_steps=4, n_test=1)
    model = build_model(cfg, generate(c))
    names = [f.name for f in model.forces]
    assert names == ["rayleigh_nonlinear", "nn"]
    comps = model.components()
    assert any(s.startswith("F:rayleigh_nonlinear") for s in comps) and any(s.startswith("F:nn") for s in comps)
    G = model.G
    g0 = random_pose(G, 3)
    g1 = G.retract(g0, 0.05 * torch.randn(3, G.dim, dtype=torch.float64))
    xi = kinetic.velocity_estimate(G, G.increment(g0, g1), model.h)
    total = 0.5 * model.h * (model.forces[0](g0, xi) + model.forces[1](g0, xi))
    torch.testing.assert_close(model.half_force(g0, g1), total)


# ------------------------------------------------------------------ discrete dissipation
def discrete_energy(model, traj: Pose) -> torch.Tensor:
    """E_{k+1/2} = K_d(g_k, g_{k+1}) / h summed over bodies, (T, S): the kinetic discrete Lagrangian
    over h, i.e. per body (tr J_d - tr(W_k J_d)) / h^2 + m |z_k + (W_k - I) rho|^2 / (2 h^2)."""
    G, h = model.G, model.h
    a, b = traj.index((slice(None), slice(0, -1))), traj.index((slice(None), slice(1, None)))
    Jd, m, rho = model._params()
    return kinetic.kinetic_lagrangian(G, G.increment(a, b), Jd, m, rho, h).detach() / h


@pytest.mark.parametrize("damping", ["none", "rayleigh", "rayleigh_nonlinear", "rayleigh_nonlinear_coupled"])
def test_structured_damping_never_gains_discrete_energy(damping):
    """Free bodies SE(3) x SO(3) with the true kinetic Lagrangian of the two_body scene (V = 0).

    Without forces the scheme conserves E_{k+1/2} (`discrete_energy`) to rounding (checked here).
    With F = -D xi~ (D constant SPSD: rayleigh) or F = -D(g) xi~ (D(g) = L(g) L(g)^T varying
    smoothly with g: rayleigh_nonlinear) the discrete work of a step is
    -(h/2) (xi~_{k-1} + xi~_k) . (D_{k-1} xi~_{k-1} + D_k xi~_k) / 2 <= 0 to leading order, and
    E_{k+1/2} never increases. (With a potential no exactly conserved discrete energy exists for
    a fixed-step variational integrator, so there is no per-step statement to test.)
    """
    G = ProductGroup(1, 1)
    model = physics_model(G, 0.05, PHYS2)
    if damping == "rayleigh":
        f = RayleighForce(G, init_diag=0.05)
        randomise(f, 0.1, seed=1)
        model.forces.append(f)
    elif damping.startswith("rayleigh_nonlinear"):
        coupling = "coupled" if damping.endswith("coupled") else "per_body"
        f = RayleighNonlinearForce(G, init_diag=0.05, width=32, depth=2, coupling=coupling)
        with torch.no_grad():  # D(g) varies by ~10x over the visited configurations
            heads = [f.net[-1].weight] if coupling == "coupled" else [f.per_body.w_se3, f.per_body.w_so3]
            for w in heads:
                w.mul_(10.0)
        model.forces.append(f)
    g0 = random_pose(G, 4, 2)
    g1 = G.retract(g0, 0.05 * torch.randn(4, G.dim, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    ro = model.rollout(g0, g1, 80, SolverOptions(tol=1e-12, max_iter=30))
    assert ro.n_failed == 0
    E = discrete_energy(model, ro.pose)
    dE = E[:, 1:] - E[:, :-1]
    if damping == "none":
        assert dE.abs().max() < 1e-11 * E.abs().max()
    else:
        assert dE.max() <= 1e-12 * E.abs().max()
        assert (E[:, -1] < 0.9 * E[:, 0]).all()  # and it does dissipate
