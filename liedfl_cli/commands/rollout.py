"""`liedfl rollout`: roll a trained model (and the true-parameter scheme) over the test split
and write `rollout.h5` (format in docs/data_format.md, section "rollout.h5"; written by
`rollout_file.write_rollout`). `liedfl train` writes `<run>/rollout.h5`; `liedfl rollout run=<run>`
writes a new folder `<run>/rollouts/<name>/` each time.

`liedfl rollout run=<run> dataset=<scene> [dataset.<key>=...]` (or `dataset=file dataset.path=<h5>`)
rolls the run out on other data: that dataset's test split, from each trajectory's true first pair,
evaluated against that dataset. The model's group and time step must be the data's (one-line
ConfigError otherwise). The folder is `<run>/rollouts/<date>_<time>_<scene>_steps<N>/` and its
`source.json` names the dataset (file, scene, config, split, trajectories), which `liedfl eval run=<run>
rollout=<folder>` then evaluates against.

`split=auto|all|train|test` picks the trajectories (`other_data.choose_split`; auto: every trajectory
of a `dataset=file|import` file, else the test split); `export=csv|npz` also writes the predictions
in the import's layout (`export.py`)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import shutil
import time
from datetime import datetime
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from ..config.typed import RunConfig, typed
from ..display.ui import console, progress_bar, warning_line
from ..errors import ConfigError, DatasetError
from ..files.rollout_file import OneStep, RolloutEntry, write_rollout
from ..lie import Pose
from ..solvers.options import SolverOptions
from ..solvers.rollout import Rollout


def warn_stiff_damping(model, label: str) -> float | None:
    """One warning line when `model`'s constant damping is so stiff that the scheme reverses the
    velocity every step (h lambda_max(M^-1 D) > 2, `models.stiffness`); returns that figure."""
    from ..models.stiffness import STIFF_DAMPING, step_factor

    stiffness = model.damping_stiffness()
    if stiffness is not None and stiffness > STIFF_DAMPING:
        warning_line(
            f"{label}: stiff damping, h*lambda_max(M^-1 D) = {stiffness:.3g} > "
            f"{STIFF_DAMPING:g}: velocity x {step_factor(stiffness):+.3f} per step, its sign flips every step "
            f"(exact: x {math.exp(-stiffness):.2g}); Newton still converges (docs/math.md, 'Stiff damping')"
        )
    return stiffness


def _roll(model, truth: Pose, steps: int, solver: SolverOptions, label: str, show: bool) -> Rollout:
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    warn_stiff_damping(model, label)
    with progress_bar(show) as bar:
        task = bar.add_task(f"rollout {label}", total=max(steps - 1, 0), loss=float("nan"))
        ro = model.rollout(g0, g1, steps, solver, progress=lambda k: bar.update(task, completed=k))
    if ro.n_failed:
        warning_line(
            f"{label}: Newton did not converge on {ro.n_failed} step(s); "
            f"first at step {ro.first_failure()} (flagged in rollout.h5; the errors stop at each trajectory's "
            "first failure)"
        )
    return ro


def one_step(model, truth: Pose, steps: int, solver: SolverOptions) -> OneStep | None:
    """The model's teacher-forced one-step predictions of samples 2..n (n = min(steps, the data's steps)),
    each from the true pair (g_{k-1}, g_k): one batched two-step rollout over all pairs
    (`solvers.one_step.one_step_predictions`), timed. None when the data has fewer than 3 poses."""
    from ..solvers.one_step import one_step_predictions

    n = min(steps, truth.R.shape[1] - 1)
    if n < 2:
        return None
    t0 = time.perf_counter()
    pose, converged = one_step_predictions(model, truth.index((slice(None), slice(0, n + 1))), solver)
    return OneStep.from_predictions(pose, converged, time.perf_counter() - t0)


def test_trajectories(dataset, max_trajectories) -> tuple[np.ndarray, Pose]:
    """(indices, poses) of the test trajectories rolled out, on the runtime's device and dtype."""
    from ..config.factory import data_pose

    idx = np.asarray(dataset.test_idx)
    if len(idx) == 0:
        raise DatasetError(f"{dataset.scene}: field 'split/test' is empty: nothing to roll out")
    if max_trajectories:
        idx = idx[: int(max_trajectories)]
    return idx, data_pose(dataset, idx)


def rollout_steps(given) -> int:
    """The rollout length from a config value (ConfigError unless an integer >= 2)."""
    try:
        steps = int(given)
    except (TypeError, ValueError):
        raise ConfigError(f"rollout steps={given!r}: must be an integer") from None
    if steps != given and not (isinstance(given, str) and given.strip().lstrip("+").isdigit()):
        raise ConfigError(f"rollout steps={given!r}: must be an integer")
    if steps < 2:
        raise ConfigError(f"rollout steps={steps}: need at least 2")
    return steps


