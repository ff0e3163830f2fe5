"""`liedfl eval`: metrics table and plots of a rollout file (a run's rollout.h5 by default) and its dataset.

Errors against ground truth cover the steps the dataset has; drift, the first non-finite step and the
Newton statistics cover the whole rollout (a rollout may be longer than the dataset); eval.md and the
printed table say which span each column covers.

Every evaluation has zero-parameter reference rows (constant velocity, constant acceleration and, with
SE(3) bodies, constant velocity with Euclidean positions; `_reference_rows`) and ratios to them over the
same samples as the model's errors (`_reference_ratios`). The `constant_velocity` row: the rollout
g_{k+1} = g_k exp(log(g_{k-1}^{-1} g_k)) from the same first pair over the same span, and the same guess
teacher-forced from every true pair (`solvers.one_step`). A model that does not beat constant velocity
has learned nothing. Every row has teacher-forced one-step errors (from the rollout file's optional
`<model>/one_step/` predictions; blank for files written without them) and its ratios to the
constant-velocity row (`one_step_vs_cv`, `rollout_vs_cv`)."""

from __future__ import annotations

import contextlib
import csv
import json
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from ..config.runs import LoadedRun
from ..config.typed import RunConfig, typed
from ..display import plots
from ..display.ui import console, print_table, warning_line
from ..errors import ConfigError
from ..evaluation import EvalOutputs
from ..evaluation.metrics import drift_metrics, error_metrics, one_step_metrics, valid_horizons, valid_steps
from ..files.io_utils import markdown_table
from ..files.rollout_file import FILE_NAME, RolloutFile, load_rollout, read_rollout
from ..lie import Pose, ProductGroup
from .outputs import show, write_outputs

SHORT = {
    "rel_rot_error_mean": "rel err",
    "rel_rot_error_final": "rel err end",
    "geodesic_error_mean": "geo err",
    "position_error_mean": "pos err",
    "max_orth_drift": "orth drift",
    "max_det_drift": "det drift",
    "newton_failures": "newton fail",
    "first_failure_step": "1st fail",
    "mean_newton_iterations": "iters",
    "nonfinite_step": "nonfinite at",
    "rollout_s_per_step": "s/step",
    "train_seconds": "train s",
    "seconds_per_epoch": "s/epoch",
    "parameters": "params",
    "one_step_rot_error_mean": "1-step rot",
    "one_step_pos_error_mean": "1-step pos",
    "one_step_vs_cv": "1-step/CV",
    "rollout_vs_cv": "geo/CV",
    "cv_geodesic_error_same_horizon": "CV geo (same steps)",
    "best_reference": "best ref",
    "one_step_vs_best": "1-step/best",
    "rollout_vs_best": "geo/best",
    "one_step_pos_vs_best": "1-step pos/best",
    "rollout_pos_vs_best": "pos/best",
    "beats_references": "beats refs",
    "valid_horizon_min": "valid to",
    "failed_trajectories": "failed traj",
    "excluded_samples": "excluded",
}
ERROR_COLUMNS = ["rel_rot_error_mean", "rel_rot_error_final", "geodesic_error_mean", "position_error_mean"]
"""Columns computed against ground truth: over the steps the dataset has, each trajectory up to its first
Newton failure (a failed step and the poses predicted from it are not the model's predictions)."""
HORIZON_COLUMNS = ["valid_horizon_min", "valid_horizon_mean", "failed_trajectories", "excluded_samples"]
"""What the errors cover: the trajectories' valid horizons (the last sample before their first Newton
failure; the error span's end without one), how many trajectories failed within the span and how
many samples the errors leave out."""
ONE_STEP_COLUMNS = ["one_step_rot_error_mean", "one_step_pos_error_mean"]
"""Teacher-forced one-step errors (each g_{k+1} from the true (g_{k-1}, g_k)), over the steps with ground truth."""
CV_COLUMNS = ["one_step_vs_cv", "rollout_vs_cv", "cv_geodesic_error_same_horizon"]
"""Ratios to the constant-velocity row: one_step_rot_error_mean and geodesic_error_mean (< 1: better than CV),
each over the same samples on both sides (a model's rollout up to each trajectory's first Newton failure:
`cv_geodesic_error_same_horizon` is constant velocity's error over those samples)."""
CONSTANT_VELOCITY = "constant_velocity"
"""The row (and curve) of the constant-velocity reference, computed from the data in every evaluation."""
CONSTANT_ACCELERATION = "constant_acceleration"
"""The row of the constant-acceleration reference R exp(2 w_k - w_{k-1}), p + 2 dp_k - dp_{k-1}: teacher-forced
from every three true poses, rolled out from the first three (`solvers.one_step`)."""
EUCLIDEAN_VELOCITY = "constant_velocity_euclidean"
"""With SE(3) bodies: constant velocity with Euclidean positions p + (p_k - p_{k-1}) (rotations as constant
velocity's), often a better guess for positions than the SE(3) one."""
REFERENCES = (CONSTANT_VELOCITY, CONSTANT_ACCELERATION, EUCLIDEAN_VELOCITY)
"""The zero-parameter references; a model beats guessing only when it beats the best of them."""
BEST_COLUMNS = ["one_step_vs_best", "rollout_vs_best", "one_step_pos_vs_best", "rollout_pos_vs_best"]
"""Ratios to the best reference over the same samples (rotation geodesic and, with SE(3) bodies, position
errors): `beats_references` is true when every one of them is below 1."""
DRIFT_COLUMNS = ["max_orth_drift", "max_det_drift"]
"""Distance from the group: over the whole rollout (as are the non-finite step and the Newton columns)."""
COLUMNS = [
    "model",
    *ERROR_COLUMNS,
    *HORIZON_COLUMNS,
    *ONE_STEP_COLUMNS,
    *CV_COLUMNS,
    "best_reference",
    *BEST_COLUMNS,
    "beats_references",
    *DRIFT_COLUMNS,
    "nonfinite_step",
    "newton_failures",
    "first_failure_step",
    "mean_newton_iterations",
    "rollout_s_per_step",
    "train_seconds",
    "seconds_per_epoch",
    "parameters",
]
_ROW_ORDER = (
    "rel_rot_error_mean",
    "rel_rot_error_final",
    "geodesic_error_mean",
    "max_orth_drift",
    "max_det_drift",
    "position_error_mean",
    "position_error_final",
    "nonfinite_step",
)
"""Order of the metric fields in a row (eval.csv's column order)."""


