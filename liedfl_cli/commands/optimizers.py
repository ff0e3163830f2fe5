"""The optimisers and learning-rate schedules of `liedfl train`, each a builder in a registry whose
names are the config's values: `train.optimizer.name` picks from `OPTIMIZERS`, `train.optimizer.schedule`
from `SCHEDULES` (an added builder is one function and one entry; `schema.py` lists the names a
config may give).

On the fused paths (`runtime.fused`) the optimisers run without per-tensor Python:
`fused_optim.FusedSOAP` (the library's kernels, bit for bit) and Adam's foreach update.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from omegaconf import DictConfig

from ..config.typed import OptimizerConfig, section
from ..errors import ConfigError
from ..solvers import runtime


def build_soap(params, cfg: OptimizerConfig, fused: bool) -> torch.optim.Optimizer:
    """SOAP (pytorch_optimizer's; `FusedSOAP` on the fused paths, the same numbers)."""
    from pytorch_optimizer import SOAP

    from .fused_optim import FusedSOAP

    return (FusedSOAP if fused else SOAP)(
        params,
        lr=cfg.lr,
        weight_decay=cfg.weight_decay,
        precondition_frequency=int(cfg.precondition_frequency),
        max_precondition_dim=int(cfg.max_precondition_dim),
    )


def build_adam(params, cfg: OptimizerConfig, fused: bool) -> torch.optim.Optimizer:
    """torch's Adam (its foreach update on the fused paths)."""
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, foreach=fused)


def build_constant(opt: torch.optim.Optimizer, epochs: int) -> None:
    """No schedule: the learning rate stays `train.optimizer.lr` (the paper's)."""
    return None


def build_cosine(opt: torch.optim.Optimizer, epochs: int) -> torch.optim.lr_scheduler.LRScheduler:
    """Cosine decay over the run's epochs to 1 % of the learning rate."""
    return torch.optim.lr_scheduler.CosineAnnealingLR(
        opt, T_max=max(epochs, 1), eta_min=0.01 * opt.param_groups[0]["lr"]
    )


OptimizerBuilder = Callable[[list, OptimizerConfig, bool], torch.optim.Optimizer]
ScheduleBuilder = Callable[[torch.optim.Optimizer, int], "torch.optim.lr_scheduler.LRScheduler | None"]

OPTIMIZERS: dict[str, OptimizerBuilder] = {"soap": build_soap, "adam": build_adam}
"""`train.optimizer.name` -> its builder(params, config, fused)."""
SCHEDULES: dict[str, ScheduleBuilder] = {"constant": build_constant, "cosine": build_cosine}
"""`train.optimizer.schedule` -> its builder(optimizer, epochs) (None: no schedule)."""


def _choices(names) -> str:
    quoted = [repr(n) for n in names]
    return " or ".join([", ".join(quoted[:-1]), quoted[-1]] if len(quoted) > 1 else quoted)


def make_optimizer(params, cfg_opt: OptimizerConfig | DictConfig) -> torch.optim.Optimizer:
    """The optimiser `train.optimizer.name` names, over `params`; unknown name -> one-line ConfigError."""
    cfg: OptimizerConfig = (  # scripts and tests may pass the section as is
        cfg_opt if isinstance(cfg_opt, OptimizerConfig) else section(OptimizerConfig, cfg_opt, "train.optimizer")
    )
    build = OPTIMIZERS.get(cfg.name)
    if build is None:
        raise ConfigError(f"train.optimizer.name must be {_choices(OPTIMIZERS)}, got {cfg.name!r}")
    return build(params, cfg, runtime.current().fused)


def make_schedule(opt: torch.optim.Optimizer, name: str, epochs: int):
    """The per-epoch learning-rate schedule `train.optimizer.schedule` names (None: constant);
    unknown name -> one-line ConfigError."""
    build = SCHEDULES.get(name)
    if build is None:
        raise ConfigError(f"train.optimizer.schedule must be {_choices(SCHEDULES)}, got {name!r}")
    return build(opt, epochs)
