"""`liedfl rollout`: roll a trained model (and the true-parameter scheme) over the test split
and write `rollout.h5` (format in docs/data_format.md, section "rollout.h5")."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
from omegaconf import DictConfig, OmegaConf

from .errors import ConfigError, DatasetError
from .factory import solver_options
from .io_utils import atomic_path
from .lie import Pose
from .solvers.options import SolverOptions
from .solvers.rollout import Rollout
from .ui import console, progress_bar


def _roll(model, truth: Pose, steps: int, solver: SolverOptions, label: str, show: bool) -> Rollout:
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    with progress_bar(show) as bar:
        task = bar.add_task(f"rollout {label}", total=max(steps - 1, 0), loss=float("nan"))
        ro = model.rollout(g0, g1, steps, solver, progress=lambda k: bar.update(task, completed=k))
    if ro.n_failed:
        console.print(
            f"[bold yellow]warning:[/] {label}: Newton did not converge on {ro.n_failed} step(s); "
            f"first at step {ro.first_failure()} (flagged in rollout.h5, counted in the eval table)"
        )
    return ro


def test_trajectories(dataset, max_trajectories) -> tuple[np.ndarray, Pose]:
    idx = np.asarray(dataset.test_idx)
    if len(idx) == 0:
        raise DatasetError(f"{dataset.scene}: field 'split/test' is empty: nothing to roll out")
    if max_trajectories:
        idx = idx[: int(max_trajectories)]
    return idx, dataset.pose(idx)


def rollout_and_save(cfg: DictConfig, model, dataset, path, steps=None) -> dict:
    """Roll out `model` (and the true scheme, if the scene has one) from each test trajectory's
    first pair; write `path`. Returns timing/solver summaries."""
    from .models.true_scheme import true_model

    given = steps or cfg.dataset.rollout_steps
    try:
        steps = int(given)
    except (TypeError, ValueError):
        raise ConfigError(f"rollout steps={given!r}: must be an integer") from None
    if steps != given and not (isinstance(given, str) and given.strip().lstrip("+").isdigit()):
        raise ConfigError(f"rollout steps={given!r}: must be an integer")
    if steps < 2:
        raise ConfigError(f"rollout steps={steps}: need at least 2")
    idx, truth = test_trajectories(dataset, cfg.rollout.max_trajectories)
    runs = {"model": model}
    if cfg.rollout.reference:
        ref = true_model(dataset)
        if ref is not None:
            runs["true_scheme"] = ref
    results = {}
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["steps"] = steps
        f.attrs["h"] = dataset.h
        f.attrs["dataset_scene"] = dataset.scene
        f.create_dataset("traj_index", data=idx)
        for name, m in runs.items():
            was_training = m.training
            m.eval()
            ro = _roll(m, truth, steps, solver_options(cfg.solver), name, cfg.ui.progress)
            m.train(was_training)
            g = f.create_group(name)
            g.create_dataset("R", data=ro.pose.R.numpy())
            g.create_dataset("p", data=ro.pose.p.numpy())
            g.create_dataset("converged", data=ro.converged.numpy())
            g.create_dataset("iterations", data=ro.iterations.numpy())
            g.create_dataset("residual_norm", data=ro.residual_norm.numpy())
            per_step = ro.seconds / max(steps - 1, 1)
            g.attrs.update(
                {
                    "seconds": ro.seconds,
                    "seconds_per_step": per_step,
                    "n_failed": ro.n_failed,
                    "first_failure": ro.first_failure() or -1,
                    "n_trajectories": len(idx),
                }
            )
            results[name] = {
                "seconds": ro.seconds,
                "seconds_per_step": per_step,
                "n_failed": ro.n_failed,
                "first_failure": ro.first_failure(),
                "mean_newton_iterations": float(ro.iterations.double().mean()) if ro.iterations.numel() else 0.0,
            }
    console.print(f"rollout of {len(idx)} test trajectories x {steps} steps written to {path}")
    return results


def run_rollout(cfg: DictConfig) -> dict:
    """`liedfl rollout run=<dir> [steps=N]`: reload the run's checkpoint and write <run>/rollout.h5."""
    from .runs import load_run

    run_cfg, model, dataset, run_dir = load_run(cfg.run, cfg.paths.data_dir)
    merged = OmegaConf.merge(
        run_cfg,
        {"rollout": {k: v for k, v in cfg.rollout.items() if v is not None}, "ui": cfg.ui, "solver": cfg.solver},
    )
    return rollout_and_save(
        merged, model, dataset, Path(run_dir) / "rollout.h5", steps=cfg.steps or run_cfg.dataset.rollout_steps
    )
