"""The trainer's objects (issue 35): the optimiser and schedule registries, each callback of `fit` on
its own (a stand-in trainer, scripted metrics), and `fit`'s loop against a hand-written one."""

from __future__ import annotations

import contextlib
import math
import signal

import pytest
import torch

from helpers import compose_config
from liedfl_cli.commands.callbacks import (
    BestModelCallback,
    CheckpointCallback,
    EarlyStoppingCallback,
    LoggerCallback,
    ProgressCallback,
    ValidationCallback,
    checkpoint_interval,
)
from liedfl_cli.commands.optimizers import OPTIMIZERS, SCHEDULES, make_optimizer, make_schedule
from liedfl_cli.commands.stopping import StopRequest, TrainingDiverged, TrainingInterrupted
from liedfl_cli.commands.trainer import fit
from liedfl_cli.commands.validation import VAL_COLUMNS, Selection
from liedfl_cli.config.typed import OptimizerConfig, TrainConfig, section
from liedfl_cli.errors import ConfigError
from liedfl_cli.solvers import runtime


# ----------------------------------------------------------------------------- registries
def _params():
    return [torch.nn.Parameter(torch.ones(3, 3)), torch.nn.Parameter(torch.zeros(3))]


@pytest.mark.parametrize("fused", [False, True])
def test_the_registry_builds_each_optimiser_with_the_configured_settings(fused):
    from pytorch_optimizer import SOAP

    from liedfl_cli.commands.fused_optim import FusedSOAP

    with runtime.using(fused=fused):
        soap = make_optimizer(_params(), OptimizerConfig(name="soap", lr=0.01, precondition_frequency=3))
        adam = make_optimizer(_params(), OptimizerConfig(name="adam", lr=0.02, weight_decay=0.1))
    assert type(soap) is (FusedSOAP if fused else SOAP) and isinstance(soap, SOAP)
    assert soap.param_groups[0]["lr"] == 0.01 and soap.param_groups[0]["precondition_frequency"] == 3
    assert type(adam) is torch.optim.Adam and adam.defaults["foreach"] is fused
    assert adam.param_groups[0]["lr"] == 0.02 and adam.param_groups[0]["weight_decay"] == 0.1
    assert set(OPTIMIZERS) == {"soap", "adam"} and set(SCHEDULES) == {"constant", "cosine"}


def test_the_registry_builds_each_schedule():
    opt = make_optimizer(_params(), OptimizerConfig(name="adam", lr=0.5))
    assert make_schedule(opt, "constant", 10) is None
    cosine = make_schedule(opt, "cosine", 10)
    assert isinstance(cosine, torch.optim.lr_scheduler.CosineAnnealingLR)
    assert cosine.T_max == 10 and cosine.eta_min == pytest.approx(0.005)


def test_an_unknown_optimiser_or_schedule_is_a_one_line_error_naming_the_field():
    with pytest.raises(ConfigError) as e:
        make_optimizer(_params(), OptimizerConfig(name="sgd"))  # the field's own check, at construction
    assert str(e.value) == "train.optimizer.name='sgd': choose one of soap, adam"
    with pytest.raises(ConfigError) as e:
        make_optimizer(_params(), {"name": "lbfgs"})  # a section as scripts pass it
    assert "train.optimizer.name" in str(e.value) and "\n" not in str(e.value)
    opt = make_optimizer(_params(), OptimizerConfig(name="adam"))
    with pytest.raises(ConfigError) as e:
        make_schedule(opt, "step", 10)
    assert str(e.value) == "train.optimizer.schedule='step': choose one of constant, cosine"


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_every_registered_optimiser_is_a_value_the_config_accepts(name, tmp_path):
    """The registry's names are the config's values: `train.optimizer.name=<name>` composes and passes
    the config check, and an unknown name fails it with a line naming the field."""
    from liedfl_cli.config.schema import validate

    paths = (f"paths.data_dir={tmp_path}", f"paths.output_dir={tmp_path}/run")
    validate(compose_config("train", (*paths, f"train.optimizer.name={name}")), "train")
    for schedule in SCHEDULES:
        validate(compose_config("train", (*paths, f"train.optimizer.schedule={schedule}")), "train")
    with pytest.raises(ConfigError, match="train.optimizer.name"):
        validate(compose_config("train", (*paths, "train.optimizer.name=sgd")), "train")


