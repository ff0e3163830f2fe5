"""The optimisers and learning-rate schedules of `liedfl train`, each a builder `build_<name>`
for a name the config field declares (`OptimizerConfig.name` / `.schedule` in config/typed.py, the one
list): `train.optimizer.name` picks from `OPTIMIZERS`, `train.optimizer.schedule` from `SCHEDULES` (an
added optimiser is its name on the field and one function here).

On the fused paths (`runtime.fused`) the optimisers run without per-tensor Python:
`fused_optim.FusedSOAP` (the library's kernels, bit for bit) and Adam's foreach update.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from omegaconf import DictConfig

from ..config.fields import allowed
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

OPTIMIZERS: dict[str, OptimizerBuilder] = {n: globals()[f"build_{n}"] for n in allowed(OptimizerConfig, "name")}
"""`train.optimizer.name` -> its builder(params, config, fused): `build_<name>` for each name the config
field declares (config/typed.py; a declared name without a builder fails at import)."""
SCHEDULES: dict[str, ScheduleBuilder] = {n: globals()[f"build_{n}"] for n in allowed(OptimizerConfig, "schedule")}
"""`train.optimizer.schedule` -> its builder(optimizer, epochs) (None: no schedule)."""


def make_optimizer(params, cfg_opt: OptimizerConfig | DictConfig) -> torch.optim.Optimizer:
    """The optimiser `train.optimizer.name` names, over `params`; unknown name -> one-line ConfigError."""
    cfg: OptimizerConfig = (  # scripts and tests may pass the section as is
        cfg_opt if isinstance(cfg_opt, OptimizerConfig) else section(OptimizerConfig, cfg_opt, "train.optimizer")
    )
    build = OPTIMIZERS.get(cfg.name)
    if build is None:
        raise ConfigError(f"train.optimizer.name={cfg.name!r}: choose one of {', '.join(OPTIMIZERS)}")
    return build(params, cfg, runtime.current().fused)


def make_schedule(opt: torch.optim.Optimizer, name: str, epochs: int):
    """The per-epoch learning-rate schedule `train.optimizer.schedule` names (None: constant);
    unknown name -> one-line ConfigError."""
    build = SCHEDULES.get(name)
    if build is None:
        raise ConfigError(f"train.optimizer.schedule={name!r}: choose one of {', '.join(SCHEDULES)}")
    return build(opt, epochs)
