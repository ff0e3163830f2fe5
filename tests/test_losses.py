"""train.loss = del | newton | rollout (liedfl_cli/models/liedflnn/losses.py, liedfl_cli/commands/finetune.py)."""

from __future__ import annotations

import copy

import pytest
import torch
from test_fused import MODELS, both_batches, make, rel, trajectories

from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import SO3, Pose, ProductGroup
from liedfl_cli.models.base import LossOptions, TrajectoryBatch
from liedfl_cli.models.euler_dflnn.model import EulerDFLNN
from liedfl_cli.models.liedflnn import losses
from liedfl_cli.models.liedflnn.engines import core as fused
from liedfl_cli.solvers.options import SolverOptions

TIGHT = SolverOptions(tol=1e-13, max_iter=30)


# ----------------------------------------------------------------------------- del: unchanged
@pytest.mark.parametrize(
    "name, value",
    [("free_so3_rayleigh", 0.25950032426288505), ("se3xso3_per_body_rayleigh", 0.06554421329712415)],
)
def test_del_loss_is_unchanged(name, value):
    """The value the code before train.loss gave on this batch (reference path), bit for bit."""
    model = make(name)
    ref, fus = both_batches(model, trajectories(model.G))
    assert float(model.loss(ref, LossOptions())[0]) == value
    assert float(model.loss(ref, LossOptions(loss="del"))[0]) == value
    assert abs(float(model.loss(fus, LossOptions(loss="del"))[0]) - value) <= 1e-14 * value


# ----------------------------------------------------------------------------- newton
def independent_newton(model, prev: Pose, cur: Pose, nxt: Pose) -> torch.Tensor:
    """H^-1 r with H the torch.func Jacobian of the full residual in delta (g_{k+1} = g_k W exp(delta))."""
    G = model.G
    inc = G.increment(cur, nxt)

    def one(pR, pp, cR, cp, iR, ip):
        gp, g, i = Pose(pR[None], pp[None]), Pose(cR[None], cp[None]), Pose(iR[None], ip[None])
        f = lambda d: model.residual(gp, g, G.compose(g, G.retract(i, d[None])))[0]
        return f(iR.new_zeros(G.dim)), torch.func.jacrev(f)(iR.new_zeros(G.dim))

    r, J = torch.vmap(one)(prev.R, prev.p, cur.R, cur.p, inc.R, inc.p)
    return torch.linalg.solve(J, r)


NEWTON_MODELS = sorted(set(MODELS) - {"se3xso3x2_nonlinear_nn"})  # its nn force: autodiff dF/dxi (slow, same code)


@pytest.mark.parametrize("name", NEWTON_MODELS)
def test_newton_loss_equals_an_independent_autodiff_solve_on_both_paths(name):
    model = make(name)
    ref, fus = both_batches(model, trajectories(model.G))
    opts = LossOptions(loss="newton")
    x = independent_newton(model, *ref.poses()).detach()
    expect = float((x * x).sum(-1).mean())
    assert float(x.norm(dim=-1).max()) < losses.NEWTON_CLIP  # nothing clipped: the plain formula applies
    loss_ref, parts_ref = model.with_path("reference").loss(ref, opts)
    fus_set = model.training_set(trajectories(model.G), 10)
    fus_set.enable_jacobian()
    idx = torch.randperm(fus_set.n, generator=torch.Generator().manual_seed(3))
    fus = fus_set.batch(idx, torch.Generator().manual_seed(1), 10)
    loss_fus, parts_fus = model.loss(fus, opts)
    assert abs(float(parts_ref["newton_loss"]) - expect) <= 1e-10 * expect
    assert abs(float(parts_fus["newton_loss"]) - expect) <= 1e-10 * expect
    assert abs(float(loss_fus - loss_ref)) <= 1e-10 * abs(float(loss_ref))
    params = [p for p in model.parameters() if p.requires_grad]
    g_ref = torch.autograd.grad(loss_ref, params, allow_unused=True)
    g_fus = torch.autograd.grad(loss_fus, params, allow_unused=True)
    scale = max(float(g.abs().max()) for g in g_ref if g is not None)
    for a, b in zip(g_fus, g_ref):
        a = torch.zeros(()) if a is None else a
        b = torch.zeros(()) if b is None else b
        assert float((a - b).abs().max()) <= 1e-9 * scale


def test_block_diagonal_decision():
    assert losses.forces_per_body(make("se3xso3_per_body_rayleigh"))
    assert losses.forces_per_body(make("free_so3_rayleigh"))  # one body
    assert not losses.forces_per_body(make("se3xso3_mlp"))  # coupled Rayleigh D
    assert not losses.forces_per_body(make("se3xso3x2_coupled_nonlinear"))


