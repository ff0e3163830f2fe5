"""Dataclass schemas of the config sections owned by liedfl: a misspelled or mistyped key in
any yaml file (experiment, budget, ...) fails with a one-line ConfigError naming the key."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from .errors import ConfigError


@dataclass
class OptimizerSchema:
    name: str = "soap"
    lr: float = 3e-3
    weight_decay: float = 0.0
    schedule: str = "constant"


@dataclass
class TrainSchema:
    epochs: int = 1000
    batch_size: int = 1024
    optimizer: OptimizerSchema = field(default_factory=OptimizerSchema)
    w_del: float = 0.5
    w_reg: float = 0.5
    reg_points: int = 10
    reg_form: str = "relu"
    epsilon: float = 10.0
    checkpoint_every: Any = "auto"  # auto | positive int (checked in train.checkpoint_interval)


@dataclass
class RolloutSchema:
    enabled: bool = True
    steps: int | None = None
    max_trajectories: int | None = None
    reference: bool = True


@dataclass
class SolverSchema:
    tol: float = 1e-5
    max_iter: int = 10
    max_halvings: int = 6


@dataclass
class ModelSchema:
    _target_: str = "liedfl_cli.models.liedflnn.LieDFLNN"
    name: str = "liedflnn"
    potential: Any = "auto"  # auto | none | mlp | uniform_gravity | a list of mlp, uniform_gravity
    residual: str = "fast"
    mlp_width: int = 64
    mlp_depth: int = 3
    init_jitter: float = 0.1
    known: list[str] = field(default_factory=list)  # parts set to the scene's true values and frozen
    gravity: Any = "auto"  # field strength of uniform_gravity: auto (the data's g, else 9.81) | a number
    learn_gravity_direction: bool = False


@dataclass
class GroupSchema:
    n_se3: int = 0
    n_so3: int = 1


SECTIONS: dict[str, Any] = {
    "train": TrainSchema,
    "rollout": RolloutSchema,
    "solver": SolverSchema,
    "group": GroupSchema,
}
CHOICES = {
    ("train", "reg_form"): ("relu", "gaussian"),
    ("train", "optimizer", "name"): ("soap", "adam"),
    ("train", "optimizer", "schedule"): ("constant", "cosine"),
    ("model", "potential"): ("auto", "mlp", "none", "uniform_gravity"),  # or a list of mlp, uniform_gravity
    ("model", "residual"): ("fast", "generic"),
}


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError for unknown keys, wrong types or invalid choices in known sections."""
    for name, schema in SECTIONS.items():
        if name not in cfg or (name == "rollout" and cfg.get("task_name") == "eval"):
            continue  # (`liedfl eval rollout=<file>`: there `rollout` is a path, not this section)
        try:
            OmegaConf.merge(OmegaConf.structured(schema), OmegaConf.to_container(cfg[name], resolve=True))
        except OmegaConfBaseException as e:
            msg = str(e).splitlines()[0]
            key = getattr(e, "full_key", None) or ""
            raise ConfigError(f"config section '{name}': {msg}" + (f" (key {name}.{key})" if key else "")) from None
    if "model" in cfg and cfg.model.get("_target_", "").endswith("LieDFLNN"):
        try:
            OmegaConf.merge(OmegaConf.structured(ModelSchema), OmegaConf.to_container(cfg.model, resolve=True))
        except OmegaConfBaseException as e:
            key = getattr(e, "full_key", None) or ""
            raise ConfigError(
                f"config section 'model': {str(e).splitlines()[0]}" + (f" (key model.{key})" if key else "")
            ) from None
        known = cfg.model.get("known") or []
        if known:
            from .models.liedflnn import KNOWN_PARTS

            bad = [k for k in known if k not in KNOWN_PARTS]
            if bad:
                raise ConfigError(
                    f"model.known={list(known)}: unknown part {bad[0]!r}; choose from {', '.join(KNOWN_PARTS)}"
                )
    for path, allowed in CHOICES.items():
        node = cfg
        for p in path:
            node = node.get(p) if isinstance(node, DictConfig) else None
            if node is None:
                break
        if isinstance(node, ListConfig) and path == ("model", "potential"):
            node = next((x for x in node if x not in ("mlp", "uniform_gravity")), None)
        if node is not None and node not in allowed:
            raise ConfigError(f"{'.'.join(path)}={node!r}: choose one of {', '.join(allowed)}")
