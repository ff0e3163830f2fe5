"""Build the model a config asks for: LieDFLNN (baseline=none) or a baseline (later issues)."""

from __future__ import annotations

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ..errors import ConfigError
from .liedflnn import LieDFLNN


def resolve_potential(cfg_model, dataset) -> str:
    """`auto` -> no potential network when the scene is known to have none (g = 0, one body)."""
    pot = cfg_model.get("potential", "auto")
    if pot != "auto":
        return pot
    if "potential" in (cfg_model.get("known") or ()):
        return "none"  # the known (true) potential replaces the network
    physics = (dataset.params or {}).get("physics") or {}
    if dataset.group.n_bodies == 1 and "g" in physics and float(physics["g"]) == 0.0:
        return "none"
    return "mlp"


def check_group(cfg: DictConfig, dataset) -> None:
    """The composed `group` must describe the dataset's bodies (dataset files select it)."""
    grp = cfg.get("group")
    if grp is None:
        return
    want = (int(grp.n_se3), int(grp.n_so3))
    have = (dataset.group.n_se3, dataset.group.n_so3)
    if want != have:
        raise ConfigError(
            f"group (n_se3={want[0]}, n_so3={want[1]}) does not match dataset '{cfg.dataset.name}' "
            f"({dataset.group.name}); drop the group override or pick a matching group"
        )


def build_model(cfg: DictConfig, dataset):
    """Instantiate `cfg.model` for the dataset's group and step (LieDFLNN when baseline is none)."""
    check_group(cfg, dataset)
    if cfg.baseline.name != "none":
        from .baselines import build_baseline

        return build_baseline(cfg, dataset)
    forces = OmegaConf.to_container(cfg.force, resolve=True) if cfg.get("force") else {}
    # _partial_ so that runtime objects (the group layout) are passed as they are, not merged
    # into the config.
    factory = instantiate(cfg.model, _partial_=True, _convert_="all")
    extra = {}
    if cfg.model.get("known"):  # known (frozen) parts take the scene's true values
        extra["physics"] = (dataset.params or {}).get("physics")
    try:
        model = factory(
            G=dataset.group,
            h=dataset.h,
            potential=resolve_potential(cfg.model, dataset),
            forces=forces,
            epsilon=float(cfg.train.epsilon),
            seed=int(cfg.seed),
            **extra,
        )
    except ValueError as e:  # bad model/force options: one clear config error
        raise ConfigError(str(e)) from None
    if not isinstance(model, LieDFLNN):
        raise ConfigError(f"model._target_ must build a LieDFLNN, got {type(model).__name__}")
    return model
