"""Bad inputs through the CLI: one line on stderr naming the file / field / index, a non-zero exit, no
Python traceback, and nothing half-written (no *.tmp* files, earlier outputs untouched).

The commands run in-process (`run_main`: the entry point's `main()`, the same code a `liedfl` process
runs, without a new interpreter per call); the process boundary itself (exit codes of a real process,
signals, the installed script) is tested in test_cli.py, test_cli_edges.py and test_hostile.py's
`proc` cases."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from helpers import compose_config
from liedfl_cli.cli import DIR_ARGS

FAST = ["budget=smoke", "ui.progress=false", "eval.plots=false"]


@pytest.fixture
def liedfl(run_main):
    """liedfl(*args, cwd) -> CompletedProcess of the command, run in-process."""
    return run_main


def one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """Assert a clean failure: non-zero exit, exactly one stderr line `error: ...` holding every needle."""
    assert proc.returncode != 0, f"expected a failure\n{proc.stdout}\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{proc.stderr}"
    line = lines[0]
    assert line.startswith("error: "), line
    for n in needles:
        assert n in line, f"{n!r} not in {line!r}"
    return line


def no_tmp_files(*dirs: Path) -> None:
    left = [p for d in dirs if d.exists() for p in d.rglob("*") if ".tmp" in p.name]
    assert not left, f"temporary files left behind: {left}"


def snapshot(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A finished smoke run, trained in-process (absolute data dir, so any cwd can reload it)."""
    from liedfl_cli.commands.train import run_train

    root = tmp_path_factory.mktemp("errors_run")
    cfg = compose_config("train", [*FAST, f"paths.output_dir={root / 'run'}", f"paths.data_dir={root / 'data'}"])
    run_train(cfg)
    return root / "run"


