"""Sweeps that finish: status.json per job, a failing job does not stop the sweep, the exit code counts
the failures, `liedfl report` lists failed runs, folder names never collide; failed single runs leave
no empty run folder (and keep a folder with content, with its status)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from liedfl_cli.commands import status

FAST = ["budget=smoke", "ui.progress=false", "eval.plots=false"]


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR")}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg", COLUMNS="200", **extra)
    return env


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-c", "from liedfl_cli.cli import main; main()", *args]


def liedfl(*args: str, cwd: Path, **env) -> subprocess.CompletedProcess:
    return subprocess.run(_cmd(*args), cwd=cwd, env=_env(**env), capture_output=True, text=True, timeout=300)


@pytest.fixture
def sweep(tmp_path, run_main) -> tuple[subprocess.CompletedProcess, Path]:
    """`liedfl train -m train.epochs=-1,1` (in-process, Hydra's basic launcher runs the jobs here too: cheaper
    per test than one subprocess per module): job 0 fails validation, job 1 trains (smoke)."""
    cwd = tmp_path / "sweep"
    cwd.mkdir()
    proc = run_main("train", "-m", *FAST, "train.epochs=-1,1", cwd=cwd)
    (sweep_dir,) = (cwd / "outputs" / "multirun").iterdir()
    return proc, sweep_dir


def test_a_failing_job_does_not_stop_the_sweep(sweep):
    proc, sweep_dir = sweep
    assert "Traceback" not in proc.stderr, proc.stderr
    failed = json.loads((sweep_dir / "0" / "status.json").read_text())
    assert failed == {"status": "failed", "exit_code": 2, "error": "train.epochs=-1: must be an integer >= 0"}
    ok = json.loads((sweep_dir / "1" / "status.json").read_text())
    assert ok["status"] == "ok" and ok["exit_code"] == 0
    assert (sweep_dir / "1" / "checkpoints" / "last.pt").is_file() and (sweep_dir / "1" / "eval.csv").is_file()


def test_the_sweep_exit_code_counts_the_failed_jobs(sweep):
    proc, sweep_dir = sweep
    assert proc.returncode == 1
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert errors[0] == "error: [job 0] train.epochs=-1: must be an integer >= 0"
    assert errors[-1] == f"error: 1 of 2 jobs failed: {Path('outputs') / 'multirun' / sweep_dir.name / '0'}"


def test_report_lists_failed_runs(sweep, tmp_path, run_main):
    _, sweep_dir = sweep
    proc = run_main("report", f"sweep={sweep_dir}", "plots=false", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "failed runs (1)" in proc.stdout and "0: train.epochs=-1: must be an integer >= 0" in proc.stdout
    md = (sweep_dir / "report.md").read_text()
    assert "1 runs, 1 failed." in md and "## Failed runs" in md
    assert "| 0 | train.epochs=-1: must be an integer >= 0 |" in md
    assert status.sweep_summary(sweep_dir)[:2] == (1, 2)


def test_two_sweeps_started_together_get_their_own_folders(tmp_path):
    """Both sweeps fail fast (validation), so that they start within the same second."""
    procs = [
        subprocess.Popen(
            _cmd("train", "-m", *FAST, "train.epochs=-1,-2"),
            cwd=tmp_path,
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [2, 2], outs
    sweeps = sorted((tmp_path / "outputs" / "multirun").iterdir())
    assert len(sweeps) == 2, sweeps
    for s in sweeps:
        assert sorted(d.name for d in s.iterdir() if d.is_dir()) == ["0", "1"]
        for job in ("0", "1"):
            assert json.loads((s / job / "status.json").read_text())["status"] == "failed"
    # names carry sub-second precision
    assert all(len(s.name.split("_")[1].split("-")) == 4 for s in sweeps)


def test_a_sweep_where_every_job_succeeds_exits_zero(tmp_path, run_main):
    proc = run_main("data", "-m", "budget=smoke", "ui.progress=false", "dataset.seed=1,2", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "all 2 jobs finished" in proc.stdout
    (sweep_dir,) = (tmp_path / "outputs" / "multirun").iterdir()
    assert status.sweep_summary(sweep_dir) == (0, 2, [])


def test_hydra_full_error_keeps_hydras_full_message(tmp_path):
    short = liedfl("train", "dataset=nosuch", cwd=tmp_path)
    assert len([ln for ln in short.stderr.splitlines() if ln.strip()]) == 1
    full = liedfl("train", "dataset=nosuch", cwd=tmp_path, HYDRA_FULL_ERROR="1")
    assert full.returncode != 0 and "Available options" in full.stderr and len(full.stderr.splitlines()) > 3
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- single runs
def test_a_failed_run_with_content_keeps_its_folder_and_records_the_failure(tmp_path, monkeypatch, capfd):
    """A failure after the run wrote something: the folder stays, with status.json and the error line."""
    from liedfl_cli import cli
    from liedfl_cli.commands import train
    from liedfl_cli.errors import DatasetError
    from liedfl_cli.files.io_utils import write_json

    def run_train(cfg):
        out = Path(cfg.paths.output_dir)
        write_json(out / "components.json", {"model": "x"})
        raise DatasetError("somewhere.h5: dataset 'R' is broken")

    monkeypatch.setattr(train, "run_train", run_train)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["liedfl", "train", *FAST, "hydra.run.dir=run"])
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 2
    assert capfd.readouterr().err.strip() == "error: somewhere.h5: dataset 'R' is broken"
    st = json.loads((tmp_path / "run" / "status.json").read_text())
    assert st == {"status": "failed", "exit_code": 2, "error": "somewhere.h5: dataset 'R' is broken"}
    assert (tmp_path / "run" / "components.json").is_file()


def test_a_run_that_fails_before_writing_leaves_no_folder(tmp_path, monkeypatch, capfd):
    from liedfl_cli import cli
    from liedfl_cli.commands import train
    from liedfl_cli.errors import DatasetError

    def run_train(cfg):
        raise DatasetError("x.h5: group 'split' is missing")

    monkeypatch.setattr(train, "run_train", run_train)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep").mkdir()  # an existing parent stays
    monkeypatch.setattr(sys, "argv", ["liedfl", "train", *FAST, "hydra.run.dir=keep/a/b/run"])
    with pytest.raises(SystemExit):
        cli.main()
    assert "x.h5" in capfd.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["keep"] and list((tmp_path / "keep").iterdir()) == []


def test_remove_unused_run_dir_never_removes_content(tmp_path):
    run = tmp_path / "a" / "run"
    (run / ".hydra").mkdir(parents=True)
    for n in status.HYDRA_FILES:
        (run / ".hydra" / n).write_text("x: 1\n")
    (run / "notes.txt").write_text("mine")
    status._state.update(run_dir=str(run), keep_from=str(tmp_path))
    try:
        assert not status.remove_unused_run_dir(run)
        assert (run / "notes.txt").is_file() and (run / ".hydra" / "config.yaml").is_file()
        (run / "notes.txt").unlink()
        (run / ".hydra" / "extra.yaml").write_text("y")  # not one of Hydra's files
        assert not status.remove_unused_run_dir(run)
        (run / ".hydra" / "extra.yaml").unlink()
        status._state.update(keep_from=str(run))  # the folder existed before the run
        assert not status.remove_unused_run_dir(run)
        status._state.update(keep_from=str(tmp_path))
        assert status.remove_unused_run_dir(run)
        assert list(tmp_path.iterdir()) == []
        assert not status.remove_unused_run_dir(tmp_path / "other")  # not the recorded run
    finally:
        status.reset()


def test_status_of_a_job_without_status_file(tmp_path):
    done, crashed = tmp_path / "0", tmp_path / "1"
    for d in (done, crashed):
        (d / ".hydra").mkdir(parents=True)
    (done / "eval.csv").write_text("model\nmodel\n")  # a run of a liedfl version without status.json
    (tmp_path / "2").mkdir()
    (tmp_path / "2" / "status.json").write_text("{garbled")
    failed = dict((d.name, e) for d, e in status.failed_runs(tmp_path))
    assert set(failed) == {"1", "2"}
    assert "did not finish" in failed["1"] and "unreadable" in failed["2"]


def test_an_interruption_with_a_message_is_one_line_and_recorded(tmp_path, monkeypatch, capfd):
    """What the training loop raises on Ctrl-C after saving a checkpoint: exit 130, the message kept."""
    from liedfl_cli import cli
    from liedfl_cli.commands import train
    from liedfl_cli.files.io_utils import write_json

    def run_train(cfg):
        write_json(Path(cfg.paths.output_dir) / "components.json", {"model": "x"})
        raise KeyboardInterrupt("checkpoint saved; resume with `liedfl train resume=run`")

    monkeypatch.setattr(train, "run_train", run_train)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["liedfl", "train", *FAST, "hydra.run.dir=run"])
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 130
    line = "interrupted: checkpoint saved; resume with `liedfl train resume=run`"
    assert capfd.readouterr().err.strip() == f"error: {line}"
    assert json.loads((tmp_path / "run" / "status.json").read_text()) == {
        "status": "interrupted",
        "exit_code": 130,
        "error": line,
    }


# ----------------------------------------------------------------------------- launchers
def test_a_submitit_launcher_without_the_plugin_is_one_line(monkeypatch, capfd):
    """`hydra/launcher=liedfl_local` names the plugin's class: without the `cluster` extra, one line naming
    it, before the sweep folder exists (the plugin's own submitit_* configs are then Hydra's 'Could not
    find' error, with the same hint)."""
    import importlib.util

    from omegaconf import OmegaConf

    cfg = OmegaConf.create(
        {
            "hydra": {
                "launcher": {"_target_": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"},
                "runtime": {"choices": {"hydra/launcher": "liedfl_local"}},
            }
        }
    )
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == status.SUBMITIT_PLUGIN else find_spec(name, *a)
    )
    with pytest.raises(SystemExit) as e:
        status.check_launcher(cfg)
    assert e.value.code == 2
    assert capfd.readouterr().err.strip() == (
        'error: hydra/launcher=liedfl_local: hydra-submitit-launcher is not installed (pip install -e ".[cluster]")'
    )
    status.check_launcher(OmegaConf.create({"hydra": {"launcher": {"_target_": "x.JoblibLauncher"}}}))  # others: ok


def test_a_missing_submitit_config_names_the_extra(capfd):
    from hydra.errors import MissingConfigException

    from liedfl_cli import cli

    e = MissingConfigException(
        "In 'hydra/config': Could not find 'hydra/launcher/submitit_local'\n\nAvailable options in 'hydra/launcher':"
        "\n\tbasic\n\tjoblib\n\tliedfl_local",
        missing_cfg_file="hydra/launcher/submitit_local",
    )
    with pytest.raises(SystemExit):
        cli._hydra_failure("train", e)
    err = capfd.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Could not find 'hydra/launcher/submitit_local'" in err
    assert 'pip install -e ".[cluster]"' in err and "available: basic, joblib, liedfl_local" in err
