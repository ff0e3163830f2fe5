"""Structured potentials: uniform_gravity (closed-form gradient vs autodiff, equal to the scenes' true
gravity at the true parameters, shared m / rho_COM), lists of parts, and what `model.potential=auto`
chooses from the data's declarations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.commands.train import count_parameters
from liedfl_cli.config.schema import validate
from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.mechanics.potentials import (
    GravityPotential,
    MLPPotential,
    SumPotential,
    UniformGravityPotential,
    left_gradient,
)
from liedfl_cli.models.base import BuildContext
from liedfl_cli.models.liedflnn.model import LieDFLNN

GROUPS = [ProductGroup(0, 1), ProductGroup(1, 0), ProductGroup(1, 2), ProductGroup(2, 1)]


def random_pose(G: ProductGroup, n: int, seed: int = 0) -> Pose:
    gen = torch.Generator().manual_seed(seed)
    return Pose(
        so3.exp(2.0 * torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )


def model_with_gravity(G: ProductGroup, learn_direction: bool = False, seed: int = 0) -> LieDFLNN:
    m = LieDFLNN(G, 0.05, potential="uniform_gravity", forces=(), learn_gravity_direction=learn_direction, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    return m


@pytest.mark.parametrize("learn_direction", [False, True])
@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_uniform_gravity_gradient_closed_form_equals_autodiff(G, learn_direction):
    V = model_with_gravity(G, learn_direction).potential
    g = random_pose(G, 7, seed=3)
    closed = V.left_gradient(g)
    auto = left_gradient(V, G, g)
    assert closed.shape == (7, G.dim)
    torch.testing.assert_close(closed, auto, rtol=1e-12, atol=1e-12)
    # and against a central finite difference of V(g exp(t e_i)) in each tangent direction
    eps = 1e-6
    fd = torch.stack(
        [
            (V(G.perturb(g, eps * e)) - V(G.perturb(g, -eps * e))) / (2 * eps)
            for e in torch.eye(G.dim, dtype=torch.float64)
        ],
        -1,
    )
    torch.testing.assert_close(closed, fd, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_uniform_gravity_at_the_true_parameters_is_the_scenes_gravity(G):
    """m g e3.(p + R rho) per SE(3) body and the pivot form m g e3.R rho per SO(3) body."""
    gen = torch.Generator().manual_seed(5)
    masses = 0.5 + torch.rand(G.n_bodies, generator=gen, dtype=torch.float64)
    rhos = torch.randn(G.n_bodies, 3, generator=gen, dtype=torch.float64)
    truth = GravityPotential(G, masses, rhos, 9.81)
    m = LieDFLNN(G, 0.05, potential="uniform_gravity", forces=(), gravity=9.81)
    with torch.no_grad():
        if G.n_se3:
            m.mass.set_value(masses[: G.n_se3])
            m.rho.copy_(rhos[: G.n_se3])
        if G.n_so3:
            m.potential.moment.copy_(masses[G.n_se3 :, None] * rhos[G.n_se3 :])
    g = random_pose(G, 9, seed=2)
    torch.testing.assert_close(m.potential(g), truth(g), rtol=1e-13, atol=1e-12)


def test_uniform_gravity_shares_mass_and_centre_of_mass_with_the_kinetic_term():
    G = ProductGroup(1, 1)
    m = LieDFLNN(G, 0.05, potential=["uniform_gravity", "mlp"], forces=("rayleigh",), mlp_width=8, mlp_depth=1)
    grav = m.potential.terms[0]
    assert grav.mass is m.mass and grav.rho is m.rho
    # counted once: J_d 12, m 1, rho 3, pivot moment 3, MLP (21*8+8 + 8+1 = 185), D 9*10/2 + 9 = 54
    assert count_parameters(m) == 12 + 1 + 3 + 3 + 185 + 54
    comps = m.components()
    assert comps[3].startswith("V:uniform_gravity") and comps[3].endswith("(188)"), comps
    # the state dict round-trips into a fresh model (the shared tensors appear under both names)
    fresh = LieDFLNN(G, 0.05, potential=["uniform_gravity", "mlp"], forces=("rayleigh",), mlp_width=8, mlp_depth=1)
    with torch.no_grad():
        m.rho.add_(1.0)
    fresh.load_state_dict(m.state_dict())
    assert fresh.potential.terms[0].rho is fresh.rho
    torch.testing.assert_close(fresh.rho, m.rho)
    # a gradient through the potential reaches the kinetic term's mass and centre of mass
    g = random_pose(G, 4)
    m.potential(g).sum().backward()
    assert m.mass.log_x.grad.abs().sum() > 0 and m.rho.grad.abs().sum() > 0


@pytest.mark.parametrize("G", [ProductGroup(1, 0), ProductGroup(1, 2)], ids=lambda G: G.name)
def test_residual_fast_equals_generic_with_structured_potentials(G):
    a = LieDFLNN(G, 0.05, potential=["uniform_gravity", "mlp"], forces=("rayleigh",), mlp_width=8, mlp_depth=2)
    b = LieDFLNN(G, 0.05, potential=["uniform_gravity", "mlp"], forces=("rayleigh",), mlp_width=8, mlp_depth=2)
    b.residual_mode = "generic"
    with torch.no_grad():
        for p in a.parameters():
            p.add_(0.2 * torch.randn_like(p))
    b.load_state_dict(a.state_dict())
    g0 = random_pose(G, 5, seed=1)
    step = lambda g, s: G.compose(g, G.exp(0.05 * torch.randn(5, G.dim, dtype=torch.float64, generator=s)))
    s = torch.Generator().manual_seed(9)
    g1 = step(g0, s)
    g2 = step(g1, s)
    torch.testing.assert_close(a.residual(g0, g1, g2), b.residual(g0, g1, g2), rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------- options and auto
def ctx(G, physics=None, metadata=None) -> BuildContext:
    return BuildContext(G, 0.05, physics=physics, metadata=metadata or {}, forces={"rayleigh": {}})


@pytest.mark.parametrize(
    ("choice", "kinds"),
    [
        ("none", []),
        ("mlp", [MLPPotential]),
        ("uniform_gravity", [UniformGravityPotential]),
        (["uniform_gravity", "mlp"], [UniformGravityPotential, MLPPotential]),
    ],
)
def test_potential_options(choice, kinds):
    m = LieDFLNN.from_config(ctx(ProductGroup(1, 1), {"g": 9.81}), potential=choice, mlp_width=8)
    V = m.potential
    got = [] if V is None else [type(t) for t in V.terms] if isinstance(V, SumPotential) else [type(V)]
    assert got == kinds


@pytest.mark.parametrize("bad", ["gravity", ["mlp", "mlp"], ["none"], [], ["uniform_gravity", "spring"]])
def test_bad_potential_options_are_one_line_config_errors(bad):
    with pytest.raises(ConfigError, match="model.potential") as e:
        LieDFLNN.from_config(ctx(ProductGroup(1, 0), {"g": 9.81}), potential=bad)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("G", "physics", "metadata", "parts", "why"),
    [
        (ProductGroup(0, 1), {"g": 0.0}, {}, [], "free body"),
        (ProductGroup(0, 1), {"g": 9.81}, {}, ["uniform_gravity"], "gravity g = 9.81"),
        (ProductGroup(1, 0), {"g": 9.81}, {}, ["uniform_gravity"], "gravity g = 9.81"),
        (ProductGroup(1, 1), {"g": 9.81, "interaction": {"kind": "spring"}}, {}, ["uniform_gravity", "mlp"], "inter"),
        (ProductGroup(1, 1), {"g": 0.0}, {}, [], "no interaction"),
        # nothing declared (real recordings, a user's file): no learned potential, the overrides named
        (ProductGroup(1, 22), None, {}, [], "model.potential=mlp learns one"),
        (ProductGroup(0, 1), None, {}, [], "dataset.gravity=9.81 declares"),
        (ProductGroup(0, 1), None, {"potential": "none"}, [], "declare no potential"),
        (ProductGroup(0, 2), None, {"gravity": 3.7}, ["uniform_gravity"], "g = 3.7"),
        (ProductGroup(0, 1), None, {"gravity": 0}, [], "free body"),
    ],
)
def test_auto_reads_the_data_and_says_what_it_chose(G, physics, metadata, parts, why):
    c = ctx(G, physics, metadata)
    got, reason = c.resolve_potential_parts("auto")
    assert list(got) == parts and why in reason
    m = LieDFLNN.from_config(c, potential="auto", mlp_width=8)
    assert m.notes and m.notes[0].startswith("potential: auto: ") and why in m.notes[0]
    if "uniform_gravity" in parts:
        grav = m.potential.terms[0] if isinstance(m.potential, SumPotential) else m.potential
        expect = (physics or {}).get("g", metadata.get("gravity"))
        assert float(grav.gravity) == pytest.approx(expect)
    # the baselines' view of auto (MLP or nothing)
    assert c.resolve_potential("auto") == ("mlp" if parts else "none")
    with pytest.raises(ConfigError):
        c.resolve_potential("uniform_gravity")


def test_known_potential_with_auto_builds_no_learned_potential():
    phys = {"J": [1.5, 1.4, 1.2], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1, 0.1, 0.1]}
    m = LieDFLNN.from_config(ctx(ProductGroup(0, 1), phys), potential="auto", known=["potential"])
    assert isinstance(m.potential, GravityPotential) and "model.known" in m.notes[0]
    with pytest.raises(ConfigError, match="choose one"):
        LieDFLNN.from_config(ctx(ProductGroup(0, 1), phys), potential="uniform_gravity", known=["potential"])


@pytest.mark.parametrize(
    "override",
    ["model.potential=uniform_gravity", "model.potential=[uniform_gravity,mlp]", "model.learn_gravity_direction=true"],
)
def test_potential_overrides_compose_and_validate(override, tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"paths.data_dir={tmp_path}", "dataset=heavy_se3", override])
    validate(cfg)


def test_a_misspelled_potential_in_a_list_is_rejected(tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"paths.data_dir={tmp_path}", "model.potential=[uniform,mlp]"])
    with pytest.raises(ConfigError, match=r"model.potential=\['uniform', 'mlp'\]: unknown part 'uniform'"):
        validate(cfg)


# ----------------------------------------------------------------------------- identifiability and recovery
def _heavy_se3(D):
    from omegaconf import OmegaConf

    from liedfl_cli.cli import CONF_DIR
    from liedfl_cli.data.scenes import generate

    c = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "dataset" / "heavy_se3.yaml"))
    c.pop("defaults", None)
    c.update(n_trajectories=8, steps=20, train_steps=20, rollout_steps=20, n_test=1)
    c["physics"]["D"] = D
    return generate(c)


@pytest.mark.parametrize(("D", "identifiable"), [([0.1, 0.1, 0.1, 0.0, 0.0, 0.0], False), ([0.1] * 6, True)])
def test_the_mass_is_identifiable_only_when_translation_and_rotation_couple(D, identifiable):
    """Exp 3's scene (damping on the rotation only): the centre of mass falls freely and the rotation about
    it is torque-free and damped by a pure torque, so the DEL residual of the true scheme does not depend
    on m (J_d, rho, D fixed); with translational damping at the body origin it does."""
    from liedfl_cli.models.true_scheme import true_model

    ds = _heavy_se3(D)
    ref = true_model(ds)
    m = LieDFLNN(ds.group, ds.h, potential="uniform_gravity", forces=("rayleigh",), gravity=9.81)
    m.load_state_dict(ref.state_dict(), strict=False)
    data = ds.pose()
    g0, g1, g2 = (data.index((slice(None), slice(a, a + 18))) for a in range(3))
    loss = []
    with torch.no_grad():
        torch.testing.assert_close(m.residual(g0, g1, g2), ref.residual(g0, g1, g2), rtol=1e-10, atol=1e-12)
        for f in (1.0, 3.0):
            m.mass.set_value(ref.mass() * f)
            loss.append(float((m.residual(g0, g1, g2) ** 2).mean()))
    if identifiable:
        assert loss[1] > 1e3 * loss[0]
    else:
        assert loss[1] == pytest.approx(loss[0], rel=1e-5)


def test_recovery_reports_pivot_moments_and_field_direction():
    from omegaconf import OmegaConf

    from liedfl_cli.cli import CONF_DIR
    from liedfl_cli.config.recovery import parameter_recovery
    from liedfl_cli.data.scenes import generate
    from liedfl_cli.models.true_scheme import true_model

    c = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "dataset" / "heavy_so3.yaml"))
    c.pop("defaults", None)
    c.update(n_trajectories=4, steps=10, train_steps=10, rollout_steps=10)
    ds = generate(c)
    m = LieDFLNN(ds.group, ds.h, potential="uniform_gravity", forces=("rayleigh",), learn_gravity_direction=True)
    m.load_state_dict(true_model(ds).state_dict(), strict=False)
    with torch.no_grad():
        m.potential.moment.copy_(0.5 * torch.tensor([[0.0, 0.5, 1.0]], dtype=torch.float64))
    rec = parameter_recovery(m, ds)
    assert rec["pivot_moment_over_trace_rel_error"] < 1e-12 and rec["gravity_direction_error_rad"] < 1e-7
    with torch.no_grad():
        m.potential.moment.mul_(1.1)
        m.potential.direction_raw.copy_(torch.tensor([0.0, 0.1, 1.0], dtype=torch.float64))
    rec = parameter_recovery(m, ds)
    assert rec["pivot_moment_over_trace_rel_error"] == pytest.approx(0.1, rel=1e-9)
    assert rec["gravity_direction_error_rad"] == pytest.approx(float(np.arctan(0.1)), rel=1e-9)


@pytest.mark.parametrize("n_se3,n_so3", [(0, 1), (1, 0), (2, 3)])
def test_declared_gravity_left_gradient_in_closed_form_equals_autodiff(n_se3, n_so3):
    """`GravityPotential.left_gradient` (the declared scenes' gravity: the true scheme's potential) against
    the generic autodiff `left_gradient` and against d/d eta of V(g exp(eta)), through both covector paths."""
    from liedfl_cli.lie import ProductGroup
    from liedfl_cli.mechanics.potentials import GravityPotential, left_gradient
    from liedfl_cli.models.liedflnn.engines import maps as fused_maps
    from liedfl_cli.models.liedflnn.model import LieDFLNN

    G = ProductGroup(n_se3, n_so3)
    gen = torch.Generator().manual_seed(3)
    B = G.n_bodies
    V = GravityPotential(G, 0.5 + torch.rand(B, generator=gen, dtype=torch.float64),
                         torch.randn(B, 3, generator=gen, dtype=torch.float64), 9.81)  # fmt: skip
    g = G.exp(torch.randn(6, G.dim, generator=gen, dtype=torch.float64))
    closed = V.left_gradient(g)
    assert float(closed.abs().max()) > 0.1
    assert torch.allclose(closed, left_gradient(V, G, g), rtol=1e-12, atol=1e-13)
    eta = torch.zeros(6, G.dim, dtype=torch.float64)
    ref = torch.func.grad(lambda e: V(G.perturb(g, e)).sum())(eta)
    assert torch.allclose(closed, ref, rtol=1e-12, atol=1e-13)
    model = LieDFLNN(G, 0.05, potential=[], forces=[])
    model.potential = V
    assert torch.allclose(model.potential_covector(g), -0.05 * ref, rtol=1e-12, atol=1e-13)
    assert torch.allclose(fused_maps.potential_covector(model, g), -0.05 * ref, rtol=1e-12, atol=1e-13)
