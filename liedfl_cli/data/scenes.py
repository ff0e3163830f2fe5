"""The scene registry `SCENES` (name -> generator) and the dataset front door.

Each generator takes a dataset config (omegaconf DictConfig or plain dict, the fields of
conf/dataset/*.yaml; see `scene_common`) and returns a `Dataset`. The generators live beside this
module (`scenes_rigid`: Exp 1-3, `scenes_multibody`: two bodies and PD control, `mocap`: the CMU
recordings) and are listed here explicitly: adding a scene means one generator function and one
line in `SCENES` (plus its conf/dataset/<name>.yaml). `get_dataset(cfg, data_dir)` caches the
result as `<data_dir>/<name>-<hash>.h5`, keyed by the generator-relevant part of the config;
train_steps / rollout_steps only tell the consumers how much of each trajectory to use, they do not
change the data (nor the hash). Every scene also takes `noise` and `smoothing` (`transforms`), applied
after its generator.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from ..errors import ConfigError, DatasetError
from . import transforms
from .hdf5 import Dataset, load_dataset, save_dataset
from .mocap import REAL_DATA_SCENES, cmu_cartwheel
from .scene_common import (
    GENERATOR_VERSION,
    REQUIRED_KEYS,
    check_config,
    config_hash,
    generator_config,
    haar_rotations,
    make_split,
    to_dict,
    uniform_ball,
)
from .scenes_multibody import pd_control, two_body
from .scenes_rigid import free_rigid_body, heavy_se3, heavy_so3

Generator = Callable[..., Dataset]

SCENES: dict[str, Generator] = {
    "heavy_so3": heavy_so3,
    "free_rigid_body": free_rigid_body,
    "heavy_se3": heavy_se3,
    "two_body": two_body,
    "pd_control": pd_control,
    "cmu_cartwheel": cmu_cartwheel,
}
"""Every scene a dataset config may name (`dataset.name`), with its generator `fn(cfg, progress=None)`."""


def _checked(cfg) -> dict:
    """The dataset config as a plain dict, its common fields checked and its scene registered."""
    c = check_config(to_dict(cfg), SCENES)
    transforms.noise_spec(c.get("noise"))
    transforms.smoothing_spec(c.get("smoothing"))
    return c


def _generate(c: dict, progress=None) -> Dataset:
    """The scene's generator, then the options of every scene (noise, smoothing: `transforms`)."""
    ds = SCENES[c["name"]](c, progress)
    return transforms.apply(ds, c, smoothing_done=c["name"] in REAL_DATA_SCENES)


FILE_SCENE = "file"
"""`dataset=file dataset.path=<file.h5>`: a dataset file read as it is (conf/dataset/file.yaml)."""


FILE_IGNORED_KEYS = ("n_trajectories", "steps", "n_test")
"""Generator keys that budget files (conf/budget/smoke.yaml) set on every dataset: a file has its own
trajectories and length, so they are accepted and ignored."""


def is_file_config(cfg) -> bool:
    """Whether a dataset config names a file (`name: file`)."""
    get = getattr(cfg, "get", None)
    return callable(get) and get("name") == FILE_SCENE


def load_file(cfg) -> tuple[Dataset, Path]:
    """The dataset of `dataset=file`: `path` read and validated (`load_dataset`), then its `noise` and
    `smoothing` options applied in memory (the file is not copied into the cache)."""
    c = to_dict(cfg)
    allowed = {"name", "path", "train_steps", "rollout_steps", *transforms.OPTION_KEYS, "defaults"}
    allowed |= set(FILE_IGNORED_KEYS)
    unknown = sorted(set(c) - allowed)
    if unknown:
        keys = sorted(allowed - {"defaults", *FILE_IGNORED_KEYS})
        raise ConfigError(f"dataset=file: unknown key(s) {unknown} (allowed: {keys})")
    path = c.get("path")
    if not isinstance(path, str) or not path or path == "???":
        raise ConfigError("dataset=file needs dataset.path=<a liedfl HDF5 dataset file>")
    for key in ("train_steps", "rollout_steps"):
        v = c.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"dataset.{key}={v!r}: null (the whole file) or a positive integer")
    transforms.noise_spec(c.get("noise"))
    transforms.smoothing_spec(c.get("smoothing"))
    ds = load_dataset(Path(path).expanduser())
    ds = transforms.apply(ds, {**c, "seed": ds.seed})
    return ds, Path(path)


def dataset_steps(cfg, dataset, key: str) -> int:
    """`dataset.train_steps` / `dataset.rollout_steps`, or the dataset's length where it is null."""
    value = cfg.get(key) if cfg is not None else None
    return int(dataset.n_steps) if value is None else int(value)


def dataset_path(cfg, data_dir="outputs/data") -> Path:
    """`<data_dir>/<name>-<config_hash>.h5`."""
    return Path(data_dir) / f"{_checked(cfg)['name']}-{config_hash(cfg)}.h5"


def generate(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Generate the dataset described by `cfg` (no caching)."""
    if is_file_config(cfg):
        return load_file(cfg)[0]
    c = _checked(cfg)
    return _generate(c, progress)


def get_dataset(cfg, data_dir="outputs/data", console=None) -> tuple[Dataset, Path]:
    """Load `<data_dir>/<name>-<hash>.h5` if present (validated), else generate, save and return it.

    console: optional rich Console for the progress display (default: a stderr console).
    `dataset=file`: the named file itself (`load_file`).
    """
    if is_file_config(cfg):
        return load_file(cfg)
    c = _checked(cfg)
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
        ds = _generate(c, lambda tt: prog.update(task, completed=tt))
    save_dataset(ds, path)
    console.print(
        f"[green]generated[/green] {c['name']}: {ds.n_trajectories} trajectories x {ds.n_steps} steps "
        f"in {time.perf_counter() - start:.1f} s -> {path}",
        soft_wrap=True,
    )
    return ds, path


__all__ = [
    "SCENES",
    "FILE_SCENE",
    "load_file",
    "dataset_steps",
    "GENERATOR_VERSION",
    "REQUIRED_KEYS",
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
