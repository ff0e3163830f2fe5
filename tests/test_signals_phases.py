"""SIGTERM (and SIGINT) outside the training loop: data generation, rollout, evaluation, report and the
phases of `liedfl train` after training (issue 18, item 4). Each ends with one line, exit code 143
(130 for SIGINT), a status where there is a run folder, and nothing half-made."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import SMOKE, cli_env, train_run


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """One finished smoke run (trained in-process)."""
    return train_run(tmp_path_factory.mktemp("signals_run"), *SMOKE)


def hook(target: str, sig: str = "SIGTERM") -> str:
    """Python run before `liedfl`'s main: `target` ('module:attribute') first sends `sig` to the process."""
    module, attr = target.split(":")
    return (
        f"import os, signal, importlib\nm = importlib.import_module({module!r})\nreal = m.{attr}\n"
        f"def hooked(*a, **k):\n    os.kill(os.getpid(), signal.{sig})\n    return real(*a, **k)\n"
        f"m.{attr} = hooked\n"
    )


def _defaults() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def liedfl(args, cwd: Path, python: str = "", ignore_sigint: bool = False) -> subprocess.CompletedProcess:
    code = python + "\nimport sys\nfrom liedfl_cli.cli import main\nsys.argv = ['liedfl', *sys.argv[1:]]\nmain()\n"

    def pre():
        _defaults()
        if ignore_sigint:  # as under nohup, or as a background job of a script
            signal.signal(signal.SIGINT, signal.SIG_IGN)

    return subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=cli_env(), capture_output=True,
                          text=True, timeout=300, preexec_fn=pre)  # fmt: skip


def _snapshot(root: Path) -> dict[str, float]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in sorted(root.rglob("*"))}


def _contents(root: Path) -> dict[str, str]:
    """Every path under root -> "dir" or the sha1 of its bytes (folders' mtimes move with a lock file)."""
    return {
        str(p.relative_to(root)): "dir" if p.is_dir() else hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
    }


def _one_line(proc, progress: bool = False) -> str:
    """The one error line on stderr (progress: the lines of completed phases may come before it)."""
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert "Traceback" not in proc.stderr and len(errors) == 1 and lines[-1] == errors[0], proc.stderr
    assert progress or len(lines) == 1, proc.stderr
    return lines[-1]


def _copy(trained: Path, tmp_path: Path) -> Path:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained, run)
    return run


# ----------------------------------------------------------------------------- data generation
def test_sigterm_during_data_generation_leaves_nothing(tmp_path):
    proc = liedfl(["data", "budget=smoke", "ui.progress=false"], tmp_path, hook("liedfl_cli.data.scenes:_generate"))
    assert proc.returncode == 143, proc.stderr
    assert _one_line(proc) == "error: SIGTERM: interrupted during data generation; nothing written"
    assert list(tmp_path.iterdir()) == []


def test_sigterm_during_the_data_generation_of_train_leaves_no_run_folder(tmp_path):
    proc = liedfl(["train", *SMOKE], tmp_path, hook("liedfl_cli.data.scenes:_generate"))
    assert proc.returncode == 143, proc.stderr
    assert "SIGTERM: interrupted during data generation" in _one_line(proc)
    assert list(tmp_path.iterdir()) == []  # the run folder Hydra made is taken back


