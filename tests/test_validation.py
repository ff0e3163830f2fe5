"""Validation split, validation passes, model selection (best.pt), early stopping, and the
checkpoint that rollout / eval / the API use (docs/validation.md)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import liedfl_cli.commands.train as train_mod
from helpers import SMOKE, compose_config, single_body_models
from liedfl_cli.commands.train import run_train
from liedfl_cli.commands.validation import VAL_COLUMNS, Selection, make_val_split, select_option, val_interval
from liedfl_cli.config.schema import validate
from liedfl_cli.config.typed import TrainConfig
from liedfl_cli.errors import ConfigError
from liedfl_cli.files.checkpoint import load_checkpoint


def _cfg(tmp: Path, run: str, extra=()):
    paths = (f"paths.data_dir={tmp}/data", f"paths.output_dir={tmp}/{run}", "runtime.threads=1")
    return compose_config("train", (*SMOKE, *paths, *extra))


def _rows(run: Path) -> list[dict]:
    with open(run / "train_metrics.csv") as f:
        return list(csv.DictReader(f))


def _script(monkeypatch, values):
    """Validation passes that report `values` (val_one_step_error) in turn, without running the model."""
    it = iter(values)

    def measure(self, model):
        v = next(it)
        return {**dict.fromkeys(VAL_COLUMNS), "val_one_step_error": v, "val_rollout_error": v, "val_seconds": 0.0}

    monkeypatch.setattr(train_mod.Validator, "measure", measure)


# ----------------------------------------------------------------------------- selection logic
def test_selection_keeps_the_earlier_best_when_a_later_pass_is_worse():
    s = Selection("val_one_step_error")
    history = [(1, 3.0), (2, 1.0), (3, 2.0), (4, math.nan), (5, math.inf), (6, 1.5)]
    improved = [s.update(e, {"val_one_step_error": v})[0] for e, v in history]
    assert improved == [True, True, False, False, False, False]
    assert (s.best, s.best_epoch, s.bad_passes) == (1.0, 2, 4)


def test_non_finite_metrics_never_become_best():
    s = Selection("val_rollout_error")
    for e, v in enumerate([math.nan, math.inf, None], start=1):
        assert s.update(e, {"val_rollout_error": v}) == (False, False)
    assert s.best is None and s.best_epoch is None


def test_early_stopping_counts_passes_without_improvement_beyond_min_delta():
    s = Selection("val_one_step_error", patience=2, min_delta=0.1)
    assert s.update(1, {"val_one_step_error": 1.0}) == (True, False)
    assert s.update(2, {"val_one_step_error": 0.95}) == (False, False)  # better, but not by min_delta
    assert s.update(3, {"val_one_step_error": 0.5}) == (True, False)  # resets the count
    assert s.update(4, {"val_one_step_error": 0.5}) == (False, False)
    assert s.update(5, {"val_one_step_error": 0.6}) == (False, True)
    assert s.stopped and s.best_epoch == 3
    again = Selection("val_one_step_error", patience=2, min_delta=0.1)
    again.restore(s.state())
    assert again.state() == s.state()


def test_val_every_auto_gives_about_twenty_passes():
    assert val_interval("auto", 1000) == 50
    assert val_interval("auto", 7) == 1
    assert val_interval(3, 1000) == 3
    with pytest.raises(ConfigError, match="train.val_every"):
        val_interval(0, 10)


# ----------------------------------------------------------------------------- split
def test_trajectory_split_is_disjoint_deterministic_and_leaves_the_test_split_alone():
    test = np.array([3, 7, 11])
    train = np.setdiff1d(np.arange(40), test)
    a = make_val_split(train, 50, 0.1, seed=0)
    assert a.kind == "trajectories" and len(a.val_idx) == 4 and len(a.train_idx) == 33
    assert not set(a.val_idx) & set(a.train_idx) and not set(a.val_idx) & set(test)
    assert sorted({*a.val_idx, *a.train_idx}) == sorted(train)
    assert (a.val_start, a.val_stop, a.train_steps) == (0, 50, 50)
    b = make_val_split(train, 50, 0.1, seed=0)
    assert np.array_equal(a.val_idx, b.val_idx)
    assert not np.array_equal(a.val_idx, make_val_split(train, 50, 0.1, seed=1).val_idx)


def test_few_trajectories_split_in_time():
    s = make_val_split(np.array([0, 1]), 470, 0.1, seed=0)
    assert s.kind == "time" and np.array_equal(s.val_idx, [0, 1]) and np.array_equal(s.train_idx, [0, 1])
    # training on steps 0..423; validation poses 422..470: every predicted pose (424..470) is unseen
    assert (s.train_steps, s.val_start, s.val_stop) == (423, 422, 470)
    one = make_val_split(np.array([5]), 20, 0.2, seed=0)  # a single train trajectory: in time too
    assert (one.kind, one.train_steps, one.val_start, one.val_stop) == ("time", 16, 15, 20)


def test_too_short_or_too_large_splits_are_one_line_config_errors():
    with pytest.raises(ConfigError, match=r"leaving 1 \(need 2\)") as e:
        make_val_split(np.array([0, 1]), 2, 0.1, seed=0)
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match="holds out 6 of the 6"):
        make_val_split(np.arange(6), 10, 0.95, seed=0)
    with pytest.raises(ConfigError, match=r"\[0, 1\)"):
        make_val_split(np.arange(6), 10, 1.0, seed=0)


def test_val_fraction_zero_turns_validation_off_and_forces_select_last():
    s = make_val_split(np.arange(10), 10, 0.0, seed=0)
    assert s.kind == "none" and len(s.val_idx) == 0 and len(s.train_idx) == 10
    select, notes = select_option(TrainConfig(select="val_rollout"), s)
    assert select == "last" and notes == ["no validation split: train.select=val_rollout -> last"]


def test_val_fraction_does_not_change_the_cached_dataset():
    from liedfl_cli.data.scenes import dataset_path

    base = compose_config("train", SMOKE).dataset
    names = {dataset_path(compose_config("train", (*SMOKE, f"dataset.val_fraction={f}")).dataset) for f in (0, 0.3)}
    assert names == {dataset_path(base)}


# ----------------------------------------------------------------------------- config keys
@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("+train.val_evry=3", "did you mean 'train.val_every'"),
        ("+train.early_stopping.patiense=3", "did you mean 'train.early_stopping.patience'"),
        ("+dataset.val_fracton=0.2", "did you mean 'dataset.val_fraction'"),
        ("train.select=best", "train.select='best': choose one of val_one_step, val_rollout, last"),
        ("dataset.val_fraction=1.0", r"dataset.val_fraction=1.0: must be a number in \[0, 1\)"),
        ("train.early_stopping.patience=0", "train.early_stopping.patience=0"),
        ("train.val_horizon=1", "train.val_horizon=1"),
    ],
)
def test_schema_checks_the_new_keys(override, message):
    with pytest.raises(ConfigError, match=message):
        validate(compose_config("train", (*SMOKE, override)), "train")


def test_rollout_and_eval_take_checkpoint_best_or_last():
    validate(compose_config("rollout", ["run=x", "checkpoint=last"]), "rollout")
    with pytest.raises(ConfigError, match="checkpoint='newest': choose one of best, last"):
        validate(compose_config("eval", ["run=x", "checkpoint=newest"]), "eval")


# ----------------------------------------------------------------------------- end to end
def test_training_validates_selects_and_rolls_out_the_selected_checkpoint(tmp_path):
    s = run_train(_cfg(tmp_path, "run", ["train.epochs=4", "dataset.n_trajectories=12"]))
    run = Path(s["run_dir"])
    rows = _rows(run)
    assert len(rows) == 4 and all(c in rows[0] for c in VAL_COLUMNS)
    for r in rows:  # every epoch has a pass here (auto: about 20 passes per run)
        for c in ("val_one_step_error", "val_rollout_error", "val_cv_one_step_error"):
            assert math.isfinite(float(r[c])) and float(r[c]) > 0, (c, r[c])
        assert r["val_one_step_pos_error"] == r["val_rollout_pos_error"] == ""  # SO(3): no positions
        assert float(r["val_one_step_vs_cv"]) == pytest.approx(
            float(r["val_one_step_error"]) / float(r["val_cv_one_step_error"])
        )
    assert s["validation"]["split"] == "trajectories"  # 10 train trajectories: 1 held out whole
    errors = [float(r["val_one_step_error"]) for r in rows]
    best_epoch = int(np.argmin(errors)) + 1
    best = load_checkpoint(run / "checkpoints" / "best.pt")
    assert best["epoch"] == best_epoch and best["selected_by"] == "val_one_step_error"
    assert best["val"]["val_one_step_error"] == pytest.approx(min(errors))
    assert s["checkpoint"] == {
        "checkpoint": "best.pt",
        "checkpoint_epoch": best_epoch,
        "selected_by": "val_one_step_error",
        "value": pytest.approx(min(errors)),
    }
    with open(run / "eval.csv") as f:
        model_row = next(csv.DictReader(f))
    assert model_row["checkpoint"] == "best.pt" and int(model_row["checkpoint_epoch"]) == best_epoch
    # validation time is reported apart and is not training time
    t = s["timings"]
    assert t["val_seconds"] == pytest.approx(sum(float(r["val_seconds"]) for r in rows))
    assert t["train_seconds"] == pytest.approx(float(rows[-1]["seconds"]), abs=0.05)


def test_best_pt_holds_the_earlier_weights_when_later_epochs_are_worse(tmp_path, monkeypatch):
    _script(monkeypatch, [3.0, 1.0, 2.0, 4.0])
    s = run_train(_cfg(tmp_path, "run", ["train.epochs=4", "rollout.enabled=false", "train.val_every=1"]))
    monkeypatch.undo()
    assert s["checkpoint"]["checkpoint_epoch"] == 2
    two = run_train(_cfg(tmp_path, "two", ["train.epochs=2", "rollout.enabled=false"]))
    a = load_checkpoint(Path(s["run_dir"]) / "checkpoints" / "best.pt")["state_dict"]
    b = load_checkpoint(Path(two["run_dir"]) / "checkpoints" / "last.pt")["state_dict"]
    c = load_checkpoint(Path(s["run_dir"]) / "checkpoints" / "last.pt")["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)  # the weights after epoch 2
    assert not all(torch.equal(a[k], c[k]) for k in a)  # not the final ones


def test_early_stopping_stops_training(tmp_path, monkeypatch):
    _script(monkeypatch, [1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    extra = ["train.epochs=6", "rollout.enabled=false", "train.val_every=1", "train.early_stopping.patience=2"]
    s = run_train(_cfg(tmp_path, "run", extra))
    run = Path(s["run_dir"])
    assert len(_rows(run)) == 3 and s["timings"]["epochs"] == 3
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    assert last["epoch"] == 3 and last["selection"]["stopped"] and last["selection"]["best_epoch"] == 1
    assert s["checkpoint"]["checkpoint_epoch"] == 1


def test_select_last_writes_no_best_and_rolls_out_the_last_epoch(tmp_path, capsys):
    s = run_train(_cfg(tmp_path, "run", ["train.select=last", "rollout.enabled=false"]))
    run = Path(s["run_dir"])
    # smoke data: 4 train trajectories of 8 steps -> split in time, the last step validates
    out = capsys.readouterr().out
    assert "validation in time: poses 6..8 of each of the 4 train trajectories" in out
    assert "training on steps 0..7" in out and "checkpoint: last.pt (epoch 2)" in out
    assert s["validation"]["split"] == "time" and s["dataset"]["val"] == 4
    assert not (run / "checkpoints" / "best.pt").exists()
    assert s["checkpoint"] == {"checkpoint": "last.pt", "checkpoint_epoch": 2}
    assert all(r["val_one_step_error"] for r in _rows(run))  # still measured


def test_no_validation_leaves_the_columns_out_and_selects_last(tmp_path):
    s = run_train(_cfg(tmp_path, "run", ["dataset.val_fraction=0", "rollout.enabled=false"]))
    rows = _rows(Path(s["run_dir"]))
    assert "val_one_step_error" not in rows[0] and s["checkpoint"]["checkpoint"] == "last.pt"
    assert s["validation"]["split"] == "none"


def test_rollout_eval_and_api_use_and_report_the_selected_checkpoint(tmp_path, capsys):
    from liedfl_cli import api
    from liedfl_cli.commands.evaluate import run_eval
    from liedfl_cli.commands.rollout import run_rollout

    s = run_train(_cfg(tmp_path, "run", ["train.epochs=3"]))
    run = Path(s["run_dir"])
    best_epoch = s["checkpoint"]["checkpoint_epoch"]
    common = [f"run={run}", "ui.progress=false", "eval.plots=false", f"paths.data_dir={tmp_path}/data"]
    capsys.readouterr()
    r = run_rollout(compose_config("rollout", common))
    assert r["checkpoint"]["checkpoint"] == "best.pt" and r["checkpoint"]["checkpoint_epoch"] == best_epoch
    assert f"checkpoint: best.pt (epoch {best_epoch}, val_one_step_error" in capsys.readouterr().out
    assert json.loads((Path(r["dir"]) / "checkpoint.json").read_text())["checkpoint"] == "best.pt"
    r = run_rollout(compose_config("rollout", [*common, "checkpoint=last"]))
    assert r["checkpoint"] == {"checkpoint": "last.pt", "checkpoint_epoch": 3}
    rows = run_eval(compose_config("eval", [*common, f"rollout={r['dir']}"]))  # the rollout's own record
    assert rows[0]["checkpoint"] == "last.pt" and rows[0]["checkpoint_epoch"] == 3
    assert api.load_run(run, data_dir=tmp_path / "data").checkpoint["checkpoint"] == "best.pt"
    assert api.load_run(run, data_dir=tmp_path / "data", checkpoint="last").checkpoint["checkpoint_epoch"] == 3
    # a run written before best.pt existed
    (run / "checkpoints" / "best.pt").unlink()
    (run / "checkpoint.json").unlink()
    rows = run_eval(compose_config("eval", common))
    assert rows[0]["checkpoint"] == "last.pt"


@pytest.mark.parametrize("model", single_body_models())
def test_every_baseline_validates(tmp_path, model):
    s = run_train(_cfg(tmp_path, "run", [f"model={model}", "rollout.enabled=false", "train.epochs=1"]))
    row = _rows(Path(s["run_dir"]))[0]
    assert math.isfinite(float(row["val_one_step_error"])) and math.isfinite(float(row["val_rollout_error"]))
    assert s["checkpoint"]["checkpoint"] == "best.pt"


@pytest.mark.parametrize("name", ["soap", "adam"])
def test_weight_decay_reaches_both_optimizers(name):
    from omegaconf import OmegaConf

    from liedfl_cli.commands.train import make_optimizer

    cfg = OmegaConf.create({"name": name, "lr": 1e-3, "weight_decay": 0.25})
    opt = make_optimizer([torch.nn.Parameter(torch.ones(3))], cfg)
    assert opt.param_groups[0]["weight_decay"] == 0.25
