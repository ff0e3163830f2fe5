"""The rollout file (liedfl_cli/files/rollout_file.py: one writer, reader and validator of rollout.h5), the
general evaluation over it (spans of the columns) and the scene-evaluation registry.

Everything runs on small in-memory datasets and hand-made rollouts: no training."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch

from liedfl_cli.commands.evaluate import run_eval_from_objects
from liedfl_cli.config.typed import EvalConfig, RunConfig
from liedfl_cli.data.hdf5 import Dataset
from liedfl_cli.errors import DatasetError
from liedfl_cli.files.rollout_file import RolloutEntry, load_rollout, read_rollout, write_rollout
from liedfl_cli.lie import Pose, so3

N = 6  # dataset steps
TEST = [1, 2]


def tiny_dataset(n_se3: int = 0, T: int = 4, steps: int = N, seed: int = 0) -> Dataset:
    rng = np.random.default_rng(seed)
    B = n_se3 + 1
    R = so3.exp(torch.from_numpy(0.3 * rng.standard_normal((T, steps + 1, B, 3)))).numpy()
    return Dataset(
        R=R,
        p=rng.standard_normal((T, steps + 1, n_se3, 3)),
        h=0.1,
        scene="free_rigid_body",
        body_names=[f"b{i}" for i in range(B)],
        body_kinds=["se3"] * n_se3 + ["so3"],
        split={"train": [0, 3], "test": TEST},
    )


def entry(R: np.ndarray, p: np.ndarray) -> RolloutEntry:
    T, S = R.shape[0], R.shape[1] - 1
    return RolloutEntry(
        R=R.copy(),
        p=p.copy(),
        converged=np.ones((T, S - 1), bool),
        iterations=np.full((T, S - 1), 2),
        residual_norm=np.zeros((T, S - 1)),
        attrs={"seconds": 1.0, "seconds_per_step": 0.5, "n_failed": 0, "first_failure": -1, "n_trajectories": T},
    )


def perfect(ds: Dataset, path: Path, idx=TEST) -> Path:
    """A rollout file whose model reproduces the test trajectories exactly."""
    write_rollout(
        path, steps=ds.n_steps, h=ds.h, scene=ds.scene, traj_index=idx, rollouts={"model": entry(ds.R[idx], ds.p[idx])}
    )
    return path


def replace(path: Path, key: str, value) -> None:
    with h5py.File(path, "r+") as f:
        del f[key]
        f.create_dataset(key, data=value)


CFG = RunConfig("eval", eval=EvalConfig(plots=False))  # what a command passes on (config/typed.py)


# ----------------------------------------------------------------------------- format
def test_write_read_round_trip(tmp_path):
    ds = tiny_dataset(n_se3=1)
    path = perfect(ds, tmp_path / "rollout.h5")
    rf = load_rollout(path, ds)
    assert (rf.steps, rf.h, rf.scene, rf.group) == (N, 0.1, "free_rigid_body", "SE(3) x SO(3)")
    assert rf.traj_index.tolist() == TEST and list(rf.models) == ["model"]
    np.testing.assert_array_equal(rf.model.R, ds.R[TEST])
    np.testing.assert_array_equal(rf.model.p, ds.p[TEST])
    assert rf.model.converged.dtype == bool and rf.model.converged.shape == (2, N - 1)
    assert rf.model.first_failure is None and rf.model.n_failed == 0
    assert not list(tmp_path.glob(".*tmp*"))


def test_first_failure_is_the_sample_that_was_not_solved(tmp_path):
    """converged[:, j] flags the solve that produced sample j + 2: a failure of the very first solve is
    sample 2 (samples 0 and 1 are the given pair), in the file's attribute and in the evaluation."""
    ds = tiny_dataset()
    e = entry(ds.R[TEST], ds.p[TEST])
    e.converged[1, 0] = False
    e.converged[0, 3] = False
    fake = SimpleNamespace(
        pose=Pose(torch.from_numpy(e.R), torch.from_numpy(e.p)),
        converged=torch.from_numpy(e.converged),
        iterations=torch.from_numpy(e.iterations),
        residual_norm=torch.from_numpy(e.residual_norm),
        seconds=1.0,
    )
    rf = write_rollout(
        tmp_path / "rollout.h5", steps=N, h=ds.h, scene=ds.scene, traj_index=TEST, rollouts={"model": fake}
    )
    assert rf.model.first_failure == 2 and rf.model.n_failed == 2
    with h5py.File(tmp_path / "rollout.h5") as f:
        assert int(f["model"].attrs["first_failure"]) == 2 and int(f["model"].attrs["n_failed"]) == 2
    row = run_eval_from_objects(CFG, ds, tmp_path)[0]
    assert row["first_failure_step"] == 2 and row["newton_failures"] == 2