# ----------------------------------------------------------------------------- callbacks alone
class _Trainer:
    """A stand-in for `trainer.Trainer`: the attributes and methods the callbacks use."""

    def __init__(self, epochs: int, bad: str = ""):
        self.epochs, self.start, self.epoch = epochs, 1, 0
        self.model = object()
        self.history: list[dict] = []
        self.start_note, self.start_pass = None, None
        self.saved_epoch = None
        self.val_seconds, self.excluded = 0.0, 0.0
        self.validated = self.improved = self.early = False
        self.losses: dict = {}
        self.scope = contextlib.ExitStack()
        self.bad = bad

    def exclude(self, seconds: float) -> None:
        self.excluded += seconds

    def elapsed(self) -> float:
        return 0.0

    def weights_usable(self) -> str:
        return self.bad

    def state(self, epoch: int) -> dict:
        return {"epoch": epoch}

    def run(self, callbacks, epochs=None) -> int | None:
        """Epochs 1.. with `callbacks` -> the epoch at which one ended the training (None: all ran)."""
        for epoch in range(1, (epochs or self.epochs) + 1):
            self.epoch = epoch
            self.validated = self.improved = self.early = False
            self.losses = {"loss": 1.0 / epoch}
            row = {"epoch": epoch, "loss": 1.0 / epoch}
            self.history.append(row)
            if any(cb.on_epoch_end(self, row) for cb in callbacks):
                return epoch
        return None


class _ScriptedValidator:
    """A validator whose passes return the given one-step errors, one per pass."""

    def __init__(self, values, every: int = 1):
        self.values, self.every, self.passes = iter(values), every, 0

    def due(self, epoch: int, epochs: int) -> bool:
        return epoch % self.every == 0 or epoch == epochs

    def measure(self, model) -> dict:
        self.passes += 1
        return {**dict.fromkeys(VAL_COLUMNS), "val_one_step_error": next(self.values), "val_seconds": 0.0}


def test_early_stopping_stops_at_the_pass_that_uses_up_the_patience(capsys):
    selection = Selection("val_one_step_error", patience=2, min_delta=0.1)
    validator = _ScriptedValidator([3.0, 2.0, 1.95, 2.5, 1.0, 0.5])  # 1.95: not better by more than 0.1
    trainer = _Trainer(epochs=6)
    stopped = trainer.run([ValidationCallback(validator, selection), EarlyStoppingCallback(selection)])
    assert stopped == 4 and validator.passes == 4
    assert selection.best == 2.0 and selection.best_epoch == 2 and selection.stopped
    assert "early stopping after epoch 4/6" in capsys.readouterr().out


def test_without_patience_or_between_passes_nothing_stops():
    selection = Selection("val_one_step_error")  # patience None: off
    validator = _ScriptedValidator([3.0, 4.0, 5.0, 6.0], every=2)
    trainer = _Trainer(epochs=8)
    assert trainer.run([ValidationCallback(validator, selection), EarlyStoppingCallback(selection)]) is None
    assert validator.passes == 4  # epochs 2, 4, 6, 8
    first, second = trainer.history[:2]
    assert first["val_one_step_error"] is None and set(VAL_COLUMNS) <= set(first)  # the columns, empty
    assert second["val_one_step_error"] == 3.0 and second["val_seconds"] is not None


