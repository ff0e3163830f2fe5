"""The scene registry `SCENES` (name -> generator) and the dataset front door.

Each generator takes a dataset config (a `DatasetConfig` or plain dict, the fields of
liedfl_cli/conf/dataset/*.yaml; see `scene_common`) and returns a `Dataset`. The generators live
beside this module (`scenes_rigid`: Exp 1-3, `scenes_multibody`: two bodies and PD control,
`mocap`: the CMU recordings, `files`: the user's own data, `file` and `import`) and are listed here
explicitly: adding a scene means one generator function and one line in `SCENES` (plus its
conf/dataset/<name>.yaml). `get_dataset(cfg, data_dir)` caches the result as
`<data_dir>/<name>-<hash>.h5`, keyed by the generator-relevant part of the config; train_steps /
rollout_steps only tell the consumers how much of each trajectory to use, they do not change the
data (nor the hash). A user's file also hashes its content. Every scene also takes `noise` and
`smoothing` (`transforms`), applied after its generator.
"""

from __future__ import annotations

import copy
import time
import warnings
from collections.abc import Callable
from pathlib import Path

from ..errors import DatasetError, DataWarning
from . import transforms
from .dataset_config import DatasetConfig
from .files import SOURCE_SCENES, check_source_config, file_digest, from_file, hashed_config, import_recording
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
    "file": from_file,
    "import": import_recording,
}
"""Every scene a dataset config may name (`dataset.name`), with its generator `fn(cfg, progress=None)`."""


FILE_SCENE = "file"
"""`dataset=file dataset.path=<file.h5>`: a dataset file in liedfl's format (data/files.py)."""


def check_dataset(cfg) -> dict:
    """The dataset config as a plain dict, its common fields checked and its scene registered
    (ConfigError naming the key). A `DatasetConfig` checked at the door (`from_section`) is not
    checked again: its checked form is returned (a copy)."""
    if isinstance(cfg, DatasetConfig) and cfg.checked is not None:
        return copy.deepcopy(cfg.checked)
    c = to_dict(cfg)
    if c.get("name") in SOURCE_SCENES:  # the user's own file (data/files.py): its own keys
        c = check_source_config(c)
    else:
        c = check_config(c, SCENES)
    transforms.noise_spec(c.get("noise"))
    transforms.smoothing_spec(c.get("smoothing"))
    return c


def dataset_section(d, checked_as=None) -> DatasetConfig:
    """A configured `dataset` section (a plain mapping) as a `DatasetConfig`, checked once (one-line
    ConfigError naming the key): the door of the data layer. checked_as: the mapping to check in its
    place (`liedfl rollout`'s relaxed split); the section keeps its configured keys (`as_dict`)."""
    out = DatasetConfig.from_mapping(d)
    out.checked = check_dataset(out if checked_as is None else DatasetConfig.from_mapping(checked_as))
    return out


def _hash(c: dict) -> str:
    """The cache hash of a checked config; a user's file also hashes its content (files.hashed_config)."""
    return config_hash(hashed_config(c) if c["name"] in SOURCE_SCENES else c)


def _with_digest(c: dict) -> dict:
    """A source scene's config with the SHA-256 of its file(s), computed once (generator and cache name)."""
    if c["name"] in SOURCE_SCENES and not c.get("source_sha256"):
        from .files import _paths

        c = {**c, "source_sha256": file_digest(_paths(c))}
    return c


def _generate(c: dict, progress=None) -> Dataset:
    """The scene's generator, then the options of every scene (noise, smoothing: `transforms`). The
    recordings (mocap, `import`) smooth during their import, before cropping."""
    ds = SCENES[c["name"]](c, progress)
    smoothing_done = c["name"] in REAL_DATA_SCENES or c["name"] == "import"
    if c["name"] == FILE_SCENE:  # the noise stream follows the file's own seed
        c = {**c, "seed": ds.seed}
    return transforms.apply(ds, c, smoothing_done=smoothing_done)


def dataset_steps(cfg, dataset, key: str) -> int:
    """`dataset.train_steps` / `dataset.rollout_steps`, or the dataset's length where it is null."""
    value = cfg.get(key) if cfg is not None else None
    return int(dataset.n_steps) if value is None else int(value)


def _path(c: dict, data_dir) -> Path:
    """The cache file of a checked config with its digest."""
    return Path(data_dir) / f"{c['name']}-{_hash(c)}.h5"


def dataset_path(cfg, data_dir="outputs/data") -> Path:
    """`<data_dir>/<name>-<config_hash>.h5`."""
    return _path(_with_digest(check_dataset(cfg)), data_dir)


def generate(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Generate the dataset described by `cfg` (no caching)."""
    return _generate(_with_digest(check_dataset(cfg)), progress)


def get_dataset(cfg, data_dir="outputs/data", console=None) -> tuple[Dataset, Path]:
    """Load `<data_dir>/<name>-<hash>.h5` if present (validated), else generate, save and return it.

    console: optional rich Console for the progress display (default: a stderr console).
    `dataset=file` / `dataset=import`: the user's file read (data/files.py) and cached like a scene.
    """
    c = _with_digest(check_dataset(cfg))  # checked once (not again when `cfg` was checked at the door)
    path = _path(c, data_dir)
    if path.exists():
        ds = load_dataset(path)
        stored = ds.params.get("config_hash")
        if stored is not None and stored != _hash(c):
            raise DatasetError(
                f"{path}: attribute 'params' holds config_hash {stored!r} but the file name says "
                f"{_hash(c)!r}; delete the file to regenerate it"
            )
        return ds, path

    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = console or Console(stderr=True)
    t_end = float(c["h"]) * int(c["steps"]) if c["name"] not in SOURCE_SCENES else 1.0
    start = time.perf_counter()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("t = {task.completed:.2f} / {task.total:.2f} s"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as prog:
        what = (
            f"reading {c['path']}"
            if c["name"] in SOURCE_SCENES
            else f"simulating {c['name']} ({c['n_trajectories']} trajectories x {c['steps']} steps)"
        )
        task = prog.add_task(what, total=t_end)
        ds = _generate(c, lambda tt: prog.update(task, completed=tt))
    with warnings.catch_warnings():
        if c["name"] in SOURCE_SCENES:  # the user's file was checked (and warned about) when read
            warnings.simplefilter("ignore", DataWarning)
        save_dataset(ds, path)
    console.print(
        f"[green]{'read' if c['name'] in SOURCE_SCENES else 'generated'}[/green] {c['name']}: "
        f"{ds.n_trajectories} trajectories x {ds.n_steps} steps in {time.perf_counter() - start:.1f} s -> {path}",
        soft_wrap=True,
    )
    return ds, path


__all__ = [
    "SCENES",
    "FILE_SCENE",
    "dataset_steps",
    "check_dataset",
    "dataset_section",
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
