"""Training: fit a model to the samples of the train split, with checkpoints that resume.

loss = the model's `loss(batch, opts)` (for the DEL models w_DEL * mean ||r_k||^2 + w_reg *
mean penalty(log|det H|) over `reg_points` random pairs). Samples are batched tensors.

Every `train.checkpoint_every` epochs (`auto`: whenever a minute has passed) the model, optimiser,
scheduler, RNG states, epoch and loss history go to `checkpoints/last.pt`, and each epoch's
metrics (loss parts, learning rate `lr`, seconds, validation) are appended to `train_metrics.csv` as
training goes, and with `logger=tensorboard` also written as TensorBoard scalars (`loggers/`).
SIGINT/SIGTERM finish the current epoch, save a checkpoint and stop with one line saying how to
resume (a second signal stops at once). `liedfl train resume=<run dir>` (`run_resume`) continues
from the last checkpoint and, for the same seed, ends with the same losses and weights as an uninterrupted run.

Validation (`validation.py`, docs/validation.md): a split taken from the train split
(`dataset.val_fraction`), a pass every `train.val_every` epochs (its columns in train_metrics.csv,
its time left out of the training time), the best pass's weights in `checkpoints/best.pt`
(`train.select`), early stopping (`train.early_stopping`); after training the selected weights are
rolled out and evaluated.
"""

from __future__ import annotations

import contextlib
import copy
import math
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from ..config.typed import OptimizerConfig, RunConfig, TrainConfig, section, typed
from ..display.ui import PlainProgress, console, err_console, progress_bar, warning_line
from ..errors import CheckpointError, ConfigError, DatasetError, LiedflError
from ..files.checkpoint import (
    CHECKPOINT_FILE,
    capture_rng_state,
    check_training_state,
    checkpoint_record,
    describe_checkpoint,
    load_checkpoint,
    load_state,
    new_run_id,
    restore_rng_state,
    run_provenance,
    save_checkpoint,
)
from ..files.io_utils import write_json
from ..lie import Pose
from ..loggers import MetricsLog, make_loggers
from ..models.liedflnn.losses import check_loss, check_rollout_horizon, training_stage
from ..solvers import runtime
from .validation import (
    VAL_COLUMNS,
    Selection,
    Validator,
    ValSplit,
    format_pass,
    make_selection,
    make_val_split,
    select_option,
    val_fraction,
    val_interval,
)

AUTO_CHECKPOINT_SECONDS = 60.0  # `checkpoint_every: auto` loses at most about this much work


