"""The articulated model against an engine nobody here wrote (MuJoCo chains) and against constant velocity.

Fast tier: the true-parameter articulated scheme predicts MuJoCo chains far better than constant
velocity (the per-body family cannot: issue 17), world- and parent-rotation files of the same motion
give the same physical predictions, the scheme converges to MuJoCo at second order at fixed final time,
and `liedfl train ... model.kinetic=articulated` runs end to end. Slow tier: training on an unseen chain
for 400 epochs meets the issue's acceptance figures.
"""

from __future__ import annotations

import csv
import json

import pytest
import torch

from liedfl_cli.errors import ConfigError
from liedfl_cli.evaluation.metrics import geodesic_error, position_error
from liedfl_cli.lie.tree import forward_kinematics
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, articulated_true_model
from liedfl_cli.solvers.one_step import constant_velocity_one_step, constant_velocity_rollout, one_step_predictions
from liedfl_cli.solvers.options import SolverOptions

pytest.importorskip("mujoco")
from liedfl_cli.data.hdf5 import save_dataset
from liedfl_cli.data.mujoco_chain import chain_dataset

TIGHT = SolverOptions(tol=1e-12, max_iter=20)


def _true_scheme(ds):
    return articulated_true_model(ds.tree, ds.h, ds.params["physics"])


@pytest.fixture(autouse=True)
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.mark.parametrize(
    "kw",
    [
        {"links": 3, "rotations": "world", "joint_damping": 0.05},
        {"links": 4, "rotations": "parent", "gravity": 9.81, "joint_damping": 0.1},
        {"links": 2, "rotations": "world", "root": "pinned", "gravity": 9.81, "joint_damping": 0.0, "h": 0.01},
    ],
)
def test_true_articulated_scheme_beats_constant_velocity_on_mujoco_chains(kw):
    ds = chain_dataset(n_trajectories=3, steps=30, seed=7, **{"h": 0.05, **kw})
    truth = ds.pose()
    model = _true_scheme(ds)
    pred, conv = one_step_predictions(model, truth, TIGHT)
    assert bool(conv.all())
    cv = constant_velocity_one_step(ds.group, truth)
    target = truth.index((slice(None), slice(2, None)))
    ratio = float(geodesic_error(pred.R, target.R).mean() / geodesic_error(cv.R, target.R).mean())
    assert ratio < 0.05, ratio  # measured 0.003-0.02; the per-body family stays >= 1 (issue 17)
    if ds.group.n_se3:
        pos = float(position_error(pred.p, target.p).mean() / position_error(cv.p, target.p).mean())
        assert pos < 0.05, pos
    ro = model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), 30, TIGHT)
    assert ro.n_failed == 0
    cvr = constant_velocity_rollout(ds.group, truth.index((slice(None), 0)), truth.index((slice(None), 1)), 30)
    assert float(geodesic_error(ro.pose.R, truth.R).mean()) < 0.05 * float(geodesic_error(cvr.R, truth.R).mean())


def test_world_and_parent_files_of_one_motion_predict_the_same_bodies():
    """The DEL equations do not depend on the coordinates: the same MuJoCo motion written with world or
    parent-relative rotations gives the same world poses (FK) of the predicted bodies."""
    world, parent = (
        chain_dataset(n_trajectories=2, steps=12, h=0.05, seed=3, rotations=r) for r in ("world", "parent")
    )
    preds = []
    for ds in (world, parent):
        truth = ds.pose()
        ro = _true_scheme(ds).rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), 12, TIGHT)
        preds.append(forward_kinematics(ds.tree, ro.pose))
    torch.testing.assert_close(preds[0].R, preds[1].R, atol=1e-9, rtol=0)
    torch.testing.assert_close(preds[0].p, preds[1].p, atol=1e-9, rtol=0)


def test_rollout_converges_to_mujoco_at_second_order():
    """Error at a fixed final time (1 s) for h = 0.05 and 0.025 (MuJoCo's own step 1e-3): ratio ~ 4."""
    errs = []
    for h, n in ((0.05, 20), (0.025, 40)):
        ds = chain_dataset(n_trajectories=2, steps=n, h=h, seed=5, links=3, joint_damping=0.05)
        truth = ds.pose()
        ro = _true_scheme(ds).rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, TIGHT)
        w_pred, w_true = forward_kinematics(ds.tree, ro.pose), forward_kinematics(ds.tree, truth)
        errs.append(float(position_error(w_pred.p[:, -1], w_true.p[:, -1]).mean()))
    order = torch.log2(torch.tensor(errs[0] / errs[1]))
    assert 1.6 < float(order) < 2.6, (errs, float(order))


