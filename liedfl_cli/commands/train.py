"""`liedfl train`: data -> model -> fit -> checkpoint -> recovery -> rollout -> eval, and its resume.

The training itself is `trainer.fit` (the loop) with the callbacks of `default_callbacks`
(`callbacks.py`): validation and selection, `checkpoints/best.pt`, the metric loggers, the progress
display, early stopping, and every `train.checkpoint_every` epochs (`auto`: whenever a minute has
passed) the model, optimiser, scheduler, RNG states, epoch and loss history in `checkpoints/last.pt`.
Each epoch's metrics (loss parts, learning rate `lr`, seconds, validation) are appended to
`train_metrics.csv` as training goes, and with `logger=tensorboard` also written as TensorBoard scalars
(`loggers/`). The optimiser and its schedule come from `optimizers.py`'s registries.
SIGINT/SIGTERM finish the current epoch, save a checkpoint and stop with one line saying how to
resume (a second signal stops at once; `stopping.py`). `liedfl train resume=<run dir>` (`run_resume`)
continues from the last checkpoint and, for the same seed, ends with the same losses and weights as
an uninterrupted run.

Validation (`validation.py`, docs/validation.md): a split taken from the train split
(`dataset.val_fraction`), a pass every `train.val_every` epochs (its columns in train_metrics.csv,
its time left out of the training time), the best pass's weights in `checkpoints/best.pt`
(`train.select`), early stopping (`train.early_stopping`); after training the selected weights are
rolled out and evaluated.
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from ..config.typed import RunConfig, TrainConfig, typed
from ..display.ui import console, err_console, warning_line
from ..errors import CheckpointError, ConfigError, DatasetError, LiedflError
from ..files.checkpoint import (
    CHECKPOINT_FILE,
    check_training_state,
    checkpoint_record,
    describe_checkpoint,
    load_checkpoint,
    load_state,
    new_run_id,
    run_provenance,
    save_checkpoint,
)
from ..files.io_utils import write_json
from ..lie import Pose
from ..loggers import Logger, MetricsLog, make_loggers
from ..models.liedflnn.losses import check_loss, check_rollout_horizon
from .callbacks import (
    BestModelCallback,
    CheckpointCallback,
    EarlyStoppingCallback,
    LoggerCallback,
    ProgressCallback,
    ValidationCallback,
    checkpoint_interval,
)
from .optimizers import make_optimizer, make_schedule
from .stopping import StopRequest, TrainingDiverged, TrainingInterrupted, graceful_stop, stop_reason
from .trainer import Callback, fit
from .validation import (
    VAL_COLUMNS,
    Selection,
    Validator,
    ValSplit,
    make_selection,
    make_val_split,
    select_option,
    val_fraction,
    val_interval,
)

__all__ = [  # the training's names scripts and tests import from here
    "StopRequest",
    "TrainingDiverged",
    "TrainingInterrupted",
    "checkpoint_interval",
    "count_parameters",
    "fit",
    "graceful_stop",
    "make_optimizer",
    "make_schedule",
    "run_resume",
    "run_train",
    "stop_reason",
]


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
    """`run_train`'s steps, in order (each helper below does one)."""
    from ..config.factory import configure_runtime
    from ..files.signals import set_phase

    run = typed(cfg, "train")  # the one conversion: below here only typed objects travel
    assert run.train is not None and run.rollout is not None and run.dataset is not None, "a train config"
    configure_runtime(run.runtime)  # threads, fused paths, compilation, device, dtype
    out = Path(run.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoints" / "last.pt"
    torch.manual_seed(int(run.seed or 0))
    set_phase("data generation")
    dataset, data_path = _train_dataset(run, resume, accept_changed_dataset)
    split, validator, selection = _check_data(cfg, run, dataset, data_path, resume)
    resumable = ckpt.is_file() and resume is not None
    set_phase("training", f"resume with: liedfl train resume={out}" if resumable else None)
    model = _train_model(run, dataset, out, resume, ckpt)
    files = RunCheckpoints(model, _recorded_config(cfg, run, model, out), data_path, out, resume, selection)
    result = _train(run, model, dataset, split, validator, selection, files, resume)
    timings = _timings(result, count_parameters(model))
    files.save_last(result["state"], timings)  # the trained model is saved before anything else can fail
    redo = f"the trained model is saved in {ckpt}: `liedfl train resume={out}` redoes the evaluation"
    set_phase("evaluation", redo)
    _say_trained(result, validator is not None, ckpt)
    used = use_selected(model, out, selection, result["epochs"])
    summary = _summary(run, dataset, split, selection, files, timings, result, used)
    recovery = _recovery(model, dataset, out)
    if run.rollout.enabled:
        _roll_out_and_evaluate(run, model, dataset, files, used, timings, summary, redo)
    write_json(out / "summary.json", summary)
    _closing_summary(model, dataset, recovery, summary, result["history"], out)
    return summary


def _check_data(
    cfg: DictConfig, run: RunConfig, dataset, data_path, resume: dict | None
) -> tuple[ValSplit, Validator | None, Selection]:
    """Every check that needs the data, before the run folder holds anything: the steps a file leaves
    open, a test split to roll out, the validation split and selection, the rollout loss's horizon."""
    from ..data.files import complete_steps

    assert run.train is not None and run.rollout is not None and run.dataset is not None, "a train config"
    complete_steps(run.dataset, dataset)  # a file's null train_steps / rollout_steps: all its steps
    _record_steps(cfg, run)
    if run.rollout.enabled and len(dataset.test_idx) == 0:  # fail now, not after training
        source = ((dataset.params or {}).get("source") or {}).get("file") or data_path  # the user's file
        raise ConfigError(
            f"{source}: the dataset's test split is empty, so there is nothing to roll out after training; "
            "give it test trajectories (dataset=file: dataset.split=default) or set rollout.enabled=false"
        )
    split, validator, selection = validation_setup(run, dataset, resume)
    if run.train.loss == "rollout":
        check_rollout_horizon(run.train.rollout_loss.horizon, int(run.dataset.train_steps or 0))
    return split, validator, selection


def _train_model(run: RunConfig, dataset, out: Path, resume: dict | None, ckpt: Path):
    """The model to train (a resumed run's with the checkpoint's weights), printed and described in
    components.json."""
    from ..config.factory import build_model

    assert run.train is not None, "a train config"
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
    record = {"model": type(model).__name__, "components": comps, "parameters": n_params, "notes": list(model.notes)}
    write_json(out / "components.json", record)
    return model


def _recorded_config(cfg: DictConfig, run: RunConfig, model, out: Path) -> dict:
    """The config the run's checkpoints keep: resolved, user paths absolute, the joints as resolved."""
    _absolute_user_paths(cfg, run)
    config = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(config, dict)
    _store_joints(model, config, out)
    return config


class RunCheckpoints:
    """The run's checkpoint writers: `save_last` (`checkpoints/last.pt`: weights, config, training
    state, the dataset file's path and SHA-256, the run's id) and `save_best` (`checkpoints/best.pt`:
    the selected validation pass's weights)."""

    def __init__(self, model, config: dict, data_path, out: Path, resume: dict | None, selection: Selection):
        from ..files.dataset_identity import file_sha256

        self.model, self.config, self.selection = model, config, selection
        self.last, self.best = out / "checkpoints" / "last.pt", out / "checkpoints" / "best.pt"
        self.dataset_path = str(Path(data_path).resolve())
        self.dataset_sha256 = file_sha256(self.dataset_path)  # rollout, eval and resume check the file is unchanged
        self.run_id = str((resume or {}).get("run_id") or new_run_id())  # the run's stable id (rollout provenance)
        self.components = model.components()

    def _identity(self) -> dict:
        return {"dataset_path": self.dataset_path, "dataset_sha256": self.dataset_sha256,
                "components": self.components, "run_id": self.run_id}  # fmt: skip

    def save_last(self, train_state: dict, timings: dict | None = None) -> None:
        extra = {**self._identity(), **train_state}
        if timings is not None:
            extra["timings"] = timings
        save_checkpoint(self.last, self.model, self.config, extra)

    def save_best(self, epoch: int, row: dict) -> None:
        val = {k: v for k, v in row.items() if k in VAL_COLUMNS and v is not None}
        extra = {**self._identity(), "epoch": epoch, "val": val}
        save_checkpoint(self.best, self.model, self.config, {**extra, "selected_by": self.selection.metric})


def default_callbacks(
    run: RunConfig,
    validator: Validator | None,
    selection: Selection,
    files: RunCheckpoints,
    log: Logger,
    stop: StopRequest | None,
) -> list[Callback]:
    """The callbacks of `liedfl train`, in the order they run after each epoch (`callbacks.py`)."""
    assert run.train is not None, "a train config"
    return [
        ValidationCallback(validator, selection),
        BestModelCallback(files.save_best),
        LoggerCallback(log.log),
        ProgressCallback(bar=run.ui.progress),
        EarlyStoppingCallback(selection),
        CheckpointCallback(files.save_last, checkpoint_interval(run.train.checkpoint_every), stop),
    ]


def _train(
    run: RunConfig, model, dataset, split: ValSplit, validator: Validator | None, selection: Selection,
    files: RunCheckpoints, resume: dict | None,
) -> dict:  # fmt: skip
    """The training of the run (with `train.loss=rollout` its fine-tuning), or, for a resumed run
    whose training is done, the result its checkpoint recorded -> `fit`'s result."""
    from ..config.factory import data_pose

    assert run.train is not None, "a train config"
    out, epochs = files.last.parent.parent, int(run.train.epochs)
    history = list(resume.get("history", [])) if resume else []
    log = make_loggers(run.logger.name, out, history)
    if resume is None:
        files.best.unlink(missing_ok=True)  # a reused run directory: no stale best.pt
    train_data = data_pose(dataset, split.train_idx)
    if resume is not None and (int(resume["epoch"]) >= epochs or selection.stopped):  # done: redo what follows
        log.close()
        result = _finished(resume, history, selection, epochs, files.last)
    else:
        result = _fit_run(run, model, train_data, split, validator, selection, files, log, resume)
    done_before = resume is not None and int(resume["epoch"]) >= epochs  # a finished run: evaluation only
    if run.train.loss == "rollout" and not done_before:  # train.loss=rollout: fine-tune
        result = _finetune_stage(run, model, train_data, result, out)
    return result


def _fit_run(
    run: RunConfig, model, train_data: Pose, split: ValSplit, validator: Validator | None, selection: Selection,
    files: RunCheckpoints, log: Logger, resume: dict | None,
) -> dict:  # fmt: skip
    """`fit` with the run's callbacks, stopped by a signal through `graceful_stop`; its errors said
    as the run's (how to resume, which checkpoint, which learning rate)."""
    assert run.train is not None, "a train config"
    out = files.last.parent.parent
    if resume is not None:
        console.print(f"resuming {out} at epoch {int(resume['epoch']) + 1}/{int(run.train.epochs)}")
    with graceful_stop() as stop:
        try:
            callbacks = default_callbacks(run, validator, selection, files, log, stop)
            seed = int(run.seed or 0)
            result = fit(model, train_data, run.train, split.train_steps, seed, callbacks, resume=resume)
        except TrainingInterrupted as e:
            raise TrainingInterrupted(f"{e}; resume with: liedfl train resume={out}", e.exit_code) from None
        except CheckpointError as e:  # the resumed training state: name the file it came from
            ckpt = files.last
            raise CheckpointError(e if str(e).startswith(str(ckpt)) else f"{ckpt}: {e}") from None
        except TrainingDiverged as e:
            raise _diverged(e, run.train, files.last, resume is not None) from None
        finally:
            log.close()
    return result


def _finished(resume: dict, history: list[dict], selection: Selection, epochs: int, ckpt: Path) -> dict:
    """The result of a resumed run whose training is done (all epochs, or stopped early), from its
    checkpoint: the evaluation is redone, the training is not."""
    timings = resume.get("timings", {})
    result = {"history": history, "train_seconds": timings.get("train_seconds", 0.0)}
    result["epochs"] = int(resume["epoch"])
    result["seconds_per_epoch"] = result["train_seconds"] / max(result["epochs"], 1)
    result["val_seconds"] = timings.get("val_seconds", 0.0)
    result["n_samples"] = timings.get("n_samples")
    keys = ("epoch", "optimizer", "scheduler", "rng", "history", "selection", "val_every")
    result["state"] = {k: resume.get(k) for k in keys}
    why = "stopped early" if selection.stopped else f"all {epochs} epochs are trained"
    console.print(f"{ckpt}: {why} (epoch {result['epochs']}); redoing the evaluation")
    return result


def _timings(result: dict, n_params: int) -> dict:
    """The run's `timings` (checkpoint, summary.json)."""
    return {
        "train_seconds": result["train_seconds"],
        "seconds_per_epoch": result["seconds_per_epoch"],
        "epochs": result["epochs"],
        "n_samples": result["n_samples"],
        "parameters": n_params,
        "val_seconds": result["val_seconds"],
        **{str(k): result[k] for k in ("del_seconds", "finetune_seconds", "start_seconds") if k in result},
    }


def _say_trained(result: dict, validated: bool, ckpt: Path) -> None:
    """The line saying what was trained, in how long, and where it is saved."""
    console.print(
        f"trained {result['epochs']} epochs in {result['train_seconds']:.1f} s "
        + (f"(+ {result['val_seconds']:.1f} s validation) " if validated else "")
        + (f"(final loss {result['history'][-1]['loss']:.3e}); " if result["history"] else "(the start only); ")
        + f"checkpoint {ckpt}"
    )


def _summary(
    run: RunConfig, dataset, split: ValSplit, selection: Selection, files: RunCheckpoints, timings: dict,
    result: dict, used: dict,
) -> dict:  # fmt: skip
    """summary.json before the rollout and evaluation add theirs."""
    from ..data.checks import step_rotation_summary

    assert run.dataset is not None, "a train config"
    return {
        "run_dir": str(Path(run.paths.output_dir)),
        "run_id": files.run_id,
        "dataset_path": files.dataset_path,
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


def _recovery(model, dataset, out: Path) -> dict | None:
    """Learned vs true parameters (recovery.json), where the model can represent the truth."""
    from ..config.recovery import parameter_recovery

    try:
        recovery = parameter_recovery(model, dataset)
    except (ValueError, RuntimeError, KeyError, IndexError) as e:  # the model cannot represent the truth
        warning_line(f"parameter recovery skipped ({type(e).__name__}: {e})")
        recovery = None
    if recovery is not None:
        write_json(out / "recovery.json", recovery)
    return recovery


def _roll_out_and_evaluate(
    run: RunConfig, model, dataset, files: RunCheckpoints, used: dict, timings: dict, summary: dict, redo: str
) -> None:
    """The selected weights rolled out on the test split (rollout.h5), evaluated (eval.csv, eval.md) and,
    for scenes with their own evaluation, that too; the results go into `summary`."""
    from ..files.signals import set_phase
    from .evaluate import run_eval_from_objects
    from .outputs import run_scene_eval
    from .rollout import rollout_and_save

    assert run.rollout is not None, "a train config"
    out = Path(run.paths.output_dir)
    set_phase("rollout", redo)
    provenance = run_provenance(out, files.run_id, (run.model or {}).get("name"), used)
    ro = rollout_and_save(run, model, dataset, out / "rollout.h5", steps=run.rollout.steps, provenance=provenance)
    summary["rollout"] = ro
    set_phase("evaluation", redo)
    write_json(out / CHECKPOINT_FILE, used)  # which checkpoint rolled out (liedfl eval reads it)
    summary["eval"] = run_eval_from_objects(run, dataset, out, timings, checkpoint=used)
    extra = run_scene_eval(run.scene_eval_options(), model, dataset, out)
    if extra is not None:
        summary["extra_eval"] = extra


def _closing_summary(model, dataset, recovery: dict | None, summary: dict, history: list, out: Path) -> None:
    """What was learned, printed at the end (a model whose parameters cannot be read this way: the
    summary without them)."""
    from ..display.closing_summary import print_closing_summary
    from ..models.learned_physics import gather

    try:
        first = next(model.parameters(), None)
        on_cpu = first is None or (first.device.type == "cpu" and first.dtype == torch.float64)
        physics = gather(
            model if on_cpu else copy.deepcopy(model).to(device="cpu", dtype=torch.float64), dataset, recovery
        )
    except (ValueError, RuntimeError, KeyError, IndexError, AttributeError, TypeError) as e:
        warning_line(f"closing summary: learned physics left out ({type(e).__name__}: {e})")
        physics = None
    print_closing_summary(physics, summary, history, out)


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
