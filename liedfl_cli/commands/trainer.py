"""The training loop: `fit` trains a model on the samples of its data for `train.epochs` epochs of
shuffled mini-batches; what happens after each epoch (validation, best model, loggers, progress,
early stopping, checkpoints) is the callbacks' (`callbacks.py`), objects with the hooks of `Callback`
that share the loop's state, the `Trainer`.

loss = the model's `loss(batch, opts)` (for the DEL models w_DEL * mean ||r_k||^2 + w_reg *
mean penalty(log|det H|) over `reg_points` random pairs). Samples are batched tensors. A training
resumed from a checkpoint's state (`resume`) continues its optimiser, schedule and random streams
and, for the same seed, ends with the same losses and weights as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence

import torch
from omegaconf import DictConfig

from ..config.typed import TrainConfig, section
from ..errors import CheckpointError, ConfigError
from ..files.checkpoint import capture_rng_state, restore_rng_state
from ..lie import Pose
from ..models.liedflnn.losses import training_stage
from .optimizers import make_optimizer, make_schedule
from .stopping import TrainingDiverged


def _loss_value(model, batch, opts) -> tuple[torch.Tensor | None, dict, str]:
    """(loss, parts, '') or (None, {}, what it became) when it is non-finite or overflows."""
    try:
        loss, parts = model.loss(batch, opts)
    except OverflowError as e:
        return None, {}, f"too large ({e})"
    if not torch.isfinite(loss):
        return None, {}, str(loss.item())
    return loss, parts, ""


def _fused_value(grad_fn, params: list, batch, opts) -> tuple[float | None, dict, str]:
    """`_loss_value` plus the backward pass of a fused gradient (`Model.value_and_grad`):
    the gradients are set on `params` (no autograd graph, nothing to zero)."""
    try:
        loss, parts, grads = grad_fn(batch, opts)
    except OverflowError as e:
        return None, {}, f"too large ({e})"
    if grads is None:
        return None, {}, str(loss)
    for p, g in zip(params, grads):
        p.grad = g
    return loss, parts, ""


def _first_resumed_step(opt) -> None:
    """The first optimizer step after a resume: a restored state that `load_state_dict` accepted but
    the step cannot use (a missing or reshaped buffer of the checkpoint) is a CheckpointError line."""
    try:
        opt.step()
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(
            f"checkpoint training state is not usable: the optimizer's step fails ({type(e).__name__}: {e})"
        ) from None


class Callback:
    """One piece of a training's per-epoch work; every hook does nothing unless overridden."""

    def on_train_start(self, trainer: Trainer) -> None:
        """Before the first epoch of this `fit` call (after the model's start and a resume's restore)."""

    def on_epoch_end(self, trainer: Trainer, row: dict) -> bool:
        """After epoch `trainer.epoch`, whose metrics are `row` (already in `trainer.history`) -> stop?"""
        return False

    def on_train_end(self, trainer: Trainer) -> None:
        """After the last epoch run (not after an error)."""

    def state(self) -> dict:
        """What this callback adds to the training state of a checkpoint (restored by its maker)."""
        return {}


