"""A trained run rolled out on other data (`liedfl rollout run=<run> dataset=<scene> ...`, `dataset=file`),
training on a user's HDF5 file, and the dataset options of every scene (`dataset.noise`,
`dataset.smoothing`: data/transforms.py)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.data.hdf5 import load_dataset, save_dataset
from liedfl_cli.data.scene_common import config_hash
from liedfl_cli.data.scenes import generate, get_dataset
from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import so3

SMOKE = ["budget=smoke", "ui.progress=false", "eval.plots=false"]


def _compose(name: str, overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


@pytest.fixture
def _liedfl(run_main):
    """_liedfl(*args, cwd) -> CompletedProcess of the command run in-process (`run_main`)."""
    return run_main


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, Path]:
    """A smoke-trained LieDFLNN on the free rigid body (SO(3), h = 0.1): (run dir, data dir)."""
    from liedfl_cli.commands.train import run_train

    tmp = tmp_path_factory.mktemp("other_data")
    cfg = _compose("train", [*SMOKE, f"paths.output_dir={tmp / 'run'}", f"paths.data_dir={tmp / 'data'}"])
    run_train(cfg)
    return tmp / "run", tmp / "data"


def _rollout(run_dir: Path, data_dir: Path, *overrides: str) -> dict:
    from liedfl_cli.commands.rollout import run_rollout

    cfg = _compose("rollout", [f"run={run_dir}", f"paths.data_dir={data_dir}", *SMOKE[1:], *overrides])
    return run_rollout(cfg)


def test_rollout_on_other_data_writes_its_own_folder(run):
    run_dir, data_dir = run
    own = {n: (run_dir / n).read_bytes() for n in ("rollout.h5", "eval.csv", "eval.md")}
    other = ["dataset=free_rigid_body", "dataset.n_trajectories=14", "dataset.n_test=3", "dataset.seed=5"]
    out = _rollout(run_dir, data_dir, *other, "steps=15")
    folder = Path(out["dir"])
    assert folder.parent == run_dir / "rollouts" and folder.name.endswith("_free_rigid_body_steps15")
    src = json.loads((folder / "source.json").read_text())
    assert (
        src["scene"] == "free_rigid_body" and src["dataset_config"]["seed"] == 5 and len(src["test_trajectories"]) == 3
    )
    ds = load_dataset(src["dataset_path"])
    assert ds.n_trajectories == 14
    with open(folder / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["model"] for r in rows] == ["model", "true_scheme", "constant_velocity", "constant_acceleration"]
    assert int(rows[0]["rollout_steps"]) == 15
    assert {n: (run_dir / n).read_bytes() for n in own} == own  # the run's own files are untouched
    # liedfl eval of that folder evaluates against the same (other) dataset
    (folder / "eval.csv").unlink()
    from liedfl_cli.commands.evaluate import run_eval

    eval_cfg = _compose("eval", [f"run={run_dir}", f"rollout={folder}", f"paths.data_dir={data_dir}", *SMOKE[1:]])
    rows2 = run_eval(eval_cfg)
    assert rows2[0]["rel_rot_error_mean"] == pytest.approx(float(rows[0]["rel_rot_error_mean"]), rel=1e-12)


def test_noisy_and_smoothed_other_data(run):
    """Dataset overrides reach the other dataset: its noise, its smoothing."""
    run_dir, data_dir = run
    base = ["dataset=free_rigid_body", "dataset.n_trajectories=14", "dataset.n_test=3", "steps=12"]
    out = _rollout(run_dir, data_dir, *base, "dataset.noise.rotation=0.01", "dataset.smoothing={window: 7, order: 2}")
    src = json.loads((Path(out["dir"]) / "source.json").read_text())
    ds = load_dataset(src["dataset_path"])
    assert ds.params["noise"]["rotation"] == 0.01 and ds.params["smoothing"]["window"] == 7


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["dataset=heavy_se3"], "models SO(3) but dataset 'heavy_se3' is SE(3): the model's group must be the data's"),
        (["dataset=cmu_cartwheel"], "models SO(3) but dataset 'cmu_cartwheel' is SE(3) x SO(3)^22"),
        (["dataset=free_rigid_body", "dataset.h=0.05", "dataset.n_trajectories=12", "dataset.steps=20",
          "dataset.rollout_steps=20", "dataset.train_steps=20"],
         "was trained with h=0.1 but dataset 'free_rigid_body' has h=0.05"),
    ],
)  # fmt: skip
def test_rollout_on_data_the_model_does_not_fit_is_a_one_line_error(run, overrides, message, _liedfl):
    run_dir, data_dir = run
    before = sorted(p.name for p in (run_dir / "rollouts").iterdir()) if (run_dir / "rollouts").is_dir() else []
    proc = _liedfl("rollout", f"run={run_dir}", f"paths.data_dir={data_dir}", *overrides, *SMOKE[1:], cwd=run_dir)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(lines) == 1 and message in lines[0], proc.stderr
    after = sorted(p.name for p in (run_dir / "rollouts").iterdir()) if (run_dir / "rollouts").is_dir() else []
    assert after == before


def test_a_users_file_trains_and_rolls_out(run, tmp_path):
    """`dataset=file dataset.path=<h5>`: a file without generator metadata, for rollout and for training."""
    run_dir, data_dir = run
    src, _ = get_dataset(_compose("train", ["budget=smoke"]).dataset, data_dir)
    src.params, src.scene = {}, "my_recordings"
    path = save_dataset(src, tmp_path / "mine.h5")
    out = _rollout(run_dir, data_dir, "dataset=file", f"dataset.path={path}", "steps=10")
    assert Path(out["dir"]).name.endswith("_my_recordings_steps10")
    recorded = Path(json.loads((Path(out["dir"]) / "source.json").read_text())["dataset_path"])
    assert recorded.parent == data_dir.resolve() and recorded.name.startswith("file-")  # the cached copy
    assert load_dataset(recorded).params["source"]["file"] == str(path)  # of the user's file
    from liedfl_cli.commands.train import run_train

    cfg = _compose(
        "train",
        [*SMOKE, "dataset=file", f"dataset.path={path}", f"paths.output_dir={tmp_path / 'r'}", "train.epochs=1"],
    )
    summary = run_train(cfg)
    notes = json.loads((tmp_path / "r" / "components.json").read_text())["notes"]
    # nothing declared: auto builds no learned potential and names the override (issue 21, item 4)
    assert len(notes) == 1 and notes[0].startswith("potential: auto: none") and "model.potential=mlp" in notes[0]
    assert summary["rollout"]["model"]["n_failed"] == 0
    with pytest.raises(ConfigError, match="dataset.path"):
        get_dataset({"name": "file", "path": "???"}, data_dir)  # (the data layer takes plain mappings)
    with pytest.raises(ConfigError, match="unknown config key 'dataset.omega'"):
        get_dataset({"name": "file", "path": str(path), "omega": 1}, data_dir)


# ----------------------------------------------------------------------------- noise and smoothing
def _scene(name: str, **kw) -> dict:
    c = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "dataset" / f"{name}.yaml"))
    c.pop("defaults", None)
    c.update({"n_trajectories": 6, "n_test": 2, "steps": 60, "train_steps": 40, "rollout_steps": 60, **kw})
    return c


@pytest.mark.parametrize("name", ["free_rigid_body", "heavy_so3", "heavy_se3", "two_body", "pd_control"])
def test_noise_and_smoothing_work_on_every_scene(name):
    if name == "pd_control":
        c = _scene(name, n_trajectories=2, n_test=1)
    elif name == "two_body":  # the noise and smoothing act on any trajectory: a coarser ODE tolerance (6x faster)
        c = _scene(name, solver={"method": "RK45", "rtol": 1e-6, "atol": 1e-8})
    else:
        c = _scene(name)
    clean = generate(c)
    noisy = generate({**c, "noise": {"rotation": 1e-2, "position": 1e-2}})
    both = generate({**c, "noise": {"rotation": 1e-2, "position": 1e-2}, "smoothing": {"window": 11, "order": 3}})
    np.testing.assert_array_equal(noisy.extras["R_clean"], clean.R)  # the clean poses are kept
    for ds in (noisy, both):
        assert so3.orthogonality_error(torch.from_numpy(ds.R)).max() < 1e-12  # still rotations
        assert np.abs(np.linalg.det(ds.R) - 1).max() < 1e-12

    def err(ds):
        d = so3.geodesic_distance(torch.from_numpy(ds.R), torch.from_numpy(clean.R)).numpy()
        return float(np.sqrt((d[:, 10:-10] ** 2).mean()))  # away from the ends

    assert 0.01 < err(noisy) < 0.025  # |sigma N(0, I_3)| ~ sqrt(3) sigma
    assert err(both) < 0.6 * err(noisy)
    if clean.n_se3:
        p_err = lambda ds: float(np.sqrt(((ds.p - clean.p)[:, 10:-10] ** 2).sum(-1).mean()))
        assert p_err(both) < 0.6 * p_err(noisy)
    assert both.params["smoothing"]["window"] == 11 and both.params["noise"]["rotation"] == 1e-2
    again = generate({**c, "noise": {"rotation": 1e-2, "position": 1e-2}})
    np.testing.assert_array_equal(again.R, noisy.R)  # reproducible from the dataset seed


def test_smoothing_leaves_uniform_rotation_unchanged_and_clean_data_close():
    c = _scene("free_rigid_body", physics={"J": [1.0, 1.0, 1.0], "m": 0.5, "rho": [0, 0, 0], "g": 0.0, "D": [0.0] * 3})
    clean = generate(c)  # a spherical free body turns at constant angular velocity
    sm = generate({**c, "smoothing": {"window": 9, "order": 2}})
    np.testing.assert_allclose(sm.R, clean.R, atol=1e-11)


def test_options_off_do_not_change_the_cache_name():
    c = _scene("heavy_se3")
    plain = {k: v for k, v in c.items() if k not in ("noise", "smoothing")}
    assert config_hash(c) == config_hash(plain)  # noise zeros and smoothing null are "off"
    assert config_hash({**c, "noise": {"rotation": 1e-3, "position": 0.0}}) != config_hash(plain)


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("smoothing", {"window": 10, "order": 2}, "must be odd"),
        ("smoothing", {"window": 5, "order": 5}, "order"),
        ("smoothing", {"window": 5}, "dataset.smoothing must be"),
        ("noise", {"rotation": -1.0}, "non-negative"),
        ("noise", {"rot": 1.0}, "dataset.noise must be"),
    ],
)
def test_bad_options_are_config_errors(key, value, match):
    with pytest.raises(ConfigError, match=match):
        generate({**_scene("free_rigid_body"), key: value})


def test_smoothing_composes_from_the_command_line(tmp_path):
    cfg = _compose(
        "train", ["dataset=heavy_se3", "dataset.smoothing={window: 15, order: 4}", "dataset.noise.rotation=1e-3"]
    )
    assert cfg.dataset.smoothing.window == 15 and cfg.dataset.noise.rotation == 1e-3
    shutil.rmtree(tmp_path, ignore_errors=True)
