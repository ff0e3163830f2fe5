"""Configs -> objects: the model a run asks for, its loss and solver options.

This is the only place where model configs meet model classes. `model._target_` names the class
(conf/model/<name>.yaml; `baseline=<name>` only selects that file); it must be a `Model` of
this package, and the class's `from_config(ctx, **options)` builds it for the dataset.

Where models and data live (`runtime.device`, `runtime.dtype`) is decided here too: `place` moves a
model there, `data_pose` converts a dataset's trajectories; nothing below the pipeline chooses.
"""

from __future__ import annotations

import inspect
import math
from typing import TypeVar

import torch
from hydra.utils import get_class
from omegaconf import DictConfig
from torch import nn

from ..errors import ConfigError
from ..lie import Pose
from ..models.base import BuildContext, Model
from ..solvers.execution import ExecutionPlan
from ..solvers.runtime import RuntimeOptions
from . import resolvers  # noqa: F401  (registers the config resolvers)
from .typed import RunConfig, typed

PACKAGE_PREFIX = "liedfl_cli.models."


def _typed(run: RunConfig | DictConfig) -> RunConfig:
    """A command passes its `RunConfig`; scripts and tests may pass a composed config."""
    return run if isinstance(run, RunConfig) else typed(run)


def model_class(target: str) -> type[Model]:
    """The class named by `model._target_`: only this package's models are accepted."""
    if not isinstance(target, str) or not target.startswith(PACKAGE_PREFIX):
        raise ConfigError(f"model._target_={target!r}: must name a model class under {PACKAGE_PREFIX}*")
    try:
        cls = get_class(target)
    except Exception:
        raise ConfigError(f"model._target_={target!r}: no such class") from None
    if not (isinstance(cls, type) and issubclass(cls, Model)):
        raise ConfigError(f"model._target_={target!r}: not a liedfl model (a subclass of models.base.Model)")
    if inspect.isabstract(cls):  # Model, ImplicitModel, ...: from_config is not implemented
        raise ConfigError(
            f"model._target_={target!r}: an abstract base class, not a model; pick a model with "
            "model=<name> (liedfl train --help lists them)"
        )
    return cls


def check_group(run: RunConfig, dataset) -> None:
    """The composed `group` must describe the dataset's bodies (dataset files select it)."""
    grp = run.group
    if grp is None:
        return
    want = (int(grp.n_se3), int(grp.n_so3))
    have = (dataset.group.n_se3, dataset.group.n_so3)
    if want != have:
        name = run.dataset.name if run.dataset is not None else None
        raise ConfigError(
            f"group (n_se3={want[0]}, n_so3={want[1]}) does not match dataset '{name}' "
            f"({dataset.group.name}); drop the group override or pick a matching group"
        )


def build_context(run: RunConfig | DictConfig, dataset) -> BuildContext:
    run = _typed(run)
    assert run.train is not None and run.seed is not None, "a train config"
    return BuildContext(
        group=dataset.group,
        h=float(dataset.h),
        seed=int(run.seed),
        epsilon=float(run.train.epsilon),
        forces=run.force or {},
        physics=(dataset.params or {}).get("physics"),
        metadata=dataset.params or {},
        tree=getattr(dataset, "tree", None),
        train_poses=(lambda: dataset.pose("train")) if getattr(dataset, "tree", None) is not None else None,
        total_mass=_total_mass(run),
    )


def _total_mass(run: RunConfig) -> float | None:
    """dataset.total_mass as a positive number, or None; ConfigError for anything else."""
    value = run.dataset.total_mass if run.dataset is not None else None
    if value is None:
        return None
    try:
        m = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.total_mass={value!r}: a positive number (kg) or null") from None
    if not (m > 0 and math.isfinite(m)):
        raise ConfigError(f"dataset.total_mass={value!r}: a positive number (kg) or null")
    return m


def execution_plan() -> ExecutionPlan:
    """The plan of the models this command builds: its `runtime` section as applied by
    `configure_runtime` (`runtime.fused`, `runtime.compile`; the defaults before it runs)."""
    from ..solvers import runtime

    return ExecutionPlan.from_runtime(runtime.current())


def build_model(run: RunConfig | DictConfig, dataset, plan: ExecutionPlan | None = None) -> Model:
    """The model of `run.model` for the dataset's group and step; `model.name` names it. Built on the
    CPU in float64 (the same initial weights whatever the runtime), then moved to the runtime's
    device and dtype (`place`), and given `plan` (default: this command's, `execution_plan`)."""
    run = _typed(run)
    check_group(run, dataset)
    options = dict(run.model or {})
    cls = model_class(options.pop("_target_", None))
    name = str(options.pop("name", cls.__name__.lower()))
    variant = cls.variant_for(options, getattr(dataset, "tree", None) is not None)
    if variant is not None:  # e.g. LieDFLNN on a kinematic tree: the articulated model, same options
        cls = model_class(variant)
    try:
        model = cls.from_config(build_context(run, dataset), **options)
    except ConfigError:
        raise
    except ValueError as e:  # invalid option values: one clear config error
        raise ConfigError(f"model={name}: {e}") from None
    model.name = name
    model.set_plan(plan if plan is not None else execution_plan())
    return place(model)


def placement() -> tuple[torch.device, torch.dtype]:
    """(device, dtype) of this command's models and data: `runtime.device` / `runtime.dtype` as
    applied by `configure_runtime` (cpu / float64 before it runs)."""
    from ..solvers import runtime

    return runtime.placement()


ModuleT = TypeVar("ModuleT", bound=nn.Module)


def place(module: ModuleT) -> ModuleT:
    """`module` moved to the runtime's device and dtype (in place; floating-point parameters and
    buffers only). A no-op on the CPU in float64."""
    device, dtype = placement()
    return module.to(device=device, dtype=dtype)


def data_pose(dataset, traj_idx=None) -> Pose:
    """`dataset.pose(traj_idx)` (trajectories on the CPU in float64 as loaded) converted to the
    runtime's device and dtype."""
    device, dtype = placement()
    return dataset.pose(traj_idx, dtype=dtype, device=device)


def configure_runtime(run: RunConfig | RuntimeOptions | DictConfig):
    """Apply the runtime settings (threads, fused paths, compilation, device, dtype) to this process; a job
    of a joblib sweep runs on one thread (the jobs share the cores). `runtime.device=cuda` without a
    CUDA device: ConfigError."""
    from ..solvers import runtime

    parallel = False
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            parallel = "joblib" in str(HydraConfig.get().launcher.get("_target_", "")).lower()
    except Exception:  # no Hydra context (tests, scripts): not a sweep job
        parallel = False
    opts = run if isinstance(run, RuntimeOptions) else _typed(run).runtime
    return runtime.configure(opts, parallel_job=parallel)
