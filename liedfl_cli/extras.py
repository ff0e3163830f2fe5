"""Scene-specific evaluations that run after the standard eval (torque recovery for control
scenes, the mocap table for recordings). Modules register a function by scene name:

    EXTRA_EVALS["pd_control"] = fn(cfg, model, dataset, run_dir) -> dict | None
"""

from __future__ import annotations

from collections.abc import Callable

EXTRA_EVALS: dict[str, Callable] = {}


def run_extra_evals(cfg, model, dataset, run_dir) -> dict | None:
    fn = EXTRA_EVALS.get(dataset.scene)
    return fn(cfg, model, dataset, run_dir) if fn is not None else None


from . import mocap_eval  # noqa: E402,F401  (registers EXTRA_EVALS["cmu_cartwheel"])
