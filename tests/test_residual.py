"""The closed-form fast paths equal the generic autodiff residual; regularity blocks agree."""

import pytest
import torch

from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.mechanics import kinetic
from liedfl_cli.models.del_loss import regularity_penalty
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model

GROUPS = [ProductGroup(0, 1), ProductGroup(1, 0), ProductGroup(1, 2), ProductGroup(2, 1)]


def random_triplet(G, n=6, step=0.2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.randn(*s, generator=gen, dtype=torch.float64)
    g0 = Pose(so3.exp(rnd(n, G.n_bodies, 3)), rnd(n, G.n_se3, 3))
    g1 = G.retract(g0, step * rnd(n, G.dim))
    g2 = G.retract(g1, step * rnd(n, G.dim))
    return g0, g1, g2


def random_model(G, potential, seed=0):
    torch.manual_seed(seed)
    m = LieDFLNN(G, 0.07, potential=potential, forces=["rayleigh"], init_jitter=0.5, seed=seed)
    with torch.no_grad():
        if m.rho is not None:
            m.rho.copy_(torch.randn_like(m.rho))
        m.forces[0].D.L_entries.copy_(0.3 * torch.randn_like(m.forces[0].D.L_entries))
    return m


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
@pytest.mark.parametrize("potential", ["none", "mlp"])
def test_fast_residual_equals_generic(G, potential):
    model = random_model(G, potential)
    g0, g1, g2 = random_triplet(G)
    fast = model.residual(g0, g1, g2)
    model.residual_mode = "generic"
    generic = model.residual(g0, g1, g2)
    assert fast.shape == (6, G.dim)
    assert fast.abs().max() > 1e-3  # a non-trivial residual
    torch.testing.assert_close(fast, generic, rtol=0, atol=1e-10)


@pytest.mark.parametrize("G", [ProductGroup(0, 1), ProductGroup(1, 0)], ids=lambda G: G.name)
def test_true_gravity_model_fast_equals_generic(G):
    physics = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1] * G.dim}
    model = physics_model(G, 0.05, physics)
    g0, g1, g2 = random_triplet(G, step=0.05)
    fast = model.residual(g0, g1, g2)
    model.residual_mode = "generic"
    torch.testing.assert_close(fast, model.residual(g0, g1, g2), rtol=0, atol=1e-10)


def test_so3_fast_path_matches_paper_matrix_form():
    """vee of the paper's skew-matrix equation (SO(3) rigid body, no potential, no force)."""
    G = ProductGroup(0, 1)
    model = LieDFLNN(G, 0.1, potential="none", forces=[], init_jitter=0.4)
    g0, g1, g2 = random_triplet(G)
    Jd = model.inertia.Jd()[0]
    Wk = (g1.R.transpose(-1, -2) @ g2.R)[:, 0]
    Wkm = (g0.R.transpose(-1, -2) @ g1.R)[:, 0]
    A = (Jd @ Wk.transpose(-1, -2) + Jd @ Wkm - Wk @ Jd - Wkm.transpose(-1, -2) @ Jd) / 0.1
    torch.testing.assert_close(model.residual(g0, g1, g2), so3.vee(A), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_kinetic_derivatives_match_finite_differences(G):
    model = random_model(G, "none")
    Jd, m, rho = model._params()
    g0, g1, _ = random_triplet(G, n=2)
    inc = G.increment(g0, g1)
    d1 = kinetic.kinetic_d1(G, inc, Jd, m, rho, model.h)
    d2 = kinetic.kinetic_d2(G, inc, Jd, m, rho, model.h)
    K = lambda a, b: kinetic.kinetic_lagrangian(G, G.increment(G.retract(g0, a), G.retract(g1, b)), Jd, m, rho, model.h)
    eps = 1e-6
    for i in range(G.dim):
        e = torch.zeros(2, G.dim, dtype=torch.float64)
        e[:, i] = eps
        z = torch.zeros_like(e)
        fd1 = (K(e, z) - K(-e, z)) / (2 * eps)
        fd2 = (K(z, e) - K(z, -e)) / (2 * eps)
        torch.testing.assert_close(d1[:, i], fd1, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(d2[:, i], fd2, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_mixed_hessian_closed_form_equals_autodiff(G):
    model = random_model(G, "mlp")
    g0, g1, _ = random_triplet(G, step=0.5)
    fast = model.regularity_logdet(g0, g1)
    H = model.mixed_hessian_autodiff(g0, g1)
    ref = torch.stack([torch.linalg.slogdet(H[..., s, s]).logabsdet for s in G.body_slices()], -1)
    torch.testing.assert_close(fast, ref, rtol=0, atol=1e-9)
    # off-diagonal (inter-body) blocks vanish: the Lagrangian is a sum of per-body terms
    mask = torch.ones(G.dim, G.dim, dtype=torch.bool)
    for s in G.body_slices():
        mask[s, s] = False
    if mask.any():
        assert H[..., mask].abs().max() < 1e-12 * H.abs().max()  # relative: entries ~ J/h


def test_so3_regularity_matches_paper_determinant():
    """|det H| = det(tr(W^T J_d) I - W^T J_d) / h^3 (paper appendix, SO(3) case)."""
    G = ProductGroup(0, 1)
    model = LieDFLNN(G, 0.1, forces=[], init_jitter=0.4)
    g0, g1, _ = random_triplet(G, step=0.3)
    W = (g0.R.transpose(-1, -2) @ g1.R)[:, 0]
    Jd = model.inertia.Jd()[0]
    WtJ = W.transpose(-1, -2) @ Jd
    tr = WtJ.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    ref = torch.log(torch.linalg.det(tr * torch.eye(3, dtype=torch.float64) - WtJ).abs() / 0.1**3)
    torch.testing.assert_close(model.regularity_logdet(g0, g1)[:, 0], ref, rtol=0, atol=1e-10)


def test_regularity_penalties():
    x = torch.tensor([0.0, 5.0, 10.0, 20.0], dtype=torch.float64)
    relu = regularity_penalty(x, 10.0, "relu")
    torch.testing.assert_close(relu, torch.tensor([10.0, 5.0, 0.0, 0.0], dtype=torch.float64))
    gauss = regularity_penalty(torch.tensor([1e6], dtype=torch.float64), 10.0, "gaussian")
    assert torch.isfinite(gauss).all() and gauss.item() == 0.0  # no overflow far above threshold
    peak = regularity_penalty(torch.tensor([10.0], dtype=torch.float64), 10.0, "gaussian")
    assert abs(peak.item() - 1 / (2 * torch.pi) ** 0.5) < 1e-12
    with pytest.raises(ValueError, match="reg_form"):
        regularity_penalty(x, 1.0, "cubic")


def test_parameterisations_are_spd_and_spsd():
    torch.manual_seed(1)
    G = ProductGroup(1, 2)
    for seed in range(5):
        m = random_model(G, "none", seed=seed)
        with torch.no_grad():
            for p in m.parameters():
                p.copy_(3 * torch.randn_like(p))
        Jd = m.inertia.Jd()
        J = m.inertia.J()
        assert torch.linalg.eigvalsh(Jd).min() > 0 and torch.linalg.eigvalsh(J).min() > 0
        ev = torch.linalg.eigvalsh(J)
        # physical (triangle inequality); eigenvalues reach ~350 here: the slack is relative to them
        assert (ev[:, 0] + ev[:, 1] >= ev[:, 2] * (1 - 1e-12)).all()
        D = m.forces[0].D()
        torch.testing.assert_close(D, D.T)
        assert torch.linalg.eigvalsh(D).min() > -1e-10 * D.abs().max()  # entries reach ~260