def _rows(
    rf: RolloutFile,
    truth: Pose,
    timings: dict | None,
    names: dict[str, str] | None = None,
    group: ProductGroup | None = None,
) -> tuple[list[dict], dict]:
    """One row per rolled-out model, then the constant-velocity row (when `group` is given): errors and
    one-step errors over the steps with ground truth (truth's length), drift, non-finite step and
    Newton statistics over the whole rollout; per-step curves of each; ratios to constant velocity.
    `model` is the rollout entry (`model`, `true_scheme`, `constant_velocity`), `name` what it is
    (`liedflnn`, `true scheme`, `constant velocity`)."""
    rows, curves = [], {}
    names = names or plots.display_names([*rf.models, CONSTANT_VELOCITY])
    n = min(rf.steps, truth.R.shape[1] - 1)
    target = truth.index((slice(None), slice(2, n + 1)))  # what the one-step predictions predict
    for name, ro in rf.models.items():
        valid = valid_steps(torch.from_numpy(np.asarray(ro.converged, dtype=bool)), n)
        row, curves[name] = _errors(name, names, ro.pose, truth, n, valid)
        if ro.one_step is not None:
            conv = torch.from_numpy(np.asarray(ro.one_step.converged, dtype=bool))
            row.update(one_step_metrics(ro.one_step.pose, target, conv))
            row["one_step_newton_failures"] = ro.one_step.n_failed
        else:
            row.update({k: None for k in ONE_STEP_COLUMNS if k != "one_step_pos_error_mean" or truth.p.shape[-2]})
        row.update(dict.fromkeys(CV_COLUMNS))  # filled below, once the constant-velocity row exists
        row["newton_failures"] = ro.n_failed
        row["first_failure_step"] = ro.first_failure
        row["mean_newton_iterations"] = ro.mean_iterations
        sps = ro.seconds_per_step
        row["rollout_s_per_step"] = sps if sps is not None else float("nan")
        if name == "model" and timings:
            row.update({k: timings.get(k) for k in ("train_seconds", "seconds_per_epoch", "parameters")})
        row["error_steps"] = n
        row["rollout_steps"] = ro.steps
        row["rollout_trajectories"] = int(ro.R.shape[0])
        rows.append(row)
    if group is not None:
        refs = _reference_rows(group, truth, target, n, rf.steps, names)
        for ref_row, curve, _, _ in refs.values():
            rows.append(ref_row)
            curves[ref_row["model"]] = curve
        cv_row = refs[CONSTANT_VELOCITY][0]
        for r in rows:
            entry = rf.models.get(r["model"]) if r["model"] not in refs else None
            _reference_ratios(r, entry, refs, truth, target, n, cv_row)
    return rows, curves