def test_articulated_training_runs_end_to_end(tmp_path, monkeypatch):
    from helpers import compose_config
    from liedfl_cli.commands.train import run_train
    from liedfl_cli.solvers import runtime

    monkeypatch.setattr(runtime, "_current", runtime.current())  # run_train configures the runtime: restore it

    path = tmp_path / "chain.h5"
    save_dataset(chain_dataset(n_trajectories=10, steps=12, h=0.05, seed=1, links=3), path)
    cfg = compose_config(
        "train",
        overrides=[
            "dataset=file",
            f"dataset.path={path}",
            "model.kinetic=articulated",
            "train.epochs=3",
            "ui.progress=false",
            "eval.plots=false",
            f"paths.data_dir={tmp_path / 'data'}",
            f"paths.output_dir={tmp_path / 'run'}",
            "runtime.threads=1",
        ],
    )
    summary = run_train(cfg)
    run = tmp_path / "run"
    comps = json.loads((run / "components.json").read_text())
    assert comps["model"] == "ArticulatedLieDFLNN"
    assert any(c.startswith("tree (3 bodies") for c in comps["components"])
    rows = {r["model"]: r for r in csv.DictReader((run / "eval.csv").open())}
    assert {"model", "true_scheme", "constant_velocity"} <= set(rows)
    assert float(rows["true_scheme"]["one_step_vs_cv"]) < 0.05
    assert float(rows["model"]["one_step_rot_error_mean"]) > 0
    rec = json.loads((run / "recovery.json").read_text())
    assert rec["kinetic"] == "articulated" and len(rec["bodies"]) == 3
    assert summary["timings"]["epochs"] == 3


def test_articulated_needs_a_tree_in_the_data():
    from liedfl_cli.lie import ProductGroup
    from liedfl_cli.models.articulated.model import build_articulated
    from liedfl_cli.models.base import BuildContext

    ctx = BuildContext(group=ProductGroup(1, 2), h=0.05)
    with pytest.raises(ConfigError, match="needs a kinematic tree"):
        build_articulated(ctx, (), {}, "")


@pytest.mark.slow
def test_training_on_an_unseen_chain_beats_constant_velocity_tenfold():
    """The issue's acceptance figures at 400 epochs with the default loss (del) and the geometric start."""
    from liedfl_cli.models.base import LossOptions

    ds = chain_dataset(n_trajectories=128, steps=100, h=0.05, seed=99, links=3, rotations="world")
    train = ds.pose(ds.split["train"])
    test = ds.pose(ds.split["test"][:8])
    model = ArticulatedLieDFLNN(ds.tree, ds.h, forces={"rayleigh": {"coupling": "coupled"}})
    ts = model.training_set(train, 100)
    from pytorch_optimizer import SOAP

    opt = SOAP([p for p in model.parameters() if p.requires_grad], lr=3e-3)
    opts = LossOptions()
    gen = torch.Generator().manual_seed(0)
    for _ in range(400):
        perm = torch.randperm(ts.n, generator=gen)
        for a in range(0, ts.n, 1024):
            opt.zero_grad()
            loss, _ = model.loss(ts.batch(perm[a : a + 1024], gen, 10), opts)
            loss.backward()
            opt.step()
    pred, _ = one_step_predictions(model, test)
    target = test.index((slice(None), slice(2, None)))
    cv = constant_velocity_one_step(ds.group, test)
    assert float(geodesic_error(pred.R, target.R).mean() / geodesic_error(cv.R, target.R).mean()) <= 0.1
    g0, g1 = test.index((slice(None), 0)), test.index((slice(None), 1))
    ro = model.rollout(g0, g1, 50)
    cvr = constant_velocity_rollout(ds.group, g0, g1, 50)
    t50 = test.index((slice(None), slice(0, 51)))
    assert ro.n_failed == 0
    assert float(geodesic_error(ro.pose.R, t50.R).mean()) <= 0.2 * float(geodesic_error(cvr.R, t50.R).mean())
