"""What every scene generator shares: dataset-config handling, the cache hash, the train/test split,
random initial conditions and the `params` dict of a generated dataset.

The generators (`scenes_rigid`, `scenes_multibody`, `mocap`) import this module; the scene registry
(`scenes.SCENES`) imports the generators. Nothing here knows which scenes exist.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from ..errors import ConfigError
from ..lie import so3
from .physics import SolverOptions

GENERATOR_VERSION = 1
"""Bump when generated data would change for the same config (it is part of the cache hash)."""

NON_GENERATOR_KEYS = ("train_steps", "rollout_steps", "val_fraction", "total_mass")
"""Config keys that select how data is used, not what is generated (excluded from the hash)."""

TRAIN_TIME_KEYS = ("val_fraction", "total_mass")
"""Dataset keys read by the trainer only (the validation split, taken from the train split at train
time: liedfl_cli/commands/validation.py); `to_dict` drops them, so no generator sees them."""

REQUIRED_KEYS = (
    "name",
    "h",
    "n_trajectories",
    "steps",
    "train_steps",
    "rollout_steps",
    "test_fraction",
    "n_test",
    "seed",
    "physics",
    "initial",
    "solver",
)
"""Fields every dataset config has (conf/dataset/*.yaml), in this order."""


# --------------------------------------------------------------------------- config handling
def _plain_copy(x):
    """A deep copy with every mapping a dict and every non-string sequence other than a tuple a list
    (any Mapping / Sequence implementation a caller passes becomes plain data)."""
    if isinstance(x, Mapping):
        return {k: _plain_copy(v) for k, v in x.items()}
    if isinstance(x, tuple):
        return tuple(_plain_copy(v) for v in x)
    if isinstance(x, Sequence) and not isinstance(x, (str, bytes)):
        return [_plain_copy(v) for v in x]
    return copy.deepcopy(x)


def to_dict(cfg) -> dict[str, Any]:
    """DatasetConfig / Mapping -> plain nested dict (a copy), without TRAIN_TIME_KEYS."""
    from .dataset_config import DatasetConfig

    if isinstance(cfg, DatasetConfig):
        out = cfg.as_dict()
    elif isinstance(cfg, Mapping):
        out = _plain_copy(cfg)
    else:
        raise ConfigError(f"dataset config must be a mapping, got {type(cfg).__name__}")
    for k in TRAIN_TIME_KEYS:
        out.pop(k, None)
    return out


def _canonical(x):
    """Normalise for hashing: numbers -> float (so 1 and 1.0 agree), tuples -> lists, keys sorted later."""
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if isinstance(x, (int, float, np.integer, np.floating)):
        return float(x)
    if isinstance(x, Mapping):
        return {str(k): _canonical(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_canonical(v) for v in x]
    raise ConfigError(f"dataset config value {x!r} of type {type(x).__name__} is not JSON-compatible")


OPTIONAL_KEYS = ("noise", "smoothing")
"""Keys every dataset config may have (data/transforms.py); when off (null, or a noise of zeros) they are
left out of the hash, so datasets cached before they existed keep their names."""


def _option_off(key: str, value) -> bool:
    if value is None:
        return True
    if key == "noise" and isinstance(value, Mapping):
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) and v == 0 for v in value.values())
    return False


def generator_config(cfg) -> dict[str, Any]:
    """The part of the dataset config that determines the generated data (plus the generator version)."""
    c = to_dict(cfg)
    out = {k: v for k, v in c.items() if k not in NON_GENERATOR_KEYS and not (k in OPTIONAL_KEYS and _option_off(k, v))}
    out["generator_version"] = GENERATOR_VERSION
    return out


def config_hash(cfg) -> str:
    """First 10 hex digits of the SHA-1 of the canonical JSON of `generator_config(cfg)`."""
    text = json.dumps(_canonical(generator_config(cfg)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def check_config(c: dict, scenes: Mapping | None = None) -> dict:
    """Check the common fields of a dataset config; returns it (ConfigError on problems).

    scenes: the registry to check `name` against (the front door in `scenes` passes `SCENES`;
    a generator called directly does not know the registry)."""
    missing = [k for k in REQUIRED_KEYS if k not in c]
    if missing:
        raise ConfigError(f"dataset config is missing {missing} (have {sorted(c)})")
    if scenes is not None and c["name"] not in scenes:
        raise ConfigError(f"dataset.name={c['name']!r} is not a registered scene; choose one of {sorted(scenes)}")

    def num(key, kind=float, positive=True):
        v = c[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and int(v) != v):
            raise ConfigError(f"dataset.{key} must be {'an integer' if kind is int else 'a number'}, got {v!r}")
        if positive and not v > 0:
            raise ConfigError(f"dataset.{key} must be positive, got {v!r}")
        return kind(v)

    files = c.get("files", ())  # scenes of recordings: n_trajectories follows the files, so check them first
    if "files" in c and (not isinstance(files, (list, tuple)) or not files):
        raise ConfigError(f"dataset.files must be a non-empty list of recordings, got {files!r}")
    num("h"), num("n_trajectories", int), num("steps", int), num("train_steps", int), num("rollout_steps", int)
    num("seed", int, positive=False)
    if not 0.0 <= num("test_fraction", positive=False) < 1.0:
        raise ConfigError(f"dataset.test_fraction must lie in [0, 1), got {c['test_fraction']!r}")
    if c["n_test"] is not None and not (num("n_test", int, positive=False) >= 0 and c["n_test"] <= c["n_trajectories"]):
        raise ConfigError(
            f"dataset.n_test must be null or an integer in [0, n_trajectories={c['n_trajectories']}], "
            f"got {c['n_test']!r}"
        )
    need = max(int(c["train_steps"]), int(c["rollout_steps"]))
    if int(c["steps"]) < need:
        raise ConfigError(f"dataset.steps={c['steps']} is shorter than max(train_steps, rollout_steps)={need}")
    from .memory import check_fits

    # a lower bound: one body's R (9) and p (3) in float64 per pose
    check_fits(
        f"dataset.n_trajectories={c['n_trajectories']} x dataset.steps={c['steps']}",
        float(c["n_trajectories"]) * (float(c["steps"]) + 1) * 12 * 8,
    )
    for sub in ("physics", "initial", "solver"):
        if not isinstance(c[sub], Mapping):
            raise ConfigError(f"dataset.{sub} must be a mapping, got {c[sub]!r}")
    SolverOptions.from_config(c["solver"])
    return c


def section(c: dict, key: str, allowed: tuple[str, ...], numbers: tuple[str, ...] = ()) -> dict:
    """The mapping `dataset.<key>` with exactly the keys `allowed` (ConfigError naming the key otherwise);
    the keys in `numbers` must be finite real numbers (returned as floats)."""
    if not isinstance(c.get(key), Mapping):
        raise ConfigError(f"dataset.{key} is required for scene {c['name']!r} (keys {list(allowed)})")
    d = dict(c[key])
    missing, unknown = [k for k in allowed if k not in d], sorted(set(d) - set(allowed))
    if missing or unknown:
        raise ConfigError(
            f"dataset.{key} for scene {c['name']!r}: missing {missing}, unknown {unknown} (expected {list(allowed)})"
        )
    for name in numbers:
        d[name] = finite_number(d[name], f"{key}.{name}")
    return d


def finite_number(x, name: str) -> float:
    """`dataset.<name>` as a float: a finite real number (not a boolean or a string), ConfigError otherwise."""
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
        raise ConfigError(f"dataset.{name} must be a finite number, got {x!r}")
    return float(x)


def vector(x, n: int, name: str) -> list[float]:
    """A list of n finite numbers from `dataset.<name>` (ConfigError otherwise)."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ConfigError(f"dataset.{name} must be a list of {n} finite numbers, got {x!r}")
    return [float(v) for v in a]


def rigid_physics(c: dict, dim: int) -> dict:
    """Validated `dataset.physics` of a single rigid body {J (3), m, rho (3), g, D (dim diagonal or dim x dim)}
    as plain floats."""
    ph = section(c, "physics", ("J", "m", "rho", "g", "D"))
    for key, n in (("J", 3), ("rho", 3)):
        if np.shape(ph[key]) != (n,):
            raise ConfigError(f"dataset.physics.{key} must be a list of {n} numbers, got {ph[key]!r}")
    J, D = np.asarray(ph["J"], float), np.asarray(ph["D"], float)
    if (J <= 0).any():
        raise ConfigError(f"dataset.physics.J must have positive diagonal entries, got {ph['J']}")
    D_out: list[float] | list[list[float]]
    if D.shape == (dim,):
        if (D < 0).any():
            raise ConfigError(f"dataset.physics.D must be non-negative (positive semidefinite), got {ph['D']}")
        D_out = [float(x) for x in D]
    elif D.shape == (dim, dim):  # a full damping matrix (symmetric positive semidefinite)
        if not np.isfinite(D).all() or np.abs(D - D.T).max() > 1e-12 * max(1.0, np.abs(D).max()):
            raise ConfigError(f"dataset.physics.D must be symmetric, got {ph['D']}")
        if np.linalg.eigvalsh(D).min() < -1e-12 * max(1.0, np.abs(D).max()):
            raise ConfigError(f"dataset.physics.D must be positive semidefinite, got {ph['D']}")
        D_out = [[float(x) for x in row] for row in D]
    else:
        raise ConfigError(
            f"dataset.physics.D must be a list of {dim} numbers (diagonal) or a {dim}x{dim} matrix, got {ph['D']!r}"
        )
    from .checks import check_physics

    check_physics({"J": ph["J"], "m": ph["m"], "rho": ph["rho"], "g": ph["g"], "D": D_out}, 1, dim,
                  prefix="dataset.physics", error=ConfigError)  # fmt: skip
    return {
        "J": [float(x) for x in ph["J"]],
        "m": float(ph["m"]),
        "rho": [float(x) for x in ph["rho"]],
        "g": float(ph["g"]),
        "D": D_out,
    }


# --------------------------------------------------------------------------- sampling and splitting
def make_split(n_trajectories: int, test_fraction: float, n_test: int | None, seed) -> dict[str, np.ndarray]:
    """Random split by trajectory: sorted disjoint index arrays 'train' and 'test'."""
    k = int(n_test) if n_test is not None else int(round(test_fraction * n_trajectories))
    perm = np.random.default_rng(seed).permutation(n_trajectories)
    return {"train": np.sort(perm[k:]).astype(np.int64), "test": np.sort(perm[:k]).astype(np.int64)}


def rngs(seed: int):
    """Independent streams for initial conditions and for the split (split does not move with ICs)."""
    ic, split = np.random.SeedSequence(int(seed)).spawn(2)
    return np.random.default_rng(ic), split


def haar_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """n Haar-uniform rotations (normalised Gaussian quaternions), (n, 3, 3)."""
    return so3.from_quaternion(torch.from_numpy(rng.standard_normal((n, 4)))).numpy()


def uniform_ball(rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
    """n points uniform in the ball of the given radius in R^3, (n, 3)."""
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return radius * rng.random((n, 1)) ** (1.0 / 3.0) * d


def sample_times(c: dict) -> np.ndarray:
    """h * (0, 1, ..., steps): the sample times of a generated trajectory."""
    return float(c["h"]) * np.arange(int(c["steps"]) + 1, dtype=np.float64)


# --------------------------------------------------------------------------- dataset params
def _json_native(d):
    return json.loads(json.dumps(d, sort_keys=True))


def dataset_params(c: dict, **fields) -> dict:
    """`params` of a generated dataset: the generator config, its hash and version, then `fields` in order."""
    return {
        "config": _json_native(generator_config(c)),
        "config_hash": config_hash(c),
        "generator_version": GENERATOR_VERSION,
        **fields,
    }


def simulation_info(sim) -> dict:
    """params["simulation"] of a simulated dataset."""
    return {"max_orthogonality_drift": sim.max_drift, "nfev": sim.nfev}


__all__ = [
    "GENERATOR_VERSION",
    "NON_GENERATOR_KEYS",
    "OPTIONAL_KEYS",
    "REQUIRED_KEYS",
    "to_dict",
    "generator_config",
    "config_hash",
    "check_config",
    "section",
    "vector",
    "rigid_physics",
    "make_split",
    "rngs",
    "haar_rotations",
    "uniform_ball",
    "sample_times",
    "dataset_params",
    "simulation_info",
]