def test_generic_residual_mode_newton_loss_has_parameter_gradients():
    G, kw = MODELS["se3_mlp_rayleigh"]
    from liedfl_cli.models.liedflnn.model import LieDFLNN

    fast, generic = LieDFLNN(G, 0.1, init_jitter=0.3, **kw), LieDFLNN(G, 0.1, init_jitter=0.3, residual="generic", **kw)
    generic.load_state_dict(fast.state_dict())
    fast, generic = fast.with_path("reference"), generic.with_path("reference")
    data = trajectories(G)
    b = fast.training_set(data, 10).batch(torch.arange(20), torch.Generator().manual_seed(0), 10)
    la, _ = fast.loss(b, LossOptions(loss="newton"))
    lb, _ = generic.loss(b, LossOptions(loss="newton"))
    assert abs(float(la - lb)) <= 1e-10 * abs(float(la))
    ga = torch.autograd.grad(la, list(fast.parameters()), allow_unused=True)
    gb = torch.autograd.grad(lb, list(generic.parameters()), allow_unused=True)
    for a, c in zip(ga, gb):
        if a is not None:
            assert c is not None and float((a - c).abs().max()) <= 1e-8 * max(1.0, float(a.abs().max()))


def test_singular_and_huge_steps_are_masked_and_clipped_with_finite_gradients():
    J = torch.eye(3, dtype=torch.float64).repeat(3, 1, 1)
    J[1, 2] = 0.0  # singular
    J[2] *= 1e-9  # nearly singular: a huge step
    J.requires_grad_(True)
    r = torch.tensor([[0.1, 0.0, 0.0], [0.2, 0.1, 0.3], [0.1, 0.1, 0.1]], dtype=torch.float64, requires_grad=True)
    x, singular, clipped = losses.newton_step(J, r)
    assert singular.tolist() == [False, True, False] and clipped.tolist() == [False, False, True]
    assert torch.equal(x[0], r[0].detach()) and torch.equal(x[1], torch.zeros(3, dtype=torch.float64))
    assert abs(float(x[2].norm()) - losses.NEWTON_CLIP) < 1e-12
    loss, parts = losses.newton_regularity_loss(x, singular, clipped, None, LossOptions(loss="newton"))
    gJ, gr = torch.autograd.grad(loss, (J, r))
    assert torch.isfinite(gJ).all() and torch.isfinite(gr).all()
    assert float(parts["singular"]) == pytest.approx(1 / 3) and float(parts["clipped"]) == pytest.approx(1 / 3)


@pytest.mark.parametrize("name", ["free_so3_rayleigh", "se3xso3_mlp"])
def test_newton_residual_is_the_first_order_one_step_error(name):
    """Data from a scheme, a model off by a small parameter error: |H^-1 r| on the data equals the
    model's Newton-solved one-step error to O(error)."""
    truth = make(name, seed=1)
    truth.requires_grad_(False)
    g0 = Pose(*(t[:, 0] for t in (trajectories(truth.G, T=6).R, trajectories(truth.G, T=6).p)))
    g1 = truth.G.retract(
        g0, 0.05 * torch.randn(6, truth.G.dim, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    )
    data = truth.rollout(g0, g1, 6, TIGHT).pose
    ratios = []
    for eps in (1e-3, 1e-4):
        model = copy.deepcopy(truth)
        with torch.no_grad():
            for p in model.parameters():
                p.add_(eps * torch.randn(p.shape, generator=torch.Generator().manual_seed(5), dtype=p.dtype))
        trip = [Pose(data.R[:, j : j + 4].flatten(0, 1), data.p[:, j : j + 4].flatten(0, 1)) for j in range(3)]
        x, _, _ = losses.newton_residual(model, *trip)
        pred = model.rollout(trip[0], trip[1], 2, TIGHT)
        e = model.G.log(model.G.increment(trip[2], Pose(pred.pose.R[:, 2], pred.pose.p[:, 2])))
        err = float((e + x).norm(dim=-1).max() / e.norm(dim=-1).max())  # e = -H^-1 r to first order
        ratios.append(err)
        assert err < 0.03
    assert ratios[1] < 0.3 * ratios[0]  # the mismatch is second order: it falls with the error


# ----------------------------------------------------------------------------- rollout (IFT)
@pytest.mark.parametrize("use_fused", [True, False], ids=["fused", "reference"])
def test_rollout_loss_gradient_matches_central_differences(use_fused):
    truth = make("se3xso3_mlp", seed=1)
    truth.requires_grad_(False)
    gen = torch.Generator().manual_seed(2)
    g0 = truth.G.retract(
        Pose(*(t[:, 0] for t in (trajectories(truth.G, T=4).R, trajectories(truth.G, T=4).p))),
        torch.zeros(4, truth.G.dim, dtype=torch.float64),
    )
    g1 = truth.G.retract(g0, 0.05 * torch.randn(4, truth.G.dim, generator=gen, dtype=torch.float64))
    windows = TrajectoryBatch(truth.rollout(g0, g1, 5, TIGHT).pose)  # k = 4
    model = copy.deepcopy(truth)
    model.requires_grad_(True)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1e-2 * torch.randn(p.shape, generator=torch.Generator().manual_seed(5), dtype=p.dtype))
    opts = LossOptions(loss="rollout", w_reg=0.0, solver=TIGHT)
    model = model.with_path("fused" if use_fused else "reference")
    p = model.inertia.abc
    loss, parts = model.loss(windows, opts)
    (g,) = torch.autograd.grad(loss, [p])
    assert float(parts["not_converged"]) == 0.0
    eps = 1e-5
    for i in (0, 2):
        vals = []
        for s in (1.0, -1.0):
            with torch.no_grad():
                p[0, i] += s * eps
                vals.append(float(model.loss(windows, opts)[0]))
                p[0, i] -= s * eps
        fd = (vals[0] - vals[1]) / (2 * eps)
        assert abs(float(g[0, i]) - fd) <= 1e-5 * abs(fd), (float(g[0, i]), fd)