def test_solver_rollout_first_failure_matches_the_file():
    from liedfl_cli.solvers.rollout import Rollout

    T, S = 1, 5
    conv = torch.ones(T, S - 1, dtype=torch.bool)
    conv[0, 0] = False  # the solve for g_2 failed
    ro = Rollout(Pose(torch.zeros(T, S + 1, 1, 3, 3), torch.zeros(T, S + 1, 0, 3)), conv, conv.long(), conv.double(), 0)
    assert ro.first_failure() == 2


# ----------------------------------------------------------------------------- validation
def _edit_traj_count(path):  # one predicted trajectory for two test trajectories
    with h5py.File(path, "r+") as f:
        for k in ("R", "p", "converged", "iterations", "residual_norm"):
            a = f[f"model/{k}"][:1]
            del f[f"model/{k}"]
            f[f"model/{k}"] = a


def _edit_rank(path):
    with h5py.File(path, "r+") as f:
        a = f["model/R"][:, :, 0]
        del f["model/R"]
        f["model/R"] = a


def _edit_group(path):  # SE(3) x SO(3) poses for an SO(3) dataset
    with h5py.File(path, "r+") as f:
        R, p = f["model/R"][...], f["model/p"][...]
        del f["model/R"], f["model/p"]
        f["model/R"] = np.concatenate([R, R], axis=2)
        f["model/p"] = np.zeros(p.shape[:2] + (1, 3))
        f.attrs["group"] = "SE(3) x SO(3)"


def _set_attr(key, value):
    def edit(path):
        with h5py.File(path, "r+") as f:
            f.attrs[key] = value

    return edit


BAD_FILES = {
    "too_few_trajectories": (_edit_traj_count, ["'model/R'", "holds 1 trajectories", "'traj_index' lists 2"]),
    "wrong_rank": (_edit_rank, ["'model/R'", "rank 4"]),
    "wrong_group": (_edit_group, ["'model/R'", "SE(3) x SO(3)", "the dataset is on SO(3)"]),
    "traj_index_in_train_split": (lambda p: replace(p, "traj_index", [0, 2]), ["'traj_index'", "trajectory 0", "test"]),
    "traj_index_out_of_range": (
        lambda p: replace(p, "traj_index", [1, 9]),
        ["'traj_index'", "trajectory 9", "index 1"],
    ),
    "traj_index_not_integer": (lambda p: replace(p, "traj_index", [1.0, 2.0]), ["'traj_index'", "integers"]),
    "steps_longer_than_R": (_set_attr("steps", N + 4), ["'model/R'", f"'steps' = {N + 4}"]),
    "steps_not_a_number": (_set_attr("steps", "abc"), ["'steps'", "abc"]),
    "other_scene": (_set_attr("dataset_scene", "heavy_se3"), ["'dataset_scene'", "heavy_se3", "free_rigid_body"]),
    "other_h": (_set_attr("h", 0.05), ["'h'", "0.05"]),
    "converged_wrong_shape": (lambda p: replace(p, "model/converged", np.ones((2, N), bool)), ["'model/converged'"]),
    "missing_iterations": (lambda p: replace(p, "model/iterations", 0) or _drop(p, "model/iterations"), ["iterations"]),
    "no_model_group": (lambda p: _drop(p, "model"), ["'model'"]),
    "group_attr_disagrees": (_set_attr("group", "SE(3)"), ["'group'", "SE(3)"]),
}


