"""Same horizon or no ratio: a rollout cut short by a Newton failure is compared with the references
over the same samples (each trajectory up to its first failure), and both sides are stored."""

from __future__ import annotations

import csv

import numpy as np
import torch

from liedfl_cli.commands.evaluate import run_eval_from_objects
from liedfl_cli.config.typed import EvalConfig, RunConfig
from liedfl_cli.data.hdf5 import Dataset
from liedfl_cli.files.rollout_file import RolloutEntry, write_rollout
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
    ent = RolloutEntry(
        R=R,
        p=np.zeros((T, N + 1, 0, 3)),
        converged=conv,
        iterations=np.full((T, N - 1), 2),
        residual_norm=np.zeros((T, N - 1)),
        attrs={"seconds": 1.0, "seconds_per_step": 0.1, "n_failed": 1, "first_failure": FAIL + 2, "n_trajectories": T},
    )
    write_rollout(tmp_path / "rollout.h5", steps=N, h=ds.h, scene=ds.scene, traj_index=idx, rollouts={"model": ent})
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
