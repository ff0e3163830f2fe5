"""Checkpoints during training, interruption by signal, and resume (bit-identical to an
uninterrupted run for the same seed)."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

import liedfl_cli.train as train_mod
from helpers import SMOKE, cli_command, cli_env, compose_config
from liedfl_cli.checkpoint import load_checkpoint
from liedfl_cli.errors import CheckpointError, ConfigError
from liedfl_cli.train import TrainingInterrupted, run_resume, run_train

CONF = str(Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf")


def _cfg(tmp: Path, run: str, extra=(), name="train"):
    if name == "resume":
        return compose_config("resume", extra)
    paths = (f"paths.data_dir={tmp}/data", f"paths.output_dir={tmp}/{run}")
    return compose_config("train", (*SMOKE, "train.epochs=6", "train.checkpoint_every=2", *paths, *extra))


def _losses(run: Path) -> list[list[str]]:
    with open(run / "train_metrics.csv") as f:
        rows = list(csv.DictReader(f))
    return [[r[k] for k in r if k != "seconds"] for r in rows]


def _stop_at(monkeypatch, epoch: int) -> None:
    """Deliver a 'SIGINT' to fit after `epoch` (as the real handler does: set the request)."""
    real = train_mod.graceful_stop

    class _Stop(train_mod.StopRequest):
        pass

    import contextlib

    @contextlib.contextmanager
    def fake():
        with real() as stop:
            original = train_mod.MetricsLog.append

            def append(self, row):
                original(self, row)
                if row["epoch"] == epoch:
                    stop.signum = signal.SIGINT

            monkeypatch.setattr(train_mod.MetricsLog, "append", append)
            yield stop

    monkeypatch.setattr(train_mod, "graceful_stop", fake)


@pytest.mark.parametrize("baseline", ["none", "glnn_lie_heun"])
def test_interrupted_then_resumed_equals_uninterrupted(tmp_path, monkeypatch, baseline):
    full = run_train(_cfg(tmp_path, "full", [f"baseline={baseline}"]))
    _stop_at(monkeypatch, 3)
    with pytest.raises(TrainingInterrupted, match=r"after epoch 3/6; checkpoint saved; resume with") as e:
        run_train(_cfg(tmp_path, "cut", [f"baseline={baseline}"]))
    assert e.value.exit_code == 128 + signal.SIGINT
    cut = tmp_path / "cut"
    ck = load_checkpoint(cut / "checkpoints" / "last.pt")
    assert ck["epoch"] == 3 and len(ck["history"]) == 3
    assert len(_losses(cut)) == 3 and not (cut / "rollout.h5").exists()  # nothing after training ran
    monkeypatch.undo()
    run_resume(_cfg(tmp_path, "", [f"resume={cut}", "ui.progress=false"], name="resume"))
    assert _losses(cut) == _losses(Path(full["run_dir"]))
    a = load_checkpoint(Path(full["run_dir"]) / "checkpoints" / "last.pt")["state_dict"]
    b = load_checkpoint(cut / "checkpoints" / "last.pt")["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (cut / "eval.csv").is_file()


def test_checkpoints_are_written_during_training(tmp_path, monkeypatch):
    seen = []
    real_save = train_mod.save_checkpoint
    monkeypatch.setattr(
        train_mod, "save_checkpoint", lambda p, m, c, e: (seen.append(e.get("epoch")), real_save(p, m, c, e))
    )
    run_train(_cfg(tmp_path, "run", ["rollout.enabled=false"]))
    assert seen == [2, 4, 6]  # every 2 epochs, then the final one


def test_resume_of_a_finished_run_redoes_the_evaluation_and_can_extend(tmp_path):
    s = run_train(_cfg(tmp_path, "run", ["rollout.enabled=false"]))
    run = Path(s["run_dir"])
    run_resume(_cfg(tmp_path, "", [f"resume={run}", "ui.progress=false"], name="resume"))
    assert len(_losses(run)) == 6
    run_resume(_cfg(tmp_path, "", [f"resume={run}", "ui.progress=false", "epochs=8"], name="resume"))
    assert [r[0] for r in _losses(run)] == [str(i) for i in range(1, 9)]
    with pytest.raises(ConfigError, match="already at epoch 8"):
        run_resume(_cfg(tmp_path, "", [f"resume={run}", "epochs=5"], name="resume"))


def test_resume_needs_a_checkpoint_with_training_state(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        run_resume(_cfg(tmp_path, "", [f"resume={tmp_path / 'empty'}"], name="resume"))
    with pytest.raises(ConfigError, match="no such run directory"):
        run_resume(_cfg(tmp_path, "", [f"resume={tmp_path / 'nope'}"], name="resume"))


def test_bad_checkpoint_every_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="checkpoint_every"):
        run_train(_cfg(tmp_path, "run", ["train.checkpoint_every=0"]))


def test_sigint_saves_a_checkpoint_and_says_how_to_resume(tmp_path):
    """The real handler in a real process: SIGINT mid-training -> exit 130, one line, resumable."""
    run = tmp_path / "run"
    args = [
        "train",
        "budget=smoke",
        "ui.progress=false",
        "train.epochs=100000",
        f"paths.data_dir={tmp_path}/data",
        f"hydra.run.dir={run}",
    ]
    proc = subprocess.Popen(
        [*cli_command(), *args], cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    deadline = time.time() + 120
    metrics = run / "train_metrics.csv"
    while time.time() < deadline and not (metrics.exists() and len(metrics.read_text().splitlines()) >= 3):
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    text = err.decode()
    errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert proc.returncode == 130, text
    assert len(errors) == 1 and "resume with: liedfl train resume=" in errors[0] and "Traceback" not in text
    ck = load_checkpoint(run / "checkpoints" / "last.pt")
    assert ck["epoch"] >= 2 and len(_losses(run)) == ck["epoch"]
    assert json.loads((run / "status.json").read_text())["status"] == "interrupted"
    # a resumed run that finishes says so in its status.json (a sweep's report then counts it as done)
    resume = [*cli_command(), "train", f"resume={run}", f"epochs={ck['epoch'] + 1}", "ui.progress=false"]
    done = subprocess.run(resume, cwd=tmp_path, env=cli_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads((run / "status.json").read_text())["status"] == "ok"
