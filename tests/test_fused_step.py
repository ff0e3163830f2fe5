"""The fused optimiser step of `train.fit` (issue 20 item 5): `fused_optim.FusedSOAP` against the
library's SOAP, `fused_step.RotationalGradient` against autograd, and whole training runs on both
update paths. SOAP's first eigenbasis makes training sensitive to the last bit of a gradient
(tests/test_fused.py), so the fused paths run the library's and autograd's kernels and give their bits on
this machine; the comparisons below still allow 1e-13 relative, because a BLAS may pick its kernel by
memory alignment on another CPU (CI), which these tests are not about."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from pytorch_optimizer import SOAP

from liedfl_cli.commands import fused_optim
from liedfl_cli.commands.fused_optim import FusedSOAP
from liedfl_cli.lie import SE3, SO3, Pose, ProductGroup, so3
from liedfl_cli.models.base import LossOptions, oriented_logdet
from liedfl_cli.models.liedflnn.engines import gradient as fused_step
from liedfl_cli.models.liedflnn.engines.gradient import RotationalGradient
from liedfl_cli.models.liedflnn.engines.training import _oriented_relu, _penalty_and_slope
from liedfl_cli.models.liedflnn.model import LieDFLNN

SHAPES = [(1, 3), (1, 3), (6,), (3,), (4, 5)]  # the default run's four tensors and an MLP-like weight


def _params(shapes, seed: int = 1) -> list[torch.nn.Parameter]:
    gen = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=gen, dtype=torch.float64)) for s in shapes]


def _run(cls, shapes, steps: int, **kwargs):
    params = _params(shapes)
    opt = cls(params, lr=3e-3, precondition_frequency=4, **kwargs)
    gen = torch.Generator().manual_seed(2)
    for _ in range(steps):
        for p in params:
            p.grad = torch.randn(p.shape, generator=gen, dtype=torch.float64)
        opt.step()
    return params, opt


@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
def test_fused_soap_takes_the_library_steps_bit_for_bit(weight_decay):
    """13 steps: the first (the library's own), list steps, and three eigenbasis refreshes."""
    ref, ref_opt = _run(SOAP, SHAPES, 13, weight_decay=weight_decay)
    new, new_opt = _run(FusedSOAP, SHAPES, 13, weight_decay=weight_decay)
    assert new_opt._list_group() is not None  # the list step was taken, not the fallback
    for a, b in zip(new, ref):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(new_opt.state[a][key], ref_opt.state[b][key], rtol=1e-13, atol=0)


def test_fused_soap_lists_3d_tensors_and_leaves_parameters_without_a_gradient_alone():
    """Exp 4's shapes: per-body force heads (3-D) and a potential's last bias, which gets no
    gradient (a constant shift of V is not in the DEL equations): the library skips it."""
    shapes = [*SHAPES, (2, 3, 4), (1, 5, 2), (1,)]
    runs = []
    for cls in (SOAP, FusedSOAP):
        params = _params(shapes)
        opt = cls(params, lr=3e-3, precondition_frequency=4)
        gen = torch.Generator().manual_seed(2)
        for _ in range(13):
            for p in params[:-1]:
                p.grad = torch.randn(p.shape, generator=gen, dtype=torch.float64)
            opt.step()
        runs.append((params, opt))
    (ref, ref_opt), (new, new_opt) = runs
    assert new_opt._list_group() is not None  # the list step was taken, not the fallback
    assert new[-1].grad is None and torch.equal(new[-1], _params(shapes)[-1]) and not new_opt.state[new[-1]]
    for a, b in zip(new, ref):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)
        for key in ("exp_avg", "exp_avg_sq"):
            if key in ref_opt.state[b]:
                torch.testing.assert_close(new_opt.state[a][key], ref_opt.state[b][key], rtol=1e-13, atol=0)
        for qa, qb in zip(new_opt.state[a].get("Q", []), ref_opt.state[b].get("Q", [])):
            if len(qb):
                torch.testing.assert_close(qa, qb, rtol=1e-13, atol=0)


def test_fused_soap_falls_back_to_the_library_for_other_tensors():
    """A dimension above max_precondition_dim (no preconditioner on it): the library's step for
    the whole group."""
    ref, _ = _run(SOAP, SHAPES, 6, max_precondition_dim=4)
    new, new_opt = _run(FusedSOAP, SHAPES, 6, max_precondition_dim=4)
    assert new_opt._list_group() is None
    for a, b in zip(new, ref):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)