def test_the_best_model_is_saved_when_the_selected_metric_improves():
    saved = []
    selection = Selection("val_one_step_error")
    validator = _ScriptedValidator([3.0, 1.0, 2.0, 0.5])
    trainer = _Trainer(epochs=4)
    trainer.run([ValidationCallback(validator, selection), BestModelCallback(lambda e, r: saved.append(e))])
    assert saved == [1, 2, 4]


def test_the_start_pass_is_epoch_zero_of_the_selection():
    saved = []
    selection = Selection("val_one_step_error")
    trainer = _Trainer(epochs=2)
    trainer.start_note = "a start of its own"
    callbacks = [ValidationCallback(_ScriptedValidator([1.0, 2.0, 0.5]), selection),
                 BestModelCallback(lambda e, r: saved.append(e))]  # fmt: skip
    for cb in callbacks:
        cb.on_train_start(trainer)  # type: ignore[arg-type]
    assert trainer.start_pass is not None and saved == [0]
    trainer.run(callbacks)
    assert saved == [0, 2] and selection.best_epoch == 2


def test_the_checkpoint_callback_saves_every_n_epochs_but_not_the_last():
    saved = []
    trainer = _Trainer(epochs=7)
    trainer.run([CheckpointCallback(lambda state: saved.append(state["epoch"]), every=2)])
    assert saved == [2, 4, 6] and trainer.saved_epoch == 6


def test_a_stop_request_saves_a_checkpoint_then_interrupts():
    saved, stop = [], StopRequest()
    trainer = _Trainer(epochs=9)
    logger = LoggerCallback(lambda row: setattr(stop, "signum", signal.SIGTERM) if row["epoch"] == 3 else None)
    with pytest.raises(TrainingInterrupted, match="SIGTERM: training stopped after epoch 3/9; checkpoint saved") as e:
        trainer.run([logger, CheckpointCallback(lambda state: saved.append(state["epoch"]), every=5, stop=stop)])
    assert saved == [3] and e.value.exit_code == 128 + signal.SIGTERM


def test_the_checkpoint_callback_never_saves_diverged_weights():
    saved = []
    trainer = _Trainer(epochs=5, bad="nan")
    with pytest.raises(TrainingDiverged) as e:
        trainer.run([CheckpointCallback(lambda state: saved.append(state["epoch"]), every=2)])
    assert saved == [] and e.value.epoch == 2 and e.value.saved is None and "the end of epoch 2" in str(e.value)


def test_checkpoint_interval_is_auto_or_a_positive_integer():
    assert checkpoint_interval("auto") is None and checkpoint_interval(3) == 3
    for bad in (0, -1, "often", 1.5):
        with pytest.raises(ConfigError, match="train.checkpoint_every"):
            checkpoint_interval(bad)


def test_the_logger_gets_every_row_with_its_validation_columns():
    rows = []
    trainer = _Trainer(epochs=3)
    validator = _ScriptedValidator([1.0, 2.0, 3.0])
    trainer.run([ValidationCallback(validator, Selection(None)), LoggerCallback(rows.append)])
    assert [r["epoch"] for r in rows] == [1, 2, 3] and [r["val_one_step_error"] for r in rows] == [1.0, 2.0, 3.0]


def test_progress_without_the_bar_prints_an_epoch_line_per_tenth(capsys):
    trainer = _Trainer(epochs=20)
    progress = ProgressCallback(bar=False)
    with trainer.scope:
        progress.on_train_start(trainer)  # type: ignore[arg-type]
        trainer.run([progress])
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("epoch ")]
    assert [line.split()[1] for line in lines] == [f"{e}/20" for e in range(2, 21, 2)]


# ----------------------------------------------------------------------------- the loop
def _tiny(free_body_dataset, tmp_path, *overrides):
    from liedfl_cli.config.factory import build_model

    cfg = compose_config(
        "train",
        ("budget=smoke", f"paths.data_dir={tmp_path}", f"paths.output_dir={tmp_path}/run", "train.epochs=3",
         "train.batch_size=16", *overrides),
    )  # fmt: skip
    ds = free_body_dataset
    return cfg, build_model(cfg, ds), ds.pose(ds.train_idx), int(cfg.dataset.train_steps)


