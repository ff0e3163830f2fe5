"""Damping that can be learned: every entry of D receives gradient at the start, a non-diagonal true D
is recovered, and the per-body damping of multibody scenes (constant blocks and D_b(g_b) from a shared
trunk with one head per body) has the right shapes, blocks, symmetry, PSD-ness and locality."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from liedfl_cli.commands.train import count_parameters, fit
from liedfl_cli.config.recovery import parameter_recovery
from liedfl_cli.data.scenes import generate
from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.mechanics.damping import PerBodyDampingNet, PerBodySPSD, block_diagonal
from liedfl_cli.mechanics.forces import RayleighForce, RayleighNonlinearForce, force_jacobian_xi
from liedfl_cli.mechanics.parameterizations import SPSDMatrix
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.solvers.newton import jacobian

GROUPS = [ProductGroup(0, 1), ProductGroup(1, 0), ProductGroup(1, 2), ProductGroup(2, 3), ProductGroup(0, 3)]
D_TRUE = [[0.05, 0.02, 0.01], [0.02, 0.06, -0.015], [0.01, -0.015, 0.04]]


def random_pose(G: ProductGroup, n: int, seed: int = 0) -> Pose:
    gen = torch.Generator().manual_seed(seed)
    return Pose(
        so3.exp(2.0 * torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )


def randomise(module, scale: float, seed: int = 0) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen, dtype=p.dtype))


# ----------------------------------------------------------------------------- learnable D
@pytest.mark.parametrize("dim", [3, 6, 9])
def test_every_damping_entry_gets_gradient_at_the_start(dim):
    """D = L L^T + diag(lambda^2) starts at init_diag I with L = c I, lambda = c 1 (c != 0): the
    gradient of a generic loss reaches every parameter (with L = 0 it reached none of L's)."""
    D = SPSDMatrix(dim, init_diag=0.02)
    torch.testing.assert_close(D(), 0.02 * torch.eye(dim, dtype=torch.float64))
    target = torch.randn(dim, dim, generator=torch.Generator().manual_seed(dim), dtype=torch.float64)
    ((D() - target) ** 2).sum().backward()
    assert (D.L_entries.grad != 0).all() and (D.lam.grad != 0).all()
    # the old start (L = 0): no L entry learns
    D0 = SPSDMatrix(dim, init_diag=0.02)
    with torch.no_grad():
        D0.L_entries.zero_()
        D0.lam.fill_(0.02**0.5)
    ((D0() - target) ** 2).sum().backward()
    assert (D0.L_entries.grad == 0).all()


def test_set_matrix_round_trips():
    A = torch.tensor(D_TRUE, dtype=torch.float64)
    for M in (A, torch.diag(torch.tensor([0.1, 0.0, 0.3], dtype=torch.float64))):
        D = SPSDMatrix(3)
        D.set_matrix(M)
        torch.testing.assert_close(D(), M, rtol=0, atol=1e-11)


def _recover(zero_L: bool) -> dict:
    cfg = {
        "name": "free_rigid_body",
        "h": 0.05,
        "n_trajectories": 24,
        "steps": 40,
        "train_steps": 40,
        "rollout_steps": 40,
        "test_fraction": 0.0,
        "n_test": 0,
        "seed": 0,
        "physics": {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.0, 0.0], "g": 0.0, "D": D_TRUE},
        "initial": {"omega_std": 1.0},
        "solver": {"method": "DOP853", "rtol": 1e-10, "atol": 1e-12},
    }
    ds = generate(cfg)
    model = LieDFLNN(ds.group, ds.h, forces=("rayleigh",), epsilon=10.0, seed=0)
    if zero_L:  # the previous initialisation
        with torch.no_grad():
            model.forces[0].D.L_entries.zero_()
            model.forces[0].D.lam.fill_(float(model.forces[0].D().diagonal()[0]) ** 0.5 * 2**0.5)
    train = OmegaConf.create(
        {
            "epochs": 100,
            "batch_size": 256,
            "optimizer": {"name": "soap", "lr": 3e-3, "weight_decay": 0.0},
            "w_del": 0.5,
            "w_reg": 0.5,
            "reg_points": 10,
            "reg_form": "relu",
            "epsilon": 10.0,
        }
    )
    fit(model, ds.pose(ds.train_idx), train, 40)
    return parameter_recovery(model, ds) | {"L": model.forces[0].D.L.detach()}


