"""No config or data error leaves a run folder behind (trust round 3): the errors that need the
data (found after loading) are raised before anything is written into the run folder, and what a
failing start wrote is taken back with the folder Hydra created. A folder that existed before is
left as it was."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from own_data import write_h5

from helpers import run_main

SMOKE = ("train", "dataset=heavy_so3", "budget=smoke")

CASES = {
    "val_fraction too large for the data": ("dataset.val_fraction=0.99",),
    "early stopping without a metric": ("train.early_stopping.patience=3", "train.select=last"),
    "newton loss on a baseline without it": ("train.loss=newton", "baseline=glnn_rk4"),
    "rollout horizon longer than the window": ("train.loss=rollout", "train.rollout_loss.horizon=50"),
    "one training step": ("dataset.train_steps=1",),
    "articulated model without a tree": ("model.kinetic=articulated",),
    "no test trajectories to roll out": ("dataset.n_test=0",),
    "validation horizon": ("train.val_horizon=1",),
}
NEEDLES = {
    "val_fraction too large for the data": "dataset.val_fraction=0.99",
    "early stopping without a metric": "train.early_stopping.patience",
    "newton loss on a baseline without it": "train.loss=newton is not available for glnn_rk4",
    "rollout horizon longer than the window": "train.rollout_loss.horizon=50",
    "one training step": "dataset.train_steps=1: need at least 2 steps",
    "articulated model without a tree": "model.kinetic=articulated needs a kinematic tree",
    "no test trajectories to roll out": "dataset.n_test=0",
    "validation horizon": "train.val_horizon=1",
}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("shared_data")


@pytest.mark.parametrize("case", list(CASES))
def test_a_config_error_leaves_no_run_folder(case, tmp_path, data_dir, capfd, monkeypatch):
    run = tmp_path / "outputs" / "run"
    proc = run_main(
        *SMOKE, *CASES[case], f"hydra.run.dir={run}", f"paths.data_dir={data_dir}", cwd=tmp_path,
        capfd=capfd, monkeypatch=monkeypatch,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    errors = [x for x in proc.stderr.splitlines() if x.startswith("error:")]  # (besides "generated ...")
    assert len(errors) == 1 and NEEDLES[case] in errors[0] and "Traceback" not in proc.stderr, proc.stderr
    assert not run.exists() and not (tmp_path / "outputs").exists()


def test_a_bad_data_file_leaves_no_run_folder(tmp_path, data_dir, capfd, monkeypatch):
    path = write_h5(tmp_path / "rec.h5")
    with h5py.File(path, "r+") as f:
        f.attrs["body_names"] = json.dumps("abc")  # round 3: once split into three bodies a, b, c
    run = tmp_path / "run"
    proc = run_main(
        "train", "dataset=file", f"dataset.path={path}", "budget=smoke", f"hydra.run.dir={run}",
        f"paths.data_dir={data_dir}", cwd=tmp_path, capfd=capfd, monkeypatch=monkeypatch,
    )  # fmt: skip
    assert proc.returncode == 2 and "attribute 'body_names' must be a JSON list" in proc.stderr, proc.stderr
    assert not run.exists()


def test_an_existing_folder_is_left_as_it_was(tmp_path, data_dir, capfd, monkeypatch):
    run = tmp_path / "mine"
    run.mkdir()
    (run / "notes.txt").write_text("the user's")
    proc = run_main(
        *SMOKE, *CASES["early stopping without a metric"], f"hydra.run.dir={run}", f"paths.data_dir={data_dir}",
        cwd=tmp_path, capfd=capfd, monkeypatch=monkeypatch,
    )  # fmt: skip
    assert proc.returncode == 2
    assert (run / "notes.txt").read_text() == "the user's"


# ----------------------------------------------------------------------------- the round's cosmetic findings
@pytest.mark.parametrize(
    "override, needle",
    [
        ("eval.plots=2", "error: eval.plots=2: must be true or false"),
        ("eval.plots=yes", "error: eval.plots='yes': must be true or false"),
        ("train.early_stopping=5", "error: train.early_stopping=5: must be a mapping of patience, min_delta"),
    ],
)
def test_a_flag_or_section_of_the_wrong_kind_is_our_one_line(override, needle, tmp_path, capfd, monkeypatch):
    proc = run_main(*SMOKE, override, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, capfd=capfd,
                    monkeypatch=monkeypatch)  # fmt: skip
    assert proc.returncode == 2 and proc.stderr.strip().startswith(needle), proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_an_unwritable_run_folder_is_one_line_without_hydras_warning(tmp_path, capfd, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    proc = run_main(*SMOKE, f"hydra.run.dir={blocker / 'run'}", cwd=tmp_path, capfd=capfd, monkeypatch=monkeypatch)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith(f"error: hydra.run.dir={blocker / 'run'}: cannot create the run folder")
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr  # no "UserWarning: Callback ... raised"


def test_an_empty_test_split_names_the_users_file_not_the_cache(tmp_path, data_dir, capfd, monkeypatch):
    path = write_h5(tmp_path / "rec.h5")
    with h5py.File(path, "r+") as f:
        del f["split/test"]
        f.create_dataset("split/test", data=np.zeros(0, dtype=np.int64))
    proc = run_main(
        "train", "dataset=file", f"dataset.path={path}", "budget=smoke", f"hydra.run.dir={tmp_path / 'run'}",
        f"paths.data_dir={data_dir}", cwd=tmp_path, capfd=capfd, monkeypatch=monkeypatch,
    )  # fmt: skip
    errors = [x for x in proc.stderr.splitlines() if x.startswith("error:")]
    assert proc.returncode == 2 and errors and errors[0].startswith(f"error: {path}: the dataset's test split is empty")
