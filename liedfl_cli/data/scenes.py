"""Ground-truth scenes of the paper's experiments, registered by name in `SCENES`.

Each generator takes a dataset config (omegaconf DictConfig or plain dict, the fields of
conf/dataset/*.yaml) and returns a `Dataset`.  `get_dataset(cfg, data_dir)` caches the result as
`<data_dir>/<name>-<hash>.h5`, keyed by the generator-relevant part of the config.

Config fields: name, h, n_trajectories, steps (generated length N), train_steps, rollout_steps,
test_fraction, n_test (null or int), seed, physics {J (diag), m, rho, g, D (diag, length 3 or 6)},
initial {scene specific}, solver {method, rtol, atol}.  train_steps / rollout_steps only tell
the consumers how much of each trajectory to use; they do not change the data (nor the hash).
"""

from __future__ import annotations

import copy
import hashlib
import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import ConfigError, DatasetError
from ..lie import so3
from .hdf5 import Dataset, load_dataset, save_dataset
from .physics import RigidBodySE3, RigidBodySO3, Simulation, SolverOptions, simulate_se3, simulate_so3

GENERATOR_VERSION = 1
"""Bump when generated data would change for the same config (it is part of the cache hash)."""

NON_GENERATOR_KEYS = ("train_steps", "rollout_steps")
"""Config keys that select how data is used, not what is generated (excluded from the hash)."""

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

Generator = Callable[..., Dataset]
SCENES: dict[str, Generator] = {}


def register_scene(name: str):
    """Decorator adding a generator `fn(cfg, progress=None) -> Dataset` to `SCENES` under `name`."""

    def deco(fn: Generator) -> Generator:
        if name in SCENES:
            raise ValueError(f"scene {name!r} registered twice")
        SCENES[name] = fn
        return fn

    return deco


