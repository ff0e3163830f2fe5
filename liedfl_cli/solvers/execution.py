"""How a model's work is computed, as one explicit object: which implementation serves it and whether
its hot paths are compiled (diffrax's habit: passed in, never read from a process global).

The command builds an `ExecutionPlan` from the typed `runtime` section (`ExecutionPlan.from_runtime`)
and hands it to model building (`config.factory.build_model` sets it on the model and every model it
wraps, `Model.set_plan`); the trainer adds the size of the coming training run (`for_training`); a
rollout asks with its own size (`wants_compile("rollout", trajectories x steps)`). A model built
without one (scripts, tests) gets the defaults: the fused paths, `compile: auto`.

    path      fused | reference   the model's fast engines where they apply, or the reference paths
                                  (autograd residuals, the generic Newton loop), for comparison
    compile   auto | true | false torch.compile (CPU inductor) of the fused hot paths; auto compiles
                                  only work large enough to repay the compilation (docs/benchmarks.md);
                                  true and auto also run the articulated rollout's native step where
                                  it applies (`models.articulated.engines.native`, built once in ~2 s)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from ..errors import ConfigError
from . import compile as compile_cache

PATHS = ("fused", "reference")
COMPILE_CHOICES = ("auto", "true", "false")
ModelPath = Literal["fused", "reference"]
CompileWork = Literal["rollout", "train"]

COMPILE_MIN_WORK = {"rollout": 5.0e7, "train": 1.0e5}
"""`compile: auto` compiles a hot path only for work large enough to repay the one-off compilation
(tens of seconds on 2 cores, docs/benchmarks.md): a rollout of trajectories x steps row-steps, a
training run of optimiser steps."""


def check_path(path: object) -> ModelPath:
    """`path` if it is "fused" or "reference"; else a one-line ConfigError (a ValueError)."""
    if path not in PATHS:
        raise ConfigError(f"model path must be one of {PATHS}, got {path!r}")
    return path  # type: ignore[return-value]


@dataclass(frozen=True)
class ExecutionPlan:
    """Path and compile policy of one model (module docstring); `train_steps`: the optimiser steps of
    the training run under way (0 outside training), which `compile: auto` weighs for training."""

    path: ModelPath = "fused"
    compile: str = "auto"
    train_steps: float = 0.0

    def __post_init__(self) -> None:
        check_path(self.path)
        comp = self.compile
        comp = {True: "true", False: "false"}.get(comp, comp) if isinstance(comp, bool) else str(comp)
        if comp not in COMPILE_CHOICES:
            raise ConfigError(f"runtime.compile={self.compile!r}: choose one of {', '.join(COMPILE_CHOICES)}")
        object.__setattr__(self, "compile", comp)

    @classmethod
    def from_runtime(cls, opts) -> ExecutionPlan:
        """The plan of a typed `runtime` section (`solvers.runtime.RuntimeOptions`)."""
        return cls(path="fused" if opts.fused else "reference", compile=opts.compile)

    def on_path(self, path: ModelPath) -> ExecutionPlan:
        return replace(self, path=check_path(path))

    def for_training(self, steps: float) -> ExecutionPlan:
        """This plan for a training run of `steps` optimiser steps."""
        return replace(self, train_steps=float(steps))

    def wants_native(self) -> bool:
        """Whether a fused rollout may run compiled native code (`models.articulated.engines.native`,
        built once per machine in seconds, so at any size): not under `compile: false`, which keeps every
        path in eager torch."""
        return self.path == "fused" and self.compile != "false"

    def wants_compile(self, kind: CompileWork, work: float | None = None) -> bool:
        """Whether to compile the hot path `kind` for `work` (a rollout's trajectories x steps; for
        "train" the plan's `train_steps` unless given) under this plan's `compile`."""
        if self.compile == "false":
            return False
        size = self.train_steps if (work is None and kind == "train") else float(work or 0.0)
        if self.compile == "auto" and size < COMPILE_MIN_WORK[kind]:
            return False
        if not compile_cache.compiler_available():
            compile_cache.say_once(
                "runtime.compile: no C++ compiler found (g++/c++/clang++), running the fused paths uncompiled"
            )
            return False
        return True
