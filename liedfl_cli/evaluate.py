"""`liedfl eval`: metrics table and plots of a run from its rollout.h5 and dataset."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np
import torch
from omegaconf import DictConfig
from rich.table import Table

from . import plots
from .errors import DatasetError
from .io_utils import fmt, markdown_table, write_csv, write_json, write_text
from .lie import Pose
from .metrics import trajectory_metrics
from .ui import console

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
}
COLUMNS = [
    "model",
    "rel_rot_error_mean",
    "rel_rot_error_final",
    "geodesic_error_mean",
    "position_error_mean",
    "max_orth_drift",
    "max_det_drift",
    "nonfinite_step",
    "newton_failures",
    "first_failure_step",
    "mean_newton_iterations",
    "rollout_s_per_step",
    "train_seconds",
    "seconds_per_epoch",
    "parameters",
]


def read_rollout(path) -> tuple[dict, np.ndarray, dict]:
    """-> ({name: Pose + diagnostics}, traj_index, attrs); clear error for a bad file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: rollout file not found (run `liedfl rollout run=<dir>` first)")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"{path}: not an HDF5 file ({e})") from None
    try:
        with f:
            if "traj_index" not in f or "model" not in f:
                raise DatasetError(f"{path}: dataset 'traj_index' or group 'model' missing")
            if "steps" not in f.attrs:
                raise DatasetError(f"{path}: attribute 'steps' is missing")
            out = {}
            for name in f:
                if not isinstance(f[name], h5py.Group):
                    continue
                g = f[name]
                missing = [k for k in ("R", "p", "converged", "iterations") if k not in g]
                if missing:
                    raise DatasetError(f"{path}: group '{name}' lacks dataset '{missing[0]}'")
                out[name] = {
                    "pose": Pose(torch.from_numpy(g["R"][...]), torch.from_numpy(g["p"][...])),
                    "converged": g["converged"][...],
                    "iterations": g["iterations"][...],
                    **{k: g.attrs[k] for k in g.attrs},
                }
            return out, f["traj_index"][...], dict(f.attrs)
    except DatasetError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise DatasetError(f"{path}: cannot read rollout file ({type(e).__name__}: {e})") from None


def _rows(rollouts: dict, truth: Pose, timings: dict | None):
    rows, curves = [], {}
    S = truth.R.shape[1]
    for name, ro in rollouts.items():
        pred = ro["pose"]
        s = min(S, pred.R.shape[1])
        m = trajectory_metrics(pred.index((slice(None), slice(0, s))), truth.index((slice(None), slice(0, s))))
        curves[name] = m["curves"]
        row = {"model": name, **m["scalars"]}
        row["newton_failures"] = int((~ro["converged"].astype(bool)).sum())
        ff = int(ro.get("first_failure", -1))
        row["first_failure_step"] = ff if ff >= 0 else None
        row["mean_newton_iterations"] = float(ro["iterations"].mean()) if ro["iterations"].size else 0.0
        row["rollout_s_per_step"] = float(ro.get("seconds_per_step", float("nan")))
        if name == "model" and timings:
            row.update({k: timings.get(k) for k in ("train_seconds", "seconds_per_epoch", "parameters")})
        rows.append(row)
    return rows, curves


def run_eval_from_objects(cfg: DictConfig, dataset, run_dir, timings: dict | None = None) -> list[dict]:
    run_dir = Path(run_dir)
    rollouts, idx, attrs = read_rollout(run_dir / "rollout.h5")
    bad = (idx < 0) | (idx >= dataset.n_trajectories)
    if bad.any():
        j = int(bad.nonzero()[0][0])
        raise DatasetError(
            f"{run_dir / 'rollout.h5'}: dataset 'traj_index' has trajectory {int(idx[j])} at index {j}, "
            f"but the run's dataset has {dataset.n_trajectories}; re-run `liedfl rollout run={run_dir}`"
        )
    truth = dataset.pose(idx)
    rows, curves = _rows(rollouts, truth, timings)
    recovery_path = run_dir / "recovery.json"
    write_csv(run_dir / "eval.csv", rows)
    cols = [c for c in COLUMNS if any(r.get(c) is not None for r in rows)]
    md = (
        f"# Evaluation: {dataset.scene} ({dataset.group.name}, h={dataset.h}), "
        f"{len(idx)} test trajectories x {int(attrs['steps'])} steps\n\n"
    )
    md += markdown_table(rows, cols)
    if recovery_path.is_file():
        rec = json.loads(recovery_path.read_text())
        md += "\n## Parameter recovery (normalised by tr J_d)\n\n" + markdown_table([rec], list(rec))
    write_text(run_dir / "eval.md", md)
    write_json(run_dir / "eval_curves.json", {k: {kk: vv.tolist() for kk, vv in v.items()} for k, v in curves.items()})
    table = Table(title=f"{dataset.scene}: test rollout ({len(idx)} x {int(attrs['steps'])} steps)")
    for c in cols:
        table.add_column(SHORT.get(c, c), overflow="fold")
    for r in rows:
        table.add_row(*[fmt(r.get(c)) for c in cols])
    console.print(
        "columns: rel err = mean ||R^-R||_F/||R||_F over steps; geo err = mean geodesic error (rad); "
        "drifts are maxima over the rollout; full names in eval.md",
        style="dim",
    )
    console.print(table)
    if cfg.eval.plots:
        h = dataset.h
        pdir = run_dir / "plots"
        plots.error_vs_step(curves, h, pdir / "error_vs_step.png")
        plots.drift_vs_step(curves, h, pdir / "drift_vs_step.png")
        preds = {k: v["pose"] for k, v in rollouts.items()}
        plots.sphere(truth.R.numpy(), {k: v.R.numpy() for k, v in preds.items()}, pdir / "sphere.png")
        plots.predicted_vs_true(
            Pose(truth.R.numpy(), truth.p.numpy()),
            {k: Pose(v.R.numpy(), v.p.numpy()) for k, v in preds.items()},
            h,
            pdir / "predicted_vs_true.png",
        )
        hist = run_dir / "train_metrics.csv"
        if hist.is_file():
            with open(hist) as f:
                history = [{k: float(v) for k, v in r.items() if k and v not in (None, "")} for r in csv.DictReader(f)]
            if history and all("epoch" in r for r in history):
                plots.loss_curve(history, pdir / "loss.png")
    return rows


def run_eval(cfg: DictConfig) -> list[dict]:
    """`liedfl eval run=<dir>`: recompute eval.csv / eval.md / plots of a run, and the scene's
    extra evaluation (torque recovery, mocap table) when it has one."""
    from omegaconf import OmegaConf

    from .checkpoint import load_checkpoint
    from .extras import run_extra_evals
    from .runs import load_run

    run_cfg, model, dataset, run_dir = load_run(cfg.run, cfg.paths.data_dir)
    timings = load_checkpoint(Path(run_dir) / "checkpoints" / "last.pt").get("timings")
    rows = run_eval_from_objects(cfg, dataset, run_dir, timings)
    run_extra_evals(OmegaConf.merge(run_cfg, {"eval": cfg.eval, "ui": cfg.ui}), model, dataset, run_dir)
    return rows
