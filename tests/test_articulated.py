"""The articulated discrete Lagrangian (`models.articulated`): the closed forms through the FK Jacobian
against autodiff of L_d through forward kinematics, on free and pinned roots, world and parent
rotations, with potentials and joint-space forces."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from liedfl_cli.lie import Pose, so3
from liedfl_cli.lie.tree import Tree
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedTriplets
from liedfl_cli.models.base import LossOptions, TripletSet

H = 0.05


def _tree(rotations: str, free_root: bool, parents=(-1, 0, 1, 1, 3)) -> Tree:
    rng = np.random.default_rng(5)
    offsets = rng.normal(scale=0.5, size=(len(parents), 3))
    if free_root:
        offsets[0] = 0.0
    return Tree.from_lists(parents, offsets, rotations, free_root)


def _trajectories(tree: Tree, T: int = 4, N: int = 5, seed: int = 0, speed: float = 0.3) -> Pose:
    """Smooth random coordinate trajectories (T, N+1): constant random velocities plus a wobble."""
    G = tree.group
    gen = torch.Generator().manual_seed(seed)
    R0 = so3.exp(torch.randn(T, tree.n_bodies, 3, generator=gen, dtype=torch.float64))
    p0 = torch.randn(T, G.n_se3, 3, generator=gen, dtype=torch.float64)
    xi = speed * torch.randn(T, G.dim, generator=gen, dtype=torch.float64)
    g = Pose(R0, p0)
    Rs, ps = [g.R], [g.p]
    for k in range(N):
        g = G.retract(g, xi * (1 + 0.1 * k))
        Rs.append(g.R)
        ps.append(g.p)
    return Pose(torch.stack(Rs, 1), torch.stack(ps, 1))


def _model(tree: Tree, residual: str, forces, potential=("uniform_gravity", "mlp")) -> ArticulatedLieDFLNN:
    torch.manual_seed(0)
    m = ArticulatedLieDFLNN(tree, H, potential=potential, forces=forces, residual=residual, mlp_width=8, mlp_depth=2)
    with torch.no_grad():  # move away from the symmetric start so every term matters
        for p in m.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return m


CASES = [
    ("world", True, {"rayleigh": {"coupling": "coupled"}}),
    ("parent", True, {"rayleigh": {"coupling": "per_body"}}),
    ("world", False, {"rayleigh_nonlinear": {"coupling": "per_body", "width": 8, "depth": 2}}),
    ("parent", False, {}),
]


@pytest.mark.parametrize(("rotations", "free_root", "forces"), CASES)
def test_fast_residual_and_jacobian_equal_autodiff_through_fk(rotations, free_root, forces):
    tree = _tree(rotations, free_root)
    data = _trajectories(tree)
    fast = _model(tree, "fast", forces)
    generic = _model(tree, "generic", forces)
    generic.load_state_dict(fast.state_dict())
    G = tree.group
    a, b, c = (data.index((slice(None), k)) for k in (1, 2, 3))
    r_fast, r_gen = fast.residual(a, b, c), generic.residual(a, b, c)
    assert r_fast.shape == (4, G.dim)
    assert r_gen.detach().abs().max() > 1e-3  # not a trivial comparison
    torch.testing.assert_close(r_fast, r_gen, atol=1e-10 * max(1.0, float(r_gen.detach().abs().max())), rtol=0)
    inc = G.increment(b, c)
    J_fast, J_gen = fast.jacobian_var(b, inc), generic.jacobian_var(b, inc)
    torch.testing.assert_close(J_fast, J_gen, atol=1e-8 * float(J_gen.detach().abs().max()), rtol=0)


@pytest.mark.parametrize("free_root", [True, False])
def test_the_coordinate_mlp_potential_takes_the_closed_form_and_equals_autodiff(free_root, monkeypatch):
    """Exp 4's articulated potential (an MLP of the joint coordinates): its covector and the
    parameters' gradients through it, closed form (`mlp_derivatives`) against autograd."""
    from torch.func import grad

    from liedfl_cli.models import mlp_derivatives

    tree = _tree("parent", free_root)
    model = _model(tree, "fast", {}, potential=("mlp",))
    assert model.potential_coord is not None
    g = _trajectories(tree).index((slice(None), 2))
    G = tree.group
    taken = []
    closed_form = mlp_derivatives.mlp_potential_covector
    monkeypatch.setattr(mlp_derivatives, "mlp_potential_covector", lambda *a: taken.append(1) or closed_form(*a))
    world, A = None, None
    cov = model.potential_covector(g, world, A)
    assert taken == [1]
    eta = g.R.new_zeros(*g.R.shape[:-3], G.dim)
    ref = -H * grad(lambda e: model.potential_coord(G.perturb(g, e)).sum())(eta)
    assert ref.detach().abs().max() > 1e-4
    torch.testing.assert_close(cov, ref, rtol=1e-12, atol=1e-14)
    params = [p for p in model.potential_coord.parameters() if p.requires_grad]
    weights = torch.randn_like(ref)
    d_closed = torch.autograd.grad((cov * weights).sum(), params, allow_unused=True)
    d_ref = torch.autograd.grad((ref * weights).sum(), params, allow_unused=True)
    for x, y in zip(d_closed, d_ref):
        assert (x is None) == (y is None)
        if x is not None:
            torch.testing.assert_close(x, y, rtol=1e-11, atol=1e-13)


EXP4_FORCES = {  # Exp 4's three forces at once (each called once on both time levels, stacked)
    "rayleigh": {"coupling": "per_body"},
    "rayleigh_nonlinear": {"coupling": "per_body", "width": 8, "depth": 2},
    "nn": {"width": 8, "depth": 2},
}


