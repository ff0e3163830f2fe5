"""The closed-form MLP derivatives of the fused rollout (`models.mlp_derivatives`) equal autograd
to 1e-10 relative in float64 and finite differences to their truncation error, and a rollout with
them matches the reference (autograd) path to the Newton tolerance."""

from __future__ import annotations

import pytest
import torch
from torch import nn
from torch.func import jacrev

from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, so3
from liedfl_cli.mechanics.forces import NNForce, force_jacobian_xi
from liedfl_cli.mechanics.potentials import left_gradient
from liedfl_cli.models import mlp_derivatives
from liedfl_cli.models.liedflnn.engines import core as fused
from liedfl_cli.models.liedflnn.engines import maps as fused_maps
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.solvers.options import SolverOptions

ACTIVATIONS = {
    "gelu": lambda: nn.GELU(),
    "gelu_tanh": lambda: nn.GELU(approximate="tanh"),
    "tanh": lambda: nn.Tanh(),
    "softplus": lambda: nn.Softplus(),
    "softplus_threshold": lambda: nn.Softplus(beta=2.0, threshold=1.0),  # the linear branch is reached
    "silu": lambda: nn.SiLU(),
}


def net(act: str, n_in: int = 7, out: int = 1, width: int = 6, depth: int = 2, seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    mods: list[nn.Module] = []
    d = n_in
    for _ in range(depth):
        mods += [nn.Linear(d, width, dtype=torch.float64), ACTIVATIONS[act]()]
        d = width
    mods.append(nn.Linear(d, out, dtype=torch.float64))
    return nn.Sequential(*mods)


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


def inputs(n_in: int = 7, T: int = 9, seed: int = 1) -> torch.Tensor:
    return 2.0 * torch.randn(T, n_in, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def autograd_gradient(f: nn.Module, x: torch.Tensor) -> torch.Tensor:
    x = x.clone().requires_grad_(True)
    return torch.autograd.grad(f(x)[..., 0].sum(), x)[0]


@pytest.mark.parametrize("act", sorted(ACTIVATIONS))
@pytest.mark.parametrize("graph", [False, True], ids=["no_grad", "differentiable"])
def test_value_and_gradient_equal_autograd(act, graph):
    f, x = net(act), inputs()
    f.requires_grad_(graph)
    with torch.set_grad_enabled(graph):
        got = mlp_derivatives.value_and_gradient(f, x)
    assert got is not None
    value, grad = got
    assert rel(value, f(x)[..., 0].detach()) <= 1e-12
    assert rel(grad, autograd_gradient(f, x)) <= 1e-10
    assert grad.requires_grad == graph  # training differentiates it for the parameters


@pytest.mark.parametrize("act", sorted(ACTIVATIONS))
def test_the_differentiable_gradient_backpropagates_as_a_double_backward(act):
    """Training differentiates dV/dx for the parameters and x: the one-node activation (`_ActAndSlope`)
    gives the gradients of a double backward through autograd, and its own derivative matches finite
    differences (gradcheck); a second backward through it raises instead of returning zeros."""
    f, x = net(act), inputs()
    c = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    params = list(f.parameters())

    def loss_closed(xx):
        value, grad = mlp_derivatives.value_and_gradient(f, xx)
        return (grad * c).sum() + (value * value).sum()

    def loss_autograd(xx):
        (grad,) = torch.autograd.grad(f(xx)[..., 0].sum(), xx, create_graph=True)
        return (grad * c).sum() + (f(xx)[..., 0] ** 2).sum()

    xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    got = torch.autograd.grad(loss_closed(xa), [xa, *params])
    want = torch.autograd.grad(loss_autograd(xb), [xb, *params])
    for g, w in zip(got, want):
        assert rel(g, w) <= 1e-10
    z = inputs(n_in=5, T=4, seed=7).requires_grad_(True)
    act_mod = ACTIVATIONS[act]()
    assert torch.autograd.gradcheck(lambda zz: mlp_derivatives._ActAndSlope.apply(zz, act_mod), (z,))
    a, s = mlp_derivatives._ActAndSlope.apply(z, act_mod)
    (dz,) = torch.autograd.grad(s.sum(), z, create_graph=True)
    with pytest.raises(RuntimeError):
        dz.sum().backward()


def test_the_differentiable_gradient_works_under_torch_func_transforms():
    """`losses.autodiff_jacobian_var` takes vmap(jacrev(...)) of residuals that hold dV/dx, and the loss then
    differentiates that Jacobian for the parameters: a second derivative through the slope."""
    f, x = net("gelu"), inputs()
    row = lambda xi: mlp_derivatives.value_and_gradient(f, xi[None])[1][0]
    hess = torch.vmap(torch.func.jacrev(row))(x)
    want = torch.stack([torch.autograd.functional.hessian(lambda xi: f(xi[None])[0, 0], xi) for xi in x])
    assert rel(hess, want) <= 1e-10
    (g_w,) = torch.autograd.grad(hess.sum(), f[0].weight)
    xx = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(f(xx)[..., 0].sum(), xx, create_graph=True)
    ref_hess_sum = sum(torch.autograd.grad(g[:, i].sum(), xx, create_graph=True)[0].sum() for i in range(x.shape[1]))
    (g_w_ref,) = torch.autograd.grad(ref_hess_sum, f[0].weight)
    assert rel(g_w, g_w_ref) <= 1e-10


@pytest.mark.parametrize("act", sorted(ACTIVATIONS))
def test_hessian_vector_product_equals_autograd_and_finite_differences(act):
    f, x = net(act), inputs()
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    got = mlp_derivatives.gradient_and_hvp(f, x, v)
    assert got is not None
    grad, hvp = got
    xg = x.clone().requires_grad_(True)
    g_ref = torch.autograd.grad(f(xg)[..., 0].sum(), xg, create_graph=True)[0]
    hvp_ref = torch.autograd.grad((g_ref * v).sum(), xg)[0]
    assert rel(grad, g_ref.detach()) <= 1e-10
    assert rel(hvp, hvp_ref) <= 1e-10
    eps = 1e-5
    fd = (autograd_gradient(f, x + eps * v) - autograd_gradient(f, x - eps * v)) / (2 * eps)
    assert rel(hvp, fd) <= 1e-6


@pytest.mark.parametrize("act", sorted(ACTIVATIONS))
def test_forward_jacobian_equals_autograd(act):
    f, x = net(act, n_in=7, out=4), inputs()
    lin = f[0]
    assert isinstance(lin, nn.Linear)
    z1 = nn.functional.linear(x, lin.weight, lin.bias)
    value, J = mlp_derivatives.value_and_jacobian(f, z1, lin.weight[:, 4:])  # with respect to inputs 4..6
    J_ref = torch.func.vmap(jacrev(f))(x)[..., 4:]
    assert rel(value, f(x).detach()) <= 1e-12
    assert rel(J, J_ref) <= 1e-10


def test_unsupported_networks_are_declined():
    assert mlp_derivatives.layers(nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1))) is None
    assert mlp_derivatives.layers(nn.Sequential(nn.Linear(3, 4), nn.GELU())) is None  # ends in an activation
    assert (
        mlp_derivatives.value_and_gradient(nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1)), inputs(3))
        is None
    )