def _reference_rows(
    group: ProductGroup, truth: Pose, target: Pose, n: int, steps: int, names: dict
) -> dict[str, tuple[dict, dict, Pose, Pose | None]]:
    """{reference: (row, curves, rollout, one-step guesses)} of the zero-parameter references, computed
    from the data: constant velocity (from the first true pair), constant acceleration (from the first
    three true poses; its sample 2 is the data's) and, with SE(3) bodies, constant velocity with Euclidean
    positions (`solvers.one_step`). One-step guesses: None with fewer than 3 poses."""
    from ..solvers import one_step as ref

    g = [truth.index((slice(None), k)) for k in range(min(3, n + 1))]
    made: dict[str, tuple[Pose, Pose | None]] = {
        CONSTANT_VELOCITY: (
            ref.constant_velocity_rollout(group, g[0], g[1], steps),
            ref.constant_velocity_one_step(group, truth.index((slice(None), slice(0, n + 1)))) if n >= 2 else None,
        )
    }
    if n >= 2:
        ca_one = ref.constant_acceleration_one_step(group, truth.index((slice(None), slice(0, n + 1))))
        made[CONSTANT_ACCELERATION] = (ref.constant_acceleration_rollout(g[0], g[1], g[2], steps), ca_one)
    if truth.p.shape[-2] > 0:
        made[EUCLIDEAN_VELOCITY] = (
            ref.euclidean_velocity_rollout(g[0], g[1], steps),
            ref.euclidean_velocity_one_step(group, truth.index((slice(None), slice(0, n + 1)))) if n >= 2 else None,
        )
    names = {
        CONSTANT_ACCELERATION: "constant acceleration",
        EUCLIDEAN_VELOCITY: "constant velocity (Euclidean p)",
        **names,
    }
    out = {}
    for key, (rollout, one) in made.items():
        # constant acceleration starts from three true poses: over 2 steps or fewer it predicts no sample
        none = torch.zeros(truth.R.shape[0], n + 1, dtype=torch.bool) if _no_ca_rollout(key, n) else None
        row, curve = _errors(key, names, rollout, truth, n, none)
        if none is not None:  # no horizon either: nothing was predicted, nothing failed
            row.update(
                dict.fromkeys(("valid_horizon_min", "valid_horizon_mean", "failed_trajectories", "excluded_samples"))
            )
        row.update({k: None for k in ONE_STEP_COLUMNS if k != "one_step_pos_error_mean" or truth.p.shape[-2]})
        if one is not None:
            row.update(one_step_metrics(one, target))
        row.update(
            dict.fromkeys(("newton_failures", "first_failure_step", "mean_newton_iterations", "rollout_s_per_step"))
        )
        row.update({"error_steps": n, "rollout_steps": steps, "rollout_trajectories": int(truth.R.shape[0])})
        out[key] = (row, curve, rollout, one)
    return out


def _no_ca_rollout(key: str, n: int) -> bool:
    """Whether `key` is constant acceleration over n <= 2 error steps: its rollout's samples 0-2 are the
    data's, so it predicts nothing there and is no rollout reference (its one-step guesses still are)."""
    return key == CONSTANT_ACCELERATION and n < 3


def _reference_ratios(r: dict, entry, refs: dict, truth: Pose, target: Pose, n: int, cv_row: dict) -> None:
    """The ratio columns of row `r` (CV_COLUMNS, BEST_COLUMNS), each reference measured over the same
    samples as the row: a model's rollout up to each trajectory's first Newton failure (the reference's
    error over those samples is stored beside it: `cv_geodesic_error_same_horizon`), its one-step errors
    over its converged solves. `entry`: the model's rollout entry (None for a reference row, whose
    samples are all the steps)."""
    span = (slice(None), slice(0, n + 1))
    valid = one_conv = None
    if entry is not None:
        valid = valid_steps(torch.from_numpy(np.asarray(entry.converged, dtype=bool)), n)
        if entry.one_step is not None:
            one_conv = torch.from_numpy(np.asarray(entry.one_step.converged, dtype=bool))
    rot: dict[str, float] = {}
    pos: dict[str, float] = {}
    rot1: dict[str, float] = {}
    pos1: dict[str, float] = {}
    for key, (_, _, rollout, one) in refs.items():
        if not _no_ca_rollout(key, n):
            sc = error_metrics(rollout.index(span), truth.index(span), valid)["scalars"]
            rot[key] = sc["geodesic_error_mean"]
            if "position_error_mean" in sc:
                pos[key] = sc["position_error_mean"]
        if one is not None:
            o = one_step_metrics(one, target, one_conv)
            rot1[key] = o["one_step_rot_error_mean"]
            if "one_step_pos_error_mean" in o:
                pos1[key] = o["one_step_pos_error_mean"]
    r["cv_geodesic_error_same_horizon"] = rot.get(CONSTANT_VELOCITY)
    r["rollout_vs_cv"] = _ratio(r.get("geodesic_error_mean"), rot.get(CONSTANT_VELOCITY))
    r["one_step_vs_cv"] = _ratio(r.get("one_step_rot_error_mean"), rot1.get(CONSTANT_VELOCITY))
    r["best_reference"] = _best(rot)
    r["rollout_vs_best"] = _ratio(r.get("geodesic_error_mean"), _min(rot))
    r["one_step_vs_best"] = _ratio(r.get("one_step_rot_error_mean"), _min(rot1))
    if pos:
        r["rollout_pos_vs_best"] = _ratio(r.get("position_error_mean"), _min(pos))
        r["one_step_pos_vs_best"] = _ratio(r.get("one_step_pos_error_mean"), _min(pos1))
    ratios = [float(x) for x in (r.get(k) for k in BEST_COLUMNS) if x is not None]
    beats = all(math.isfinite(x) and x < 1 for x in ratios) if ratios else None
    r["beats_references"] = beats if entry is not None else None