def rollout_and_save(run: RunConfig, model, dataset, path, steps=None, provenance: dict | None = None) -> dict:
    """Roll out `model` (and the true scheme, if the scene has one, on the same device and dtype) from
    each test trajectory's first pair; write `path` (CPU float64) with `provenance` (the run, model and
    checkpoint: `checkpoint.run_provenance`) and the rollout's dtype. Returns timing/solver summaries."""
    from ..config.factory import place
    from ..data.scenes import dataset_steps
    from ..models.liedflnn.substeps import same_step
    from ..models.true_scheme import true_model

    assert run.rollout is not None, "a rollout section"
    steps = rollout_steps(steps if steps is not None else dataset_steps(run.dataset, dataset, "rollout_steps"))
    idx, truth = test_trajectories(dataset, run.rollout.max_trajectories)
    runs = {"model": model}
    if run.rollout.reference:
        ref = true_model(dataset)
        if ref is not None:  # on the model's own step (its sub-steps and order)
            runs["true_scheme"] = place(same_step(ref, model))
    rollouts = {}
    for name, m in runs.items():
        was_training = m.training
        m.eval()
        label = (getattr(m, "name", "") or name) if name == "model" else name.replace("_", " ")  # liedflnn, true scheme
        ro = _roll(m, truth, steps, run.solver, label, run.ui.progress)
        entry = RolloutEntry.from_rollout(ro)
        entry.one_step = one_step(m, truth, steps, run.solver)
        m.train(was_training)
        rollouts[name] = entry
    prov = {**(provenance or {}), "dtype": str(truth.R.dtype).removeprefix("torch.")}
    written = write_rollout(
        path, steps=steps, h=dataset.h, scene=dataset.scene, traj_index=idx, rollouts=rollouts, provenance=prov
    )
    results = {name: entry.summary() for name, entry in written.models.items()}
    for name, entry in written.models.items():
        if entry.one_step is not None:
            results[name]["one_step_seconds"] = float(entry.one_step.attrs["seconds"])
    one = {k: e.one_step for k, e in written.models.items() if e.one_step is not None}
    note = ""
    if one:
        note = "; teacher-forced one-step predictions of {} pairs in {}".format(
            next(iter(one.values())).attrs["n_pairs"],
            ", ".join(f"{o.attrs['seconds']:.3g} s ({k})" for k, o in one.items()),
        )
    console.print(f"rollout of {len(idx)} test trajectories x {steps} steps written to {path}" + (note if one else ""))
    return results


def own_source(run_dir, run_cfg: RunConfig, dataset, data_dir) -> dict:
    """The `source.json` record of a rollout of the run's own dataset over other trajectories than its
    test split (`split=all|train`): the run's dataset file, so that `liedfl eval` evaluates those."""
    from ..config.runs import _recorded_dataset
    from ..data.scenes import dataset_path
    from ..files.checkpoint import load_checkpoint

    assert run_cfg.dataset is not None, "a trained run has a dataset section"
    recorded = load_checkpoint(Path(run_dir) / "checkpoints" / "last.pt").get("dataset_path")
    path = _recorded_dataset(Path(run_dir), recorded) or dataset_path(run_cfg.dataset, data_dir)
    return {
        "dataset_path": str(Path(path).resolve()),
        "scene": dataset.scene,
        "group": dataset.group.name,
        "h": dataset.h,
        "dataset_config": run_cfg.dataset.as_dict(),
    }


ROLLOUT_KEYS = ("steps", "max_trajectories", "reference")
"""The `rollout` keys `liedfl rollout` sets over the run's own (when not null)."""


def with_command_settings(run: RunConfig, command: RunConfig) -> RunConfig:
    """The run's typed config with this rollout command's settings: its `ui`, `solver` and `eval`
    sections, and its non-null `rollout` keys over the run's."""
    assert run.rollout is not None and command.rollout is not None
    given = {k: getattr(command.rollout, k) for k in ROLLOUT_KEYS if getattr(command.rollout, k) is not None}
    return dataclasses.replace(
        run,
        rollout=dataclasses.replace(run.rollout, **given),
        ui=command.ui,
        solver=command.solver,
        eval=command.eval,
    )


def new_rollout_dir(run_dir, steps: int, tag: str | None = None) -> Path:
    """Create and return a new folder `<run>/rollouts/<date>_<time>[_<tag>]_steps<N>` (suffix _2, _3, ...
    if taken); `tag`: the other dataset's scene name when rolling out on other data."""
    base = Path(run_dir) / "rollouts"
    base.mkdir(exist_ok=True)
    stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    if tag:
        stamp += "_" + "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in str(tag))
    for k in range(1, 1000):
        out = base / (f"{stamp}_steps{steps}" + (f"_{k}" if k > 1 else ""))
        try:
            out.mkdir()
            return out
        except FileExistsError:
            continue
    raise ConfigError(f"{base}: cannot create a new rollout folder for {stamp}_steps{steps}")


