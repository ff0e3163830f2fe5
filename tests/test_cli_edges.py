"""Edges of the `liedfl` command line (issue 21, item 6): --version, a closed stdout pipe, a misspelt key
without `+`, --help after overrides, run=latest / resume=latest. Nothing here trains. The misspelt-key and
run=latest messages and --help after overrides come from `main()` run in-process (`run_main`); --version,
the pipes and --help into them through a real process."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import cli_command, cli_env, run_cli
from liedfl_cli import __version__
from liedfl_cli.cli import _resolve_latest, _with_help_overrides, latest_run


# ----------------------------------------------------------------------------- --version
@pytest.mark.parametrize("args", [["--version"], ["-V"], ["train", "--version"], ["eval", "-V"]])
def test_version(args, tmp_path):
    proc = run_cli(*args, cwd=tmp_path, ok=True)
    assert proc.stdout.strip() == f"liedfl {__version__}"
    assert "Hydra" not in proc.stdout + proc.stderr


# ----------------------------------------------------------------------------- closed pipe
@pytest.mark.parametrize("args", [["--help"], ["train", "--help"]])
def test_closed_stdout_pipe_is_quiet(args, tmp_path):
    """`liedfl train --help | head -1`: stdout's reader is gone before liedfl writes; no traceback, and
    exit code 141 (128 + SIGPIPE, as for other commands whose reader went away)."""
    r, w = os.pipe()
    os.close(r)  # no reader: every write to stdout fails with EPIPE
    try:
        proc = subprocess.run([*cli_command(), *args], cwd=tmp_path, env=cli_env(), stdout=w,
                              stderr=subprocess.PIPE, text=True, timeout=120)  # fmt: skip
    finally:
        os.close(w)
    assert proc.returncode == 141, proc.stderr
    assert proc.stderr == "", proc.stderr


def test_help_piped_into_head(tmp_path):
    """The shell's `liedfl train --help | head -1`."""
    cmd = " ".join([*(f"'{c}'" for c in cli_command()), "train", "--help"]) + " | head -1"
    proc = subprocess.run(["bash", "-c", cmd], cwd=tmp_path, env=cli_env(), capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0 and proc.stdout.startswith("liedfl train:"), proc
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr


# ----------------------------------------------------------------------------- misspelt key without +
@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (
            ["dataset=file", "dataset.pth=3"],
            "unknown config key 'dataset.pth' for scene 'file' (did you mean 'dataset.path'?)",
        ),
        (["dataset.pth=3"], "unknown config key 'dataset.pth' for scene 'free_rigid_body' (did you mean 'dataset.h'?)"),
        (["train.epoch=3"], "unknown config key 'train.epoch' (did you mean 'train.epochs'?)"),
        (["-m", "dataset=file", "dataset.pth=3", "seed=1,2"], "(did you mean 'dataset.path'?)"),
        (["dataset.zzzzzz=1"], "unknown config key 'dataset.zzzzzz' for scene 'free_rigid_body' (valid keys: h,"),
    ],
)
def test_misspelt_key_without_plus(args, expected, tmp_path, run_main):
    proc = run_main("train", *args, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1, proc.stderr
    assert expected in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and "not in struct" not in proc.stderr
    assert not (tmp_path / "outputs").exists()


# ----------------------------------------------------------------------------- --help after overrides
def test_help_overrides_join_the_users():
    """argparse takes one run of positional words: Hydra's help overrides go next to the user's ones."""
    ours = _with_help_overrides("train", ["dataset=import", "--help"])
    assert len(ours) == 4 and ours[2:] == ["dataset=import", "--help"] and ours[0].startswith("hydra.help.")
    assert _with_help_overrides("train", ["dataset=file"]) == ["dataset=file"]


@pytest.mark.parametrize(
    "args", [["dataset=import", "--help"], ["--help", "dataset=import"], ["-h", "model=neural_ode"]]
)
def test_help_with_overrides(args, tmp_path, run_main):
    proc = run_main("train", *args, cwd=tmp_path, ok=True)  # (the pipe tests above run --help as a process)
    assert proc.stdout.startswith("liedfl train: train and evaluate a model")
    assert "== Configuration groups ==" in proc.stdout and "== Config ==" in proc.stdout
    assert "hydra.help" not in proc.stdout + proc.stderr and "usage:" not in proc.stderr
    if "dataset=import" in args:
        assert "name: import" in proc.stdout  # the composed config is the one asked for


# ----------------------------------------------------------------------------- run=latest
def _fake_run(root: Path, name: str, mtime: float | None) -> Path:
    run = root / "outputs" / "runs" / name
    (run / "checkpoints").mkdir(parents=True)
    if mtime is not None:
        last = run / "checkpoints" / "last.pt"
        last.write_bytes(b"not a checkpoint")
        os.utime(last, (mtime, mtime))
    return run


def test_latest_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert latest_run() is None
    now = time.time()
    _fake_run(tmp_path, "2026-01-02_b", now - 100)
    newest = _fake_run(tmp_path, "2026-01-01_a", now)  # the name sorts first: the checkpoint's time decides
    _fake_run(tmp_path, "2026-01-03_c", None)  # no checkpoints/last.pt: not a run
    (tmp_path / "outputs" / "runs" / "a_file").write_text("")
    assert latest_run() == Path("outputs/runs/2026-01-01_a") and newest.is_dir()
    assert _resolve_latest("rollout", ["run=latest", "steps=3"]) == ["run=outputs/runs/2026-01-01_a", "steps=3"]
    assert _resolve_latest("resume", ["resume=latest"]) == ["resume=outputs/runs/2026-01-01_a"]
    assert _resolve_latest("train", ["run=latest"]) == ["run=latest"]


@pytest.mark.parametrize(("command", "key"), [("rollout", "run"), ("eval", "run"), ("train", "resume")])
def test_latest_without_runs(command, key, tmp_path, run_main):
    proc = run_main(command, f"{key}=latest", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr == (
        f"error: {key}=latest: no run under outputs/runs/ (no run folder with checkpoints/last.pt)\n"
    ), proc.stderr
    assert not (tmp_path / "outputs").exists()


def test_latest_picks_the_newest_run(tmp_path, run_main):
    """run=latest names the newest run (here a broken one: the error names its checkpoint)."""
    now = time.time()
    _fake_run(tmp_path, "old", now - 100)
    _fake_run(tmp_path, "new", now)
    proc = run_main("eval", "run=latest", cwd=tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "new" in proc.stderr and "old" not in proc.stderr, proc.stderr


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-x", "-q"]))
