"""Training: fit a model to the samples of the train split, with checkpoints that resume.

loss = the model's `loss(batch, opts)` (for the DEL models w_DEL * mean ||r_k||^2 + w_reg *
mean penalty(log|det H|) over `reg_points` random pairs). Samples are batched tensors.

Every `train.checkpoint_every` epochs (`auto`: whenever a minute has passed) the model, optimiser,
scheduler, RNG states, epoch and loss history go to `checkpoints/last.pt`, and each epoch's
metrics are appended to `train_metrics.csv` as training goes. SIGINT/SIGTERM finish the current
epoch, save a checkpoint and stop with one line saying how to resume (a second signal stops at
once). `liedfl train resume=<run dir>` (`run_resume`) continues from the last checkpoint and, for
the same seed, ends with the same losses and weights as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import csv
import math
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from .checkpoint import capture_rng_state, load_checkpoint, load_state, restore_rng_state, save_checkpoint
from .errors import CheckpointError, ConfigError, LiedflError
from .factory import loss_options
from .io_utils import write_json
from .lie import Pose
from .models.losses import training_stage
from .solvers import runtime
from .ui import console, err_console, progress_bar

AUTO_CHECKPOINT_SECONDS = 60.0  # `checkpoint_every: auto` loses at most about this much work


class TrainingInterrupted(LiedflError):
    """Training stopped by SIGINT/SIGTERM after saving a checkpoint."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


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
    that a job reaching its time limit saves a checkpoint it can be resumed from."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():  # handlers need the main thread
        yield stop
        return

    def handler(signum, frame):
        if stop.signum is not None:
            raise KeyboardInterrupt
        stop.signum = signum
        console.print("[bold yellow]stop requested:[/] finishing the epoch and saving a checkpoint (again: stop now)")

    signums: list[int] = [signal.SIGINT, signal.SIGTERM]
    warning = _cluster_warning_signal()
    if warning is not None:
        signums.append(warning)
    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


class MetricsLog:
    """train_metrics.csv, one row per epoch appended as training goes (the header comes with the
    first row). On resume the rows past the checkpoint's epoch are dropped first."""

    def __init__(self, path: Path, history: list[dict]):
        self.path = path
        self.keys: list[str] | None = None
        path.parent.mkdir(parents=True, exist_ok=True)
        if history:
            self._rewrite(history)
        elif path.exists():
            path.unlink()

    def _rewrite(self, rows: list[dict]) -> None:
        from .io_utils import write_csv

        write_csv(self.path, rows)
        self.keys = list(rows[0])

    def append(self, row: dict) -> None:
        if self.keys is None:
            self._rewrite([row])
            return
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.keys, extrasaction="ignore").writerow(row)


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