def test_fused_soap_falls_back_when_a_gradient_appears_after_the_first_step():
    """A parameter whose first gradient comes late has no state yet: the library creates it, so
    that step is the library's; the next ones are listed again."""
    shapes = [*SHAPES, (2, 3)]
    runs = []
    for cls in (SOAP, FusedSOAP):
        params = _params(shapes)
        opt = cls(params, lr=3e-3, precondition_frequency=4)
        gen = torch.Generator().manual_seed(2)
        listed = []
        for step in range(9):
            for p in params if step >= 3 else params[:-1]:
                p.grad = torch.randn(p.shape, generator=gen, dtype=torch.float64)
            if cls is FusedSOAP:
                listed.append(opt._list_group() is not None)
            opt.step()
        runs.append((params, listed))
    (ref, _), (new, listed) = runs
    assert listed == [False, True, True, False, True, True, True, True, True]
    for a, b in zip(new, ref):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)


def test_fused_soap_checkpoints_are_interchangeable_with_the_library():
    """A FusedSOAP state loads into SOAP and back; both continue with the same steps."""
    params, opt = _run(FusedSOAP, SHAPES, 7)
    state = opt.state_dict()
    runs = []
    for cls in (SOAP, FusedSOAP):
        ps = [torch.nn.Parameter(p.detach().clone()) for p in params]
        o = cls(ps, lr=3e-3, precondition_frequency=4)
        o.load_state_dict(copy.deepcopy(state))  # as from a checkpoint file: tensors of its own
        gen = torch.Generator().manual_seed(5)
        for _ in range(6):
            for p in ps:
                p.grad = torch.randn(p.shape, generator=gen, dtype=torch.float64)
            o.step()
        runs.append(ps)
    for a, b in zip(*runs):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)
    assert not torch.equal(runs[0][0], params[0])  # the continued steps moved the parameters


def _trajectories(T: int = 4, N: int = 14, h: float = 0.1, bodies: int = 1) -> Pose:
    gen = torch.Generator().manual_seed(0)
    k = torch.arange(N + 1, dtype=torch.float64)[None, :, None, None]
    w0 = torch.randn(T, 1, bodies, 3, generator=gen, dtype=torch.float64)
    w1 = torch.randn(T, 1, bodies, 3, generator=gen, dtype=torch.float64)
    return Pose(so3.exp(w0 + h * k * w1), torch.zeros(T, N + 1, 0, 3, dtype=torch.float64))


@pytest.mark.parametrize(
    ("form", "frozen_inertia", "bodies"),
    [("relu", False, 1), ("gaussian", False, 1), ("relu", True, 1), ("relu", False, 2), ("gaussian", False, 5)],
)
def test_rotational_gradient_equals_autograd(form, frozen_inertia, bodies):
    """One body (the default run), frozen inertia (model.known=[inertia]), two bodies (J_d in
    Python floats) and five (`_InertiaJd`'s tensor path; undamped: a 15x15 D is not covered)."""
    G = SO3 if bodies == 1 else ProductGroup(0, bodies)
    forces = ["rayleigh"] if bodies < 5 else []
    model = LieDFLNN(G, 0.1, potential="none", forces=forces, init_jitter=0.3, seed=0)
    model.inertia.requires_grad_(not frozen_inertia)
    params = [p for p in model.parameters() if p.requires_grad]
    opts = LossOptions(reg_form=form, epsilon=10.0 if form == "relu" else 5.0)
    samples = model.training_set(_trajectories(bodies=bodies), 10)
    grad_fn = RotationalGradient.make(model, samples, opts, params)
    assert grad_fn is not None
    batch = samples.batch(torch.arange(samples.n), torch.Generator().manual_seed(1), 10)
    loss, parts, grads = grad_fn(batch, opts)
    ref_loss, ref_parts = model.loss(batch, opts)
    ref_grads = torch.autograd.grad(ref_loss, params)
    assert math.isclose(loss, float(ref_loss.detach()), rel_tol=1e-13)
    assert parts.keys() == ref_parts.keys()
    assert all(math.isclose(parts[k], float(v.detach()), rel_tol=1e-13, abs_tol=0) for k, v in ref_parts.items())
    assert grads is not None and len(grads) == len(params)
    for g, r in zip(grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-13, atol=0)
        assert float(r.abs().max()) > 0  # a gradient that could differ