# ----------------------------------------------------------------------------- rollout
@pytest.mark.parametrize("sig,code", [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_during_a_rollout_leaves_no_rollout_folder(trained, tmp_path, sig, code):
    run = _copy(trained, tmp_path)
    before = _snapshot(run)
    proc = liedfl(
        ["rollout", f"run={run}", "steps=20", "ui.progress=false"],
        tmp_path,
        hook("liedfl_cli.commands.rollout:_roll", sig),
    )
    assert proc.returncode == code, proc.stderr
    line = _one_line(proc)
    assert (f"{sig}: interrupted during rollout; nothing kept" in line) if sig == "SIGTERM" else ("interrupted" in line)
    assert _snapshot(run) == before  # no rollouts/<name>/, no lock, nothing changed


def test_the_issues_reproducer_sigterm_to_a_long_rollout(trained, tmp_path):
    """`liedfl rollout run=R steps=400000 & sleep 15; kill -TERM $!` (waiting for the rollout folder instead)."""
    run = _copy(trained, tmp_path)
    code = "import sys\nfrom liedfl_cli.cli import main\nsys.argv = ['liedfl', *sys.argv[1:]]\nmain()\n"
    proc = subprocess.Popen([sys.executable, "-c", code, "rollout", f"run={run}", "steps=400000", "ui.progress=false"],
                            cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_defaults)  # fmt: skip
    deadline = time.time() + 120
    while time.time() < deadline and not list(run.glob("rollouts/*")) and proc.poll() is None:
        time.sleep(0.1)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: SIGTERM: interrupted during rollout"), err
    assert not (run / "rollouts").exists() and not (run / ".lock").exists()


# ----------------------------------------------------------------------------- evaluation
def test_sigterm_during_an_evaluation_marks_the_run_until_an_evaluation_completes(trained, tmp_path, run_main):
    run = _copy(trained, tmp_path)
    (run / "status.json").write_text(json.dumps({"status": "ok", "exit_code": 0}))
    before = _contents(tmp_path)
    proc = liedfl(
        ["eval", f"run={run}", *SMOKE[1:]], tmp_path, hook("liedfl_cli.commands.evaluate:run_eval_from_objects")
    )
    assert proc.returncode == 143, proc.stderr
    line = _one_line(proc)
    assert line.startswith("error: SIGTERM: interrupted during evaluation; to redo it: liedfl eval run=")
    assert f"liedfl eval run={run}" in line
    after = _contents(tmp_path)
    assert [k for k in set(before) | set(after) if before.get(k) != after.get(k)] == ["run/status.json"]
    st = json.loads((run / "status.json").read_text())
    assert st["status"] == "interrupted" and st["phase"] == "evaluation" and st["exit_code"] == 143
    assert st["previous"] == {"status": "ok", "exit_code": 0}
    assert not (run / ".lock").exists()
    run_main("eval", f"run={run}", *SMOKE[1:], cwd=tmp_path, ok=True)  # (no signal: in this process)
    assert json.loads((run / "status.json").read_text()) == {"status": "ok", "exit_code": 0}


def test_sigterm_during_the_evaluation_of_an_outside_rollout_removes_its_copy(trained, tmp_path):
    import shutil

    run = _copy(trained, tmp_path)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    shutil.copy(run / "rollout.h5", outside / "rollout.h5")
    before = _contents(tmp_path)
    proc = liedfl(["eval", f"run={run}", f"rollout={outside}", *SMOKE[1:]], tmp_path,
                  hook("liedfl_cli.commands.evaluate:run_eval_from_objects"))  # fmt: skip
    assert proc.returncode == 143, proc.stderr
    line = _one_line(proc)
    assert "SIGTERM: interrupted during evaluation" in line and f"rollout={outside}" in line, line
    assert _contents(tmp_path) == before  # no evals/<copy>/ left, the outside rollout as it was


# (report: test_hostile.py's `sigterm-during-report`, over a sweep with a job)


# ----------------------------------------------------------------------------- train after training
def test_sigterm_during_the_rollout_of_train_records_the_phase_and_keeps_the_model(tmp_path):
    proc = liedfl(
        ["train", *SMOKE, "hydra.run.dir=run"], tmp_path, hook("liedfl_cli.commands.rollout:rollout_and_save")
    )
    assert proc.returncode == 143, proc.stderr
    run = tmp_path / "run"
    line = _one_line(proc, progress=True)  # ("generated <dataset>" came before)
    assert "SIGTERM: interrupted during rollout; the trained model is saved" in line and f"resume={run}" in line
    st = json.loads((run / "status.json").read_text())
    assert st["status"] == "interrupted" and st["phase"] == "rollout" and st["exit_code"] == 143
    assert (run / "checkpoints" / "last.pt").is_file() and not (run / "rollout.h5").exists()
    assert not (run / ".lock").exists() and not [p for p in run.rglob("*") if ".tmp" in p.name]


# ----------------------------------------------------------------------------- inherited-ignored SIGINT
def test_an_inherited_ignored_sigint_stays_ignored_outside_training(trained, tmp_path):
    run = _copy(trained, tmp_path)
    proc = liedfl(["rollout", f"run={run}", "steps=12", *SMOKE[1:]], tmp_path,
                  hook("liedfl_cli.commands.rollout:_roll", "SIGINT"), ignore_sigint=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (folder,) = (run / "rollouts").iterdir()
    assert (folder / "rollout.h5").is_file() and (folder / "eval.csv").is_file()
    assert os.environ.get("LIEDFL_RUN_LOCK") is None and not (run / ".lock").exists()