# --------------------------------------------------------------------------- config handling
def to_dict(cfg) -> dict[str, Any]:
    """DictConfig / Mapping -> plain nested dict (interpolations resolved)."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"dataset config must be a mapping, got {type(cfg).__name__}")
    return copy.deepcopy(dict(cfg))


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


def generator_config(cfg) -> dict[str, Any]:
    """The part of the dataset config that determines the generated data (plus the generator version)."""
    c = to_dict(cfg)
    out = {k: v for k, v in c.items() if k not in NON_GENERATOR_KEYS}
    out["generator_version"] = GENERATOR_VERSION
    return out


def config_hash(cfg) -> str:
    """First 10 hex digits of the SHA-1 of the canonical JSON of `generator_config(cfg)`."""
    text = json.dumps(_canonical(generator_config(cfg)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def dataset_path(cfg, data_dir="outputs/data") -> Path:
    """`<data_dir>/<name>-<config_hash>.h5`."""
    return Path(data_dir) / f"{_check(to_dict(cfg))['name']}-{config_hash(cfg)}.h5"


def _check(c: dict) -> dict:
    """Check the common fields of a dataset config; returns it (ConfigError on problems)."""
    missing = [k for k in REQUIRED_KEYS if k not in c]
    if missing:
        raise ConfigError(f"dataset config is missing {missing} (have {sorted(c)})")
    if c["name"] not in SCENES:
        raise ConfigError(f"dataset.name={c['name']!r} is not a registered scene; choose one of {sorted(SCENES)}")

    def num(key, kind=float, positive=True):
        v = c[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and int(v) != v):
            raise ConfigError(f"dataset.{key} must be {'an integer' if kind is int else 'a number'}, got {v!r}")
        if positive and not v > 0:
            raise ConfigError(f"dataset.{key} must be positive, got {v!r}")
        return kind(v)

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
    for sub in ("physics", "initial", "solver"):
        if not isinstance(c[sub], Mapping):
            raise ConfigError(f"dataset.{sub} must be a mapping, got {c[sub]!r}")
    SolverOptions.from_config(c["solver"])
    return c


def _keys(c: dict, sub: str, allowed: tuple[str, ...]) -> dict:
    d = dict(c[sub])
    missing, unknown = [k for k in allowed if k not in d], sorted(set(d) - set(allowed))
    if missing or unknown:
        raise ConfigError(
            f"dataset.{sub} for scene {c['name']!r}: missing {missing}, unknown {unknown} (expected {list(allowed)})"
        )
    return d


def make_split(n_trajectories: int, test_fraction: float, n_test: int | None, seed) -> dict[str, np.ndarray]:
    """Random split by trajectory: sorted disjoint index arrays 'train' and 'test'."""
    k = int(n_test) if n_test is not None else int(round(test_fraction * n_trajectories))
    perm = np.random.default_rng(seed).permutation(n_trajectories)
    return {"train": np.sort(perm[k:]).astype(np.int64), "test": np.sort(perm[:k]).astype(np.int64)}


def _rngs(seed: int):
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


def _assemble(c: dict, sim: Simulation, body, kinds: list[str], split_seed, scene_params: dict) -> Dataset:
    T = sim.R.shape[0]
    R = sim.R[:, :, None]
    if sim.p is not None:
        p, v = sim.p[:, :, None], sim.v[:, :, None]
        tau_ext, f_ext = body.external_wrench(sim.R, sim.p, sim.w, sim.v)
        energy = body.energy(sim.R, sim.p, sim.w, sim.v)
        f_ext = f_ext[:, :, None]
    else:
        p = np.zeros(sim.R.shape[:2] + (0, 3))
        v, f_ext = p.copy(), p.copy()
        tau_ext = body.external_torque(sim.R, sim.w)
        energy = body.energy(sim.R, sim.w)
    gen = generator_config(c)
    params = {
        "config": _canonical_json_native(gen),
        "config_hash": config_hash(c),
        "generator_version": GENERATOR_VERSION,
        "physics": scene_params,
        "simulation": {"max_orthogonality_drift": sim.max_drift, "nfev": sim.nfev},
    }
    return Dataset(
        R=R,
        p=p,
        h=float(c["h"]),
        scene=c["name"],
        body_names=["body"],
        body_kinds=kinds,
        params=params,
        seed=int(c["seed"]),
        split=make_split(T, float(c["test_fraction"]), c["n_test"], split_seed),
        extras={"omega": sim.w[:, :, None], "v": v, "tau_ext": tau_ext[:, :, None], "f_ext": f_ext, "energy": energy},
        t=sim.t,
    )


def _canonical_json_native(d):
    return json.loads(json.dumps(d, sort_keys=True))


def _times(c: dict) -> np.ndarray:
    return float(c["h"]) * np.arange(int(c["steps"]) + 1, dtype=np.float64)


def _physics(c: dict, dim: int) -> dict:
    ph = _keys(c, "physics", ("J", "m", "rho", "g", "D"))
    for key, n in (("J", 3), ("rho", 3), ("D", dim)):
        if np.shape(ph[key]) != (n,):
            raise ConfigError(f"dataset.physics.{key} must be a list of {n} numbers, got {ph[key]!r}")
    J, D = np.asarray(ph["J"], float), np.asarray(ph["D"], float)
    if (J <= 0).any():
        raise ConfigError(f"dataset.physics.J must have positive diagonal entries, got {ph['J']}")
    if (D < 0).any():
        raise ConfigError(f"dataset.physics.D must be non-negative (positive semidefinite), got {ph['D']}")
    return {
        "J": [float(x) for x in ph["J"]],
        "m": float(ph["m"]),
        "rho": [float(x) for x in ph["rho"]],
        "g": float(ph["g"]),
        "D": [float(x) for x in ph["D"]],
    }


# --------------------------------------------------------------------------- scenes
@register_scene("heavy_so3")
def heavy_so3(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 1: heavy rigid body on SO(3) with damping; R0 = I, w0 = omega_scale * U(ball(omega_radius))."""
    c = _check(to_dict(cfg))
    ph = _physics(c, 3)
    ini = _keys(c, "initial", ("omega_scale", "omega_radius"))
    rng, split_seed = _rngs(c["seed"])
    T = int(c["n_trajectories"])
    w0 = float(ini["omega_scale"]) * uniform_ball(rng, T, float(ini["omega_radius"]))
    R0 = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    body = RigidBodySO3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_so3(body, R0, w0, _times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["so3"], split_seed, ph)