class TrainingInterrupted(LiedflError):
    """Training stopped by SIGINT/SIGTERM after saving a checkpoint."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


class TrainingDiverged(LiedflError):
    """The training loss became non-finite (or overflowed): the learning rate is too large, or the
    weights it started from are unusable. `first`: on the first step of this `fit` call."""

    def __init__(self, epoch: int, batch: int | None, value: str, first: bool, saved: int | None):
        where = f"epoch {epoch}, batch {batch}" if batch is not None else f"the end of epoch {epoch}"
        super().__init__(f"training diverged at {where}: the loss became {value}")
        self.epoch, self.batch, self.value, self.first, self.saved = epoch, batch, value, first, saved


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


def _weights_usable(model, samples, opts) -> str:
    """'' when the loss at the current weights is finite on a few samples (a private generator: the
    training's random streams are untouched), else what it became. Weights one step past a divergence
    are finite but huge; their loss is not."""
    gen = torch.Generator().manual_seed(0)
    idx = torch.arange(min(4, samples.n))
    with torch.no_grad():
        _, _, bad = _loss_value(model, samples.batch(idx, gen, opts.reg_points), opts)
    return bad


class StopRequest:
    """Set by the signal handlers of `graceful_stop`; read by `fit` after each epoch."""

    def __init__(self) -> None:
        self.signum: int | None = None


def _cluster_warning_signal() -> int | None:
    """The signal submitit sends a job shortly before its time limit or a preemption (SIGUSR2 unless
    SUBMITIT_PREEMPT_SIGNAL says otherwise; `hydra.launcher.signal_delay_s` before the limit on SLURM);
    None outside a submitit job."""
    import os

    if not os.environ.get("SUBMITIT_EXECUTOR"):
        return None
    return getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2"), None)


def stop_reason(signum: int) -> str:
    name = signal.Signals(signum).name
    if signum == _cluster_warning_signal():
        return f"{name} (submitit: the job's time limit is near, or it is preempted)"
    return name


@contextlib.contextmanager
def graceful_stop():
    """SIGINT/SIGTERM -> finish the epoch, checkpoint, stop; a second signal stops at once. In a
    submitit job (sweeps on SLURM, `hydra/launcher=liedfl_local`) also submitit's warning signal, so
    that a job reaching its time limit saves a checkpoint it can be resumed from. A SIGINT that the
    process inherited ignored (`nohup`, a background job of a script: asked not to be interrupted by
    Ctrl-C) stays ignored; SIGTERM is always handled (README, "Interruptions and resume")."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():  # handlers need the main thread
        yield stop
        return

    def handler(signum, frame):
        if stop.signum is not None:
            raise KeyboardInterrupt
        stop.signum = signum
        console.print("[bold yellow]stop requested:[/] finishing the epoch and saving a checkpoint (again: stop now)")

    signums: list[int] = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signums.append(signal.SIGINT)
    warning = _cluster_warning_signal()
    if warning is not None:
        signums.append(warning)
    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


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


def make_optimizer(params, cfg_opt: OptimizerConfig | DictConfig) -> torch.optim.Optimizer:
    """SOAP or Adam; on the fused paths (`runtime.fused`) without per-tensor Python:
    `fused_optim.FusedSOAP` (the library's kernels, bit for bit) and Adam's foreach update."""
    if not isinstance(cfg_opt, OptimizerConfig):  # scripts and tests may pass the section as is
        cfg_opt = section(OptimizerConfig, cfg_opt, "train.optimizer")
    name = cfg_opt.name
    fused = runtime.current().fused
    if name == "soap":
        from pytorch_optimizer import SOAP

        from .fused_optim import FusedSOAP

        every = int(cfg_opt.precondition_frequency)
        largest = int(cfg_opt.max_precondition_dim)
        return (FusedSOAP if fused else SOAP)(
            params,
            lr=cfg_opt.lr,
            weight_decay=cfg_opt.weight_decay,
            precondition_frequency=every,
            max_precondition_dim=largest,
        )
    if name == "adam":
        return torch.optim.Adam(params, lr=cfg_opt.lr, weight_decay=cfg_opt.weight_decay, foreach=fused)
    raise ConfigError(f"train.optimizer.name must be 'soap' or 'adam', got {name!r}")


def make_schedule(opt, name: str, epochs: int):
    """Per-epoch learning-rate schedule: constant (paper) or cosine decay to 1% of lr."""
    if name == "constant":
        return None
    if name == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(
            opt, T_max=max(epochs, 1), eta_min=0.01 * opt.param_groups[0]["lr"]
        )
    raise ConfigError(f"train.optimizer.schedule must be 'constant' or 'cosine', got {name!r}")


def fit(
    model,
    data: Pose,
    cfg_train: TrainConfig | DictConfig,
    steps: int,
    seed: int = 0,
    show_progress: bool = True,
    log_epochs: bool = True,
    *,
    resume: dict | None = None,
    save: Callable[[dict], None] | None = None,
    on_epoch: Callable[[dict], None] | None = None,
    stop: StopRequest | None = None,
    validator: Validator | None = None,
    selection: Selection | None = None,
    save_best: Callable[[int, dict], None] | None = None,
) -> dict:
    """Train `model` on the first `steps` steps of `data` (T, N+1, ...).

    The model says what a sample is (`model.training_set`: pose triplets or whole windows);
    each epoch visits the samples in shuffled mini-batches (plus `reg_points` random pairs per
    batch for models with a regularity term). Returns history and timings.

    resume: the training state of a checkpoint (`epoch`, `optimizer`, `scheduler`, `rng`,
    `history`) to continue from. save(state): called with that state at checkpoint times
    (`cfg_train.checkpoint_every`) and when `stop` is set. on_epoch(row): each epoch's metrics.
    """
    if not isinstance(cfg_train, TrainConfig):  # scripts and tests may pass a `train` section as is
        cfg_train = section(TrainConfig, cfg_train, "train")
    # train.loss: newton changes the batches' loss; rollout trains with del here (fine-tuning: finetune.py)
    opts, samples = training_stage(model, data, int(steps), cfg_train.loss_options())
    start_note, start_seconds = None, 0.0
    if resume is None and cfg_train.start != "none":
        ts = time.perf_counter()
        start_note = model.initial_fit(samples, cfg_train.start)
        start_seconds = time.perf_counter() - ts
        if start_note and log_epochs:
            console.print(f"[bold]start[/] {start_note}", highlight=False)
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
    every = checkpoint_interval(cfg_train.checkpoint_every)
    history: list[dict] = []
    start, offset = 1, start_seconds  # the model's start counts as training time
    if resume is not None:
        try:
            opt.load_state_dict(resume["optimizer"])
            if sched is not None and resume.get("scheduler") is not None:
                sched.load_state_dict(resume["scheduler"])
            restore_rng_state(resume["rng"], {"batches": gen})
            history = [dict(r) for r in resume["history"]]
            start = int(resume["epoch"]) + 1
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointError(f"checkpoint training state is not usable ({type(e).__name__}: {e})") from None
        offset = float(history[-1]["seconds"]) if history else 0.0

    def state(epoch: int) -> dict:
        return {
            "epoch": epoch,
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict() if sched is not None else None,
            "rng": capture_rng_state({"batches": gen}),
            "history": history,
            "selection": selection.state() if selection is not None else None,
            "val_every": validator.every if validator is not None else None,
        }

    val_seconds = sum(float(r.get("val_seconds") or 0.0) for r in history)
    if start_note and validator is not None and selection is not None:
        # the start is a candidate too: epochs that move away from it cannot lose it (best.pt)
        tv = time.perf_counter()
        row0 = validator.measure(model)
        improved, _ = selection.update(0, row0)
        if improved and save_best is not None:
            save_best(0, row0)
        val_seconds += time.perf_counter() - tv
        if log_epochs:
            console.print(f"start: {format_pass(row0)}", highlight=False)
    no_pass = dict.fromkeys(VAL_COLUMNS) if validator is not None else {}
    val_text = next((format_pass(r) for r in reversed(history) if r.get("val_one_step_error") is not None), "")
    last = start - 1
    saved_epoch = start - 1 if resume is not None else None  # the epoch of the last checkpoint written
    t0 = time.perf_counter() - offset
    last_save = time.perf_counter()
    plain = PlainProgress(epochs, start - 1, enabled=show_progress and log_epochs)  # lines a log file keeps
    last_line = time.perf_counter()  # the last epoch line with ui.progress=false
    with progress_bar(show_progress) as bar:
        task = bar.add_task("train", total=epochs, completed=start - 1, loss=float("nan"), val=val_text)
        for epoch in range(start, epochs + 1):
            perm = torch.randperm(n, generator=gen)
            sums: dict[str, float] = {}
            for b in range(n_batches):
                idx = perm[b * bs : (b + 1) * bs]
                batch = samples.batch(idx, gen, opts.reg_points)
                value: float | torch.Tensor | None
                if grad_fn is not None:  # forward and backward fused, no autograd graph
                    value, parts, bad = _fused_value(grad_fn, params, batch, opts)
                else:
                    opt.zero_grad(set_to_none=True)
                    value, parts, bad = _loss_value(model, batch, opts)
                    if value is not None:
                        value.backward()
                if value is None:
                    raise TrainingDiverged(epoch, b, bad, first=epoch == start and b == 0, saved=saved_epoch)
                if resume is not None and epoch == start and b == 0:  # the restored state's first use
                    _first_resumed_step(opt)
                else:
                    opt.step()
                for k, v in {"loss": value, **parts}.items():
                    sums[k] = sums.get(k, 0.0) + (v if isinstance(v, float) else float(v.detach())) / n_batches
            lr = float(opt.param_groups[0]["lr"])  # the rate this epoch's steps used
            if sched is not None:
                sched.step()
            row = {"epoch": epoch, **sums, "lr": lr, "seconds": time.perf_counter() - t0, **no_pass}
            early = validated = False
            if validator is not None and validator.due(epoch, epochs):
                validated = True
                tv = time.perf_counter()
                row.update(validator.measure(model))
                improved, early = selection.update(epoch, row) if selection is not None else (False, False)
                if improved and save_best is not None:
                    save_best(epoch, row)
                spent = time.perf_counter() - tv
                row["val_seconds"] = spent  # the pass and best.pt
                val_seconds += spent
                t0 += spent  # validation is not training time
                val_text = format_pass(row)
            history.append(row)
            last = epoch
            if on_epoch is not None:
                on_epoch(row)
            bar.update(task, advance=1, loss=sums["loss"], val=val_text)
            plain.update(epoch, sums["loss"], val_text, validated=validated or early)
            tenth = epoch % max(1, epochs // 10) == 0 or epoch == epochs or early
            if log_epochs and not show_progress and (tenth or time.perf_counter() - last_line >= 60.0):
                last_line = time.perf_counter()  # (also at least once a minute: a log file sees progress)
                console.print(
                    f"epoch {epoch}/{epochs}  "
                    + "  ".join(f"{k} {v:.3e}" for k, v in sums.items())
                    + (f"  {val_text}" if val_text else "")
                    + f"  ({time.perf_counter() - t0:.1f} s)",
                    highlight=False,
                )
            if early:
                assert selection is not None
                console.print(
                    f"early stopping after epoch {epoch}/{epochs}: {selection.metric} has not improved by more than "
                    f"{selection.min_delta:g} for {selection.bad_passes} validation passes "
                    f"(best {selection.best if selection.best is not None else float('nan'):.3e} "
                    f"at epoch {selection.best_epoch})",
                    highlight=False,
                )
                break
            signum = stop.signum if stop is not None else None
            stopping = signum is not None
            due = (epoch % every == 0) if every else (time.perf_counter() - last_save >= AUTO_CHECKPOINT_SECONDS)
            if save is not None and epoch < epochs and (due or stopping):
                bad = _weights_usable(model, samples, opts)  # never save diverged weights over good ones
                if bad:
                    raise TrainingDiverged(epoch, None, bad, first=False, saved=saved_epoch)
                save(state(epoch))
                saved_epoch = epoch
                last_save = time.perf_counter()
            if signum is not None and epoch < epochs:
                raise TrainingInterrupted(
                    f"{stop_reason(signum)}: training stopped after epoch {epoch}/{epochs}; checkpoint saved",
                    128 + int(signum),
                )
    wall = time.perf_counter() - t0
    if last >= start:  # the last step's weights (their loss was never computed)
        bad = _weights_usable(model, samples, opts)
        if bad:
            raise TrainingDiverged(last, None, bad, first=False, saved=saved_epoch)
    return {
        "history": history,
        "train_seconds": wall,
        "seconds_per_epoch": wall / max(last, 1),
        "val_seconds": val_seconds,
        "epochs": last,
        "start": start_note,
        "start_seconds": start_seconds,
        "n_samples": n,
        "batches_per_epoch": n_batches,
        "state": state(last),
    }


def _first_resumed_step(opt) -> None:
    """The first optimizer step after a resume: a restored state that `load_state_dict` accepted but
    the step cannot use (a missing or reshaped buffer of the checkpoint) is a CheckpointError line."""
    try:
        opt.step()
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(
            f"checkpoint training state is not usable: the optimizer's step fails ({type(e).__name__}: {e})"
        ) from None


def validation_setup(run: RunConfig, dataset, resume: dict | None) -> tuple[ValSplit, Validator | None, Selection]:
    """The validation split (`dataset.val_fraction`, taken from the train split), the validation
    passes (`train.val_every`, `train.val_horizon`) and the selection (`train.select`,
    `train.early_stopping`), restored from `resume`; prints what was chosen."""
    from ..config.factory import data_pose
    from ..data.scenes import dataset_steps

    assert run.train is not None and run.dataset is not None, "a train config"
    steps = dataset_steps(run.dataset, dataset, "train_steps")
    seed = int(dataset.seed) if int(dataset.seed) >= 0 else 0
    split = make_val_split(dataset.train_idx, steps, val_fraction(run.dataset.val_fraction), seed)
    select, notes = select_option(run.train, split)
    selection = make_selection(run.train, select)
    if resume is not None:
        selection.restore(resume.get("selection"))
    validator = None
    if split.kind != "none":
        horizon = run.train.val_horizon
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 2:
            raise ConfigError(f"train.val_horizon={horizon!r}: must be an integer >= 2")
        every = val_interval(run.train.val_every, int(run.train.epochs))
        if resume is not None and resume.get("val_every"):  # the schedule of the run, also when extended
            every = int(resume["val_every"])
        truth = data_pose(dataset, split.val_idx).index((slice(None), slice(split.val_start, split.val_stop + 1)))
        validator = Validator(dataset.group, truth, run.solver, horizon, every)
        console.print(
            f"[bold]validation[/] {split.describe()}; a pass every {every} epochs (and the last): one-step error on "
            f"{validator.n_pairs} pairs (constant velocity: {validator.cv_error:.3e} rad), rollout error over "
            f"{validator.horizon} steps; selecting by {selection.metric or 'last'}",
            highlight=False,
        )
    else:
        console.print(f"[bold]validation[/] {split.describe()}: checkpoint = the last epoch", highlight=False)
    for note in notes:
        console.print(f"[bold yellow]note:[/] {note}", highlight=False)
    return split, validator, selection


def use_selected(model, out: Path, selection: Selection, last_epoch: int) -> dict:
    """Load the selected weights (`checkpoints/best.pt`) into `model` unless the selection is `last`
    or found nothing finite; print and return which checkpoint the model now holds."""
    best = out / "checkpoints" / "best.pt"
    if selection.metric is not None and selection.best_epoch is not None and best.is_file():
        payload = load_checkpoint(best)
        load_state(best, model, payload)
        used = checkpoint_record(best, payload)
    else:
        used = {"checkpoint": "last.pt", "checkpoint_epoch": int(last_epoch)}
        if selection.metric is not None:
            used["note"] = f"no finite {selection.metric} in any validation pass: nothing selected"
    console.print(describe_checkpoint(used), highlight=False)
    return used


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def _train_dataset(run: RunConfig, resume: dict | None, accept_changed: bool):
    """(dataset, its file) for training. A resumed run reads the file its checkpoint recorded (an
    absolute path: resuming works from any directory), which must still be the file trained on
    (`dataset_identity`); a run whose recorded file is gone gets it again from its config."""
    from ..data.hdf5 import load_dataset
    from ..data.scenes import get_dataset
    from ..files.dataset_identity import check_unchanged

    state = resume or {}
    recorded = state.get("dataset_path")
    if recorded and Path(str(recorded)).is_absolute() and Path(str(recorded)).is_file():
        path = Path(str(recorded))
        ckpt = Path(run.paths.output_dir) / "checkpoints" / "last.pt"
        check_unchanged(ckpt, state.get("dataset_sha256"), path, accept_changed)
        return load_dataset(path), path
    assert run.dataset is not None, "a train config"
    return get_dataset(run.dataset, run.paths.data_dir, console=err_console)


def _absolute_user_paths(cfg: DictConfig, run: RunConfig) -> None:
    """`dataset.path` (dataset=file / import) made absolute in the config the run records: a resume
    or rollout from another directory finds the same file (the cache name does not hash the path)."""
    from ..files.dataset_identity import absolute

    path = OmegaConf.select(cfg, "dataset.path", default=None)
    if isinstance(path, str) and path and not Path(path).is_absolute():
        with open_dict(cfg.dataset):
            cfg.dataset.path = absolute(path)
        if run.dataset is not None:
            run.dataset.scene["path"] = cfg.dataset.path


def _record_steps(cfg: DictConfig, run: RunConfig) -> None:
    """The steps `complete_steps` filled in (a file's null train_steps / rollout_steps) written to the
    config the run records too; `rollout.steps` follows `dataset.rollout_steps` there."""
    assert run.dataset is not None and run.rollout is not None
    for key in ("train_steps", "rollout_steps"):
        if key in cfg.dataset and cfg.dataset[key] is None:
            with open_dict(cfg.dataset):
                cfg.dataset[key] = getattr(run.dataset, key)
    if run.rollout.steps is None:
        run.rollout.steps = OmegaConf.select(cfg, "rollout.steps", default=None)


def _store_joints(model, config: dict, out: Path) -> None:
    """An articulated model's joints, as resolved (declared or inferred), go into the run's saved config
    (`model.joints` as {kinds, axes}: rollout, eval, resume and export rebuild exactly these) and into
    joints.json; the inference's table is printed."""
    record = model.joint_record()
    if record is None:
        return
    if record.get("inference"):
        console.print(record["inference"], highlight=False, markup=False)
    if isinstance(config.get("model"), dict):
        config["model"]["joints"] = {"kinds": record["kinds"], "axes": record["axes"]}
    write_json(out / "joints.json", record)


def run_train(cfg: DictConfig, resume: dict | None = None, accept_changed_dataset: bool = False) -> dict:
    """`liedfl train`: data -> model -> fit (with checkpoints) -> checkpoint -> recovery ->
    rollout -> eval. `resume`: a checkpoint payload to continue from. Returns a summary.
    accept_changed_dataset: resume although the dataset file changed since training (a warning).

    A config or data error before the first checkpoint leaves no run folder behind: the files this
    job wrote into the folder it created are removed (`status.discard_new_run_outputs`; the CLI then
    removes the folder with Hydra's files), so a failed start never looks like a run."""
    from .status import discard_new_run_outputs

    out = Path(str(cfg.paths.output_dir))
    try:
        return _run_train(cfg, resume, accept_changed_dataset)
    except (ConfigError, DatasetError):
        if resume is None and not (out / "checkpoints" / "last.pt").exists():
            discard_new_run_outputs(out)
        raise


def _run_train(cfg: DictConfig, resume: dict | None, accept_changed_dataset: bool) -> dict:
    from ..config.factory import build_model, configure_runtime, data_pose
    from ..data.files import complete_steps
    from ..files.signals import set_phase
    from .evaluate import run_eval_from_objects
    from .rollout import rollout_and_save

    run = typed(cfg, "train")  # the one conversion: below here only typed objects travel
    assert run.train is not None and run.rollout is not None and run.dataset is not None, "a train config"
    configure_runtime(run.runtime)  # threads, fused paths, compilation, device, dtype
    out = Path(run.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoints" / "last.pt"
    best = out / "checkpoints" / "best.pt"
    torch.manual_seed(int(run.seed or 0))
    set_phase("data generation")
    dataset, data_path = _train_dataset(run, resume, accept_changed_dataset)
    complete_steps(run.dataset, dataset)  # a file's null train_steps / rollout_steps: all its steps
    _record_steps(cfg, run)
    if run.rollout.enabled and len(dataset.test_idx) == 0:  # fail now, not after training
        source = ((dataset.params or {}).get("source") or {}).get("file") or data_path  # the user's file
        raise ConfigError(
            f"{source}: the dataset's test split is empty, so there is nothing to roll out after training; "
            "give it test trajectories (dataset=file: dataset.split=default) or set rollout.enabled=false"
        )
    # every check that needs the data runs here, before the run folder holds anything
    split, validator, selection = validation_setup(run, dataset, resume)
    if run.train.loss == "rollout":
        check_rollout_horizon(run.train.rollout_loss.horizon, int(run.dataset.train_steps or 0))
    resumable = ckpt.is_file() and resume is not None
    set_phase("training", f"resume with: liedfl train resume={out}" if resumable else None)
    model = build_model(run, dataset)  # on the runtime's device, in its dtype
    check_loss(model, run.train.loss)
    if resume is not None:
        load_state(ckpt, model, resume)
    n_params = count_parameters(model)
    comps = model.components()
    console.print(
        f"[bold]model[/] {type(model).__name__} on {dataset.group.name}, h={dataset.h}: "
        f"components {', '.join(comps)}; {n_params} trainable parameters"
    )
    for note in model.notes:  # e.g. what model.potential=auto chose and why
        console.print(f"[bold]model[/] {note}", highlight=False)
    write_json(
        out / "components.json",
        {
            "model": type(model).__name__,
            "components": comps,
            "parameters": n_params,
            "notes": list(model.notes),
        },
    )
    _absolute_user_paths(cfg, run)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    _store_joints(model, config, out)
    dataset_path = str(Path(data_path).resolve())
    from ..files.dataset_identity import file_sha256

    dataset_sha256 = file_sha256(dataset_path)  # rollout, eval and resume check the file is unchanged
    run_id = str((resume or {}).get("run_id") or new_run_id())  # the run's stable id (rollout provenance)

    def save(train_state: dict, timings: dict | None = None) -> None:
        extra = {"dataset_path": dataset_path, "dataset_sha256": dataset_sha256, "components": comps,
                 "run_id": run_id, **train_state}  # fmt: skip
        if timings is not None:
            extra["timings"] = timings
        save_checkpoint(ckpt, model, config, extra)

    history = list(resume.get("history", [])) if resume else []
    log = make_loggers(run.logger.name, out, history)
    epochs = int(run.train.epochs)
    if resume is None:
        best.unlink(missing_ok=True)  # a reused run directory: no stale best.pt

    def save_best(epoch: int, row: dict) -> None:
        val = {k: v for k, v in row.items() if k in VAL_COLUMNS and v is not None}
        extra = {"dataset_path": dataset_path, "dataset_sha256": dataset_sha256, "components": comps,
                 "run_id": run_id, "epoch": epoch, "val": val}  # fmt: skip
        save_checkpoint(best, model, config, {**extra, "selected_by": selection.metric})

    train_data = data_pose(dataset, split.train_idx)
    done = resume is not None and (int(resume["epoch"]) >= epochs or selection.stopped)
    if done:  # training done: redo what follows it
        assert resume is not None
        log.close()
        result = {"history": history, "train_seconds": resume.get("timings", {}).get("train_seconds", 0.0)}
        result["epochs"] = int(resume["epoch"])
        result["seconds_per_epoch"] = result["train_seconds"] / max(result["epochs"], 1)
        result["val_seconds"] = resume.get("timings", {}).get("val_seconds", 0.0)
        result["n_samples"] = resume.get("timings", {}).get("n_samples")
        keys = ("epoch", "optimizer", "scheduler", "rng", "history", "selection", "val_every")
        result["state"] = {k: resume.get(k) for k in keys}
        why = "stopped early" if selection.stopped else f"all {epochs} epochs are trained"
        console.print(f"{ckpt}: {why} (epoch {result['epochs']}); redoing the evaluation")
    else:
        if resume is not None:
            console.print(f"resuming {out} at epoch {int(resume['epoch']) + 1}/{epochs}")
        with graceful_stop() as stop:
            try:
                result = fit(
                    model,
                    train_data,
                    run.train,
                    split.train_steps,
                    seed=int(run.seed or 0),
                    show_progress=run.ui.progress,
                    resume=resume,
                    save=save,
                    on_epoch=log.log,
                    stop=stop,
                    validator=validator,
                    selection=selection,
                    save_best=save_best,
                )
            except TrainingInterrupted as e:
                raise TrainingInterrupted(f"{e}; resume with: liedfl train resume={out}", e.exit_code) from None
            except CheckpointError as e:  # the resumed training state: name the file it came from
                raise CheckpointError(e if str(e).startswith(str(ckpt)) else f"{ckpt}: {e}") from None
            except TrainingDiverged as e:
                raise _diverged(e, run.train, ckpt, resume is not None) from None
            finally:
                log.close()
    done_before = resume is not None and int(resume["epoch"]) >= epochs  # a finished run: evaluation only
    if run.train.loss == "rollout" and not done_before:  # train.loss=rollout: fine-tune
        result = _finetune_stage(run, model, train_data, result, out)
    timings = {
        "train_seconds": result["train_seconds"],
        "seconds_per_epoch": result["seconds_per_epoch"],
        "epochs": result["epochs"],
        "n_samples": result["n_samples"],
        "parameters": n_params,
        "val_seconds": result["val_seconds"],
        **{str(k): result[k] for k in ("del_seconds", "finetune_seconds", "start_seconds") if k in result},
    }
    # the trained model is saved before anything else can fail
    save(result["state"], timings)
    redo = f"the trained model is saved in {ckpt}: `liedfl train resume={out}` redoes the evaluation"
    set_phase("evaluation", redo)
    console.print(
        f"trained {result['epochs']} epochs in {result['train_seconds']:.1f} s "
        + (f"(+ {result['val_seconds']:.1f} s validation) " if validator is not None else "")
        + (f"(final loss {result['history'][-1]['loss']:.3e}); " if result["history"] else "(the start only); ")
        + f"checkpoint {ckpt}"
    )
    used = use_selected(model, out, selection, result["epochs"])
    from ..data.checks import step_rotation_summary

    summary = {
        "run_dir": str(out),
        "run_id": run_id,
        "dataset_path": dataset_path,
        "dataset": {
            "scene": dataset.scene,
            "group": dataset.group.name,
            "h": dataset.h,
            "trajectories": dataset.n_trajectories,
            "steps": dataset.n_steps,
            "train_steps": int(run.dataset.train_steps or 0),
            "train": len(dataset.train_idx),
            "test": len(dataset.test_idx),
            "val": len(split.val_idx),
        },
        "timings": timings,
        "final_loss": result["history"][-1]["loss"] if result["history"] else None,  # None: train.epochs=0
        "validation": {"split": split.kind, "description": split.describe(), **selection.state()},
        "checkpoint": used,
        "data_step_rotation": step_rotation_summary(dataset),
    }
    from ..config.recovery import parameter_recovery

    try:
        recovery = parameter_recovery(model, dataset)
    except (ValueError, RuntimeError, KeyError, IndexError) as e:  # the model cannot represent the truth
        warning_line(f"parameter recovery skipped ({type(e).__name__}: {e})")
        recovery = None
    if recovery is not None:
        write_json(out / "recovery.json", recovery)
    if run.rollout.enabled:
        set_phase("rollout", redo)
        provenance = run_provenance(out, run_id, (run.model or {}).get("name"), used)
        ro = rollout_and_save(run, model, dataset, out / "rollout.h5", steps=run.rollout.steps, provenance=provenance)
        summary["rollout"] = ro
        set_phase("evaluation", redo)
        write_json(out / CHECKPOINT_FILE, used)  # which checkpoint rolled out (liedfl eval reads it)
        summary["eval"] = run_eval_from_objects(run, dataset, out, timings, checkpoint=used)
        from .outputs import run_scene_eval

        extra = run_scene_eval(run.scene_eval_options(), model, dataset, out)
        if extra is not None:
            summary["extra_eval"] = extra
    write_json(out / "summary.json", summary)
    from ..display.closing_summary import print_closing_summary
    from ..models.learned_physics import gather

    try:  # what was learned (a model whose parameters cannot be read this way: the summary without them)
        first = next(model.parameters(), None)
        on_cpu = first is None or (first.device.type == "cpu" and first.dtype == torch.float64)
        physics = gather(
            model if on_cpu else copy.deepcopy(model).to(device="cpu", dtype=torch.float64), dataset, recovery
        )
    except (ValueError, RuntimeError, KeyError, IndexError, AttributeError, TypeError) as e:
        warning_line(f"closing summary: learned physics left out ({type(e).__name__}: {e})")
        physics = None
    print_closing_summary(physics, summary, result["history"], out)
    return summary


def _diverged(e: TrainingDiverged, train: TrainConfig, ckpt: Path, resumed: bool) -> LiedflError:
    """The one-line error of a diverged training: from a resumed checkpoint's own weights, the
    checkpoint is unusable; otherwise the learning rate diverged. last.pt is never overwritten by
    diverged weights: the line names the last good checkpoint (or says there is none)."""
    if resumed and e.first:
        return CheckpointError(
            f"{ckpt}: the training loss at the checkpoint's weights is {e.value}: the weights are unusable "
            "(retrain, or resume an earlier copy of the run)"
        )
    lr = train.optimizer.lr
    kept = (
        f"the last good checkpoint {ckpt} (epoch {e.saved}) is kept"
        if e.saved is not None
        else "no checkpoint had been saved"
    )
    if (ckpt.parent / "best.pt").is_file():
        kept += " (best.pt: the best validated epoch)"
    e.args = (
        f"{e}: the learning rate diverged (train.optimizer.lr={lr:g} with {train.optimizer.name}); "
        f"lower train.optimizer.lr; {kept}",
    )
    return e


def _finetune_stage(run: RunConfig, model, train_data: Pose, result: dict, out: Path) -> dict:
    """`finetune.finetune` after the DEL stage; its seconds are added to the training time."""
    from .finetune import finetune

    assert run.train is not None and run.dataset is not None, "a train config"
    log = MetricsLog(out / "finetune_metrics.csv", [])
    tuned = finetune(
        model,
        train_data,
        run.train,
        int(run.dataset.train_steps or 0),
        run.solver,
        seed=int(run.seed or 0),
        show_progress=run.ui.progress,
        on_epoch=log.append,
        make_optimizer=make_optimizer,
    )
    console.print(
        f"fine-tuned on {tuned['windows']} rollout windows for {tuned['epochs']} epochs in {tuned['seconds']:.1f} s"
    )
    result = dict(result)
    result["del_seconds"] = result["train_seconds"]
    result["train_seconds"] = result["train_seconds"] + tuned["seconds"]
    result["finetune_seconds"] = tuned["seconds"]
    return result


def run_resume(cfg: DictConfig) -> dict:
    """`liedfl train resume=<run dir> [epochs=N] [ui.progress=false]`: continue a run from
    `checkpoints/last.pt` with the run's own config (only the epoch count and the progress
    display may change), in the same run directory."""
    run_dir = Path(str(cfg.resume))
    if not run_dir.is_dir():
        raise ConfigError(f"resume={run_dir}: no such run directory")
    ckpt = run_dir / "checkpoints" / "last.pt"
    payload = load_checkpoint(ckpt)
    missing = [k for k in ("epoch", "optimizer", "rng", "history") if k not in payload]
    if missing:
        raise CheckpointError(
            f"{ckpt}: no training state (field '{missing[0]}' missing): written by a liedfl without resume"
        )
    if not isinstance(payload["config"], dict):
        raise CheckpointError(f"{ckpt}: field 'config' is not a mapping")
    check_training_state(ckpt, payload)
    saved = OmegaConf.create(payload["config"])
    saved.paths.output_dir = str(run_dir)
    if "val_fraction" not in saved.dataset:  # a run from before validation: keep its training data
        saved.dataset.val_fraction = 0.0
        console.print("[bold yellow]note:[/] a run written before validation existed: resumed without validation")
    if cfg.get("epochs") is not None:
        try:
            epochs = int(cfg.epochs)
        except (TypeError, ValueError):
            raise ConfigError(f"epochs={cfg.epochs!r}: must be an integer") from None
        if epochs < int(payload["epoch"]):
            raise ConfigError(f"epochs={epochs}: the checkpoint is already at epoch {int(payload['epoch'])}")
        saved.train.epochs = epochs
    saved.ui = cfg.ui
    from ..config.schema import validate
    from ..files.dataset_identity import accept_option

    try:  # the checkpoint's own config, with the two values a resume may change
        validate(saved, "train")
    except ConfigError as e:
        raise CheckpointError(f"{ckpt}: field 'config': {e}") from None

    return run_train(saved, resume=payload, accept_changed_dataset=accept_option(cfg.get("accept_changed_dataset")))