def _drop(path, key):
    with h5py.File(path, "r+") as f:
        del f[key]


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_rollout_file_is_one_line_naming_file_and_field(case, tmp_path):
    ds = tiny_dataset()
    path = perfect(ds, tmp_path / "rollout.h5")
    edit, needles = BAD_FILES[case]
    edit(path)
    with pytest.raises(DatasetError) as e:
        load_rollout(path, ds)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{path}: "), msg
    for n in needles:
        assert n in msg, (n, msg)


def test_eval_refuses_a_rollout_with_fewer_trajectories_than_traj_index(tmp_path):
    """Issue 11: one predicted trajectory for two test trajectories gave a wrong error (broadcast) and
    overwrote the evaluation; now it is a one-line error and nothing is written."""
    ds = tiny_dataset()
    path = perfect(ds, tmp_path / "rollout.h5")
    _edit_traj_count(path)
    (tmp_path / "eval.csv").write_text("previous\n")
    with pytest.raises(DatasetError, match="holds 1 trajectories but 'traj_index' lists 2"):
        run_eval_from_objects(CFG, ds, tmp_path)
    assert (tmp_path / "eval.csv").read_text() == "previous\n"
    assert not (tmp_path / "eval.md").exists()


def test_write_refuses_inconsistent_content(tmp_path):
    ds = tiny_dataset()
    with pytest.raises(DatasetError, match="holds 2 trajectories but 'traj_index' lists 3"):
        write_rollout(
            tmp_path / "rollout.h5",
            steps=N,
            h=ds.h,
            scene=ds.scene,
            traj_index=[0, 1, 2],
            rollouts={"model": entry(ds.R[TEST], ds.p[TEST])},
        )
    assert list(tmp_path.iterdir()) == []


def test_not_an_hdf5_file(tmp_path):
    path = tmp_path / "rollout.h5"
    path.write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="not an HDF5 file"):
        read_rollout(path)
    with pytest.raises(DatasetError, match="rollout file not found"):
        read_rollout(tmp_path / "missing.h5")


# ----------------------------------------------------------------------------- spans
def test_rollout_longer_than_the_dataset(tmp_path):
    """Errors over the steps with ground truth; drift, non-finite step and Newton statistics over the whole
    rollout (issue 11: drift was cut to the dataset's length while the heading said the full length)."""
    ds = tiny_dataset()
    S = 3 * N
    R = np.concatenate([ds.R[TEST], np.repeat(ds.R[TEST][:, -1:], S - N, axis=1)], axis=1)
    p = np.zeros((2, S + 1, 0, 3))
    R[1, 2 * N, 0] *= 1.0 + 1e-6  # drift off SO(3) after the dataset ends
    e = entry(R, p)
    e.converged[0, S - 3] = False  # the solve for sample S - 1
    rf = write_rollout(tmp_path / "rollout.h5", steps=S, h=ds.h, scene=ds.scene, traj_index=TEST, rollouts={"model": e})
    assert rf.steps == S
    row = run_eval_from_objects(RunConfig("eval", eval=EvalConfig(plots=True)), ds, tmp_path)[0]
    assert row["rel_rot_error_mean"] == 0.0 and row["rel_rot_error_final"] == 0.0  # exact over 0..N
    assert row["max_orth_drift"] > 1e-6 and row["max_det_drift"] > 1e-6  # the drift at step 2N counts
    assert row["newton_failures"] == 1 and row["first_failure_step"] == S - 1
    assert (row["error_steps"], row["rollout_steps"]) == (N, S)
    curves = json.loads((tmp_path / "eval_curves.json").read_text())["model"]
    assert len(curves["rel_rot_error"]) == N + 1 and len(curves["orth_drift"]) == S + 1
    md = (tmp_path / "eval.md").read_text()
    assert f"x {S} steps" in md and f"over steps 0..{N}" in md and f"whole rollout, steps 0..{S}" in md
    with open(tmp_path / "eval.csv") as f:
        assert int(next(csv.DictReader(f))["rollout_steps"]) == S
    for name in ("error_vs_step", "drift_vs_step", "sphere", "predicted_vs_true"):
        assert (tmp_path / "plots" / f"{name}.png").stat().st_size > 1000


