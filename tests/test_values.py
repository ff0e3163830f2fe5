"""Values that used to crash or pass silently (issue 18, items 6, 7, 9, 10), beyond the table of
test_hostile.py: a diverging learning rate keeps the last good checkpoint, tampered or unusable
checkpoints on resume, the dataset's recorded SHA-256, resume from another directory, errors over
converged Newton steps only, OSErrors naming the user's file, warnings on stderr and once.

Run: `python -m pytest tests/test_values.py -q`.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from liedfl_cli.cli import CONF_DIR

FAST = ("budget=smoke", "ui.progress=false", "eval.plots=false")


def _compose(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=list(overrides))
    GlobalHydra.instance().clear()
    return cfg


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """One finished smoke run; its dataset is the smoke cache file under <root>/data."""
    from liedfl_cli.commands.train import run_train

    root = tmp_path_factory.mktemp("values_run")
    run_train(_compose([*FAST, f"paths.output_dir={root / 'run'}", f"paths.data_dir={root / 'data'}"]))
    return root / "run"


def _cli(args: list[str], capfd) -> tuple[int, str, str]:
    """`liedfl <args>` in-process: (exit code, stdout, stderr)."""
    from liedfl_cli.cli import main

    capfd.readouterr()
    saved = sys.argv
    sys.argv = ["liedfl", *args]
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    finally:
        sys.argv = saved
        GlobalHydra.instance().clear()
    out, err = capfd.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def _copy_run(trained: Path, tmp_path: Path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    return run


def _edit_checkpoint(path: Path, fn) -> None:
    payload = torch.load(path, map_location="cpu", weights_only=True)
    fn(payload)
    torch.save(payload, path)


# ----------------------------------------------------------------------------- item 6: divergence
def test_a_diverging_learning_rate_stops_with_one_line_and_keeps_the_last_good_checkpoint(trained, tmp_path):
    from liedfl_cli.commands.train import TrainingDiverged, run_train
    from liedfl_cli.files.checkpoint import load_checkpoint

    out = tmp_path / "run"
    cfg = _compose(
        [
            *FAST,
            "train.optimizer.lr=1e300",
            "train.epochs=4",
            "train.checkpoint_every=1",
            f"paths.output_dir={out}",
            f"paths.data_dir={trained.parent / 'data'}",
        ]
    )
    with pytest.raises(TrainingDiverged) as info:
        run_train(cfg)
    message = str(info.value)
    assert "learning rate diverged" in message and "train.optimizer.lr=1e+300" in message, message
    saved = load_checkpoint(out / "checkpoints" / "last.pt")
    assert f"(epoch {saved['epoch']}) is kept" in message, message
    assert saved["epoch"] < info.value.epoch  # the diverged epoch was never written over it
    assert all(torch.isfinite(v).all() and v.abs().max() < 1e100 for v in saved["state_dict"].values())


def test_the_scalar_inertia_path_overflows_to_non_finite_values_not_an_exception():
    from liedfl_cli.models.liedflnn.engines.core import _InertiaJdScalar

    r = torch.zeros(1, 3, dtype=torch.float64)
    out = _InertiaJdScalar.apply(r, torch.tensor([[1e300, 0.0, 0.0]], dtype=torch.float64))
    assert not torch.isfinite(out).all()
    out = _InertiaJdScalar.apply(torch.full((1, 3), 1e300, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64))
    assert not torch.isfinite(out).all()


# ----------------------------------------------------------------------------- item 6/7: resume
@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda p: p.__setitem__("epoch", "2"), "field 'epoch' must be an integer >= 0, got '2'"),
        (lambda p: p.__setitem__("epoch", -5), "field 'epoch' must be an integer >= 0, got -5"),
        (lambda p: p.__setitem__("epoch", True), "field 'epoch'"),
        (lambda p: p.__setitem__("history", "rows"), "field 'history' must be a list"),
        (lambda p: p.__setitem__("history", p["history"][:1]), "field 'history' has 1 rows for epoch 2"),
        (lambda p: p["history"].__setitem__(0, [1, 2]), "field 'history[0]' is not a mapping"),
        (lambda p: p["history"][1].__setitem__("epoch", 7), "field 'history[1].epoch' must be 2, got 7"),
        (lambda p: p["history"][0].__setitem__("seconds", "slow"), "field 'history[0].seconds' must be a number"),
    ],
    ids=[
        "epoch-text",
        "epoch-negative",
        "epoch-bool",
        "history-text",
        "history-short",
        "row-list",
        "row-epoch",
        "row-seconds",
    ],  # fmt: skip
)
def test_resume_refuses_a_tampered_epoch_or_history(trained, tmp_path, capfd, edit, needle):
    run = _copy_run(trained, tmp_path)
    ckpt = run / "checkpoints" / "last.pt"
    _edit_checkpoint(ckpt, edit)
    before = ckpt.read_bytes()
    code, _, err = _cli(["train", f"resume={run}", "epochs=4", "ui.progress=false"], capfd)
    line = _one_error_line(err)
    assert code == 2 and str(ckpt) in line and needle in line, line
    assert ckpt.read_bytes() == before


def test_resume_refuses_unusable_weights_naming_the_checkpoint(trained, tmp_path, capfd):
    run = _copy_run(trained, tmp_path)
    ckpt = run / "checkpoints" / "last.pt"
    _edit_checkpoint(ckpt, lambda p: [v.mul_(1e300) for v in p["state_dict"].values() if v.is_floating_point()])
    before = ckpt.read_bytes()
    code, _, err = _cli(["train", f"resume={run}", "epochs=4", "ui.progress=false"], capfd)
    line = _one_error_line(err)
    assert code == 2 and str(ckpt) in line and "weights are unusable" in line, line
    assert ckpt.read_bytes() == before


# ----------------------------------------------------------------------------- item 7: the dataset file
def test_the_checkpoint_records_the_datasets_sha256(trained):
    from liedfl_cli.files.checkpoint import load_checkpoint
    from liedfl_cli.files.dataset_identity import file_sha256

    payload = load_checkpoint(trained / "checkpoints" / "last.pt")
    assert Path(payload["dataset_path"]).is_absolute()
    assert payload["dataset_sha256"] == file_sha256(payload["dataset_path"])


def test_a_changed_dataset_file_is_refused_unless_accepted(trained, tmp_path, capfd):
    from liedfl_cli.files.checkpoint import load_checkpoint

    run = _copy_run(trained, tmp_path)
    data = tmp_path / "data.h5"
    shutil.copy(load_checkpoint(run / "checkpoints" / "last.pt")["dataset_path"], data)
    for name in ("last.pt", "best.pt"):
        if (run / "checkpoints" / name).is_file():
            _edit_checkpoint(run / "checkpoints" / name, lambda p: p.__setitem__("dataset_path", str(data)))
    import h5py

    with h5py.File(data, "r+") as f:  # the same trajectories, another file
        f.attrs["edited"] = "yes"
    code, _, err = _cli(["rollout", f"run={run}", "ui.progress=false", "eval.plots=false"], capfd)
    line = _one_error_line(err)
    assert code == 2 and str(data) in line and "changed since" in line, line
    assert not (run / "rollouts").exists()
    code, _, err = _cli(
        ["rollout", f"run={run}", "ui.progress=false", "eval.plots=false", "accept_changed_dataset=true"], capfd
    )
    assert code == 0, err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning:") and "changed since" in ln]
    assert len(warnings) == 1, err


def test_resume_from_another_directory_with_a_relative_dataset_path(trained, tmp_path, monkeypatch, capfd):
    from liedfl_cli.files.checkpoint import load_checkpoint

    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    shutil.copy(load_checkpoint(trained / "checkpoints" / "last.pt")["dataset_path"], first / "mine.h5")
    monkeypatch.chdir(first)
    run = tmp_path / "run"
    args = ["train", *FAST, "dataset=file", "dataset.path=mine.h5", f"hydra.run.dir={run}", "rollout.enabled=false"]
    code, _, err = _cli(args, capfd)
    assert code == 0, err
    assert load_checkpoint(run / "checkpoints" / "last.pt")["config"]["dataset"]["path"] == str(first / "mine.h5")
    monkeypatch.chdir(second)
    code, _, err = _cli(["train", f"resume={run}", "epochs=3", "ui.progress=false"], capfd)
    assert code == 0, err
    assert load_checkpoint(run / "checkpoints" / "last.pt")["epoch"] == 3


# ----------------------------------------------------------------------------- item 9: Newton failures
def _synthetic_rollout(truth, fail_at: dict[int, int]):
    """A rollout entry equal to the truth, except that trajectory t fails at sample fail_at[t] (its
    solve there did not converge) and every pose from it on is garbage (the identity)."""
    from liedfl_cli.files.rollout_file import RolloutEntry

    R, p = truth.R.numpy().copy(), truth.p.numpy().copy()
    T, S1 = R.shape[:2]
    converged = np.ones((T, S1 - 2), dtype=bool)
    for t, k in fail_at.items():
        converged[t, k - 2] = False
        R[t, k:] = np.eye(3)
    return RolloutEntry(R=R, p=p, converged=converged, iterations=np.ones((T, S1 - 2), dtype=np.int64))


def test_errors_cover_converged_steps_only_with_the_valid_horizon_and_failure_count(trained):
    from liedfl_cli.commands.evaluate import _rows
    from liedfl_cli.data.hdf5 import load_dataset
    from liedfl_cli.files.checkpoint import load_checkpoint
    from liedfl_cli.files.rollout_file import RolloutFile

    dataset = load_dataset(load_checkpoint(trained / "checkpoints" / "last.pt")["dataset_path"])
    idx = np.asarray(dataset.test_idx)[:2]
    truth = dataset.pose(idx)
    n = truth.R.shape[1] - 1
    entry = _synthetic_rollout(truth, {0: 5})
    rf = RolloutFile(Path("x.h5"), n, dataset.h, idx, {"model": entry}, scene=dataset.scene)
    rows, curves = _rows(rf, truth, None, group=dataset.group)
    row = rows[0]
    scale = float(torch.linalg.matrix_norm(truth.R).mean())
    assert row["rel_rot_error_mean"] <= 1e-12 * scale  # the garbage after the failure is left out
    assert row["valid_horizon_min"] == 4 and row["failed_trajectories"] == 1
    assert row["valid_horizon_mean"] == pytest.approx((4 + n) / 2)
    assert row["excluded_samples"] == n + 1 - 5
    assert row["newton_failures"] == 1
    assert list(curves["model"]["valid_horizon"]) == [4, n]
    cv = next(r for r in rows if r["model"] == "constant_velocity")
    assert rows[-1]["model"] == "constant_acceleration"
    assert cv["model"] == "constant_velocity" and cv["valid_horizon_min"] == n and cv["failed_trajectories"] == 0


def test_without_any_converged_prediction_the_errors_are_nan_not_zero(trained):
    from liedfl_cli.commands.evaluate import _rows
    from liedfl_cli.data.hdf5 import load_dataset
    from liedfl_cli.files.checkpoint import load_checkpoint
    from liedfl_cli.files.rollout_file import RolloutFile

    dataset = load_dataset(load_checkpoint(trained / "checkpoints" / "last.pt")["dataset_path"])
    idx = np.asarray(dataset.test_idx)[:2]
    truth = dataset.pose(idx)
    n = truth.R.shape[1] - 1
    entry = _synthetic_rollout(truth, {0: 2, 1: 2})
    rf = RolloutFile(Path("x.h5"), n, dataset.h, idx, {"model": entry}, scene=dataset.scene)
    row = _rows(rf, truth, None, group=dataset.group)[0][0]
    assert np.isnan(row["rel_rot_error_mean"]) and np.isnan(row["geodesic_error_mean"])
    assert row["valid_horizon_min"] == 1 and row["failed_trajectories"] == 2


def test_a_forced_newton_failure_cuts_the_errors_in_a_real_rollout(trained, tmp_path, capfd):
    """solver.max_iter=1 with a tiny tolerance: every solve fails, so every trajectory's valid
    horizon is the data's first pair and the errors are NaN, and the warning goes to stderr."""
    import csv

    run = _copy_run(trained, tmp_path)
    args = ["rollout", f"run={run}", "ui.progress=false", "eval.plots=false", "solver.max_iter=1", "solver.tol=1e-300"]
    code, out, err = _cli(args, capfd)
    assert code == 0, err
    assert "Newton did not converge" in err and "Newton did not converge" not in out
    (folder,) = (run / "rollouts").iterdir()
    with open(folder / "eval.csv", newline="") as f:
        rows = {r["model"]: r for r in csv.DictReader(f)}
    model = rows["model"]
    assert model["valid_horizon_min"] == "1" and int(model["failed_trajectories"]) >= 1
    assert int(model["excluded_samples"]) > 0 and model["rel_rot_error_mean"] == "nan"
    assert "valid_horizon_min" in (folder / "eval.md").read_text()