@pytest.fixture
def run_copy(trained, tmp_path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(trained, dst)
    return dst


@pytest.fixture(scope="module")
def pristine_dataset(trained) -> Path:
    """The cached smoke dataset of the train config's default (where `liedfl train budget=smoke` looks
    for it: same config hash), made by the `trained` fixture's run."""
    (path,) = (trained.parent / "data").glob("*.h5")
    return path


def _corrupt_and_train(liedfl, pristine: Path, tmp_path: Path, edit) -> tuple[subprocess.CompletedProcess, Path, Path]:
    """Put an edited copy of the cached dataset where `liedfl train budget=smoke` looks for it, train."""
    data = tmp_path / "outputs" / "data" / pristine.name
    data.parent.mkdir(parents=True)
    shutil.copy(pristine, data)
    with h5py.File(data, "r+") as f:
        R = f["R"][...]
        edit(R)
        f["R"][...] = R
    run = tmp_path / "run"
    proc = liedfl("train", *FAST, f"hydra.run.dir={run}", cwd=tmp_path)
    return proc, run, data


# ----------------------------------------------------------------------------- run directories
def test_rollout_of_a_missing_run_dir(tmp_path, liedfl):
    missing = tmp_path / "nonexistent"
    line = one_line_error(liedfl("rollout", f"run={missing}", cwd=tmp_path), str(missing))
    assert "no such run directory" in line
    assert not missing.exists(), "a mistyped run= must not create the directory"


@pytest.mark.parametrize("command", sorted(DIR_ARGS))
def test_directory_argument_missing_or_mistyped(command, tmp_path, liedfl):
    """Every command whose Hydra run dir is a directory argument (run=, sweep=) checks it first."""
    key = DIR_ARGS[command][0]
    missing = tmp_path / "nonexistent"
    one_line_error(liedfl(command, f"{key}={missing}", cwd=tmp_path), f"{key}={missing}")
    one_line_error(liedfl(command, "ui.progress=false", cwd=tmp_path), f"{key}=")
    assert list(tmp_path.iterdir()) == [], "nothing may be created for a bad directory argument"


def test_eval_of_a_dir_without_checkpoint(run_copy, tmp_path, liedfl):
    shutil.rmtree(run_copy / "checkpoints")
    before = snapshot(run_copy)
    one_line_error(liedfl("eval", f"run={run_copy}", cwd=tmp_path), str(Path("checkpoints") / "last.pt"), "not found")
    assert snapshot(run_copy) == before
    no_tmp_files(run_copy)


# ----------------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("command", ["rollout", "eval"])
def test_corrupted_checkpoint(command, run_copy, tmp_path, liedfl):
    ckpt = run_copy / "checkpoints" / "last.pt"
    ckpt.write_bytes(np.random.default_rng(0).bytes(4096))
    before = snapshot(run_copy)
    one_line_error(
        liedfl(command, f"run={run_copy}", "ui.progress=false", cwd=tmp_path), str(ckpt), "not a readable checkpoint"
    )
    assert snapshot(run_copy) == before
    no_tmp_files(run_copy)


def test_checkpoint_with_wrong_shape(run_copy, tmp_path, liedfl):
    ckpt = run_copy / "checkpoints" / "last.pt"
    payload = torch.load(ckpt, map_location="cpu", weights_only=False)
    key = next(iter(payload["state_dict"]))
    payload["state_dict"][key] = torch.zeros(7, 5, dtype=torch.float64)
    torch.save(payload, ckpt)
    before = snapshot(run_copy)
    for command in ("rollout", "eval"):
        one_line_error(
            liedfl(command, f"run={run_copy}", "ui.progress=false", cwd=tmp_path),
            str(ckpt),
            f"state_dict.{key}",
            "(7, 5)",
        )
    assert snapshot(run_copy) == before
    no_tmp_files(run_copy)


def test_checkpoint_missing_a_field(run_copy, tmp_path, liedfl):
    ckpt = run_copy / "checkpoints" / "last.pt"
    payload = torch.load(ckpt, map_location="cpu", weights_only=False)
    del payload["config"]
    torch.save(payload, ckpt)
    one_line_error(liedfl("rollout", f"run={run_copy}", cwd=tmp_path), str(ckpt), "'config'")


def test_rollout_steps_not_an_integer(run_copy, tmp_path, liedfl):
    before = snapshot(run_copy)
    one_line_error(liedfl("rollout", f"run={run_copy}", "steps=abc", cwd=tmp_path), "steps", "abc")
    assert snapshot(run_copy) == before


def test_eval_of_a_corrupted_rollout(run_copy, tmp_path, liedfl):
    (run_copy / "rollout.h5").write_bytes(b"not hdf5 at all")
    one_line_error(liedfl("eval", f"run={run_copy}", "eval.plots=false", cwd=tmp_path), str(run_copy / "rollout.h5"))


# ----------------------------------------------------------------------------- datasets
def test_dataset_with_nan_in_R(pristine_dataset, tmp_path, liedfl):
    def edit(R):
        R[1, 3, 0, 0, 0] = np.nan

    proc, run, data = _corrupt_and_train(liedfl, pristine_dataset, tmp_path, edit)
    one_line_error(proc, str(Path("outputs") / "data" / data.name), "'R'", "non-finite", "(1, 3, 0, 0, 0)")
    assert not (run / "checkpoints").exists() and not (run / "eval.csv").exists()
    no_tmp_files(run, data.parent)
    assert data.is_file()  # the bad file is reported, not silently replaced


def test_dataset_with_a_gross_non_rotation(pristine_dataset, tmp_path, liedfl):
    def edit(R):
        R[0, 2, 0] *= 2.0

    proc, run, data = _corrupt_and_train(liedfl, pristine_dataset, tmp_path, edit)
    one_line_error(proc, data.name, "'R'", "not a rotation", "(0, 2, 0)")
    assert not (run / "checkpoints").exists()
    no_tmp_files(run, data.parent)


def test_slightly_off_rotations_are_projected_with_a_warning(pristine_dataset, tmp_path, liedfl):
    def edit(R):
        R[0, 2, 0] *= 1.0 + 1e-6

    proc, run, data = _corrupt_and_train(liedfl, pristine_dataset, tmp_path, edit)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "error:" not in proc.stderr
    assert "projected 1 of" in proc.stderr and data.name in proc.stderr
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "eval.csv").is_file()
    no_tmp_files(run)


# ----------------------------------------------------------------------------- config values
@pytest.mark.parametrize(
    "override,needles",
    [
        ("train.optimizer.name=sgd", ["train.optimizer.name", "sgd"]),
        ("model.residual=bogus", ["model.residual", "bogus"]),
        ("+train.epoch=3", ["train.epoch"]),
        ("train.epochs=many", ["train.epochs", "many"]),
    ],
)
def test_bad_config_value(override, needles, tmp_path, liedfl):
    run = tmp_path / "run"
    proc = liedfl("train", *FAST, override, f"hydra.run.dir={run}", cwd=tmp_path)
    one_line_error(proc, *needles)
    assert proc.returncode == 2
    assert not (run / "checkpoints").exists()
    assert not (tmp_path / "outputs").exists(), "validation must fail before any data is generated"
    no_tmp_files(tmp_path)


def test_unknown_override_key_is_a_hydra_error(tmp_path, liedfl):
    proc = liedfl("train", *FAST, "train.epoch=3", cwd=tmp_path)
    assert proc.returncode != 0
    assert "epoch" in proc.stderr and "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []  # Hydra fails at composition: no run dir
