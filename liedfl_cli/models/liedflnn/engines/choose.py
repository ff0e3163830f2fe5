"""Which of LieDFLNN's engines serves a training run or a rollout: decided here, from the model's
`ExecutionPlan` (its path and compile policy) and what it is given (each engine's own `applies` says
what it can serve). The model (`model.py`) holds the one meaning; these are the ways to compute it.

Training (the DEL loss; `choose_training_engine`):

    increments  the fused path with the closed-form residual: triplets stored as precomputed increments
                (`training.IncrementSet`), the batched residual and regularity (`training.increments_loss`,
                compiled forward and backward when the plan asks), and the no-autograd gradient of an
                SO(3)-only model (`gradient.RotationalGradient`)
    triplets    everything else: pose triplets (`base.TripletSet`) and the model's own `triplet_loss`

A batch names the engine that built it: `choose_training_engine(model, batch)` picks the one that
serves it, so a triplet batch given to a fused model is still computed (by the reference).

Rollouts (`choose_rollout_engine`), once per rollout from the start poses:

    native   one body or a product of bodies with constant Rayleigh damping, at most one learned force
             and an MLP or gravity potential, in C++ (`engines/native.py`), where the plan allows native
             code and a compiler builds it
    scalar   one to six trajectories of a single SO(3) body with a linear Newton residual, Python floats
    columns  more trajectories of such a body, in column layout ((3, 3, T) rotations)
    rows     everything else: the one Newton loop over rows (`LieDFLNN.rollout_rows`: the fused step,
             compiled when the plan asks, or the reference problem on the reference path)

Otherwise a rollout the plan compiles (`plan.wants_compile("rollout", trajectories x steps)`) takes rows:
the compiled step lives there. Every engine takes the reference problem's Newton steps to rounding
(tests/test_fused_scalar.py, tests/test_fused_columns.py, tests/test_model_path.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ....lie import Pose
from ...base import ImplicitModel, LossOptions, TripletBatch
from . import columns, native, scalar, training


@dataclass(frozen=True)
class RolloutEngine:
    """A way to roll a LieDFLNN out: `applies(model, g0)`, and `rollout(model, g0, g1, steps, opts,
    progress)` giving the `solvers.rollout.Rollout` of the reference loop."""

    name: str
    applies: Callable[[Any, Pose], bool]
    rollout: Callable[..., Any]


ROWS = RolloutEngine("rows", lambda model, g0: True, lambda model, *args: model.rollout_rows(*args))
NATIVE = RolloutEngine("native", native.applies, native.rollout)
ENGINES = (
    RolloutEngine("scalar", scalar.applies, scalar.rollout),
    RolloutEngine("columns", columns.applies, columns.rollout),
    ROWS,
)
"""The torch engines in order of preference: the first that applies serves a rollout that NATIVE does not."""


def choose_rollout_engine(model, g0: Pose, steps: int) -> RolloutEngine:
    """The engine of `model`'s rollout of `steps` steps from g0 (module docstring)."""
    if native.applies(model, g0):  # native code at any size: faster than the compiled rows
        return NATIVE
    if model.plan.wants_compile("rollout", g0.R.shape[0] * max(steps - 1, 0)):
        return ROWS
    return next(e for e in ENGINES if e.applies(model, g0))


@dataclass(frozen=True)
class TrainingEngine:
    """A way to train a LieDFLNN on the DEL loss: `applies(model)`, `serves(batch)`, its training
    samples `samples(model, poses, steps)`, the loss of one batch of them `loss(model, batch, opts)` ->
    (loss, {"del_loss", "reg_loss"}), and `value_and_grad(model, samples, opts, params)` (a callable that
    gives the loss and its gradient without autograd, or None: the trainer then uses autograd)."""

    name: str
    applies: Callable[[Any], bool]
    serves: Callable[[Any], bool]
    samples: Callable[[Any, Pose, int], Any]
    loss: Callable[[Any, Any, LossOptions], Any]
    value_and_grad: Callable[..., Any]


def _increments_loss(model, batch, opts: LossOptions):
    if model.plan.wants_compile("train"):  # the whole loss, forward and backward, compiled
        from ....solvers import compile as compile_cache
        from .maps import warm_caches

        ref = next(model.parameters())
        warm_caches(ref.dtype, ref.device, float(model.h))
        return compile_cache.compiled(training.increments_loss, "train_loss")(model, batch, opts)
    return training.increments_loss(model, batch, opts)


def _rotational_gradient(model, samples, opts: LossOptions, params):
    from .gradient import RotationalGradient

    return RotationalGradient.make(model, samples, opts, params)


INCREMENTS = TrainingEngine(
    "increments",
    applies=lambda model: model._fused(),
    serves=lambda batch: isinstance(batch, training.IncrementBatch),
    samples=lambda model, data, steps: training.IncrementSet(model, data, steps),
    loss=_increments_loss,
    value_and_grad=_rotational_gradient,
)
TRIPLETS = TrainingEngine(
    "triplets",
    applies=lambda model: True,
    serves=lambda batch: isinstance(batch, TripletBatch),
    samples=lambda model, data, steps: ImplicitModel.training_set(model, data, steps),
    loss=lambda model, batch, opts: model.triplet_loss(batch, opts),
    value_and_grad=lambda model, samples, opts, params: None,
)
TRAINING_ENGINES = (INCREMENTS, TRIPLETS)
"""In order of preference: the first that applies trains the model."""


def choose_training_engine(model, batch: Any = None) -> TrainingEngine:
    """The engine that trains `model` (the first of TRAINING_ENGINES that applies), or, given a batch,
    the one that serves it (module docstring)."""
    if batch is not None:
        found = next((e for e in TRAINING_ENGINES if e.serves(batch)), None)
        if found is None:
            raise TypeError(f"LieDFLNN trains on triplets (window = 'triplet'), got {type(batch).__name__}")
        return found
    return next(e for e in TRAINING_ENGINES if e.applies(model))