@pytest.mark.parametrize(("rotations", "free_root", "forces"), [*CASES[:2], ("parent", True, EXP4_FORCES)])
def test_training_batches_give_the_residual_and_its_gradient(rotations, free_root, forces):
    """The precomputed training set (FK done once) gives the same loss and gradients as the generic path."""
    tree = _tree(rotations, free_root)
    data = _trajectories(tree, T=3, N=6)
    fast = _model(tree, "fast", forces)
    generic = _model(tree, "generic", forces)
    generic.load_state_dict(fast.state_dict())
    opts = LossOptions(reg_points=0)
    idx = torch.arange(6)
    fs, gs = fast.training_set(data, 6), generic.training_set(data, 6)
    assert isinstance(fs, ArticulatedTriplets) and isinstance(gs, TripletSet)
    gen = torch.Generator().manual_seed(0)
    lf, _ = fast.loss(fs.batch(idx, gen, 0), opts)
    lg, _ = generic.loss(gs.batch(idx, gen, 0), opts)
    torch.testing.assert_close(lf, lg, rtol=1e-10, atol=0)
    # (the MLP potential's output bias is a constant of V: no gradient on either path)
    gf = torch.autograd.grad(lf, [p for p in fast.parameters() if p.requires_grad], allow_unused=True)
    gg = torch.autograd.grad(lg, [p for p in generic.parameters() if p.requires_grad], allow_unused=True)
    assert [x is None for x in gf] == [y is None for y in gg]
    assert sum(x is not None for x in gf) >= 8
    for x, y in zip(gf, gg):
        if x is not None and y is not None:
            torch.testing.assert_close(x, y, rtol=1e-8, atol=1e-10 * max(1.0, float(y.abs().max())))


def test_rollout_solves_the_residual_and_stays_on_the_group():
    tree = _tree("world", True)
    data = _trajectories(tree, T=3, N=4, speed=0.05)  # a few degrees per step, as sampled data
    model = _model(tree, "fast", {"rayleigh": {"coupling": "per_body"}}, potential=("uniform_gravity",))
    g0, g1 = data.index((slice(None), 0)), data.index((slice(None), 1))
    from liedfl_cli.solvers.options import SolverOptions

    ro = model.rollout(g0, g1, 6, SolverOptions(tol=1e-12, max_iter=20))
    assert bool(ro.converged.all()), ro.iterations
    pose = ro.pose
    for k in range(1, 6):
        r = model.residual(*(pose.index((slice(None), j)) for j in (k - 1, k, k + 1)))
        assert float(r.detach().abs().max()) < 1e-8 * model.mass().max().item() / H
    assert float(so3.orthogonality_error(pose.R).max()) < 1e-12


def test_vectorised_world_blocks_equal_the_per_body_closed_form_and_autodiff():
    from liedfl_cli.lie import ProductGroup
    from liedfl_cli.mechanics import articulated as art
    from liedfl_cli.mechanics import kinetic
    from liedfl_cli.models.liedflnn.model import LieDFLNN

    B = 4
    Gw = ProductGroup(B, 0)
    gen = torch.Generator().manual_seed(2)
    inc = Gw.exp(0.3 * torch.randn(5, Gw.dim, generator=gen, dtype=torch.float64))
    ref = LieDFLNN(Gw, H, potential="none", forces=(), residual="generic", init_jitter=0.3)
    Jd, m, rho = (t.detach() for t in ref._params())
    blocks = art.mixed_hessian_blocks(inc, Jd, m, rho, H)
    loop = torch.stack(kinetic.mixed_hessian_blocks(Gw, inc, Jd, m, rho, H), -3)
    torch.testing.assert_close(blocks, loop, rtol=1e-13, atol=1e-13 * float(loop.abs().max()))
    g = Gw.identity((5,))
    full = ref.mixed_hessian_autodiff(g, Gw.compose(g, inc)).detach().transpose(-1, -2)  # it is indexed (b, a)
    for b, s in enumerate(Gw.body_slices()):
        torch.testing.assert_close(
            blocks[:, b].detach(), full[:, s, s], rtol=1e-10, atol=1e-10 * float(full.abs().max())
        )


@pytest.mark.parametrize(("rotations", "free_root", "forces"), CASES[:2])
def test_newton_loss_of_the_batches_equals_the_reference_path(rotations, free_root, forces):
    """train.loss=newton: the precomputed batches (`enable_jacobian`) give the loss of the generic
    reference path (`models.liedflnn.losses.newton_loss`: autodiff Jacobian of the residual, then solve)."""
    from liedfl_cli.models.liedflnn.losses import training_stage

    tree = _tree(rotations, free_root)
    data = _trajectories(tree, T=3, N=6, speed=0.05)
    fast = _model(tree, "fast", forces)
    generic = _model(tree, "generic", forces)
    generic.load_state_dict(fast.state_dict())
    opts = LossOptions(reg_points=0, loss="newton")
    _, fs = training_stage(fast, data, 6, opts)
    assert isinstance(fs, ArticulatedTriplets) and fs.A_next is not None
    gen = torch.Generator().manual_seed(0)
    idx = torch.arange(6)
    lf, pf = fast.loss(fs.batch(idx, gen, 0), opts)
    lg, pg = generic.loss(generic.training_set(data, 6).batch(idx, gen, 0), opts)
    assert float(pf["newton_loss"]) > 0 and float(pf["singular"]) == 0
    torch.testing.assert_close(lf, lg, rtol=1e-8, atol=0)