def test_rotational_gradient_applies_only_where_it_covers_every_parameter():
    data = _trajectories()
    opts = LossOptions()
    so3_model = LieDFLNN(SO3, 0.1, potential="none", forces=["rayleigh"], seed=0)
    se3_model = LieDFLNN(SE3, 0.1, potential="none", forces=["rayleigh"], seed=0)
    mlp_model = LieDFLNN(SO3, 0.1, potential="mlp", forces=["rayleigh"], mlp_width=4, seed=0)
    for model, expected in ((so3_model, True), (mlp_model, False)):
        params = [p for p in model.parameters() if p.requires_grad]
        assert (RotationalGradient.make(model, model.training_set(data, 10), opts, params) is not None) == expected
    se3_data = Pose(data.R, torch.zeros(*data.R.shape[:3], 3, dtype=torch.float64))
    params = [p for p in se3_model.parameters() if p.requires_grad]
    assert RotationalGradient.make(se3_model, se3_model.training_set(se3_data, 10), opts, params) is None
    reference = so3_model.with_path("reference")  # the path is the model's, fixed when it was built
    params = [p for p in reference.parameters() if p.requires_grad]
    assert RotationalGradient.make(reference, reference.training_set(data, 10), opts, params) is None


def test_python_relu_penalty_is_the_tensor_formula_bit_for_bit():
    """Normal and wrong orientations, active and inactive penalties, a zero determinant."""
    eps = 10.0
    lad = torch.tensor([[12.0, 3.5], [9.0, -float("inf")], [10.0, 11.0]], dtype=torch.float64)
    sign = torch.tensor([[-1.0, -1.0], [1.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    sl = torch.return_types.slogdet((sign, lad))
    pen, slope = _oriented_relu(sl, eps)
    ref_pen, ref_slope = _penalty_and_slope(oriented_logdet(lad, -sign, eps), eps, "relu")
    ref_slope = torch.where(sign < 0, ref_slope, -torch.sign(lad - eps) * ref_slope)
    torch.testing.assert_close(pen, ref_pen, rtol=1e-13, atol=0)
    torch.testing.assert_close(slope, ref_slope, rtol=1e-13, atol=0)
    assert float(pen.max()) == float("inf") and float(pen[0, 1]) == 6.5


def _smoke_histories(tmp_path, monkeypatch, optimizer: str, epochs: int = 6):
    """Per-epoch losses and final weights of the default model on the smoke dataset with the
    fused step, then with the old update path (autograd's backward, the library's SOAP)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.cli import CONF_DIR
    from liedfl_cli.commands.train import fit
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.data.scenes import get_dataset

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                "budget=smoke",
                f"paths.data_dir={tmp_path / 'data'}",
                f"paths.output_dir={tmp_path / 'run'}",
                f"train.epochs={epochs}",
                "train.batch_size=32",
                f"train.optimizer.name={optimizer}",
                "runtime.compile=false",
            ],
        )
    ds, _ = get_dataset(cfg.dataset, cfg.paths.data_dir)
    data = ds.pose(ds.train_idx)
    out = []
    for old in (False, True):
        if old:
            monkeypatch.setattr(RotationalGradient, "make", staticmethod(lambda *a: None))
            monkeypatch.setattr(fused_optim, "FusedSOAP", SOAP)
        model = build_model(cfg, ds)
        result = fit(model, data, cfg.train, int(cfg.dataset.train_steps))
        out.append((result["history"], [p.detach().clone() for p in model.parameters()]))
    return out


@pytest.mark.parametrize("optimizer", ["soap", "adam"])
def test_fused_and_old_update_paths_give_the_same_loss_history(tmp_path, monkeypatch, optimizer):
    (new, new_w), (old, old_w) = _smoke_histories(tmp_path, monkeypatch, optimizer)
    assert len(new) == len(old) == 6
    for a, b in zip(new, old):
        for key in ("loss", "del_loss", "reg_loss"):
            assert abs(a[key] - b[key]) <= 1e-12 * abs(b[key]), (a["epoch"], key, a[key], b[key])
    assert new[-1]["loss"] < new[0]["loss"]  # it trained
    for a, b in zip(new_w, old_w):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


def test_fused_step_is_used_by_the_default_model(tmp_path, monkeypatch):
    calls = []
    real = RotationalGradient.__call__

    def counting(self, batch, opts):
        calls.append(1)
        return real(self, batch, opts)

    monkeypatch.setattr(fused_step.RotationalGradient, "__call__", counting)
    (new, _), _ = _smoke_histories(tmp_path, monkeypatch, "soap", epochs=2)
    assert len(calls) >= 2 and len(new) == 2


def test_fused_soap_runs_step_hooks_and_the_profiler_scope():
    """FusedSOAP keeps torch's step wrapper off (`step.hooked`) but takes it when a hook is
    registered or the profiler runs: hooks still see every step."""
    params, opt = _run(FusedSOAP, SHAPES, 2)
    seen = []
    handle = opt.register_step_post_hook(lambda o, args, kwargs: seen.append(o))
    opt.step()
    handle.remove()
    opt.step()
    assert seen == [opt]
    with torch.profiler.profile() as prof:
        opt.step()
    assert any(e.name == "Optimizer.step#FusedSOAP.step" for e in prof.events())