class Trainer:
    """The state of one `fit` call that its callbacks share: what trains (`model`, `samples`, `opts`,
    the optimiser `opt` and schedule `sched`, the batches' generator `gen`), where it stands (`epoch`,
    `epochs`, `start`: the first epoch of this call, `history`), the clock (`t0`; `exclude` moves it
    past work that is not training), `saved_epoch` (the last checkpoint written, None before one) and
    what this epoch's callbacks found so far (`validated`, `improved`, `early`; `losses`: the epoch's
    mean loss parts). `scope` holds what a callback opens for the epochs (the progress display)."""

    def __init__(self, model, samples, opts, opt, sched, gen: torch.Generator, epochs: int, callbacks):
        self.model, self.samples, self.opts = model, samples, opts
        self.opt, self.sched, self.gen = opt, sched, gen
        self.epochs = epochs
        self.callbacks: list[Callback] = list(callbacks)
        self.start, self.epoch = 1, 0
        self.history: list[dict] = []
        self.start_note: str | None = None
        self.start_pass: dict | None = None  # the validation pass of the model's start (epoch 0)
        self.saved_epoch: int | None = None
        self.val_seconds = 0.0
        self.t0 = time.perf_counter()
        self.validated = self.improved = self.early = False
        self.losses: dict[str, float] = {}
        self.scope = contextlib.ExitStack()

    def elapsed(self) -> float:
        """Training seconds so far (validation left out)."""
        return time.perf_counter() - self.t0

    def exclude(self, seconds: float) -> None:
        """`seconds` of validation work: counted as validation time, not as training time."""
        self.val_seconds += seconds
        self.t0 += seconds

    def weights_usable(self) -> str:
        """'' when the loss at the current weights is finite on a few samples (a private generator: the
        training's random streams are untouched), else what it became. Weights one step past a divergence
        are finite but huge; their loss is not."""
        gen = torch.Generator().manual_seed(0)
        idx = torch.arange(min(4, self.samples.n))
        with torch.no_grad():
            _, _, bad = _loss_value(self.model, self.samples.batch(idx, gen, self.opts.reg_points), self.opts)
        return bad

    def state(self, epoch: int) -> dict:
        """The training state a checkpoint keeps after `epoch` (what `resume` continues from)."""
        state = {
            "epoch": epoch,
            "optimizer": self.opt.state_dict(),
            "scheduler": self.sched.state_dict() if self.sched is not None else None,
            "rng": capture_rng_state({"batches": self.gen}),
            "history": self.history,
            "selection": None,
            "val_every": None,
        }
        for cb in self.callbacks:
            state.update(cb.state())
        return state

    def restore(self, resume: dict) -> None:
        """Continue from a checkpoint's training state (one-line CheckpointError when it is unusable)."""
        try:
            self.opt.load_state_dict(resume["optimizer"])
            if self.sched is not None and resume.get("scheduler") is not None:
                self.sched.load_state_dict(resume["scheduler"])
            restore_rng_state(resume["rng"], {"batches": self.gen})
            self.history = [dict(r) for r in resume["history"]]
            self.start = int(resume["epoch"]) + 1
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointError(f"checkpoint training state is not usable ({type(e).__name__}: {e})") from None
        self.saved_epoch = self.start - 1


def _model_start(model, samples, cfg_train: TrainConfig, resume: dict | None) -> tuple[str | None, float]:
    """`train.start`: the model's own fit before the epochs (not on resume) -> (its note, seconds)."""
    if resume is not None or cfg_train.start == "none":
        return None, 0.0
    ts = time.perf_counter()
    note = model.initial_fit(samples, cfg_train.start)
    return note, time.perf_counter() - ts


def _epoch_losses(trainer: Trainer, epoch: int, grad_fn, params: list, bs: int, n_batches: int, resumed: bool):
    """One epoch's optimiser steps over shuffled mini-batches -> the mean of each loss part.
    `resumed`: the first step of a resumed training (its restored state's first use is checked)."""
    samples, opts, opt, gen = trainer.samples, trainer.opts, trainer.opt, trainer.gen
    perm = torch.randperm(samples.n, generator=gen)
    sums: dict[str, float] = {}
    for b in range(n_batches):
        idx = perm[b * bs : (b + 1) * bs]
        batch = samples.batch(idx, gen, opts.reg_points)
        value: float | torch.Tensor | None
        if grad_fn is not None:  # forward and backward fused, no autograd graph
            value, parts, bad = _fused_value(grad_fn, params, batch, opts)
        else:
            opt.zero_grad(set_to_none=True)
            value, parts, bad = _loss_value(trainer.model, batch, opts)
            if value is not None:
                value.backward()
        first = epoch == trainer.start and b == 0
        if value is None:
            raise TrainingDiverged(epoch, b, bad, first=first, saved=trainer.saved_epoch)
        if resumed and first:  # the restored state's first use
            _first_resumed_step(opt)
        else:
            opt.step()
        for k, v in {"loss": value, **parts}.items():
            sums[k] = sums.get(k, 0.0) + (v if isinstance(v, float) else float(v.detach())) / n_batches
    return sums