def run_rollout(cfg: DictConfig) -> dict:
    """`liedfl rollout run=<dir> [steps=N] [dataset=<scene> ...]`: reload the run's checkpoint, roll it out
    into a new folder `<run>/rollouts/<name>/rollout.h5` and evaluate it there (eval.csv, eval.md, plots,
    the scene's extra evaluation). With `dataset=...` the rollout runs on that dataset's test split and
    is evaluated against it (`source.json` records it). The run's own rollout.h5 and evaluation are never
    touched; on failure the new folder is removed."""
    from ..config.factory import configure_runtime
    from ..config.other_data import SOURCE_FILE, choose_split, other_dataset, with_test_split
    from ..config.runs import load_run_checkpoint
    from ..files.checkpoint import CHECKPOINT_FILE, describe_checkpoint, load_checkpoint, run_provenance
    from ..files.io_utils import write_json
    from ..files.rollout_file import FILE_NAME
    from .evaluate import run_eval_from_objects
    from .outputs import run_scene_eval

    command = typed(cfg, "rollout")  # this command's settings, typed once
    configure_runtime(command.runtime)  # this command's runtime section: threads, device, dtype, ...
    from ..files.dataset_identity import accept_option

    loaded = load_run_checkpoint(
        command.top["run"],
        command.paths.data_dir,
        command.top.get("checkpoint") or "best",
        accept_option(command.top.get("accept_changed_dataset")),
    )
    model, dataset, run_dir, used = loaded.model, loaded.dataset, loaded.run_dir, loaded.checkpoint
    console.print(describe_checkpoint(used), highlight=False)
    other = other_dataset(command, model, run_dir)
    if loaded.config.rollout is None:  # a stored config without the section (an edited or damaged checkpoint)
        raise ConfigError(
            f"{run_dir}: the checkpoint's stored config has no rollout section (was it edited?); "
            "restore the checkpoint or train the run again"
        )
    run = with_command_settings(loaded.config, command)  # the run's typed config, this command's settings
    assert run.rollout is not None and command.rollout is not None
    source, all_asked = None, False
    if other is not None:
        dataset, ds_cfg, source, all_asked = other
        run.dataset = ds_cfg  # replaces the run's dataset section (no key-by-key merge)
    split, idx = choose_split(str(command.top.get("split") or "auto"), dataset, other is not None, all_asked)
    if split != "test":
        dataset = with_test_split(dataset, idx)
        if split == "all" and command.rollout.max_trajectories is None:
            run.rollout.max_trajectories = None  # every trajectory, not the run's training-time cap
        if source is None:  # the run's own data, other trajectories: recorded for `liedfl eval`
            source = own_source(run_dir, loaded.config, dataset, command.paths.data_dir)
    if source is not None:
        source.update(split=split, test_trajectories=[int(i) for i in idx])
    from ..data.scenes import dataset_steps

    where = ((dataset.params or {}).get("source") or {}).get("file")  # the user's file (dataset=file|import)
    where = where or (source["dataset_path"] if source is not None else dataset.scene)
    if dataset.n_steps < 2:
        raise DatasetError(
            f"{where}: {dataset.n_steps} step per trajectory; a rollout needs at least 2 to compare with"
        )
    given = command.top.get("steps")
    steps = rollout_steps(given if given is not None else dataset_steps(run.dataset, dataset, "rollout_steps"))
    tag = dataset.scene if other is not None else (split if split != "test" else None)
    from ..files.signals import set_phase

    out = new_rollout_dir(run_dir, steps, tag=tag)
    set_phase("rollout", f"nothing kept ({out} removed)")
    try:
        if source is not None:
            console.print(
                f"rolling {run_dir} out on dataset '{dataset.scene}' ({dataset.group.name}, "
                f"{len(idx)} trajectories: split={split}) from {source['dataset_path']}",
                soft_wrap=True,
            )
            write_json(out / SOURCE_FILE, source)
        path = out / FILE_NAME
        last = load_checkpoint(Path(run_dir) / "checkpoints" / "last.pt")
        provenance = run_provenance(run_dir, last.get("run_id"), loaded.model_name, used)
        results = rollout_and_save(run, model, dataset, path, steps=steps, provenance=provenance)
        timings = last.get("timings")
        write_json(out / CHECKPOINT_FILE, used)
        set_phase("evaluation", f"nothing kept ({out} removed)")
        rows = run_eval_from_objects(run, dataset, run_dir, timings, rollout_path=path, checkpoint=used)
        extra = run_scene_eval(run.scene_eval_options(), model, dataset, run_dir, rollout_path=path)
        exported = None
        if command.top.get("export"):
            from .export import export_layout, export_predictions, reimport_command

            exported = export_predictions(path, dataset, str(command.top["export"]), out)
            again = reimport_command(exported, *export_layout(dataset))
            console.print(
                f"predictions exported to {exported} (re-import: {again})",
                soft_wrap=True,
                highlight=False,
            )
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        with contextlib.suppress(OSError):
            out.parent.rmdir()  # only if empty: the first rollout of this run failed
        raise
    console.print(f"rollout and its evaluation written to {out}")
    return {
        "dir": str(out),
        "rollout": results,
        "eval": rows,
        "extra_eval": extra,
        "source": source,
        "checkpoint": used,
        "split": split,
        "export": None if exported is None else str(exported),
    }
