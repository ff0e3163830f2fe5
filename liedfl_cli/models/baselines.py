"""Baselines of the paper, selected with `baseline=<name>` (registry keys = config option names)."""
from __future__ import annotations

from ..data.errors import ConfigError

BASELINES: dict = {}


def build_baseline(cfg, dataset):
    name = cfg.baseline.name
    if name not in BASELINES:
        raise ConfigError(f"baseline={name!r} is not available; choose none or one of {sorted(BASELINES) or '[]'}")
    return BASELINES[name](cfg, dataset)
