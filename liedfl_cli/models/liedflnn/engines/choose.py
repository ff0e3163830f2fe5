"""Which of LieDFLNN's rollout engines serves a rollout: decided here, once per rollout, from the model's
`ExecutionPlan` and the start poses (each engine's own `applies` says what it can serve).

    scalar   one to six trajectories of a single SO(3) body with a linear Newton residual, Python floats
    columns  more trajectories of such a body, in column layout ((3, 3, T) rotations)
    rows     everything else: the one Newton loop over rows (`LieDFLNN.rollout_rows`: the fused step,
             compiled when the plan asks, or the reference problem on the reference path)

A rollout the plan compiles (`plan.wants_compile("rollout", trajectories x steps)`) takes rows: the
compiled step lives there. Every engine takes the reference problem's Newton steps to rounding
(tests/test_fused_scalar.py, tests/test_fused_columns.py, tests/test_model_path.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ....lie import Pose
from . import columns, scalar


@dataclass(frozen=True)
class RolloutEngine:
    """A way to roll a LieDFLNN out: `applies(model, g0)`, and `rollout(model, g0, g1, steps, opts,
    progress)` giving the `solvers.rollout.Rollout` of the reference loop."""

    name: str
    applies: Callable[[Any, Pose], bool]
    rollout: Callable[..., Any]


ROWS = RolloutEngine("rows", lambda model, g0: True, lambda model, *args: model.rollout_rows(*args))
ENGINES = (
    RolloutEngine("scalar", scalar.applies, scalar.rollout),
    RolloutEngine("columns", columns.applies, columns.rollout),
    ROWS,
)
"""In order of preference: the first that applies serves the rollout."""


def choose_rollout_engine(model, g0: Pose, steps: int) -> RolloutEngine:
    """The engine of `model`'s rollout of `steps` steps from g0 (module docstring)."""
    if model.plan.wants_compile("rollout", g0.R.shape[0] * max(steps - 1, 0)):
        return ROWS
    return next(e for e in ENGINES if e.applies(model, g0))