def _best(errors: dict[str, float]) -> str | None:
    """The reference with the smallest finite error (None when none is finite)."""
    ok = {k: v for k, v in errors.items() if math.isfinite(v)}
    return min(ok, key=lambda k: ok[k]) if ok else None


def _min(errors: dict[str, float]) -> float | None:
    best = _best(errors)
    return None if best is None else errors[best]


def _errors(
    name: str, names: dict[str, str], pred: Pose, truth: Pose, n: int, valid: torch.Tensor | None = None
) -> tuple[dict, dict]:
    """(row with the error, horizon, drift and non-finite columns, curves) of one predicted rollout.
    valid: (T, n+1) bool, the samples the errors cover (`metrics.valid_steps`); None = all."""
    span = (slice(None), slice(0, n + 1))
    err = error_metrics(pred.index(span), truth.index(span), valid)
    drift = drift_metrics(pred)
    scalars = {**err["scalars"], **drift["scalars"]}
    if valid is not None and not bool(valid[:, 2:].any()):  # no predicted sample is valid: no error to give
        scalars.update({k: float("nan") for k in err["scalars"]})
    row = {"model": name, "name": names.get(name, name), **{k: scalars[k] for k in _ROW_ORDER if k in scalars}}
    T = int(pred.R.shape[0])
    horizons = valid_horizons(valid) if valid is not None else [n] * T
    row["valid_horizon_min"] = min(horizons) if horizons else None
    row["valid_horizon_mean"] = float(np.mean(horizons)) if horizons else None
    row["failed_trajectories"] = sum(hz < n for hz in horizons)
    row["excluded_samples"] = int(T * (n + 1) - (int(valid.sum()) if valid is not None else T * (n + 1)))
    return row, {**err["curves"], **drift["curves"], "valid_horizon": np.asarray(horizons, dtype=np.int64)}


def _ratio(a, b) -> float | None:
    """a / b for the vs-CV columns: None when either is missing, NaN when b is 0 or not finite."""
    if a is None or b is None:
        return None
    return float(a) / float(b) if b > 0 and math.isfinite(b) else float("nan")


TABLE_PRIORITY = [
    "model",
    "rel_rot_error_mean",
    "geodesic_error_mean",
    "position_error_mean",
    "one_step_vs_cv",
    "rollout_vs_cv",
    "one_step_vs_best",
    "rollout_vs_best",
    "one_step_rot_error_mean",
    "max_orth_drift",
    "newton_failures",
    "valid_horizon_min",
    "failed_trajectories",
    "rollout_s_per_step",
    "rel_rot_error_final",
    "max_det_drift",
    "mean_newton_iterations",
    "first_failure_step",
    "nonfinite_step",
    "one_step_pos_error_mean",
    "train_seconds",
    "seconds_per_epoch",
    "parameters",
]
"""Which columns of the evaluation table a narrow terminal shows first (eval.md has all of them)."""


def print_eval_table(rows: list[dict], cols: list[str], title: str, out=None) -> list[str]:
    """The evaluation table on the console: rows named by the model (`liedflnn`, `true scheme`), as many
    columns as fit the terminal (TABLE_PRIORITY order; the others are named below it and are in
    eval.md); a number is never broken across lines. Returns the columns shown."""
    shown_rows = [{**r, "model": r.get("name", r["model"])} for r in rows]
    headers = {c: SHORT.get(c, c) for c in cols}
    return print_table(shown_rows, cols, headers, title=title, priority=TABLE_PRIORITY, where="eval.md", out=out)