def fit(
    model,
    data: Pose,
    cfg_train: TrainConfig | DictConfig,
    steps: int,
    seed: int = 0,
    callbacks: Sequence[Callback] = (),
    *,
    resume: dict | None = None,
) -> dict:
    """Train `model` on the first `steps` steps of `data` (T, N+1, ...) -> history and timings.

    The model says what a sample is (`model.training_set`: pose triplets or whole windows);
    each epoch visits the samples in shuffled mini-batches (plus `reg_points` random pairs per
    batch for models with a regularity term), then runs `callbacks` in order (`callbacks.py`; none:
    a silent training without validation or checkpoints). resume: the training state of a checkpoint
    (`epoch`, `optimizer`, `scheduler`, `rng`, `history`) to continue from.
    """
    if not isinstance(cfg_train, TrainConfig):  # scripts and tests may pass a `train` section as is
        cfg_train = section(TrainConfig, cfg_train, "train")
    assert isinstance(cfg_train, TrainConfig)  # (for mypy: `section` returns its schema's instance)
    # train.loss: newton changes the batches' loss; rollout trains with del here (fine-tuning: finetune.py)
    opts, samples = training_stage(model, data, int(steps), cfg_train.loss_options())
    start_note, start_seconds = _model_start(model, samples, cfg_train, resume)
    n = samples.n
    bs = n if cfg_train.full_batch else min(int(cfg_train.batch_size), n)
    n_batches = math.ceil(n / bs)
    model.set_plan(model.plan.for_training(int(cfg_train.epochs) * n_batches))  # compile: auto weighs this
    gen = torch.Generator().manual_seed(seed)
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ConfigError("the model has no trainable parameters")
    opt = make_optimizer(params, cfg_train.optimizer)
    grad_fn = model.value_and_grad(samples, opts, params)  # None: autograd's backward
    epochs = int(cfg_train.epochs)
    sched = make_schedule(opt, cfg_train.optimizer.schedule, epochs)
    trainer = Trainer(model, samples, opts, opt, sched, gen, epochs, callbacks)
    trainer.start_note = start_note
    offset = start_seconds  # the model's start counts as training time
    if resume is not None:
        trainer.restore(resume)
        offset = float(trainer.history[-1]["seconds"]) if trainer.history else 0.0
    trainer.val_seconds = sum(float(r.get("val_seconds") or 0.0) for r in trainer.history)
    last = trainer.start - 1
    with trainer.scope:
        for cb in trainer.callbacks:
            cb.on_train_start(trainer)
        trainer.t0 = time.perf_counter() - offset
        for epoch in range(trainer.start, epochs + 1):
            trainer.epoch = epoch
            trainer.validated = trainer.improved = trainer.early = False
            losses = _epoch_losses(trainer, epoch, grad_fn, params, bs, n_batches, resume is not None)
            lr = float(opt.param_groups[0]["lr"])  # the rate this epoch's steps used
            if sched is not None:
                sched.step()
            trainer.losses = losses
            row = {"epoch": epoch, **losses, "lr": lr, "seconds": trainer.elapsed()}
            trainer.history.append(row)  # the callbacks complete the row (validation columns)
            last = epoch
            if _callbacks_stop(trainer, row):
                break
        for cb in trainer.callbacks:
            cb.on_train_end(trainer)
    wall = trainer.elapsed()
    if last >= trainer.start:  # the last step's weights (their loss was never computed)
        bad = trainer.weights_usable()
        if bad:
            raise TrainingDiverged(last, None, bad, first=False, saved=trainer.saved_epoch)
    return {
        "history": trainer.history,
        "train_seconds": wall,
        "seconds_per_epoch": wall / max(last, 1),
        "val_seconds": trainer.val_seconds,
        "epochs": last,
        "start": start_note,
        "start_seconds": start_seconds,
        "n_samples": n,
        "batches_per_epoch": n_batches,
        "state": trainer.state(last),
    }


def _callbacks_stop(trainer: Trainer, row: dict) -> bool:
    """The epoch's callbacks in order, up to the first that ends the training -> whether one did."""
    return any(cb.on_epoch_end(trainer, row) for cb in trainer.callbacks)