# ----------------------------------------------------------------------------- item 6/10: OSErrors
def test_a_full_disk_names_the_users_file_in_one_line_and_leaves_no_temporary_file(trained, tmp_path, capfd):
    import liedfl_cli.files.checkpoint as checkpoint

    out = tmp_path / "run"

    def full(obj, f, *a, **k):
        Path(f).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(f))

    saved = checkpoint.torch.save
    checkpoint.torch.save = full
    try:
        args = ["train", *FAST, f"hydra.run.dir={out}", f"paths.data_dir={trained.parent / 'data'}"]
        code, _, err = _cli(args, capfd)
    finally:
        checkpoint.torch.save = saved
    line = _one_error_line(err)
    assert code == 2 and f"{out / 'checkpoints'}/" in line and "No space left on device" in line, line
    assert ".tmp" not in line and "Error executing job" not in err
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


def test_user_path_replaces_temporary_names():
    from liedfl_cli.config.preflight import user_path

    assert user_path("/a/b/.last.pt.tmp123: x") == "/a/b/last.pt: x"
    assert user_path("name = '/d/free-1.h5.tmp77', errno = 28") == "name = '/d/free-1.h5', errno = 28"
    assert user_path("/a/my.tmp/b.txt") == "/a/my.tmp/b.txt"
    assert user_path("/a/.eval.csv.tmp-node1-77-9f") == "/a/eval.csv"
    assert user_path("/a/.config.tmpl") == "/a/.config.tmpl"