def length_unit(dataset) -> str | None:
    """The unit of the dataset's positions: metres unless it records another (mocap: CMU ASF units)."""
    from ..data.mocap import ASF_UNIT_M

    unit = (dataset.params or {}).get("length_unit_m")
    if unit is None or abs(float(unit) - 1.0) < 1e-9:
        return "m"
    if abs(float(unit) / ASF_UNIT_M - 1.0) < 1e-4:
        return "CMU ASF units"
    return f"units of {float(unit):.4g} m"


def span_note(rf: RolloutFile, dataset) -> str:
    """Which steps each column covers (the errors need ground truth, the rest does not)."""
    n = min(rf.steps, dataset.n_steps)
    return (
        f"errors (rel err, rel err end, geo err, pos err) over steps 0..{n}"
        + (f" (the dataset ends at step {dataset.n_steps})" if n < rf.steps else "")
        + ", each trajectory up to its first Newton failure (valid to: the shortest such horizon; failed traj,"
        + " excluded: the trajectories cut short and the samples left out)"
        + f"; one-step errors (1-step rot, 1-step pos) over the teacher-forced predictions of steps 2..{n}"
        + f"; drift, non-finite and Newton columns over the whole rollout, steps 0..{rf.steps}"
    )


def rollout_path_arg(value, run_dir) -> Path:
    """The rollout file to evaluate: `rollout=<file or folder holding rollout.h5>`, else `<run>/rollout.h5`."""
    if value in (None, "", "???"):
        return Path(run_dir) / FILE_NAME
    path = Path(str(value)).expanduser()
    if path.is_dir():
        path = path / FILE_NAME
    if not path.is_file():
        raise ConfigError(f"rollout={value}: no such rollout file")
    return path


def run_eval_from_objects(
    run: RunConfig,
    dataset,
    run_dir,
    timings: dict | None = None,
    rollout_path=None,
    model_name: str | None = None,
    checkpoint: dict | None = None,
) -> list[dict]:
    """Evaluate a rollout file against `dataset` (`compute_eval`), print its notes and table and write
    eval.csv, eval.md, eval_curves.json and plots/ next to the file (`outputs.write_outputs`); returns
    the rows."""
    result = compute_eval(run, dataset, run_dir, timings, rollout_path, model_name, checkpoint)
    show(result)
    print_eval_table(result.summary["rows"], result.summary["columns"], result.summary["title"])
    write_outputs(result)
    return result.summary["rows"]