def make_optimizer(params, cfg_opt) -> torch.optim.Optimizer:
    name = cfg_opt.name
    if name == "soap":
        from pytorch_optimizer import SOAP

        every = int(cfg_opt.get("precondition_frequency", 10))
        largest = int(cfg_opt.get("max_precondition_dim", 10000))
        return SOAP(
            params,
            lr=cfg_opt.lr,
            weight_decay=cfg_opt.weight_decay,
            precondition_frequency=every,
            max_precondition_dim=largest,
        )
    if name == "adam":
        return torch.optim.Adam(params, lr=cfg_opt.lr, weight_decay=cfg_opt.weight_decay)
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
    cfg_train: DictConfig,
    steps: int,
    seed: int = 0,
    show_progress: bool = True,
    log_epochs: bool = True,
    *,
    resume: dict | None = None,
    save: Callable[[dict], None] | None = None,
    on_epoch: Callable[[dict], None] | None = None,
    stop: StopRequest | None = None,
) -> dict:
    """Train `model` on the first `steps` steps of `data` (T, N+1, ...).

    The model says what a sample is (`model.training_set`: pose triplets or whole windows);
    each epoch visits the samples in shuffled mini-batches (plus `reg_points` random pairs per
    batch for models with a regularity term). Returns history and timings.

    resume: the training state of a checkpoint (`epoch`, `optimizer`, `scheduler`, `rng`,
    `history`) to continue from. save(state): called with that state at checkpoint times
    (`cfg_train.checkpoint_every`) and when `stop` is set. on_epoch(row): each epoch's metrics.
    """
    # train.loss: newton changes the batches' loss; rollout trains with del here (fine-tuning: finetune.py)
    opts, samples = training_stage(model, data, int(steps), loss_options(cfg_train))
    n = samples.n
    bs = n if cfg_train.get("full_batch", False) else min(int(cfg_train.batch_size), n)
    n_batches = math.ceil(n / bs)
    runtime.plan("train", int(cfg_train.epochs) * n_batches)  # runtime.compile: auto weighs this
    gen = torch.Generator().manual_seed(seed)
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ConfigError("the model has no trainable parameters")
    opt = make_optimizer(params, cfg_train.optimizer)
    epochs = int(cfg_train.epochs)
    sched = make_schedule(opt, cfg_train.optimizer.get("schedule", "constant"), epochs)
    every = checkpoint_interval(cfg_train.get("checkpoint_every", "auto"))
    history: list[dict] = []
    start, offset = 1, 0.0
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
        }

    t0 = time.perf_counter() - offset
    last_save = time.perf_counter()
    with progress_bar(show_progress) as bar:
        task = bar.add_task("train", total=epochs, completed=start - 1, loss=float("nan"))
        for epoch in range(start, epochs + 1):
            perm = torch.randperm(n, generator=gen)
            sums: dict[str, float] = {}
            for b in range(n_batches):
                idx = perm[b * bs : (b + 1) * bs]
                opt.zero_grad(set_to_none=True)
                loss, parts = model.loss(samples.batch(idx, gen, opts.reg_points), opts)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"training loss became {loss.item()} at epoch {epoch}, batch {b}")
                loss.backward()
                opt.step()
                for k, v in {"loss": loss, **parts}.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach()) / n_batches
            if sched is not None:
                sched.step()
            row = {"epoch": epoch, **sums, "seconds": time.perf_counter() - t0}
            history.append(row)
            if on_epoch is not None:
                on_epoch(row)
            bar.update(task, advance=1, loss=sums["loss"])
            if log_epochs and not show_progress and (epoch % max(1, epochs // 10) == 0 or epoch == epochs):
                console.print(
                    f"epoch {epoch}/{epochs}  "
                    + "  ".join(f"{k} {v:.3e}" for k, v in sums.items())
                    + f"  ({time.perf_counter() - t0:.1f} s)",
                    highlight=False,
                )
            signum = stop.signum if stop is not None else None
            stopping = signum is not None
            due = (epoch % every == 0) if every else (time.perf_counter() - last_save >= AUTO_CHECKPOINT_SECONDS)
            if save is not None and epoch < epochs and (due or stopping):
                save(state(epoch))
                last_save = time.perf_counter()
            if signum is not None and epoch < epochs:
                raise TrainingInterrupted(
                    f"{stop_reason(signum)}: training stopped after epoch {epoch}/{epochs}; checkpoint saved",
                    128 + int(signum),
                )
    wall = time.perf_counter() - t0
    return {
        "history": history,
        "train_seconds": wall,
        "seconds_per_epoch": wall / max(epochs, 1),
        "n_samples": n,
        "batches_per_epoch": n_batches,
        "state": state(epochs),
    }


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def run_train(cfg: DictConfig, resume: dict | None = None) -> dict:
    """`liedfl train`: data -> model -> fit (with checkpoints) -> checkpoint -> recovery ->
    rollout -> eval. `resume`: a checkpoint payload to continue from. Returns a summary."""
    from .data.files import complete_steps
    from .data.scenes import dataset_steps, get_dataset
    from .evaluate import run_eval_from_objects
    from .factory import build_model, configure_runtime, data_pose
    from .rollout import rollout_and_save

    configure_runtime(cfg)  # threads, fused paths, compilation, device, dtype (cfg.runtime)
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoints" / "last.pt"
    torch.manual_seed(int(cfg.seed))
    dataset, data_path = get_dataset(cfg.dataset, cfg.paths.data_dir, console=err_console)
    complete_steps(cfg.dataset, dataset)  # a file's null train_steps / rollout_steps: all its steps
    if cfg.rollout.enabled and len(dataset.test_idx) == 0:  # fail now, not after training
        raise ConfigError(
            f"{data_path}: the dataset's test split is empty, so there is nothing to roll out after training; "
            "give it test trajectories (dataset=file: dataset.split=default) or set rollout.enabled=false"
        )
    model = build_model(cfg, dataset)  # on the runtime's device, in its dtype
    if resume is not None:
        load_state(ckpt, model, resume)
    n_params = count_parameters(model)
    comps = model.components()
    console.print(
        f"[bold]model[/] {type(model).__name__} on {dataset.group.name}, h={dataset.h}: "
        f"components {', '.join(comps)}; {n_params} trainable parameters"
    )
    for note in getattr(model, "notes", ()):  # e.g. what model.potential=auto chose and why
        console.print(f"[bold]model[/] {note}", highlight=False)
    write_json(
        out / "components.json",
        {
            "model": type(model).__name__,
            "components": comps,
            "parameters": n_params,
            "notes": list(getattr(model, "notes", ())),
        },
    )
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    dataset_path = str(Path(data_path).resolve())

    def save(train_state: dict, timings: dict | None = None) -> None:
        extra = {"dataset_path": dataset_path, "components": comps, **train_state}
        if timings is not None:
            extra["timings"] = timings
        save_checkpoint(ckpt, model, config, extra)

    history = list(resume.get("history", [])) if resume else []
    log = MetricsLog(out / "train_metrics.csv", history)
    train_data = data_pose(dataset, dataset.train_idx)
    epochs = int(cfg.train.epochs)
    if resume is not None and int(resume["epoch"]) >= epochs:  # training done: redo what follows it
        result = {"history": history, "train_seconds": resume.get("timings", {}).get("train_seconds", 0.0)}
        result["seconds_per_epoch"] = result["train_seconds"] / max(epochs, 1)
        result["n_samples"] = resume.get("timings", {}).get("n_samples")
        result["state"] = {k: resume[k] for k in ("epoch", "optimizer", "scheduler", "rng", "history")}
        console.print(f"{ckpt}: all {epochs} epochs are trained; redoing the evaluation")
    else:
        if resume is not None:
            console.print(f"resuming {out} at epoch {int(resume['epoch']) + 1}/{epochs}")
        with graceful_stop() as stop:
            try:
                result = fit(
                    model,
                    train_data,
                    cfg.train,
                    dataset_steps(cfg.dataset, dataset, "train_steps"),
                    seed=int(cfg.seed),
                    show_progress=cfg.ui.progress,
                    resume=resume,
                    save=save,
                    on_epoch=log.append,
                    stop=stop,
                )
            except TrainingInterrupted as e:
                raise TrainingInterrupted(f"{e}; resume with: liedfl train resume={out}", e.exit_code) from None
    done_before = resume is not None and int(resume["epoch"]) >= epochs  # a finished run: evaluation only
    if str(cfg.train.get("loss", "del")) == "rollout" and not done_before:  # train.loss=rollout: fine-tune
        result = _finetune_stage(cfg, model, train_data, result, out)
    timings = {
        "train_seconds": result["train_seconds"],
        "seconds_per_epoch": result["seconds_per_epoch"],
        "epochs": epochs,
        "n_samples": result["n_samples"],
        "parameters": n_params,
        **{str(k): result[k] for k in ("del_seconds", "finetune_seconds") if k in result},
    }
    # the trained model is saved before anything else can fail
    save(result["state"], timings)
    console.print(
        f"trained {epochs} epochs in {result['train_seconds']:.1f} s "
        f"(final loss {result['history'][-1]['loss']:.3e}); checkpoint {ckpt}"
    )
    from .data.checks import step_rotation_summary

    summary = {
        "run_dir": str(out),
        "dataset_path": dataset_path,
        "dataset": {
            "scene": dataset.scene,
            "group": dataset.group.name,
            "h": dataset.h,
            "trajectories": dataset.n_trajectories,
            "steps": dataset.n_steps,
            "train_steps": int(cfg.dataset.train_steps),
            "train": len(dataset.train_idx),
            "test": len(dataset.test_idx),
        },
        "timings": timings,
        "final_loss": result["history"][-1]["loss"],
        "data_step_rotation": step_rotation_summary(dataset),
    }
    from .recovery import parameter_recovery

    try:
        recovery = parameter_recovery(model, dataset)
    except (ValueError, RuntimeError, KeyError, IndexError) as e:  # the model cannot represent the truth
        console.print(f"[bold yellow]warning:[/] parameter recovery skipped ({type(e).__name__}: {e})")
        recovery = None
    if recovery is not None:
        write_json(out / "recovery.json", recovery)
    if cfg.rollout.enabled:
        ro = rollout_and_save(cfg, model, dataset, out / "rollout.h5", steps=cfg.rollout.steps)
        summary["rollout"] = ro
        summary["eval"] = run_eval_from_objects(cfg, dataset, out, timings)
        from .evaluation import run_extra_evals

        extra = run_extra_evals(cfg, model, dataset, out)
        if extra is not None:
            summary["extra_eval"] = extra
    write_json(out / "summary.json", summary)
    return summary


def _finetune_stage(cfg: DictConfig, model, train_data: Pose, result: dict, out: Path) -> dict:
    """`finetune.finetune` after the DEL stage; its seconds are added to the training time."""
    from .factory import solver_options
    from .finetune import finetune

    log = MetricsLog(out / "finetune_metrics.csv", [])
    tuned = finetune(
        model,
        train_data,
        cfg.train,
        int(cfg.dataset.train_steps),
        solver_options(cfg.solver),
        seed=int(cfg.seed),
        show_progress=cfg.ui.progress,
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
    saved = OmegaConf.create(payload["config"])
    saved.paths.output_dir = str(run_dir)
    if cfg.get("epochs") is not None:
        try:
            epochs = int(cfg.epochs)
        except (TypeError, ValueError):
            raise ConfigError(f"epochs={cfg.epochs!r}: must be an integer") from None
        if epochs < int(payload["epoch"]):
            raise ConfigError(f"epochs={epochs}: the checkpoint is already at epoch {int(payload['epoch'])}")
        saved.train.epochs = epochs
    saved.ui = cfg.ui
    return run_train(saved, resume=payload)