def test_a_non_diagonal_damping_is_recovered():
    """Free rigid body with a full SPD D (off-diagonal entries 20-40 % of the diagonal), 24 x 40 steps,
    100 epochs: D / tr J_d within 2 % of the truth (measured 0.4 %); with the old start (L = 0) the
    off-diagonal entries never move and the error stays at the off-diagonal size (~33 %)."""
    rec = _recover(zero_L=False)
    assert rec["D_over_trace_max_rel_error"] <= 0.02, rec
    assert rec["Jd_over_trace_max_rel_error"] <= 0.01, rec
    old = _recover(zero_L=True)
    assert torch.count_nonzero(old["L"]) == 0
    assert old["D_over_trace_max_rel_error"] > 0.25, old


# ----------------------------------------------------------------------------- per-body damping
@pytest.mark.parametrize("G", GROUPS, ids=lambda G: G.name)
def test_per_body_damping_shapes_blocks_symmetry_psd(G):
    nl = RayleighNonlinearForce(G, init_diag=0.05, width=16, depth=2, coupling="per_body")
    const = RayleighForce(G, init_diag=0.05, coupling="per_body")
    mask = block_diagonal(G, torch.ones(G.n_se3, 6, 6), torch.ones(G.n_so3, 3, 3)).to(torch.float64)
    for seed in range(3):
        randomise(nl, 1.0, seed)
        randomise(const, 1.0, seed)
        g = random_pose(G, 11, seed)
        for D in (nl.D(g), const.D()[None].expand(11, -1, -1)):
            assert D.shape == (11, G.dim, G.dim)
            assert torch.equal(D, D.transpose(-1, -2))  # exactly symmetric
            assert torch.count_nonzero(D * (1 - mask)) == 0  # no coupling between bodies
            assert torch.linalg.eigvalsh(D).min() >= -1e-12 * D.abs().max()
        xi = torch.randn(11, G.dim, dtype=torch.float64)
        torch.testing.assert_close(nl(g, xi), -(nl.D(g) @ xi[..., None])[..., 0], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(force_jacobian_xi(nl, g, xi), jacobian(lambda x, g=g: nl(g, x), xi))
        assert ((nl(g, xi) * xi).sum(-1) <= 1e-12).all()  # dissipative


@pytest.mark.parametrize("G", GROUPS[2:])
def test_per_body_constant_blocks_built_together_equal_each_blocks_own_matrix(G):
    """`PerBodySPSD` builds all blocks of a size at once (stacked parameters) and places them with one
    scatter: the same blocks as each body's `SPSDMatrix()`, the same matrix as assigning them slice by
    slice, the same force as the dim x dim product, and the same parameter gradients (autograd through
    the per-block construction as the reference)."""
    D = PerBodySPSD(G, init_diag=0.05)
    randomise(D, 1.0, seed=3)
    se, so = D.block_matrices()
    own = [blk() for blk in D.blocks]
    assert se.shape == (G.n_se3, 6, 6) and so.shape == (G.n_so3, 3, 3)
    for i, M in enumerate(own):
        got = se[i] if i < G.n_se3 else so[i - G.n_se3]
        torch.testing.assert_close(got, M, rtol=1e-14, atol=1e-15)
    slices = torch.zeros(G.dim, G.dim, dtype=torch.float64)
    for M, s in zip(own, G.body_slices()):
        slices[s, s] = M
    torch.testing.assert_close(D(), slices, rtol=1e-14, atol=1e-15)
    force = RayleighForce(G, coupling="per_body")
    force.D.load_state_dict(D.state_dict())
    g = random_pose(G, 7)
    xi = torch.randn(7, G.dim, dtype=torch.float64)
    torch.testing.assert_close(force(g, xi), -(xi @ slices.T), rtol=1e-13, atol=1e-15)
    (force(g, xi) ** 2).sum().backward()
    got = [p.grad.clone() for p in force.D.parameters()]
    force.zero_grad()
    reference = torch.zeros(G.dim, G.dim, dtype=torch.float64)
    for blk, s in zip(force.D.blocks, G.body_slices()):
        reference = reference.index_put((torch.arange(s.start, s.stop)[:, None], torch.arange(s.start, s.stop)), blk())
    ((xi @ reference.T) ** 2).sum().backward()
    for a, p in zip(got, force.D.parameters()):
        torch.testing.assert_close(a, p.grad, rtol=1e-12, atol=1e-15)


def test_per_body_damping_blocks_depend_on_their_own_body_only():
    G = ProductGroup(1, 3)
    net = PerBodyDampingNet(G, c=0.3, width=16, depth=2)
    randomise(net, 1.0)
    g = random_pose(G, 5)
    se, so = net.blocks(g)
    assert se.shape == (5, 1, 6, 6) and so.shape == (5, 3, 3, 3)
    moved = Pose(g.R.clone(), g.p.clone())
    moved.R[:, 2] = moved.R[:, 2] @ so3.exp(torch.tensor([0.4, -0.2, 0.1], dtype=torch.float64))
    se2, so2 = net.blocks(moved)
    torch.testing.assert_close(se2, se, rtol=0, atol=0)
    torch.testing.assert_close(so2[:, [0, 2]], so[:, [0, 2]], rtol=0, atol=0)
    assert (so2[:, 1] - so[:, 1]).abs().max() > 1e-6
    moved.p[:, 0] += 1.0  # the root's position enters the root's block only
    se3, so3_ = net.blocks(moved)
    assert (se3 - se).abs().max() > 1e-6
    torch.testing.assert_close(so3_[:, [0, 2]], so[:, [0, 2]], rtol=0, atol=0)


def test_per_body_damping_starts_near_init_diag_and_every_head_learns():
    G = ProductGroup(1, 2)
    nl = RayleighNonlinearForce(G, scale=2.0, init_diag=0.05, width=16, depth=2)
    g = random_pose(G, 8)
    D = nl.D(g)
    eye = 0.1 * torch.eye(G.dim, dtype=torch.float64)
    assert (D - eye).abs().max() < 0.5 * 0.1  # heads start small
    xi = torch.randn(8, G.dim, dtype=torch.float64)
    (nl(g, xi) ** 2).sum().backward()
    for p in nl.parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0


def test_per_body_constant_damping_set_matrix():
    G = ProductGroup(1, 1)
    D = PerBodySPSD(G, init_diag=0.1)
    M = torch.zeros(9, 9, dtype=torch.float64)
    M[:6, :6] = torch.eye(6, dtype=torch.float64) * 0.2 + 0.01
    M[6:, 6:] = torch.tensor(D_TRUE, dtype=torch.float64)
    D.set_matrix(M)
    torch.testing.assert_close(D(), M, rtol=0, atol=1e-11)
    M[0, 7] = M[7, 0] = 0.01
    with pytest.raises(ValueError, match="couples different bodies"):
        D.set_matrix(M)


def test_exp4_parameter_counts():
    """The Exp 4 model (SE(3) x SO(3)^22, MLPs 32x3): 30,385 parameters per body, 118,171 coupled."""
    G = ProductGroup(1, 22)
    mlp = {"width": 32, "depth": 3}
    per_body = {"rayleigh": {"coupling": "per_body"}, "rayleigh_nonlinear": mlp, "nn": mlp}
    coupled = {"rayleigh_nonlinear": {**mlp, "coupling": "coupled"}, "nn": mlp}
    a = LieDFLNN(G, 1 / 120, potential="mlp", forces=per_body, mlp_width=32, mlp_depth=3)
    b = LieDFLNN(G, 1 / 120, potential="mlp", forces=coupled, mlp_width=32, mlp_depth=3)
    assert count_parameters(a) == 30_385 and count_parameters(b) == 118_171
    assert count_parameters(a.forces[0]) == 27 + 22 * 9  # constant blocks 6x6 and 3x3
    assert count_parameters(a.forces[1]) == 7_577  # shared trunk 2,528 + heads 693 + 22 * 198
    assert count_parameters(b.forces[0]) == 95_588


# ----------------------------------------------------------------------------- stiff damping
J_FREE = [1.521, 1.362, 1.211]  # the free_rigid_body scene's inertia


def _free_body(h: float, D: list[float]) -> LieDFLNN:
    from liedfl_cli.models.true_scheme import physics_model

    return physics_model(ProductGroup(0, 1), h, {"J": J_FREE, "m": 0.5, "rho": [0.0, 0.0, 0.0], "g": 0.0, "D": D})


def _free_start(h: float, n: int = 4):
    G = ProductGroup(0, 1)
    g0 = random_pose(G, n, seed=3)
    gen = torch.Generator().manual_seed(4)
    return g0, G.retract(g0, h * torch.randn(n, 3, generator=gen, dtype=torch.float64))


def test_stiff_damping_reverses_the_spin_every_step_while_newton_converges():
    """D = 100 J at h = 0.1: h lambda(M^-1 D) = 10 on every axis. The trapezoidal forcing multiplies
    the angular velocity by (1 - 5)/(1 + 5) = -2/3 per step (the body's exp(-10) = 4.5e-5): the spin
    reverses at every step and Newton reports every step converged."""
    from liedfl_cli.models.stiffness import damping_stiffness, step_factor

    h = 0.1
    model = _free_body(h, [100.0 * j for j in J_FREE])
    stiffness = damping_stiffness(model)
    assert stiffness is not None and abs(stiffness - 10.0) <= 1e-12 * 10.0
    g0, g1 = _free_start(h)
    ro = model.rollout(g0, g1, 20)
    assert ro.n_failed == 0
    R = ro.pose.R[:, :, 0]
    w = so3.log(R[:, :-1].transpose(-1, -2) @ R[:, 1:]) / h  # body angular velocity of each step
    assert ((w[:, 1:] * w[:, :-1]).sum(-1) < 0).all()  # reversed at every step
    ratio = w[:, 1:].norm(dim=-1) / w[:, :-1].norm(dim=-1)
    assert float((ratio - abs(step_factor(10.0))).abs().max()) <= 0.01 * 2 / 3
    # the default scene's damping (D = 0.05) is far from stiff
    default = damping_stiffness(_free_body(h, [0.05] * 3))
    assert default is not None and abs(default - h * 0.05 / min(J_FREE)) <= 1e-12 * default


def test_rollout_warns_about_stiff_damping_and_not_on_the_default_scene(capsys):
    from liedfl_cli.commands.rollout import _roll
    from liedfl_cli.solvers.options import SolverOptions

    h = 0.1
    g0, g1 = _free_start(h, 2)
    truth = Pose(torch.stack((g0.R, g1.R), 1), torch.stack((g0.p, g1.p), 1))
    _roll(_free_body(h, [100.0 * j for j in J_FREE]), truth, 5, SolverOptions(), "true_scheme", False)
    lines = [x for x in capsys.readouterr().err.splitlines() if "stiff damping" in x]
    assert len(lines) == 1 and "= 10 > 2" in lines[0] and "-0.667" in lines[0], lines
    learned = LieDFLNN(ProductGroup(0, 1), h, potential="none", forces=["rayleigh"], seed=0)  # the default start
    for model in (_free_body(h, [0.05] * 3), learned):
        _roll(model, truth, 5, SolverOptions(), "model", False)
        assert "stiff damping" not in capsys.readouterr().err