def compute_eval(
    run: RunConfig,
    dataset,
    run_dir,
    timings: dict | None = None,
    rollout_path=None,
    model_name: str | None = None,
    checkpoint: dict | None = None,
) -> EvalOutputs:
    """The evaluation of a rollout file against `dataset`, computed, neither written nor printed:
    summary {"rows": rows, "columns": the columns with a value, "title": of the console table}, the
    files eval.csv, eval.md, eval_curves.json and plots/ (drawn figures) to go next to the file, and
    the notes for the console (`EvalOutputs.messages`; the command prints them, then the table).
    rollout_path: default `<run_dir>/rollout.h5`. The run's parameter recovery (recovery.json) goes
    into eval.md of any rollout of the run, the loss curve only into the run's own plots.
    model_name: what the `model` entry is (default: `run.model['name']`). checkpoint: which checkpoint the
    model's rollout came from (`checkpoint.checkpoint_record`): columns `checkpoint`, `checkpoint_epoch`."""
    run_dir = Path(run_dir)
    path = Path(rollout_path) if rollout_path is not None else run_dir / FILE_NAME
    out = path.parent
    rf = load_rollout(path, dataset)
    idx = rf.traj_index
    truth = dataset.pose(idx)
    model_name = model_name or (run.model or {}).get("name")
    names = plots.display_names([*rf.models, CONSTANT_VELOCITY], model_name)
    rows, curves = _rows(rf, truth, timings, names, group=dataset.group)
    for r in rows:  # which checkpoint rolled out (docs/validation.md)
        if checkpoint and r["model"] == "model":
            r.update(checkpoint=checkpoint.get("checkpoint"), checkpoint_epoch=checkpoint.get("checkpoint_epoch"))
    own = out.resolve() == run_dir.resolve()
    recovery_path = run_dir / "recovery.json"
    cols = [c for c in COLUMNS if any(r.get(c) is not None for r in rows)]
    title = f"{dataset.scene}: test rollout ({len(idx)} x {rf.steps} steps)"
    result = EvalOutputs({"rows": rows, "columns": cols, "title": title}, out)
    result.add("eval.csv", rows)
    note = span_note(rf, dataset)
    md = (
        f"# Evaluation: {dataset.scene} ({dataset.group.name}, h={dataset.h}), "
        f"{len(idx)} test trajectories x {rf.steps} steps\n\n"
    )
    if not own:
        md += f"Rollout file: `{path}` (run `{run_dir}`)\n\n"
    md += f"Spans: {note}.\n\n"
    md += (
        "`constant velocity`: g_{k+1} = g_k exp(log(g_{k-1}^-1 g_k)), the last increment repeated, rolled out from "
        "the same first pair and teacher-forced from every true pair (computed from the data). A model that "
        "does not beat it has learned nothing. `constant acceleration`: R_k exp(2 w_k - w_{k-1}), "
        "p_k + 2 dp_k - dp_{k-1}, teacher-forced from every three true poses and rolled out from the first three "
        "(its sample 2 is the data's); with SE(3) bodies `constant velocity (Euclidean p)`: rotations as constant "
        "velocity, positions p_k + dp_k. `one_step_*`: teacher-forced one-step errors (g_{k+1} from the "
        "true (g_{k-1}, g_k); rotation geodesic in rad); `one_step_vs_cv`, `rollout_vs_cv`: the row's "
        "one_step_rot_error_mean and geodesic_error_mean over constant velocity's over the same samples (a "
        "model's rollout up to each trajectory's first Newton failure, valid to; constant velocity's error over "
        "those samples: `cv_geodesic_error_same_horizon`); `*_vs_best`: the same over the best reference "
        "(`best_reference`, rotation; `*_pos_vs_best` positions); `beats_references`: every `*_vs_best` below 1, "
        "the only case in which a model is better than guessing"
        + (
            "; one-step columns are blank for rollout files written without one-step predictions"
            if any(e.one_step is None for e in rf.models.values())
            else ""
        )
        + ".\n\n"
    )
    md += markdown_table([{**r, "model": r["name"]} for r in rows], cols)
    if recovery_path.is_file():
        rec = json.loads(recovery_path.read_text())
        md += "\n## Parameter recovery (normalised by tr J_d)\n\n" + markdown_table([rec], list(rec))
    result.add("eval.md", md)
    result.add("eval_curves.json", {k: {kk: vv.tolist() for kk, vv in v.items()} for k, v in curves.items()})
    result.say(
        "columns: rel err = mean ||R^-R||_F/||R||_F over steps; geo err = mean geodesic error (rad); "
        "1-step = teacher-forced one-step error (each step from the true previous pair); "
        "1-step/CV, geo/CV = ratio to the constant-velocity row (< 1: better than repeating the last increment); "
        f"drifts are maxima; {note}; full names in eval.md",
        style="dim",
    )
    if rf.steps > dataset.n_steps:
        result.say(
            f"[yellow]note:[/] the rollout ({rf.steps} steps) is longer than the dataset ({dataset.n_steps} steps): "
            "errors cover the steps with ground truth only"
        )
    if run.eval.plots:
        h = dataset.h
        unit = length_unit(dataset)
        names = {
            **plots.display_names(curves),
            **names,
            "model": plots.model_label(names.get("model"), _kinetic(run, dataset, run_dir), dataset.group.n_bodies)
            or "model",
        }
        result.add("plots/error_vs_step.png", plots.draw_error_vs_step(curves, h, names, length_unit=unit))
        result.add(
            "plots/drift_vs_step.png",
            plots.draw_drift_vs_step({k: v for k, v in curves.items() if k not in REFERENCES}, h, names),
        )
        preds = {k: v.pose for k, v in rf.models.items()}
        result.add(
            "plots/sphere.png",
            plots.draw_sphere(truth.R.numpy(), {k: v.R.numpy() for k, v in preds.items()}, names=names),
        )
        result.add(
            "plots/predicted_vs_true.png",
            plots.draw_predicted_vs_true(
                plots.ArrayPose(truth.R.numpy(), truth.p.numpy()),
                {k: plots.ArrayPose(v.R.numpy(), v.p.numpy()) for k, v in preds.items()},
                h,
                names=names,
                length_unit=unit,
            ),
        )
        if dataset.group.n_bodies > 1:
            _body_plots(result, run, dataset, truth, preds, names, unit)
        hist = run_dir / "train_metrics.csv"
        if own and hist.is_file():
            with open(hist) as f:
                history = [{k: float(v) for k, v in r.items() if k and v not in (None, "")} for r in csv.DictReader(f)]
            if history and all("epoch" in r for r in history):
                result.add("plots/loss.png", plots.draw_loss_curve(history))
    return result