def test_fit_equals_a_hand_written_loop(free_body_dataset, tmp_path):
    """`fit` on the reference path with Adam and a cosine schedule: the same weights as the loop written
    out (shuffle, mini-batches, backward, step, schedule), at rtol 1e-12."""
    from liedfl_cli.models.liedflnn.losses import training_stage

    over = ("train.optimizer.name=adam", "train.optimizer.schedule=cosine", "train.start=none")
    with runtime.using(fused=False):
        cfg, model, data, steps = _tiny(free_body_dataset, tmp_path, *over)
        hand = {k: v.clone() for k, v in model.state_dict().items()}
        result = fit(model, data, cfg.train, steps, seed=5)
        cfg, twin, data, steps = _tiny(free_body_dataset, tmp_path, *over)
        twin.load_state_dict(hand)
        opts, samples = training_stage(twin, data, steps, section(TrainConfig, cfg.train, "train").loss_options())
        params = [p for p in twin.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=cfg.train.optimizer.lr, weight_decay=0.0, foreach=False)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=3, eta_min=0.01 * cfg.train.optimizer.lr)
        gen = torch.Generator().manual_seed(5)
        bs = min(16, samples.n)
        for _ in range(3):
            perm = torch.randperm(samples.n, generator=gen)
            for b in range(math.ceil(samples.n / bs)):
                opt.zero_grad(set_to_none=True)
                loss, _ = twin.loss(samples.batch(perm[b * bs : (b + 1) * bs], gen, opts.reg_points), opts)
                loss.backward()
                opt.step()
            sched.step()
    assert result["epochs"] == 3 and len(result["history"]) == 3
    a, b = model.state_dict(), twin.state_dict()
    assert all(torch.allclose(a[k], b[k], rtol=1e-12, atol=0) for k in a)
    assert any(not torch.equal(a[k], hand[k]) for k in a)  # it trained


def test_callbacks_change_no_number(free_body_dataset, tmp_path):
    """The same training with every callback of `liedfl train` (validation each epoch, best model,
    logger, progress, early stopping off, checkpoints each epoch) and with none: the same weights and
    losses, bit for bit; the checkpoint states are those of each epoch."""
    from liedfl_cli.commands.validation import Validator
    from liedfl_cli.config.factory import data_pose

    cfg, model, data, steps = _tiny(free_body_dataset, tmp_path)
    start = {k: v.clone() for k, v in model.state_dict().items()}
    plain = fit(model, data, cfg.train, steps)
    _, twin, _, _ = _tiny(free_body_dataset, tmp_path)
    twin.load_state_dict(start)
    ds = free_body_dataset
    validator = Validator(ds.group, data_pose(ds, ds.train_idx[:2]), compose_config("train").solver, 3, 1)
    selection, rows, states, best = Selection("val_one_step_error"), [], [], []
    callbacks = [
        ValidationCallback(validator, selection),
        BestModelCallback(lambda e, r: best.append(e)),
        LoggerCallback(rows.append),
        ProgressCallback(bar=False),
        EarlyStoppingCallback(selection),
        CheckpointCallback(lambda s: states.append(s["epoch"]), every=1),
    ]
    full = fit(twin, data, cfg.train, steps, callbacks=callbacks)
    a, b = model.state_dict(), twin.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [r["loss"] for r in plain["history"]] == [r["loss"] for r in full["history"]]
    assert states == [1, 2] and len(rows) == 3 and best and best[0] == 1
    assert full["state"]["selection"] == selection.state() and full["state"]["val_every"] == 1
    assert plain["state"]["selection"] is None and plain["val_seconds"] == 0.0 < full["val_seconds"]