# ----------------------------------------------------------------------------- item 10: warnings
def test_the_coarse_sampling_warning_of_a_users_file_is_printed_once(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(["data", "budget=smoke", "ui.progress=false", "dataset.initial.omega_std=12"], capfd)
    assert code == 0, err
    assert sum("sampled coarsely" in ln for ln in err.splitlines()) == 1, err
    (made,) = (tmp_path / "outputs" / "data").glob("*.h5")
    shutil.copy(made, tmp_path / "mine.h5")
    code, out, err = _cli(["data", "dataset=file", "dataset.path=mine.h5", "ui.progress=false"], capfd)
    assert code == 0, err
    coarse = [ln for ln in err.splitlines() if "sampled coarsely" in ln]
    assert len(coarse) == 1 and coarse[0].startswith("warning: mine.h5"), err
    assert "sampled coarsely" not in out


def test_messages_about_a_cached_copy_name_the_users_file(tmp_path):
    import warnings

    from omegaconf import OmegaConf

    from liedfl_cli.config.runs import _naming_the_users_file
    from liedfl_cli.errors import DatasetError, DataWarning

    cfg = OmegaConf.create({"dataset": {"name": "file", "path": "/home/me/mine.h5"}})
    cached = tmp_path / "file-abc.h5"
    with pytest.raises(DatasetError) as info, _naming_the_users_file(cfg, cached):
        raise DatasetError(f"{cached}: dataset 'R' is broken")
    assert str(info.value).endswith("(the cached copy of /home/me/mine.h5)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with _naming_the_users_file(cfg, cached):
            warnings.warn(f"{cached}: sampled coarsely", DataWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == [f"{cached}: sampled coarsely (the cached copy of /home/me/mine.h5)"]
