"""Teacher-forced one-step predictions stored at rollout time and the constant-velocity row of every
evaluation, end to end: `liedfl train budget=smoke`, then `liedfl eval` of the same run after its
rollout.h5 lost the one-step datasets (a file written before they existed)."""

from __future__ import annotations

import csv
import math

import h5py
import pytest
import torch

from helpers import compose_config


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    from liedfl_cli.commands.train import run_train

    tmp = tmp_path_factory.mktemp("one_step")
    cfg = compose_config(
        "train",
        [
            "budget=smoke",
            "ui.progress=false",
            "eval.plots=false",
            f"paths.data_dir={tmp}/data",
            f"paths.output_dir={tmp}/run",
        ],
    )
    return run_train(cfg), tmp / "run", tmp / "data"


def test_train_stores_one_step_predictions_and_reports_them_for_every_row(smoke_run):
    summary, run, _ = smoke_run
    rows = {r["model"]: r for r in summary["eval"]}
    assert list(rows) == ["model", "true_scheme", "constant_velocity", "constant_acceleration"]
    n = rows["model"]["error_steps"]
    with h5py.File(run / "rollout.h5") as f:
        T = f["traj_index"].shape[0]
        for group in ("model", "true_scheme"):
            assert f[f"{group}/one_step/R"].shape == (T, n - 1, 1, 3, 3)
            assert f[f"{group}/one_step/converged"][()].all()
            assert (
                f[f"{group}/one_step"].attrs["n_pairs"] == T * (n - 1) and f[f"{group}/one_step"].attrs["seconds"] > 0
            )
    for name, r in rows.items():
        keys = ("one_step_rot_error_mean", "one_step_vs_cv", "rollout_vs_cv", "geodesic_error_mean")
        for k in keys:
            assert r[k] is not None and math.isfinite(r[k]) and r[k] > 0, (name, k, r[k])
    # the true-parameter scheme beats constant velocity by far, step by step and over the rollout
    assert rows["true_scheme"]["one_step_vs_cv"] < 0.05 and rows["true_scheme"]["rollout_vs_cv"] < 0.05
    cv = rows["constant_velocity"]["one_step_rot_error_mean"]
    assert rows["model"]["one_step_vs_cv"] == pytest.approx(rows["model"]["one_step_rot_error_mean"] / cv, rel=1e-12)
    assert summary["rollout"]["model"]["one_step_seconds"] > 0
    with open(run / "eval.csv") as f:
        header = next(csv.reader(f))
    assert {"one_step_rot_error_mean", "one_step_vs_cv", "rollout_vs_cv"} <= set(header)


def test_the_stored_predictions_are_the_models_one_step_predictions(smoke_run):
    from liedfl_cli.config.runs import load_run
    from liedfl_cli.files.rollout_file import read_rollout
    from liedfl_cli.solvers.one_step import one_step_predictions

    _, run, data = smoke_run
    _, model, dataset, _ = load_run(run, data)
    rf = read_rollout(run / "rollout.h5")
    n = min(rf.steps, dataset.n_steps)
    truth = dataset.pose(rf.traj_index)
    pred, conv = one_step_predictions(model, truth.index((slice(None), slice(0, n + 1))))
    assert rf.model.one_step is not None
    torch.testing.assert_close(torch.from_numpy(rf.model.one_step.R), pred.R, rtol=0, atol=1e-12)
    assert conv.all()


def test_eval_of_a_run_whose_rollout_file_has_no_one_step_data(smoke_run, tmp_path):
    """`liedfl eval run=<old run>`: the constant-velocity row is still computed (it needs only the data),
    the one-step columns of the rolled-out models are blank, nothing crashes."""
    import shutil

    from liedfl_cli.commands.evaluate import run_eval

    _, run, data = smoke_run
    old = tmp_path / "old_run"
    shutil.copytree(run, old)
    with h5py.File(old / "rollout.h5", "r+") as f:
        for group in ("model", "true_scheme"):
            del f[f"{group}/one_step"]
    rows = {
        r["model"]: r
        for r in run_eval(
            compose_config("eval", [f"run={old}", f"paths.data_dir={data}", "ui.progress=false", "eval.plots=false"])
        )
    }
    assert list(rows) == ["model", "true_scheme", "constant_velocity", "constant_acceleration"]
    for name in ("model", "true_scheme"):
        assert rows[name]["one_step_rot_error_mean"] is None and rows[name]["one_step_vs_cv"] is None
        assert math.isfinite(rows[name]["rollout_vs_cv"])
    assert math.isfinite(rows["constant_velocity"]["one_step_rot_error_mean"])
    with open(old / "eval.csv") as f:
        csv_rows = {r["model"]: r for r in csv.DictReader(f)}
    assert (
        csv_rows["model"]["one_step_rot_error_mean"] == ""
        and float(csv_rows["constant_velocity"]["one_step_rot_error_mean"]) > 0
    )


def test_constant_acceleration_is_exact_on_constant_acceleration_motion():
    """A rotation about a fixed axis with a quadratic angle and a quadratic position: the
    constant-acceleration guess is exact (to rounding) from its fourth pose on, constant velocity is not."""
    from liedfl_cli.lie import Pose, ProductGroup, so3
    from liedfl_cli.solvers.one_step import constant_acceleration_one_step, constant_velocity_one_step

    G = ProductGroup(1, 0)
    t = 0.1 * torch.arange(8, dtype=torch.float64)
    a = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    a = a / a.norm()
    R = so3.exp((0.2 + 0.7 * t + 1.3 * t**2)[:, None] * a)[None, :, None]
    p = (torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) * t[:, None] + 0.5 * t[:, None] ** 2)[None, :, None]
    truth = Pose(R, p)
    ca, cv = constant_acceleration_one_step(G, truth), constant_velocity_one_step(G, truth)
    assert ca.R.shape == cv.R.shape == (1, 6, 1, 3, 3)
    assert torch.allclose(ca.R[:, 0], cv.R[:, 0])  # g_2: only two poses before it
    assert float((ca.R[:, 1:] - R[:, 3:]).abs().max()) < 1e-13
    assert float((ca.p[:, 1:] - p[:, 3:]).abs().max()) < 1e-13
    assert float((cv.R[:, 1:] - R[:, 3:]).abs().max()) > 1e-3