def _kinetic(run: RunConfig, dataset, run_dir: Path) -> str | None:
    """The run's model kind, `articulated` or `per_body`: from the run's components.json (the model
    built), else its `model.kinetic` as the model factory resolves it (`auto`: articulated for data with
    a tree; `liedfl eval` passes the command's config, not the run's)."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        built = json.loads((Path(run_dir) / "components.json").read_text()).get("model")
        if isinstance(built, str):
            return "articulated" if built.startswith("Articulated") else "per_body"
    kinetic = (run.model or {}).get("kinetic")
    if kinetic == "auto":
        return "articulated" if getattr(dataset, "tree", None) is not None else "per_body"
    return kinetic


def _body_plots(result: EvalOutputs, run: RunConfig, dataset, truth: Pose, preds: dict, names: dict, unit) -> None:
    """Multibody figures: every body's rotation (and position) error against time (one panel per body, or
    a heat map over body x time for many bodies); for data with a kinematic tree the errors are of the
    bodies' world poses and the skeleton of one predicted and recorded frame is drawn too."""
    tree = getattr(dataset, "tree", None)
    if tree is not None:
        from ..lie.tree import forward_kinematics

        def world(g: Pose) -> plots.ArrayPose:
            w = forward_kinematics(tree, g)
            return plots.ArrayPose(w.R.numpy(), w.p.numpy())
    else:

        def world(g: Pose) -> plots.ArrayPose:
            return plots.ArrayPose(g.R.numpy(), g.p.numpy())

    true_w = world(truth)
    preds_w = {k: world(v) for k, v in preds.items()}
    errors = {k: plots.body_errors(true_w, v) for k, v in preds_w.items()}
    bodies = list(getattr(dataset, "body_names", []))
    result.add("plots/error_per_body.png", plots.draw_body_errors(errors, dataset.h, bodies, names=names))
    if any("position_error" in e for e in errors.values()):
        result.add(
            "plots/position_error_per_body.png",
            plots.draw_body_errors(errors, dataset.h, bodies, "position_error", names, length_unit=unit),
        )
    if tree is not None:
        result.add(
            "plots/skeleton.png",
            plots.draw_skeleton(
                true_w.p,
                {k: v.p for k, v in preds_w.items()},
                tree.parents,
                dataset.h,
                body_names=bodies,
                names=names,
                length_unit=unit,
            ),  # fmt: skip
        )


EVALS_DIR = "evals"
"""`<run>/evals/<name>/`: where `liedfl eval run=<run> rollout=<file outside the run>` writes."""


def check_provenance(path: Path, attrs: dict, run_dir, run_id: str | None) -> bool:
    """Refuse (ConfigError, one line naming both runs) a rollout file written by another run than
    `run_dir` (id `run_id`, None for runs written before run ids existed); a file without provenance
    (written before rollout files recorded it) passes with a one-line warning. True when it is the run's."""
    other = attrs.get("run_id")
    if other in (None, ""):
        warning_line(
            f"{path}: provenance unknown (the file records no run_id: written before "
            f"rollout files recorded their run); evaluated as a rollout of run {run_dir}"
        )
        return False
    if str(other) != str(run_id):
        model = f", model {attrs['model_name']}" if attrs.get("model_name") else ""
        ours = f"run_id {run_id}" if run_id else "a run without a run_id"
        raise ConfigError(
            f"rollout={path}: written by run {attrs.get('run_dir', '?')} (run_id {other}{model}), not by run "
            f"{run_dir} ({ours}); evaluate it with `liedfl eval run={attrs.get('run_dir', '<its run>')}`"
        )
    return True


def _inside(path: Path, folder) -> bool:
    return Path(path).resolve().is_relative_to(Path(folder).resolve())


def copy_into_run(path: Path, run_dir, made: list[Path] | None = None) -> Path:
    """A rollout file outside the run evaluated as the run's: copied with its source.json and
    checkpoint.json into a new `<run>/evals/<date>_<time>_<folder of the file>/`, where the evaluation
    then writes (an evaluation never writes outside the run it evaluates). Returns the copy's path;
    `made` gets the new folder as soon as it exists (removed by the caller if the evaluation fails)."""
    import shutil
    from datetime import datetime

    from ..config.other_data import SOURCE_FILE
    from ..files.checkpoint import CHECKPOINT_FILE

    base = Path(run_dir) / EVALS_DIR
    base.mkdir(exist_ok=True)
    tag = "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in path.resolve().parent.name) or "rollout"
    stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S") + "_" + tag
    for k in range(1, 1000):
        out = base / (stamp + (f"_{k}" if k > 1 else ""))
        try:
            out.mkdir()
            if made is not None:
                made.append(out)
            break
        except FileExistsError:
            continue
    else:
        raise ConfigError(f"{base}: cannot create a new evaluation folder for {stamp}")
    for name in (FILE_NAME, SOURCE_FILE, CHECKPOINT_FILE):
        src = path if name == FILE_NAME else path.parent / name
        if src.is_file():
            shutil.copy2(src, out / name)
    console.print(f"{path} lies outside run {run_dir}: copied to {out}, evaluated there", highlight=False)
    return out / FILE_NAME


