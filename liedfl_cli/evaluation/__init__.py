"""Scene-specific evaluations that run after the general one (`evaluate.py`): the torque recovery of
the PD-control scene (Exp 5, `control.py`) and the mocap table (Exp 4, `mocap.py`).

`SCENE_EVALS` is the one registry, keyed by the dataset's declared scene (`Dataset.scene`); nothing
registers itself at import. Each entry is `fn(opts: SceneEvalOptions, model, dataset, run_dir, rollout_path=None) ->
EvalOutputs | None`; it reads the rollout file (default `<run_dir>/rollout.h5`) and computes its
summary, tables and figures; it writes nothing (the commands do: `commands.outputs.write_outputs`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .control import evaluate_control
from .mocap import evaluate_mocap
from .outputs import EvalOutputs, SceneEvalOptions

SCENE_EVALS: dict[str, Callable[..., EvalOutputs | None]] = {
    "cmu_cartwheel": evaluate_mocap,
    "pd_control": evaluate_control,
}


def run_extra_evals(opts: SceneEvalOptions, model, dataset, run_dir, rollout_path=None) -> EvalOutputs | None:
    """Run the dataset scene's evaluation, if it has one, on `rollout_path` (default the run's
    rollout.h5); returns its outputs, not yet written (None without one)."""
    fn = SCENE_EVALS.get(dataset.scene)
    if fn is None:
        return None
    return fn(opts, model, dataset, Path(run_dir), rollout_path=rollout_path)


__all__ = ["SCENE_EVALS", "EvalOutputs", "SceneEvalOptions", "run_extra_evals"]