def test_nonfinite_step_is_the_first_step_of_any_trajectory(tmp_path):
    ds = tiny_dataset()
    R = ds.R[TEST].copy()
    R[0, 5, 0, 0, 0] = np.nan
    R[1, 3, 0, 1, 1] = np.inf
    write_rollout(
        tmp_path / "rollout.h5",
        steps=N,
        h=ds.h,
        scene=ds.scene,
        traj_index=TEST,
        rollouts={"model": entry(R, ds.p[TEST])},
    )
    assert run_eval_from_objects(CFG, ds, tmp_path)[0]["nonfinite_step"] == 3


# ----------------------------------------------------------------------------- registry
def test_scene_evaluations_are_one_explicit_registry():
    from liedfl_cli.data.scenes import SCENES
    from liedfl_cli.evaluation import SCENE_EVALS, run_extra_evals
    from liedfl_cli.evaluation.control import evaluate_control
    from liedfl_cli.evaluation.mocap import evaluate_mocap

    assert {"cmu_cartwheel": evaluate_mocap, "pd_control": evaluate_control} == SCENE_EVALS
    assert set(SCENE_EVALS) <= set(SCENES)
    assert run_extra_evals(CFG, None, tiny_dataset(), Path("unused")) is None  # no evaluation for this scene


# ----------------------------------------------------------------------------- constant velocity, one-step
def _cv_by_hand(R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity guesses of samples 2..N written out with matrices, not liedfl's group code:
    g_{k+1} = g_k (g_{k-1}^-1 g_k), i.e. R_k R_{k-1}^T R_k and p_k + R_k R_{k-1}^T (p_k - p_{k-1}) (SE(3)
    bodies first; exp(log(X)) = X for the small increments of these tracks)."""
    Rp, Rc = R[:, :-2], R[:, 1:-1]
    Rt = np.swapaxes(Rp, -1, -2)
    R_next = Rc @ Rt @ Rc
    m = p.shape[-2]
    dp = p[:, 1:-1] - p[:, :-2]
    p_next = p[:, 1:-1] + np.einsum("tkbij,tkbjl,tkbl->tkbi", Rc[:, :, :m], Rt[:, :, :m], dp)
    return R_next, p_next


def test_constant_velocity_row_has_finite_errors_and_no_newton_columns(tmp_path):
    ds = tiny_dataset(n_se3=1)
    perfect(ds, tmp_path / "rollout.h5")
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    assert list(rows) == ["model", "constant_velocity", "constant_acceleration", "constant_velocity_euclidean"]
    cv = rows["constant_velocity"]
    assert cv["name"] == "constant velocity"
    for k in ("rel_rot_error_mean", "geodesic_error_mean", "position_error_mean", "max_orth_drift"):
        assert np.isfinite(cv[k]) and cv[k] >= 0, k
    for k in ("one_step_rot_error_mean", "one_step_pos_error_mean", "geodesic_error_mean"):
        assert cv[k] > 1e-3, k  # random-ish tracks: constant velocity is far from exact
    assert cv["max_orth_drift"] < 1e-13  # exp(log(.)) keeps it on the group
    assert (
        cv["newton_failures"] is None and cv["mean_newton_iterations"] is None and cv.get("rollout_s_per_step") is None
    )
    assert cv["one_step_vs_cv"] == 1.0 and cv["rollout_vs_cv"] == 1.0
    assert rows["model"]["rollout_vs_cv"] < 1e-12  # the perfect model
    with open(tmp_path / "eval.csv") as f:
        csv_rows = {r["model"]: r for r in csv.DictReader(f)}
    assert (
        csv_rows["constant_velocity"]["newton_failures"] == ""
        and float(csv_rows["constant_velocity"]["rel_rot_error_mean"]) > 0
    )
    assert "| constant velocity |" in (tmp_path / "eval.md").read_text()


def test_constant_velocity_one_step_error_matches_an_independent_computation(tmp_path):
    from scipy.spatial.transform import Rotation

    ds = tiny_dataset(n_se3=1)
    perfect(ds, tmp_path / "rollout.h5")
    cv = next(r for r in run_eval_from_objects(CFG, ds, tmp_path) if r["model"] == "constant_velocity")
    R, p = ds.R[TEST], ds.p[TEST]
    R_next, p_next = _cv_by_hand(R, p)
    rel = np.swapaxes(R_next, -1, -2) @ R[:, 2:]
    geo = Rotation.from_matrix(rel.reshape(-1, 3, 3)).magnitude()
    pos = np.linalg.norm(p_next - p[:, 2:], axis=-1)
    assert cv["one_step_rot_error_mean"] == pytest.approx(geo.mean(), rel=1e-10, abs=1e-14)
    assert cv["one_step_pos_error_mean"] == pytest.approx(pos.mean(), rel=1e-10, abs=1e-14)


def test_constant_velocity_is_exact_for_a_uniform_motion(tmp_path):
    """g_k = g_0 X^k (a body turning at constant angular velocity, a screw motion on SE(3)): the constant-
    velocity rollout and its one-step guesses reproduce it to rounding error."""
    from scipy.spatial.transform import Rotation

    T, S = 4, 30
    rng = np.random.default_rng(1)
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec([0.05, -0.11, 0.07]).as_matrix()
    X[:3, 3] = [0.02, 0.01, -0.03]
    W = Rotation.from_rotvec([-0.08, 0.03, 0.12]).as_matrix()  # the SO(3) body's constant increment
    R = np.empty((T, S + 1, 2, 3, 3))
    p = np.empty((T, S + 1, 1, 3))
    for t in range(T):
        g = np.eye(4)
        g[:3, :3] = Rotation.random(random_state=t).as_matrix()
        g[:3, 3] = rng.standard_normal(3)
        Q = Rotation.random(random_state=10 + t).as_matrix()
        for k in range(S + 1):
            gk = g @ np.linalg.matrix_power(X, k)
            R[t, k, 0], p[t, k, 0] = gk[:3, :3], gk[:3, 3]
            R[t, k, 1] = Q @ np.linalg.matrix_power(W, k)
    ds = Dataset(
        R=R, p=p, h=0.1, scene="free_rigid_body", body_names=["a", "b"], body_kinds=["se3", "so3"],
        split={"train": [0, 3], "test": TEST},
    )  # fmt: skip
    perfect(ds, tmp_path / "rollout.h5")
    cv = next(r for r in run_eval_from_objects(CFG, ds, tmp_path) if r["model"] == "constant_velocity")
    for k in ("geodesic_error_mean", "position_error_mean", "one_step_rot_error_mean", "one_step_pos_error_mean"):
        assert cv[k] < 1e-12, (k, cv[k])


def _one_step_entry(ds: Dataset, idx=TEST) -> RolloutEntry:
    """A perfect rollout entry whose one-step predictions are the true samples 2..N."""
    from liedfl_cli.files.rollout_file import OneStep

    e = entry(ds.R[idx], ds.p[idx])
    K = ds.n_steps - 1
    e.one_step = OneStep(
        R=ds.R[idx][:, 2:].copy(),
        p=ds.p[idx][:, 2:].copy(),
        converged=np.ones((len(idx), K), bool),
        attrs={"seconds": 0.1, "n_pairs": len(idx) * K},
    )
    return e


def test_one_step_predictions_round_trip_and_give_the_one_step_columns(tmp_path):
    ds = tiny_dataset(n_se3=1)
    path = tmp_path / "rollout.h5"
    write_rollout(path, steps=N, h=ds.h, scene=ds.scene, traj_index=TEST, rollouts={"model": _one_step_entry(ds)})
    with h5py.File(path) as f:
        assert f["model/one_step/R"].shape == (2, N - 1, 2, 3, 3) and f["model/one_step/converged"].dtype == bool
    rf = load_rollout(path, ds)
    assert rf.model.one_step is not None and rf.model.one_step.attrs["n_pairs"] == 2 * (N - 1)
    np.testing.assert_array_equal(rf.model.one_step.p, ds.p[TEST][:, 2:])
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    m = rows["model"]
    assert m["one_step_rot_error_mean"] < 1e-7 and m["one_step_pos_error_mean"] == 0.0  # the true samples
    assert m["one_step_vs_cv"] == pytest.approx(
        m["one_step_rot_error_mean"] / rows["constant_velocity"]["one_step_rot_error_mean"]
    )
    assert m["one_step_newton_failures"] == 0


def test_an_old_rollout_file_without_one_step_data_still_evaluates(tmp_path):
    """Files written before one-step predictions were stored: the model's one-step columns are blank, the
    constant-velocity row (data only) is complete."""
    ds = tiny_dataset(n_se3=1)
    path = perfect(ds, tmp_path / "rollout.h5")
    with h5py.File(path) as f:
        assert "one_step" not in f["model"]
    rows = {r["model"]: r for r in run_eval_from_objects(RunConfig("eval", eval=EvalConfig(plots=True)), ds, tmp_path)}
    m, cv = rows["model"], rows["constant_velocity"]
    assert m["one_step_rot_error_mean"] is None and m["one_step_pos_error_mean"] is None and m["one_step_vs_cv"] is None
    assert m["rollout_vs_cv"] < 1e-12 and np.isfinite(cv["one_step_rot_error_mean"])
    with open(tmp_path / "eval.csv") as f:
        assert next(csv.DictReader(f))["one_step_rot_error_mean"] == ""
    assert "blank for rollout files written without one-step predictions" in (tmp_path / "eval.md").read_text()
    curves = json.loads((tmp_path / "eval_curves.json").read_text())
    assert len(curves["constant_velocity"]["geodesic_error"]) == N + 1
    assert (tmp_path / "plots" / "error_vs_step.png").stat().st_size > 1000


def _reshape_one_step(key, fn):
    def edit(path):
        with h5py.File(path, "r+") as f:
            a = fn(f[f"model/one_step/{key}"][...])
            del f[f"model/one_step/{key}"]
            f[f"model/one_step/{key}"] = a

    return edit


BAD_ONE_STEP = {
    "R_fewer_predictions_than_p": (_reshape_one_step("R", lambda a: a[:, 1:]), "'model/one_step/p'"),
    "R_wrong_rank": (_reshape_one_step("R", lambda a: a[:, :, 0]), "'model/one_step/R'"),
    "p_wrong_bodies": (_reshape_one_step("p", lambda a: np.concatenate([a, a], axis=2)), "'model/one_step/p'"),
    "converged_wrong_shape": (_reshape_one_step("converged", lambda a: a[:1]), "'model/one_step/converged'"),
    "too_many_predictions": (
        lambda path: [
            _reshape_one_step(k, lambda a: np.concatenate([a, a[:, :2]], axis=1))(path) for k in ("R", "p", "converged")
        ],
        "'model/one_step/R'",
    ),
    "missing_p": (lambda path: _drop(path, "model/one_step/p"), "'model/one_step' lacks dataset 'p'"),
}


@pytest.mark.parametrize("case", sorted(BAD_ONE_STEP))
def test_a_wrong_one_step_dataset_is_one_line_naming_the_field(case, tmp_path):
    ds = tiny_dataset(n_se3=1)
    path = tmp_path / "rollout.h5"
    write_rollout(path, steps=N, h=ds.h, scene=ds.scene, traj_index=TEST, rollouts={"model": _one_step_entry(ds)})
    edit, needle = BAD_ONE_STEP[case]
    edit(path)
    with pytest.raises(DatasetError) as e:
        load_rollout(path, ds)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and needle in msg, msg


def test_one_step_predictions_must_cover_the_steps_with_ground_truth(tmp_path):
    """validate_rollout: K = min(steps, dataset steps) - 1 one-step predictions per trajectory."""
    ds = tiny_dataset(n_se3=1)
    path = tmp_path / "rollout.h5"
    e = _one_step_entry(ds)
    e.one_step.R, e.one_step.p, e.one_step.converged = (
        e.one_step.R[:, :-1],
        e.one_step.p[:, :-1],
        e.one_step.converged[:, :-1],
    )
    write_rollout(path, steps=N, h=ds.h, scene=ds.scene, traj_index=TEST, rollouts={"model": e})  # self-consistent
    with pytest.raises(DatasetError, match=r"'model/one_step/R' holds 4 one-step predictions .* need .* = 5"):
        load_rollout(path, ds)