@register_scene("free_rigid_body")
def free_rigid_body(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 2: rigid body on SO(3) (g = 0 by default) with damping; Haar R0, w0 ~ N(0, omega_std^2 I)."""
    c = _check(to_dict(cfg))
    ph = _physics(c, 3)
    ini = _keys(c, "initial", ("omega_std",))
    rng, split_seed = _rngs(c["seed"])
    T = int(c["n_trajectories"])
    R0 = haar_rotations(rng, T)
    w0 = float(ini["omega_std"]) * rng.standard_normal((T, 3))
    body = RigidBodySO3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_so3(body, R0, w0, _times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["so3"], split_seed, ph)


@register_scene("heavy_se3")
def heavy_se3(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 3: rigid body on SE(3) in gravity with damping on (w, v); Haar R0, Gaussian p0, w0, v0."""
    c = _check(to_dict(cfg))
    ph = _physics(c, 6)
    ini = _keys(c, "initial", ("p_std", "omega_std", "v_std"))
    rng, split_seed = _rngs(c["seed"])
    T = int(c["n_trajectories"])
    R0 = haar_rotations(rng, T)
    p0 = float(ini["p_std"]) * rng.standard_normal((T, 3))
    w0 = float(ini["omega_std"]) * rng.standard_normal((T, 3))
    v0 = float(ini["v_std"]) * rng.standard_normal((T, 3))
    body = RigidBodySE3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_se3(body, R0, p0, w0, v0, _times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["se3"], split_seed, ph)


# --------------------------------------------------------------------------- caching front door
def generate(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Generate the dataset described by `cfg` (no caching)."""
    c = _check(to_dict(cfg))
    return SCENES[c["name"]](c, progress)


def get_dataset(cfg, data_dir="outputs/data", console=None) -> tuple[Dataset, Path]:
    """Load `<data_dir>/<name>-<hash>.h5` if present (validated), else generate, save and return it.

    console: optional rich Console for the progress display (default: a stderr console).
    """
    c = _check(to_dict(cfg))
    path = dataset_path(c, data_dir)
    if path.exists():
        ds = load_dataset(path)
        stored = ds.params.get("config_hash")
        if stored is not None and stored != config_hash(c):
            raise DatasetError(
                f"{path}: attribute 'params' holds config_hash {stored!r} but the file name says "
                f"{config_hash(c)!r}; delete the file to regenerate it"
            )
        return ds, path

    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = console or Console(stderr=True)
    t_end = float(c["h"]) * int(c["steps"])
    start = time.perf_counter()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("t = {task.completed:.2f} / {task.total:.2f} s"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as prog:
        task = prog.add_task(
            f"simulating {c['name']} ({c['n_trajectories']} trajectories x {c['steps']} steps)", total=t_end
        )
        ds = SCENES[c["name"]](c, lambda tt: prog.update(task, completed=tt))
    save_dataset(ds, path)
    console.print(
        f"[green]generated[/green] {c['name']}: {ds.n_trajectories} trajectories x {ds.n_steps} steps "
        f"in {time.perf_counter() - start:.1f} s -> {path}",
        soft_wrap=True,
    )
    return ds, path


__all__ = [
    "SCENES",
    "GENERATOR_VERSION",
    "register_scene",
    "generator_config",
    "config_hash",
    "dataset_path",
    "make_split",
    "haar_rotations",
    "uniform_ball",
    "generate",
    "get_dataset",
    "heavy_so3",
    "free_rigid_body",
    "heavy_se3",
]

# Scenes defined in other modules register themselves into SCENES when imported.
from . import mocap, scenes_multibody  # noqa: E402,F401