def run_eval(cfg: DictConfig) -> list[dict]:
    """`liedfl eval run=<dir> [rollout=<file>]`: recompute the evaluation (eval.csv / eval.md / plots and
    the scene's extra evaluation: torque recovery, mocap table) of the run's rollout.h5, or of another
    rollout file of the run (written next to that file). A file written by another run is refused
    (`check_provenance`); one outside the run's folder is evaluated in a copy under `<run>/evals/`
    (`copy_into_run`): an evaluation writes only under the run it evaluates."""
    from ..config.factory import configure_runtime
    from ..config.runs import load_run_checkpoint
    from ..files.checkpoint import load_checkpoint
    from ..files.signals import set_phase

    command = typed(cfg, "eval")  # this command's settings, typed once
    configure_runtime(command.runtime)  # this command's runtime section (the model of the scene's extra evaluation)
    from ..files.dataset_identity import accept_option

    loaded = load_run_checkpoint(
        command.top["run"],
        command.paths.data_dir,
        command.top.get("checkpoint") or "best",
        accept_option(command.top.get("accept_changed_dataset")),
    )
    run_dir = loaded.run_dir
    path = rollout_path_arg(command.top.get("rollout"), run_dir)
    last = load_checkpoint(Path(run_dir) / "checkpoints" / "last.pt")
    check_provenance(path, read_rollout(path).attrs, run_dir, last.get("run_id"))
    own = path.parent.resolve() == Path(run_dir).resolve()
    again = f"liedfl eval run={run_dir}" + ("" if own else f" rollout={path}")
    set_phase("evaluation", f"to redo it: {again}")
    copied: list[Path] = []
    try:
        if not _inside(path, run_dir):
            path = copy_into_run(path, run_dir, made=copied)
        return _eval_rollout(command, loaded, path, last)
    except BaseException as e:
        _interrupted_eval(e, path.parent, copied[0] if copied else None, run_dir)
        raise


def _interrupted_eval(e: BaseException, out: Path, copied: Path | None, run_dir) -> None:
    """After a failed or interrupted evaluation: the copy this evaluation made under `<run>/evals/` is
    removed (nothing half-made is left); an interrupted evaluation of an existing folder (the run's, a
    rollout folder) is marked in its status.json (its eval files are each whole, but may be a mix of
    old and new), until an evaluation there completes."""
    import shutil

    from ..config.preflight import classify
    from .status import mark_interrupted

    if copied is not None:
        shutil.rmtree(copied, ignore_errors=True)
        with contextlib.suppress(OSError):
            copied.parent.rmdir()  # only if empty
        return
    if isinstance(e, KeyboardInterrupt) and _inside(out, run_dir):
        message, code = classify(e) or ("interrupted", 130)
        with contextlib.suppress(OSError):
            mark_interrupted(out, message, code, "evaluation")


def _eval_rollout(command: RunConfig, loaded: LoadedRun, path: Path, last: dict) -> list[dict]:
    from ..config.other_data import rollout_dataset
    from ..evaluation import SceneEvalOptions
    from ..files.checkpoint import describe_checkpoint, rollout_checkpoint
    from .outputs import run_scene_eval
    from .status import clear_interruption

    model, run_dir = loaded.model, loaded.run_dir
    used = rollout_checkpoint(path, loaded.checkpoint)  # the rollout's own record (checkpoint.json) when it has one
    console.print(describe_checkpoint(used), highlight=False)
    dataset, _ = rollout_dataset(path, model, loaded.dataset, loaded.config, run_dir, command.paths.data_dir)
    timings = last.get("timings")
    rows = run_eval_from_objects(
        command,
        dataset,
        run_dir,
        timings,
        rollout_path=path,
        model_name=loaded.model_name,
        checkpoint=used,
    )
    # the scene evaluation solves with the run's solver settings, draws as this command says
    opts = SceneEvalOptions(plots=command.eval.plots, solver=loaded.config.solver)
    run_scene_eval(opts, model, dataset, run_dir, rollout_path=path)
    clear_interruption(path.parent, "evaluation")
    return rows
