"""Rolling a trained run out on other data (`liedfl rollout run=<run> dataset=...`): the dataset named
on the command line, the check that the model fits it, and `source.json`, the record next to such a
rollout that `liedfl eval` reads to evaluate the rollout against the same dataset."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from ..data.dataset_config import DatasetConfig
from ..errors import ConfigError, DatasetError
from .fields import allowed
from .typed import USER_FILES, RunConfig, TopKeys, dataset_config, relaxed_dataset_config

SOURCE_FILE = "source.json"
"""Written next to a rollout of a run on other data (or of other trajectories than the test split):
which dataset and trajectories it was rolled out on."""
SPLITS = allowed(TopKeys, "split")
"""`liedfl rollout split=...`: which trajectories (auto: all of a user's file given as dataset=, else test);
declared once, on `typed.TopKeys.split`."""


def with_test_split(dataset, idx):
    """`dataset` with `idx` as its test split (the trajectories a rollout covers); the data are shared."""
    import dataclasses

    import numpy as np

    return dataclasses.replace(dataset, split={**dataset.split, "test": np.asarray(idx, dtype=np.int64)})


def choose_split(mode: str, dataset, other: bool, all_asked: bool = False):
    """(split name, trajectory indices) a rollout covers. `auto`: `all` on a user's file named on the
    command line (`dataset=file` / `dataset=import`: a new recording is rolled out whole), `test`
    otherwise (the run's own data, generated scenes, the mocap recordings: as before). `all_asked`:
    dataset.n_test or dataset.test_fraction asked for every trajectory."""
    import numpy as np

    mode = TopKeys(split=mode).split  # the values the field declares (one-line ConfigError otherwise)
    if all_asked:
        if mode == "train":
            raise ConfigError("split=train: dataset.n_test / dataset.test_fraction make every trajectory a test one")
        mode = "all"
    if mode == "auto":
        mode = "all" if other and (dataset.params or {}).get("config", {}).get("name") in USER_FILES else "test"
    if mode == "all":
        return mode, np.arange(dataset.n_trajectories, dtype=np.int64)
    idx = dataset.train_idx if mode == "train" else dataset.test_idx
    if len(idx) == 0:
        raise DatasetError(
            f"{dataset.scene}: field 'split/{mode}' is empty: nothing to roll out (split=all: every trajectory)"
        )
    return mode, np.asarray(idx, dtype=np.int64)


def _group_error(model, run_dir, scene: str, n_se3: int, n_so3: int) -> ConfigError | None:
    from ..lie import ProductGroup

    G = model.G
    if (G.n_se3, G.n_so3) == (n_se3, n_so3):
        return None
    return ConfigError(
        f"run={run_dir} models {G.name} but dataset '{scene}' is {ProductGroup(n_se3, n_so3).name}: "
        "the model's group must be the data's"
    )


def check_model_fits_data(model, dataset, run_dir) -> None:
    """The model's group and time step must be the dataset's (one-line ConfigError otherwise)."""
    err = _group_error(model, run_dir, dataset.scene, dataset.group.n_se3, dataset.group.n_so3)
    if err is not None:
        raise err
    err = _h_error(model, run_dir, dataset.scene, dataset.h)
    if err is not None:
        raise err
    err = _tree_error(model, run_dir, dataset.scene, getattr(dataset, "tree", None))
    if err is not None:
        raise err


def _tree_error(model, run_dir, scene: str, tree) -> ConfigError | None:
    """A model built on a kinematic tree (`model.tree`, e.g. model.kinetic=articulated) runs forward
    kinematics with that tree: the data must have the same one (parents, joint offsets, rotations, root)."""
    own = model.tree
    if own is None or own == tree:
        return None
    if tree is None:
        return ConfigError(f"run={run_dir} models a kinematic tree but dataset '{scene}' has none (no 'parents')")
    for field in ("parents", "rotations", "free_root", "offsets"):
        if getattr(own, field) != getattr(tree, field):
            return ConfigError(
                f"run={run_dir} was trained on a kinematic tree with other {field} than dataset '{scene}' "
                f"({getattr(own, field)} vs {getattr(tree, field)}): the model's tree must be the data's"
            )
    return None


def _h_error(model, run_dir, scene: str, h: float) -> ConfigError | None:
    if abs(float(model.h) - float(h)) <= 1e-5 * float(model.h):
        return None
    return ConfigError(
        f"run={run_dir} was trained with h={model.h:g} but dataset '{scene}' has h={float(h):g}: "
        "a discrete model only steps with its own h"
    )


def other_dataset(command: RunConfig, model, run_dir):
    """(dataset, its config, source record, whether n_test / test_fraction asked for every trajectory)
    of `dataset=...` given to `liedfl rollout` (the command's typed config: its dataset section was
    checked at the door, relaxed as a rollout reads it), or None."""
    from ..data.scenes import get_dataset

    ds_cfg = command.dataset
    if ds_cfg is None:
        return None
    grp = command.group  # set by a scene's dataset file: checked before anything is generated
    if grp is not None:
        err = _group_error(model, run_dir, str(ds_cfg.name), int(grp.n_se3), int(grp.n_so3))
        if err is not None:
            raise err
    if isinstance(ds_cfg.h, (int, float)):  # likewise the step of a generated scene
        err = _h_error(model, run_dir, str(ds_cfg.name), float(ds_cfg.h))
        if err is not None:
            raise err
    plain, all_asked = relaxed_dataset_config(ds_cfg.as_dict())
    try:
        dataset, path = get_dataset(ds_cfg, command.paths.data_dir)  # its checked (relaxed) form
    except ConfigError as e:  # dataset.n_test = every trajectory: refused for training, not for a rollout
        n_test = plain.get("n_test")
        if n_test is None or "dataset.n_test" not in str(e):
            raise
        dataset, path = get_dataset(dataset_config({**plain, "n_test": None}), command.paths.data_dir)
        if int(n_test) != dataset.n_trajectories:
            raise
        plain, all_asked = {**plain, "n_test": None}, True
    check_model_fits_data(model, dataset, run_dir)
    ds_cfg = DatasetConfig.from_mapping(plain)
    source = {
        "dataset_path": str(Path(path).resolve()),
        "scene": dataset.scene,
        "group": dataset.group.name,
        "h": dataset.h,
        "test_trajectories": [int(i) for i in dataset.test_idx],
        "dataset_config": plain,
    }
    return dataset, ds_cfg, source, all_asked


def load_source(folder) -> dict | None:
    """The `source.json` of a rollout folder (None when it is a rollout of the run's own data)."""
    path = Path(folder) / SOURCE_FILE
    if not path.is_file():
        return None
    try:
        src = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: not a valid JSON file ({type(e).__name__})") from None
    if not isinstance(src, dict) or not isinstance(src.get("dataset_path"), str):
        raise DatasetError(f"{path}: field 'dataset_path' is missing")
    return src


def rollout_dataset(path: Path, model, dataset, run_cfg: RunConfig, run_dir, data_dir) -> tuple[Any, RunConfig]:
    """(dataset, the run's typed config with that dataset's section) a rollout file belongs to: the
    run's own, or the one named by the `source.json` next to it: the recorded (cached) dataset file,
    or, where it is gone, the dataset regenerated or re-read from its config."""
    from ..data.hdf5 import load_dataset
    from ..data.scenes import get_dataset

    src = load_source(path.parent)
    if src is None:
        return dataset, run_cfg
    section = src.get("dataset_config") or {}
    ds_path = Path(src["dataset_path"])
    if ds_path.is_file():
        other = load_dataset(ds_path)
        ds_cfg = DatasetConfig.from_mapping(section) if isinstance(section.get("name"), str) else None
    else:
        ds_cfg = dataset_config(section)
        other, _ = get_dataset(ds_cfg, data_dir)
    check_model_fits_data(model, other, run_dir)
    if src.get("split") not in (None, "test"):  # split=all / train: those trajectories are the ones evaluated
        other = with_test_split(other, src.get("test_trajectories") or [])
    return other, dataclasses.replace(run_cfg, dataset=ds_cfg)


__all__ = [
    "SOURCE_FILE",
    "SPLITS",
    "check_model_fits_data",
    "choose_split",
    "load_source",
    "other_dataset",
    "relaxed_dataset_config",
    "rollout_dataset",
    "with_test_split",
]
