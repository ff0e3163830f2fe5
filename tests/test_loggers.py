"""The `logger` config group: train_metrics.csv (with the learning rate) always, TensorBoard event
files with `logger=tensorboard`, and the one-line error when the extra is not installed."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest

from helpers import SMOKE, compose_config
from liedfl_cli.commands.train import run_train
from liedfl_cli.config.schema import validate
from liedfl_cli.errors import ConfigError
from liedfl_cli.loggers.tensorboard_log import tag


def _cfg(tmp: Path, *extra: str):
    paths = (f"paths.data_dir={tmp}/data", f"paths.output_dir={tmp}/run", "runtime.threads=1")
    return compose_config("train", (*SMOKE, *paths, "rollout.enabled=false", *extra))


def _rows(run: Path) -> list[dict]:
    with open(run / "train_metrics.csv") as f:
        return list(csv.DictReader(f))


def test_csv_logs_the_learning_rate_of_each_epoch(tmp_path):
    cfg = _cfg(tmp_path, "train.optimizer.schedule=cosine", "train.optimizer.lr=1e-3")
    run_train(cfg)
    rows = _rows(tmp_path / "run")
    lrs = [float(r["lr"]) for r in rows]
    assert lrs[0] == pytest.approx(1e-3, rel=1e-12)  # the first epoch steps with the configured rate
    assert all(b < a for a, b in zip(lrs, lrs[1:])), lrs  # cosine: decreasing every epoch
    assert not (tmp_path / "run" / "tensorboard").exists()  # logger=csv (default): no event files


def test_tensorboard_missing_is_one_line_with_the_install_command(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "tensorboard" else real(name, *a))
    with pytest.raises(ConfigError) as e:
        validate(_cfg(tmp_path, "logger=tensorboard"), "train")
    assert "pip install liedfl[tensorboard]" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "run").exists()


def test_unknown_logger_key_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="logger.name='wandb'"):
        validate(_cfg(tmp_path, "logger.name=wandb"), "train")


def test_tags_of_the_metric_columns():
    assert tag("del_loss") == "loss/del_loss" and tag("loss") == "loss/loss"
    assert tag("val_one_step_error") == "val/one_step_error"
    assert tag("epoch") is None and tag("seconds") is None and tag("lr") is None


def test_tensorboard_event_file_holds_losses_validation_lr_and_epoch_time(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_train(_cfg(tmp_path, "logger=tensorboard"))
    run = tmp_path / "run"
    events = list((run / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1
    acc = EventAccumulator(str(run / "tensorboard"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    expected = {"loss/loss", "loss/del_loss", "loss/reg_loss", "lr", "time/epoch_seconds", "val/one_step_error"}
    assert expected <= tags, tags
    rows = _rows(run)
    # one loss point per epoch, equal to the CSV's (TensorBoard stores float32)
    loss = acc.Scalars("loss/loss")
    assert [e.step for e in loss] == [int(r["epoch"]) for r in rows]
    for e, r in zip(loss, rows):
        assert e.value == pytest.approx(float(r["loss"]), rel=1e-6)
    val = acc.Scalars("val/one_step_error")
    assert [e.step for e in val] == [int(r["epoch"]) for r in rows if r["val_one_step_error"]]
    assert all(e.value > 0 for e in acc.Scalars("time/epoch_seconds"))
    assert [e.value for e in acc.Scalars("lr")] == pytest.approx([float(r["lr"]) for r in rows], rel=1e-6)


def test_resumed_tensorboard_log_replaces_the_epochs_after_the_checkpoint(tmp_path):
    """A run killed after epoch 5 with its checkpoint at epoch 3 logged 4..5 twice: the resumed
    writer's purge hides the first copies, and the epoch time continues from the kept row."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from liedfl_cli.loggers import make_loggers

    def row(epoch, loss):
        return {"epoch": epoch, "loss": loss, "lr": 1e-3, "seconds": 2.0 * epoch, "val_one_step_error": None}

    first = make_loggers("tensorboard", tmp_path, [])
    for e in range(1, 6):
        first.log(row(e, 10.0 + e))
    first.close()
    history = [row(e, 10.0 + e) for e in range(1, 4)]  # the checkpoint's rows
    again = make_loggers("tensorboard", tmp_path, history)
    for e in range(4, 7):
        again.log(row(e, 20.0 + e))
    again.close()
    acc = EventAccumulator(str(tmp_path / "tensorboard"))
    acc.Reload()
    loss = acc.Scalars("loss/loss")
    assert [e.step for e in loss] == [1, 2, 3, 4, 5, 6]
    assert [e.value for e in loss] == pytest.approx([11, 12, 13, 24, 25, 26])
    assert [e.value for e in acc.Scalars("time/epoch_seconds")] == pytest.approx([2.0] * 6)
    with open(tmp_path / "train_metrics.csv") as f:
        assert [r["loss"] for r in csv.DictReader(f)] == ["11.0", "12.0", "13.0", "24.0", "25.0", "26.0"]