GROUPS = {"so3": SO3, "so3x2": ProductGroup(0, 2), "se3": SE3, "se3xso3x2": ProductGroup(1, 2)}


def poses(G: ProductGroup, T: int = 6, seed: int = 3) -> Pose:
    gen = torch.Generator().manual_seed(seed)
    return Pose(
        so3.exp(torch.randn(T, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(T, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )


def mlp_model(G: ProductGroup, **kw) -> LieDFLNN:
    model = LieDFLNN(G, 0.05, potential="mlp", mlp_width=10, mlp_depth=2, init_jitter=0.3, **kw)
    with torch.no_grad():  # a potential far from flat, so its covector matters
        model.potential.net[-1].weight.mul_(30.0)
    return model


@pytest.mark.parametrize("name", sorted(GROUPS))
def test_potential_covector_equals_autograd_and_finite_differences_on_the_group(name):
    G = GROUPS[name]
    model = mlp_model(G)
    model.requires_grad_(False)
    g = poses(G)
    with torch.no_grad():
        got = mlp_derivatives.potential_covector(model, g)
    assert got is not None
    ref = -model.h * left_gradient(model.potential, G, g)
    assert rel(got, ref) <= 1e-10
    eps = 1e-6
    fd = torch.stack(
        [
            (model.potential(G.retract(g, eps * e)) - model.potential(G.retract(g, -eps * e))) / (2 * eps)
            for e in torch.eye(G.dim, dtype=torch.float64)
        ],
        -1,
    )
    assert rel(got, -model.h * fd) <= 1e-7


def test_nn_force_value_and_jacobian_equal_autograd():
    G = ProductGroup(1, 2)
    force = NNForce(G, scale=2.0, width=8, depth=2)
    g = poses(G)
    xi = torch.randn(6, G.dim, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    with torch.no_grad():
        at = mlp_derivatives.ForcesAt(G, [force], g)
        assert at.closed and not at.other
        F = at.value(xi, key=xi)
        J_kept = at.jacobian(xi, key=xi)
        J = at.jacobian(xi)
        sub = at.restrict(torch.tensor([4, 1]))
        F_sub = sub.value(xi[[4, 1]])
    ref_F = force(g, xi)
    assert rel(F, ref_F) <= 1e-12
    assert rel(J, force_jacobian_xi(force, g, xi)) <= 1e-10
    assert torch.equal(J_kept, J)
    assert rel(F_sub, ref_F[[4, 1]]) <= 1e-12


def start(G: ProductGroup, T: int, h: float) -> tuple[Pose, Pose]:
    g0 = poses(G, T, seed=5)
    xi = torch.randn(T, G.dim, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    return g0, G.retract(g0, h * xi)


ROLLOUT_MODELS = {
    "so3_mlp_10x2_rayleigh": (SO3, dict(forces=["rayleigh"])),
    "se3_mlp_rayleigh": (SE3, dict(forces=["rayleigh"])),
    "se3xso3x2_mlp_nn_force": (ProductGroup(1, 2), dict(forces={"rayleigh": {}, "nn": {"width": 8, "depth": 2}})),
    "so3x2_mlp_rayleigh": (ProductGroup(0, 2), dict(forces=["rayleigh"])),
}


@pytest.mark.parametrize("name", sorted(ROLLOUT_MODELS))
def test_closed_form_rollout_equals_the_autograd_path_to_the_newton_tolerance(name):
    G, kw = ROLLOUT_MODELS[name]
    model = mlp_model(G, **kw)
    model.requires_grad_(False)
    g0, g1 = start(G, 4, model.h)
    # the reference path: autograd for the potential gradient and the NN force's Jacobian
    ref = model.with_path("reference").rollout(g0, g1, 8)
    new = model.rollout(g0, g1, 8)
    tol = SolverOptions().tol
    assert bool(new.converged.all()) and torch.equal(ref.iterations, new.iterations)
    assert float((ref.pose.R - new.pose.R).abs().max()) <= 10 * tol
    if G.n_se3:
        assert float((ref.pose.p - new.pose.p).abs().max()) <= 10 * tol * max(1.0, float(ref.pose.p.abs().max()))


def test_the_fused_potential_covector_uses_the_closed_form(monkeypatch):
    model = mlp_model(SO3)
    model.requires_grad_(False)
    calls = []
    # patched where potential_covector looks it up (`fused` only re-exports)
    monkeypatch.setattr(fused_maps, "left_gradient", lambda *a, **k: calls.append(1))
    with torch.no_grad():
        out = fused.potential_covector(model, poses(SO3))
    assert out.shape == (6, 3) and not calls


def test_a_single_linear_layer_has_its_weights_as_gradient():
    f = nn.Sequential(nn.Linear(5, 1, dtype=torch.float64))
    x = inputs(5)
    got = mlp_derivatives.value_and_gradient(f, x)
    assert got is not None
    assert got[1].shape == x.shape and rel(got[1], autograd_gradient(f, x)) <= 1e-12
