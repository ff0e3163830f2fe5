"""Same horizon or no ratio: a rollout cut short by a Newton failure is compared with the references
over the same samples (each trajectory up to its first failure), and both sides are stored."""

from __future__ import annotations

import csv

import numpy as np
import torch

from helpers import write_model_rollout
from liedfl_cli.commands.evaluate import run_eval_from_objects
from liedfl_cli.config.typed import EvalConfig, RunConfig
from liedfl_cli.data.hdf5 import Dataset
from liedfl_cli.lie import so3

CFG = RunConfig("eval", eval=EvalConfig(plots=False))
N = 40
FAIL = 6  # the solve producing sample FAIL + 2 of trajectory 0 fails: its valid horizon is FAIL + 1


def _geo(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (..., 3, 3), by hand."""
    c = (np.einsum("...ij,...ij->...", A, B) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def _data(T: int = 3, seed: int = 0) -> Dataset:
    """Rotations with a slowly varying angular velocity (constant velocity's error grows with the step)."""
    rng = np.random.default_rng(seed)
    k = np.arange(N + 1, dtype=float)[None, :, None, None]
    w = rng.uniform(-0.1, 0.1, (T, 1, 1, 3)) * k + 0.002 * rng.standard_normal((T, 1, 1, 3)) * k**2
    R = (so3.exp(torch.from_numpy(rng.standard_normal((T, 1, 1, 3)))) @ so3.exp(torch.from_numpy(w))).numpy()
    return Dataset(
        R=R,
        p=np.zeros((T, N + 1, 0, 3)),
        h=0.1,
        scene="free_rigid_body",
        body_names=["b0"],
        body_kinds=["so3"],
        split={"train": [0], "test": [1, 2]},
    )


def test_ratio_to_constant_velocity_covers_the_models_valid_horizon(tmp_path):
    ds = _data()
    idx = ds.split["test"]
    T = len(idx)
    rng = np.random.default_rng(3)
    R = ds.R[idx].copy()
    noise = so3.exp(torch.from_numpy(0.01 * rng.standard_normal((T, N + 1, 1, 3)))).numpy()
    R[:, 2:] = R[:, 2:] @ noise[:, 2:]  # a model with a small error at every predicted sample
    R[0, FAIL + 2 :] = np.eye(3)  # trajectory 0: the failed solve and everything after it is garbage
    conv = np.ones((T, N - 1), bool)
    conv[0, FAIL] = False
    write_model_rollout(tmp_path / "rollout.h5", ds, idx, R, np.zeros((T, N + 1, 0, 3)), conv)
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    model, cv = rows["model"], rows["constant_velocity"]
    assert model["valid_horizon_min"] == FAIL + 1 and model["failed_trajectories"] == 1

    # by hand: the valid samples, the model's and constant velocity's mean geodesic errors over them
    valid = np.ones((T, N + 1), bool)
    valid[0, FAIL + 2 :] = False
    truth = ds.R[idx][:, :, 0]
    w = np.stack([so3.log(torch.from_numpy(truth[t, 0].T @ truth[t, 1])).numpy() for t in range(T)])
    cv_R = np.stack(
        [np.stack([truth[t, 0] @ so3.exp(torch.from_numpy(k * w[t])).numpy() for k in range(N + 1)]) for t in range(T)]
    )
    model_err = _geo(R[:, :, 0], truth)[valid].mean()
    cv_err = _geo(cv_R, truth)[valid].mean()
    cv_all = _geo(cv_R, truth).mean()
    assert abs(model["geodesic_error_mean"] - model_err) < 1e-9
    assert abs(model["cv_geodesic_error_same_horizon"] - cv_err) < 1e-9
    assert abs(model["rollout_vs_cv"] - model_err / cv_err) < 1e-9
    # constant velocity over all steps is another number: the old, mixed-horizon ratio would differ
    assert abs(cv["geodesic_error_mean"] - cv_all) < 1e-9 and cv_all > 1.05 * cv_err
    assert abs(model["rollout_vs_cv"] - model_err / cv_all) > 1e-3
    # both sides are in eval.csv
    with open(tmp_path / "eval.csv") as f:
        rec = {r["model"]: r for r in csv.DictReader(f)}["model"]
    assert float(rec["cv_geodesic_error_same_horizon"]) == model["cv_geodesic_error_same_horizon"]
    assert int(rec["valid_horizon_min"]) == FAIL + 1


def _paper_plan():
    import importlib.util
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("paper_plan_same_horizon", root / "scripts" / "paper_plan.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_whole_paper_table_prints_no_mixed_horizon_ratio(tmp_path):
    import json

    plan = _paper_plan()
    old = {"model": "model", "rel_rot_error_mean": 0.36, "rollout_vs_cv": 0.566, "newton_failures": 690}
    new = {
        "model": "model",
        "rel_rot_error_mean": 0.36,
        "rollout_vs_cv": 1.7,
        "cv_geodesic_error_same_horizon": 0.01,
        "valid_horizon_min": 12,
        "error_steps": 470,
        "newton_failures": 690,
    }
    clean = {"model": "model", "rel_rot_error_mean": 0.03, "rollout_vs_cv": 0.02, "newton_failures": 0}
    jobs = {
        f"experiment=exp{i}": {"epochs": 1, "wall_seconds": 1.0, "exit_code": 0, "eval": [ev]}
        for i, ev in enumerate((old, new, clean))
    }
    path = tmp_path / "full.json"
    path.write_text(json.dumps({"jobs": jobs}))
    lines = {ln.split("|")[1].strip(): ln for ln in plan.full_table(path).splitlines() if ln.startswith("| exp")}
    assert "not comparable (different horizons)" in lines["exp0"] and "0.566" not in lines["exp0"]
    assert "(valid horizon not recorded)" in lines["exp0"]
    assert "| 1.7 |" in lines["exp1"] and "(valid to step 12 of 470)" in lines["exp1"]
    assert "| 0.02 |" in lines["exp2"] and "valid" not in lines["exp2"]
    assert set(plan.EVAL_KEYS) >= {"cv_geodesic_error_same_horizon", "valid_horizon_min", "rollout_vs_best"}


def test_a_two_step_rollout_has_no_constant_acceleration_rollout_to_compare_with(tmp_path):
    """Constant acceleration starts from three true poses: over 2 steps its rollout is the data and
    predicts nothing, so its rollout row has no error and no horizon, and the model's best-reference ratio
    is constant velocity's (it was 1e10 against constant acceleration's rounding-level "error"); its
    one-step guesses still count."""
    steps = 2
    ds = _data()
    idx = ds.split["test"]
    T = len(idx)
    rng = np.random.default_rng(4)
    R = ds.R[idx][:, : steps + 1].copy()
    R[:, 2:] = R[:, 2:] @ so3.exp(torch.from_numpy(0.01 * rng.standard_normal((T, 1, 1, 3)))).numpy()
    write_model_rollout(tmp_path / "rollout.h5", ds, idx, R, np.zeros((T, steps + 1, 0, 3)))
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    model, cv, ca = rows["model"], rows["constant_velocity"], rows["constant_acceleration"]
    assert np.isnan(ca["geodesic_error_mean"]) and ca["valid_horizon_min"] is None
    assert ca["one_step_rot_error_mean"] is not None and np.isfinite(ca["one_step_rot_error_mean"])
    assert model["best_reference"] == "constant_velocity"
    assert abs(model["rollout_vs_best"] - model["geodesic_error_mean"] / cv["geodesic_error_mean"]) < 1e-12
    assert 0.01 < model["rollout_vs_best"] < 100
