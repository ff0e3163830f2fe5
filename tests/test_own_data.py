"""Your own data: `dataset=file` (an HDF5 file in liedfl's format) and `dataset=import` (CSV / NPZ
recordings), in process and end to end through the CLI (file -> trained model -> rollout plots)."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from own_data import IMPORT, H, motion, write_csv, write_h5

from liedfl_cli.data.files import complete_steps, default_split, resample
from liedfl_cli.data.hdf5 import load_dataset
from liedfl_cli.data.scenes import dataset_path, get_dataset
from liedfl_cli.errors import ConfigError, DatasetError

FILE = {
    "name": "file",
    "n_trajectories": None,
    "steps": None,
    "train_steps": None,
    "rollout_steps": None,
    "split": "auto",
    "test_fraction": 0.2,
    "n_test": None,
    "seed": 0,
    "noise": {"rotation": 0.0, "position": 0.0},
    "smoothing": None,
}


def test_the_scene_configs_hold_exactly_the_keys_the_scenes_accept():
    import yaml

    from liedfl_cli.cli import CONF_DIR
    from liedfl_cli.data.files import FILE_KEYS, IMPORT_KEYS
    from liedfl_cli.data.scene_common import TRAIN_TIME_KEYS

    for name, keys, ref in (("file", FILE_KEYS, FILE), ("import", IMPORT_KEYS, IMPORT)):
        c = yaml.safe_load((CONF_DIR / "dataset" / f"{name}.yaml").read_text())
        c.pop("defaults")
        assert set(TRAIN_TIME_KEYS) <= set(c), name  # the trainer's keys (validation split): no scene sees them
        assert set(c) - set(TRAIN_TIME_KEYS) == set(keys) == set(ref) | {"path"}, name


@pytest.fixture
def liedfl(run_main):
    """liedfl(*args, cwd, ok=True) -> CompletedProcess of the command run in-process (`run_main`; the
    process boundary is test_cli.py's)."""

    def run(*args: str, cwd: Path, ok: bool = True):
        return run_main(*args, cwd=cwd, ok=ok)

    return run


# ----------------------------------------------------------------------------- import
@pytest.mark.parametrize("rotation", ["wxyz", "xyzw", "matrix"])
def test_csv_import_recovers_the_recording(tmp_path, rotation):
    path, R, p = write_csv(tmp_path / "log.csv", rotation=rotation)
    ds, cached = get_dataset({**IMPORT, "path": str(path), "rotation": rotation}, tmp_path / "data")
    assert cached.parent == tmp_path / "data" and cached.name.startswith("import-")
    assert ds.group.name == "SE(3)" and ds.body_kinds == ["se3"] and ds.h == H
    assert np.abs(ds.R[:, :, 0] - R).max() < 1e-9 and np.abs(ds.p[:, :, 0] - p).max() < 1e-9
    np.testing.assert_allclose(ds.t, H * np.arange(21))
    # 3 trajectories, no split in a recording: the default split, 1 test trajectory
    assert len(ds.test_idx) == 1 and len(ds.train_idx) == 2 and ds.params["split_source"] == "default split"
    assert load_dataset(cached).n_trajectories == 3


def test_the_quaternion_convention_is_required_and_changes_the_data(tmp_path):
    path, R, _ = write_csv(tmp_path / "log.csv", rotation="xyzw")
    with pytest.raises(ConfigError, match=r"dataset\.rotation is required.*wxyz.*xyzw.*matrix"):
        get_dataset({**IMPORT, "path": str(path), "rotation": "???"}, tmp_path / "data")
    right, _ = get_dataset({**IMPORT, "path": str(path), "rotation": "xyzw"}, tmp_path / "data")
    wrong, _ = get_dataset({**IMPORT, "path": str(path), "rotation": "wxyz"}, tmp_path / "data")
    assert np.abs(right.R[:, :, 0] - R).max() < 1e-9 and np.abs(wrong.R[:, :, 0] - R).max() > 0.1


def test_several_named_bodies_and_npz(tmp_path):
    path, R, p = write_csv(tmp_path / "two.csv", bodies=["arm", "base"])
    ds, _ = get_dataset({**IMPORT, "path": str(path), "bodies": ["arm", "base"]}, tmp_path / "data")
    assert ds.body_names == ["arm", "base"] and ds.group.name == "SE(3)^2"
    assert np.abs(ds.R[:, :, 1] - R).max() < 1e-9
    t, R, p = motion(2, 15)
    np.savez(tmp_path / "one.npz", t=t, R=R[0], p=p[0])  # one trajectory, one body: no T, no body axis
    ds, _ = get_dataset({**IMPORT, "path": str(tmp_path / "one.npz"), "rotation": "matrix"}, tmp_path / "data")
    assert ds.n_trajectories == 1 and ds.group.name == "SE(3)" and np.abs(ds.R[0, :, 0] - R[0]).max() < 1e-12
    assert ds.params["split_overlap"] is True and ds.train_idx.tolist() == ds.test_idx.tolist() == [0]
    q = np.zeros((2, 15, 1, 4))
    q[..., 0] = 1.0
    np.savez(tmp_path / "two.npz", t=np.stack([t, t]), q=q, body_names=np.array(["gyro"]))  # SO(3): no p
    ds, _ = get_dataset({**IMPORT, "path": str(tmp_path / "two.npz")}, tmp_path / "data")
    assert ds.n_trajectories == 2 and np.allclose(ds.R, np.eye(3)) and ds.group.name == "SO(3)"
    assert ds.body_names == ["gyro"]
    np.savez(tmp_path / "bad.npz", t=t, R=R)  # R (T, n, 3, 3) needs t of shape (T, n)
    with pytest.raises(DatasetError, match=r"bad.npz: array 'R' has shape \(2, 15, 3, 3\); need \(15, 3, 3\)"):
        get_dataset({**IMPORT, "path": str(tmp_path / "bad.npz"), "rotation": "matrix"}, tmp_path / "data")


def test_non_uniform_stamps_fail_unless_resampled_on_the_group(tmp_path):
    path, R, p = write_csv(tmp_path / "jitter.csv", jitter=0.2)
    with pytest.raises(DatasetError, match=r"not uniform.*dataset\.resample=true"):
        get_dataset({**IMPORT, "path": str(path)}, tmp_path / "data")
    ds, _ = get_dataset({**IMPORT, "path": str(path), "resample": True, "h": H}, tmp_path / "data")
    # a uniform rotation is a geodesic: resampling along geodesics reproduces it; positions (a parabola)
    # are interpolated linearly between samples
    assert ds.n_steps == 20 and ds.h == H
    assert np.abs(ds.R[:, :, 0] - R).max() < 1e-9
    assert np.abs(ds.p[:, :, 0] - p).max() < 0.01


def test_resample_interpolates_rotations_along_geodesics():
    t, R, p = motion(1, 11)
    tn, Rn, pn = resample(t, R[0][:, None], p[0][:, None], H / 2)
    assert len(tn) == 21
    t2, R2, p2 = motion(1, 21, h=H / 2)
    assert np.abs(Rn[:, 0] - R2[0]).max() < 1e-12


def test_bad_recordings_are_one_line_errors(tmp_path):
    path, _, _ = write_csv(tmp_path / "log.csv")
    text = path.read_text().splitlines()
    (tmp_path / "noq.csv").write_text("\n".join([text[0].replace("q2", "qq")] + text[1:]))
    with pytest.raises(DatasetError, match=r"noq.csv: column 'q2' is missing"):
        get_dataset({**IMPORT, "path": str(tmp_path / "noq.csv")}, tmp_path / "data")
    (tmp_path / "nan.csv").write_text("\n".join([*text[:5], text[5].replace(text[5].split(",")[3], "abc"), *text[6:]]))
    with pytest.raises(DatasetError, match=r"nan.csv: line 6, column 'q1': 'abc' is not a number"):
        get_dataset({**IMPORT, "path": str(tmp_path / "nan.csv")}, tmp_path / "data")
    with pytest.raises(ConfigError, match=r"dataset.path=.*nope.csv: no such file"):
        get_dataset({**IMPORT, "path": str(tmp_path / "nope.csv")}, tmp_path / "data")
    with pytest.raises(ConfigError, match=r"dataset.rotation='quat'"):
        get_dataset({**IMPORT, "path": str(path), "rotation": "quat"}, tmp_path / "data")


# ----------------------------------------------------------------------------- file
def test_a_file_without_split_gets_the_default_split(tmp_path):
    path = write_h5(tmp_path / "nosplit.h5", n_traj=6, split=False)
    with pytest.raises(DatasetError, match="split"):
        load_dataset(path)  # (what `liedfl train` used to meet)
    ds, cached = get_dataset({**FILE, "path": str(path)}, tmp_path / "data")
    assert sorted([*ds.train_idx, *ds.test_idx]) == list(range(6)) and len(ds.test_idx) == 1
    assert "no split in the file" in ds.params["split_source"]
    assert load_dataset(cached).split["test"].tolist() == ds.test_idx.tolist()


def test_the_files_own_split_selection_and_crop(tmp_path):
    path = write_h5(tmp_path / "my.h5", n_traj=6, n_samples=21)
    ds, _ = get_dataset({**FILE, "path": str(path)}, tmp_path / "data")
    assert ds.test_idx.tolist() == [0] and ds.train_idx.tolist() == [1, 2, 3, 4, 5]
    small, _ = get_dataset({**FILE, "path": str(path), "n_trajectories": 3, "steps": 8}, tmp_path / "data")
    assert small.n_trajectories == 3 and small.n_steps == 8 and small.train_idx.tolist() == [1, 2]
    with pytest.raises(ConfigError, match=r"dataset.steps=40: .* has only 20 steps"):
        get_dataset({**FILE, "path": str(path), "steps": 40}, tmp_path / "data")
    again, _ = get_dataset({**FILE, "path": str(path), "split": "default", "n_test": 2}, tmp_path / "data")
    assert len(again.test_idx) == 2


def test_the_cache_follows_the_files_content_not_its_name(tmp_path):
    a = write_h5(tmp_path / "a.h5")
    b = tmp_path / "b.h5"
    b.write_bytes(a.read_bytes())
    pa, pb = dataset_path({**FILE, "path": str(a)}, tmp_path), dataset_path({**FILE, "path": str(b)}, tmp_path)
    assert pa == pb
    with h5py.File(b, "a") as f:
        f.attrs["h"] = 0.1
    assert dataset_path({**FILE, "path": str(b)}, tmp_path) != pa


def test_a_minimal_config_takes_the_shipped_defaults_and_noise_is_cached(tmp_path):
    """`{"name": "file", "path": ...}` from Python is the shipped file.yaml; noise and smoothing (every
    scene's options, data/transforms.py) apply to the kept part and are part of the cached copy."""
    path = write_h5(tmp_path / "my.h5")
    plain, p_plain = get_dataset({"name": "file", "path": str(path)}, tmp_path / "data")
    assert p_plain == dataset_path({**FILE, "path": str(path)}, tmp_path / "data")
    noisy_cfg = {**FILE, "path": str(path), "noise": {"rotation": 1e-3, "position": 0.0}}
    noisy, p_noisy = get_dataset(noisy_cfg, tmp_path / "data")
    assert p_noisy != p_plain and p_noisy.is_file()
    np.testing.assert_array_equal(noisy.extras["R_clean"], plain.R)
    assert 0 < np.abs(noisy.R - plain.R).max() < 1e-2
    again = load_dataset(p_noisy)  # what a run records and reloads
    np.testing.assert_array_equal(again.R, noisy.R)
    assert again.params["noise"]["rotation"] == 1e-3
    smooth, _ = get_dataset({**noisy_cfg, "smoothing": {"window": 5, "order": 2}}, tmp_path / "data")
    assert smooth.params["smoothing"]["window"] == 5


def test_null_steps_mean_all_steps(tmp_path):
    from liedfl_cli.data.dataset_config import DatasetConfig

    ds, _ = get_dataset({**FILE, "path": str(write_h5(tmp_path / "my.h5"))}, tmp_path / "data")
    cfg = DatasetConfig.from_mapping({"name": "file", "train_steps": None, "rollout_steps": None})
    complete_steps(cfg, ds)
    assert cfg.train_steps == cfg.rollout_steps == 20
    assert cfg.as_dict() == {"name": "file", "train_steps": 20, "rollout_steps": 20}
    with pytest.raises(ConfigError, match="train_steps=30"):
        complete_steps(DatasetConfig.from_mapping({"name": "file", "train_steps": 30, "rollout_steps": None}), ds)


def test_default_split():
    split, overlap = default_split(1, 0.2, None, 0)
    assert overlap and split["train"].tolist() == split["test"].tolist() == [0]
    split, overlap = default_split(2, 0.2, None, 0)
    assert not overlap and len(split["test"]) == 1 and len(split["train"]) == 1
    assert len(default_split(10, 0.2, None, 0)[0]["test"]) == 2
    with pytest.raises(ConfigError, match="n_test=3"):
        default_split(3, 0.2, 3, 0)


# ----------------------------------------------------------------------------- end to end
FAST = ["budget=smoke", "ui.progress=false"]


def test_csv_to_trained_model_to_rollout_plots_with_the_readme_commands(tmp_path, liedfl):
    """The README's path for a CSV of quaternions and positions: import, train, roll out, evaluate."""
    write_csv(tmp_path / "log.csv", n_traj=4, n_samples=21, rotation="xyzw")
    opts = ["dataset=import", "dataset.path=log.csv", "dataset.rotation=xyzw"]
    out = liedfl("data", *opts, cwd=tmp_path).stdout
    assert "4 trajectories x 20 steps on SE(3)" in out and "train on it: liedfl train dataset=file" in out
    liedfl("train", *opts, *FAST, cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    for name in ("error_vs_step", "drift_vs_step", "sphere", "predicted_vs_true", "loss"):
        assert (run / "plots" / f"{name}.png").stat().st_size > 1000, name
    summary = json.loads((run / "summary.json").read_text())
    assert summary["dataset"]["train_steps"] == 8 and summary["dataset"]["group"] == "SE(3)"
    log = (run / "train.log").read_text()
    assert "trained 2 epochs" in log and "rollout liedflnn: 11/11" in log
    liedfl("rollout", f"run={run}", "steps=15", "ui.progress=false", cwd=tmp_path)
    (folder,) = (run / "rollouts").iterdir()
    assert (folder / "plots" / "sphere.png").is_file()
    with open(folder / "eval.csv") as f:
        row = next(csv.DictReader(f))
    assert row["model"] == "model" and row["name"] == "liedflnn" and int(row["rollout_steps"]) == 15
    liedfl("eval", f"run={run}", "ui.progress=false", "eval.plots=false", cwd=tmp_path)


def test_train_on_a_file_without_split_and_refuse_an_empty_test_split_before_training(tmp_path, liedfl):
    write_h5(tmp_path / "nosplit.h5", n_traj=6, split=False)
    liedfl("train", "dataset=file", "dataset.path=nosplit.h5", *FAST, "eval.plots=false", cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    assert (run / "eval.csv").is_file() and "_file_liedflnn" in run.name
    # a file whose split has no test trajectory: a one-line error before anything is trained
    src = tmp_path / "notest.h5"
    write_h5(src, n_traj=6)
    with h5py.File(src, "a") as f:
        del f["split/test"]
        f["split/test"] = np.zeros(0, dtype=np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        proc = liedfl("train", "dataset=file", "dataset.path=notest.h5", *FAST, cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "test split is empty" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(p.name for p in (tmp_path / "outputs" / "runs").iterdir()) == [run.name]


def test_missing_path_is_rejected_before_the_run_folder_exists(tmp_path, liedfl):
    proc = liedfl("train", "dataset=file", *FAST, cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "dataset.path" in proc.stderr
    proc = liedfl("train", "dataset=file", "dataset.path=nope.h5", *FAST, cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "dataset.path=nope.h5: no such file" in proc.stderr
    assert not (tmp_path / "outputs" / "runs").exists() or not list((tmp_path / "outputs" / "runs").iterdir())


def test_the_group_comes_from_the_file(tmp_path):
    """dataset=file drops the `group` config: the file says which group it is (no mismatch error)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.cli import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["dataset=file", f"dataset.path={tmp_path / 'x.h5'}"])
    assert "group" not in cfg and cfg.dataset.split == "auto"
    assert Path(cfg.dataset.path).name == "x.h5"
