"""`DatasetConfig`: the `dataset` section as the data layer receives it (built once by
`liedfl_cli/config/typed.py` from a command's validated config; plain Python, no config library).

The fields every scene shares are attributes; what only some scenes have (`files` of the mocap scene,
`path`, `columns`, `rotation`, ... of a user's file) is in `scene`, a plain mapping checked by the
scene's generator (the keys each scene accepts: conf/dataset/<scene>.yaml). `as_dict()` gives the
section back exactly as configured (the same keys, so the cache hash of a config does not change).

`scenes.dataset_section` is the one check of a dataset section (the scene's registry, its common
fields, noise and smoothing; `val_fraction` here), made once at the command's door; the checked form
travels in `checked`, so `scenes.get_dataset` / `dataset_path` / `generate` do not check again.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from ..errors import ConfigError


@dataclass
class DatasetConfig:
    """One dataset section. Numbers are kept as configured (the generators check them: one-line
    `ConfigError` naming the key); `None` where a scene leaves a field out or null."""

    name: str
    h: float | None = None
    n_trajectories: int | None = None
    steps: int | None = None
    train_steps: int | None = None  # null (file / import): all the steps (`files.complete_steps`)
    rollout_steps: int | None = None
    test_fraction: float | None = None
    n_test: int | None = None
    seed: int | None = None
    val_fraction: float | None = None  # read at train time only (commands/validation.py)
    total_mass: float | None = None  # articulated: the scale gauge (kg), read at train/export time only
    physics: dict[str, Any] | None = None
    initial: dict[str, Any] | None = None
    solver: dict[str, Any] | None = None  # the simulator's tolerances (data/physics.py SolverOptions)
    noise: dict[str, Any] | None = None
    smoothing: dict[str, Any] | None = None
    scene: dict[str, Any] = field(default_factory=dict)  # the scene's own keys
    present: tuple[str, ...] = ()  # the configured keys, in order ("" = every common field)
    # the section as the generators take it, once checked (`scenes.dataset_section`); None: not yet
    checked: dict[str, Any] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = self.val_fraction  # read at train time only, but refused wherever it is configured
        if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < 1):
            raise ConfigError(f"dataset.val_fraction={v!r}: must be a number in [0, 1) (0: no validation)")

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> DatasetConfig:
        """From a plain nested mapping (a resolved `dataset` section); ConfigError without a name."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"dataset config must be a mapping, got {type(d).__name__}")
        if not isinstance(d.get("name"), str):
            raise ConfigError(f"dataset.name={d.get('name')!r}: must be a scene name")
        common = {f.name for f in fields(cls)} - {"scene", "present", "checked"}
        d = copy.deepcopy(dict(d))
        return cls(
            **{k: v for k, v in d.items() if k in common},
            scene={k: v for k, v in d.items() if k not in common},
            present=tuple(d),
        )

    def as_dict(self) -> dict[str, Any]:
        """The section as a plain nested dict with the configured keys (a deep copy)."""
        out = {}
        for key in self.present:
            out[key] = self.scene[key] if key in self.scene else getattr(self, key)
        for key, value in self.scene.items():  # keys set after construction
            out.setdefault(key, value)
        return copy.deepcopy(out)

    def get(self, key: str, default: Any = None) -> Any:
        """The value of `key` (a common field or a scene key), `default` when absent."""
        if key in self.scene:
            return self.scene[key]
        return getattr(self, key) if key in self.present else default


__all__ = ["DatasetConfig"]