def test_rollout_loss_masks_non_converged_solves():
    model = make("free_so3_rayleigh")
    traj = trajectories(SO3, T=3, N=5)
    windows = TrajectoryBatch(traj)
    loss, parts = losses.rollout_window_loss(
        model, windows, LossOptions(loss="rollout"), SolverOptions(max_iter=1, tol=1e-300)
    )
    assert float(parts["not_converged"]) == 3.0  # every window stops at its first step
    assert float(parts["rollout_loss"]) == 0.0 and torch.isfinite(loss)


def test_window_set_and_its_errors():
    data = trajectories(SO3, T=2, N=10)
    ws = losses.WindowSet(data, 10, 5)
    assert ws.n == 2 * 5 and ws.traj.R.shape[1] == 7
    with pytest.raises(ConfigError, match="horizon"):
        losses.WindowSet(data, 4, 5)


# ----------------------------------------------------------------------------- configs
def test_unsupported_models_get_one_line():
    model = EulerDFLNN.from_config(
        __import__("liedfl_cli.models.base", fromlist=["BuildContext"]).BuildContext(SO3, 0.1)
    )
    model.name = "euler_dflnn"
    with pytest.raises(ConfigError, match=r"^train.loss=newton is not available for euler_dflnn$"):
        losses.check_loss(model, "newton")
    losses.check_loss(model, "del")
    with pytest.raises(ConfigError, match="choose one of del, newton, rollout"):
        losses.check_loss(make("so3_no_force"), "newtn")


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.loss=newtn", "train.loss='newtn': choose one of del, newton, rollout"),
        ("+train.rollout_loss.horizn=3", "did you mean 'train.rollout_loss.horizon'"),
        ("train.rollout_loss.horizon=0", "train.rollout_loss.horizon=0: must be a positive integer"),
        ("train.rollout_loss.lr=-1", "train.rollout_loss.lr=-1: must be a positive number"),
    ],
)
def test_config_keys_are_validated(compose_cfg, override, message):
    from liedfl_cli.config.schema import validate

    cfg = compose_cfg("train", [override])
    with pytest.raises(ConfigError) as e:
        validate(cfg, "train")
    assert message in str(e.value) and "\n" not in str(e.value)


def test_defaults_are_del():
    assert LossOptions().loss == "del"
    from liedfl_cli.config.typed import TrainConfig, section

    assert TrainConfig().loss_options().loss == "del"
    train = section(TrainConfig, {"loss": "rollout", "rollout_loss": {"horizon": 3}}, "train")
    assert train.loss_options().rollout_horizon == 3 and train.loss_options().loss == "rollout"


def test_training_stage_of_rollout_is_del_and_newton_enables_the_jacobian():
    model = make("se3xso3_mlp")
    data = trajectories(ProductGroup(1, 1))
    opts, samples = losses.training_stage(model, data, 10, LossOptions(loss="rollout"))
    assert opts.loss == "del" and "W2r" not in samples.fields
    opts, samples = losses.training_stage(model, data, 10, LossOptions(loss="newton"))
    assert opts.loss == "newton" and isinstance(samples, fused.IncrementSet) and "W2r" in samples.fields
    assert rel(samples.fields["W2r"], samples.reg_W) == 0.0
