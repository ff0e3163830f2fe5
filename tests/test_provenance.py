"""Rollout provenance (issue 18 item 1): a rollout file records the run, model and checkpoint that wrote
it; `liedfl eval run=A rollout=<another run's file>` is refused and touches nothing of the other run; a
rollout that does not start from the data's first two poses is refused; a file without provenance still
evaluates, with a warning, and the evaluation is written under the run it evaluates."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import main_in_process, train_run
from liedfl_cli.files.checkpoint import file_sha256, load_checkpoint
from liedfl_cli.files.rollout_file import PROVENANCE

FAST = ("budget=smoke", "ui.progress=false", "eval.plots=false", "runtime.threads=1")


def _train(root: Path, name: str, *overrides: str) -> Path:
    return train_run(root, *FAST, *overrides, name=name)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """Run A (the default model) and run C (the GLNN-RK4 baseline) on the same smoke data."""
    root = tmp_path_factory.mktemp("provenance")
    return _train(root, "A"), _train(root, "C", "baseline=glnn_rk4")


def _cli(capfd, *args: str) -> tuple[int, str, str]:
    """`liedfl *args` in-process: (exit code, stdout, stderr)."""
    capfd.readouterr()
    code, extra = main_in_process(*args, cwd=Path.cwd())
    cap = capfd.readouterr()
    return code, cap.out, cap.err + extra


def _state(folder: Path) -> dict[str, tuple[str, int]]:
    """{relative path: (sha1, mtime_ns)} of every file under `folder`."""
    return {
        str(p.relative_to(folder)): (hashlib.sha1(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _eval(capfd, run: Path, rollout: Path, cwd: Path, monkeypatch) -> tuple[int, str, str]:
    monkeypatch.chdir(cwd)
    return _cli(capfd, "eval", f"run={run}", f"rollout={rollout}", "eval.plots=false", "runtime.threads=1")


def test_train_records_the_run_model_and_checkpoint_in_the_rollout_file(runs):
    a, c = runs
    for run, model in ((a, "liedflnn"), (c, "glnn_rk4")):
        run_id = json.loads((run / "summary.json").read_text())["run_id"]
        assert run_id and load_checkpoint(run / "checkpoints" / "last.pt")["run_id"] == run_id
        used = json.loads((run / "checkpoint.json").read_text())["checkpoint"]
        with h5py.File(run / "rollout.h5") as f:
            attrs = {k: str(f.attrs[k]) for k in PROVENANCE if k in f.attrs}
        assert attrs["run_id"] == run_id and attrs["model_name"] == model and attrs["dtype"] == "float64"
        assert attrs["run_dir"] == str(run.resolve()) and attrs["checkpoint"] == used
        assert attrs["checkpoint_sha256"] == file_sha256(run / "checkpoints" / used)
    assert (
        json.loads((a / "summary.json").read_text())["run_id"] != json.loads((c / "summary.json").read_text())["run_id"]
    )


def test_eval_of_another_runs_rollout_is_refused_and_touches_nothing(runs, tmp_path, capfd, monkeypatch):
    a, c = runs
    before_a, before_c = _state(a), _state(c)
    code, out, err = _eval(capfd, a, c / "rollout.h5", tmp_path, monkeypatch)
    assert code == 2, (code, out, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    assert str(c.resolve()) in lines[0] and str(a) in lines[0] and "glnn_rk4" in lines[0], lines[0]
    assert _state(c) == before_c and _state(a) == before_a
    assert not list(tmp_path.iterdir())


def test_a_rollout_that_does_not_start_from_the_data_is_refused(runs, tmp_path, capfd, monkeypatch):
    a, _ = runs
    bad = a / "tampered"
    bad.mkdir()
    try:
        shutil.copy2(a / "rollout.h5", bad / "rollout.h5")
        with h5py.File(bad / "rollout.h5", "r+") as f:
            traj = int(f["traj_index"][1])
            R = f["model/R"][...]
            R[1, 1] = R[1, 1] @ np.array([[1, -1e-6, 0], [1e-6, 1, 0], [0, 0, 1]])  # a micro-radian turn
            f["model/R"][...] = R
        before = _state(bad)
        code, out, err = _eval(capfd, a, bad, tmp_path, monkeypatch)
        assert code == 2, (code, out, err)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: "), err
        assert f"sample 1 of trajectory {traj}" in lines[0] and "model/R" in lines[0], lines[0]
        assert _state(bad) == before
    finally:
        shutil.rmtree(bad)


def test_a_file_without_provenance_evaluates_with_a_warning_under_the_run(runs, tmp_path, capfd, monkeypatch):
    a, _ = runs
    old = tmp_path / "old"
    old.mkdir()
    shutil.copy2(a / "rollout.h5", old / "rollout.h5")
    with h5py.File(old / "rollout.h5", "r+") as f:
        for k in PROVENANCE:
            if k in f.attrs:
                del f.attrs[k]
    before_old, evals = _state(old), a / "evals"
    try:
        code, out, err = _eval(capfd, a, old / "rollout.h5", tmp_path, monkeypatch)
        assert code == 0, (code, out, err)
        text = " ".join((out + err).split())
        assert "provenance unknown" in text and text.count("provenance unknown") == 1, out + err
        assert _state(old) == before_old  # nothing written next to a file outside the run
        (made,) = list(evals.iterdir())
        assert made.name.endswith("_old")
        assert {"rollout.h5", "eval.csv", "eval.md", "eval_curves.json"} <= {p.name for p in made.iterdir()}
    finally:
        shutil.rmtree(evals, ignore_errors=True)


def test_liedfl_rollout_files_carry_the_runs_id_and_evaluate(runs, tmp_path, capfd, monkeypatch):
    a, _ = runs
    monkeypatch.chdir(tmp_path)
    code, out, err = _cli(capfd, "rollout", f"run={a}", "steps=4", "ui.progress=false", "eval.plots=false")
    assert code == 0, (out, err)
    try:
        (folder,) = list((a / "rollouts").iterdir())
        run_id = json.loads((a / "summary.json").read_text())["run_id"]
        with h5py.File(folder / "rollout.h5") as f:
            assert str(f.attrs["run_id"]) == run_id and str(f.attrs["model_name"]) == "liedflnn"
            used = str(f.attrs["checkpoint"])
            assert str(f.attrs["checkpoint_sha256"]) == file_sha256(a / "checkpoints" / used)
        code, out, err = _eval(capfd, a, folder, tmp_path, monkeypatch)
        assert code == 0 and "provenance" not in out + err, (out, err)
        assert not (a / "evals").exists()  # a file of the run is evaluated in place
    finally:
        shutil.rmtree(a / "rollouts", ignore_errors=True)
