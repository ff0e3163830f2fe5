"""The per-epoch work of a training, as callbacks of `trainer.fit` (lightning's habit).

A callback (`trainer.Callback`) is told when the epochs start (`on_train_start`), after each epoch
(`on_epoch_end(trainer, row)`: the epoch's metrics row, which it may extend; True ends the training
after this epoch, the later callbacks skipped) and after the last epoch (`on_train_end`); `state()` is
what it adds to the training state saved in checkpoints. `fit` calls them in the order given; `liedfl train` gives
`ValidationCallback`, `BestModelCallback`, `LoggerCallback`, `ProgressCallback`,
`EarlyStoppingCallback`, `CheckpointCallback` (`train.default_callbacks`): validation first, so that
the logger, the display and the stop decisions see its columns; the checkpoint last, so that it saves
what the epoch ended with.

The `Trainer` (`trainer.py`) is the loop's state the callbacks share: the model, the epoch count, the
history, the clock (`trainer.exclude(seconds)`: time that is not training time), this epoch's
`validated` / `improved` / `early` flags, the last checkpoint's epoch.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from ..display.ui import PlainProgress, console, progress_bar
from ..errors import ConfigError
from .stopping import StopRequest, TrainingDiverged, TrainingInterrupted, stop_reason
from .trainer import Callback, Trainer
from .validation import VAL_COLUMNS, Selection, Validator, format_pass

AUTO_CHECKPOINT_SECONDS = 60.0  # `checkpoint_every: auto` loses at most about this much work


class ValidationCallback(Callback):
    """Validation passes (`train.val_every`, and the last epoch) and the selection of the best pass:
    the VAL_COLUMNS of every row (empty without a pass), `trainer.validated`, `trainer.improved` (the
    selected metric improved) and `trainer.early` (`train.early_stopping`'s patience ran out). A model
    with a start of its own (`train.start`) is validated before the first epoch too (epoch 0): epochs
    that move away from it cannot lose it. A pass's seconds are not training time."""

    def __init__(self, validator: Validator | None, selection: Selection | None):
        self.validator, self.selection = validator, selection

    def on_train_start(self, trainer: Trainer) -> None:
        if not (trainer.start_note and self.validator is not None and self.selection is not None):
            return
        tv = time.perf_counter()
        row0 = self.validator.measure(trainer.model)
        trainer.improved, _ = self.selection.update(0, row0)
        trainer.start_pass = row0
        trainer.exclude(time.perf_counter() - tv)

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        if self.validator is None:
            return False
        row.update(dict.fromkeys(VAL_COLUMNS))  # the columns stay empty on epochs without a pass
        if not self.validator.due(trainer.epoch, trainer.epochs):
            return False
        tv = time.perf_counter()
        row.update(self.validator.measure(trainer.model))
        if self.selection is not None:
            trainer.improved, trainer.early = self.selection.update(trainer.epoch, row)
        spent = time.perf_counter() - tv
        row["val_seconds"] = spent
        trainer.exclude(spent)
        trainer.validated = True
        return False

    def state(self) -> dict:
        return {
            "selection": self.selection.state() if self.selection is not None else None,
            "val_every": self.validator.every if self.validator is not None else None,
        }


class BestModelCallback(Callback):
    """`checkpoints/best.pt`: `save_best(epoch, row)` whenever the selected metric improved (the start's
    pass is epoch 0); its seconds count as the validation pass's."""

    def __init__(self, save_best: Callable[[int, dict], None]):
        self.save_best = save_best

    def on_train_start(self, trainer: Trainer) -> None:
        if trainer.improved and trainer.start_pass is not None:
            tb = time.perf_counter()
            self.save_best(0, trainer.start_pass)
            trainer.exclude(time.perf_counter() - tb)

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        if trainer.improved:
            tb = time.perf_counter()
            self.save_best(trainer.epoch, row)
            spent = time.perf_counter() - tb
            row["val_seconds"] += spent  # the pass and best.pt
            trainer.exclude(spent)
        return False


class LoggerCallback(Callback):
    """Each epoch's row to the metric loggers (`loggers/`: train_metrics.csv, TensorBoard)."""

    def __init__(self, log: Callable[[dict], None]):
        self.log = log

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        self.log(row)
        return False


class ProgressCallback(Callback):
    """What the console shows: the model's start, then the rich progress bar (`bar=True`, with plain
    lines where stdout is a log file: `PlainProgress`) or, with `ui.progress=false`, one epoch line per
    tenth of the run (and at least one a minute)."""

    def __init__(self, bar: bool = True):
        self.show_bar = bar
        self.val_text = ""
        self.last_line = 0.0

    def on_train_start(self, trainer: Trainer) -> None:
        if trainer.start_note:
            console.print(f"[bold]start[/] {trainer.start_note}", highlight=False)
        if trainer.start_pass is not None:
            console.print(f"start: {format_pass(trainer.start_pass)}", highlight=False)
        history = trainer.history
        self.val_text = next((format_pass(r) for r in reversed(history) if r.get("val_one_step_error") is not None), "")
        self.bar = trainer.scope.enter_context(progress_bar(self.show_bar))
        done = trainer.start - 1
        self.task = self.bar.add_task(
            "train", total=trainer.epochs, completed=done, loss=float("nan"), val=self.val_text
        )
        self.plain = PlainProgress(trainer.epochs, done, enabled=self.show_bar)  # lines a log file keeps
        self.last_line = time.perf_counter()  # the last epoch line with ui.progress=false

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        epoch, epochs, losses = trainer.epoch, trainer.epochs, trainer.losses
        if trainer.validated:
            self.val_text = format_pass(row)
        self.bar.update(self.task, advance=1, loss=losses["loss"], val=self.val_text)
        self.plain.update(epoch, losses["loss"], self.val_text, validated=trainer.validated or trainer.early)
        tenth = epoch % max(1, epochs // 10) == 0 or epoch == epochs or trainer.early
        if not self.show_bar and (tenth or time.perf_counter() - self.last_line >= 60.0):
            self.last_line = time.perf_counter()  # (also at least once a minute: a log file sees progress)
            console.print(
                f"epoch {epoch}/{epochs}  "
                + "  ".join(f"{k} {v:.3e}" for k, v in losses.items())
                + (f"  {self.val_text}" if self.val_text else "")
                + f"  ({trainer.elapsed():.1f} s)",
                highlight=False,
            )
        return False


class EarlyStoppingCallback(Callback):
    """Ends the training when a validation pass used up `train.early_stopping.patience` (the selection
    counts the passes without an improvement: `Selection.update`), with one line saying why."""

    def __init__(self, selection: Selection):
        self.selection = selection

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        if not trainer.early:
            return False
        s = self.selection
        console.print(
            f"early stopping after epoch {trainer.epoch}/{trainer.epochs}: {s.metric} has not improved by more than "
            f"{s.min_delta:g} for {s.bad_passes} validation passes "
            f"(best {s.best if s.best is not None else float('nan'):.3e} at epoch {s.best_epoch})",
            highlight=False,
        )
        return True


def checkpoint_interval(value) -> int | None:
    """`train.checkpoint_every`: `auto` (None: time-based) or a positive number of epochs."""
    if value in (None, "auto"):
        return None
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"train.checkpoint_every={value!r}: must be auto or a positive integer") from None
    if n < 1 or n != value and str(n) != str(value):
        raise ConfigError(f"train.checkpoint_every={value!r}: must be auto or a positive integer")
    return n


class CheckpointCallback(Callback):
    """`save(training state)` every `every` epochs (None: whenever AUTO_CHECKPOINT_SECONDS have passed)
    and when `stop` holds a signal, then `TrainingInterrupted`; never after the last epoch (the
    command saves the finished run) and never weights whose loss is no longer finite
    (`TrainingDiverged` naming the last good checkpoint)."""

    def __init__(self, save: Callable[[dict], None], every: int | None, stop: StopRequest | None = None):
        self.save, self.every, self.stop = save, every, stop
        self.last_save = time.perf_counter()

    def on_train_start(self, trainer: Trainer) -> None:
        self.last_save = time.perf_counter()

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        epoch, epochs = trainer.epoch, trainer.epochs
        signum = self.stop.signum if self.stop is not None else None
        if self.every:
            due = epoch % self.every == 0
        else:
            due = time.perf_counter() - self.last_save >= AUTO_CHECKPOINT_SECONDS
        if epoch < epochs and (due or signum is not None):
            bad = trainer.weights_usable()  # never save diverged weights over good ones
            if bad:
                raise TrainingDiverged(epoch, None, bad, first=False, saved=trainer.saved_epoch)
            self.save(trainer.state(epoch))
            trainer.saved_epoch = epoch
            self.last_save = time.perf_counter()
        if signum is not None and epoch < epochs:
            raise TrainingInterrupted(
                f"{stop_reason(signum)}: training stopped after epoch {epoch}/{epochs}; checkpoint saved",
                128 + int(signum),
            )
        return False
