"""Rolling a trained run out on other data (`liedfl rollout run=<run> dataset=...`): the dataset named
on the command line, the check that the model fits it, and `source.json`, the record next to such a
rollout that `liedfl eval` reads to evaluate the rollout against the same dataset."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from .errors import ConfigError, DatasetError

SOURCE_FILE = "source.json"
"""Written next to a rollout of a run on other data: which dataset it was rolled out on."""


def _group_error(model, run_dir, scene: str, n_se3: int, n_so3: int) -> ConfigError | None:
    from .lie import ProductGroup

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


def other_dataset(cfg: DictConfig, model, run_dir):
    """(dataset, its file, its config, source record) of `dataset=...` given to `liedfl rollout`, or None."""
    from .data.scenes import get_dataset

    ds_cfg = cfg.get("dataset")
    if ds_cfg is None:
        return None
    grp = cfg.get("group")  # set by a scene's dataset file: checked before anything is generated
    if grp is not None:
        err = _group_error(model, run_dir, str(ds_cfg.get("name")), int(grp.n_se3), int(grp.n_so3))
        if err is not None:
            raise err
    if isinstance(ds_cfg.get("h"), (int, float)):  # likewise the step of a generated scene
        err = _h_error(model, run_dir, str(ds_cfg.get("name")), float(ds_cfg.h))
        if err is not None:
            raise err
    dataset, path = get_dataset(ds_cfg, cfg.paths.data_dir)
    check_model_fits_data(model, dataset, run_dir)
    plain = OmegaConf.to_container(ds_cfg, resolve=True)
    source = {
        "dataset_path": str(Path(path).resolve()),
        "scene": dataset.scene,
        "group": dataset.group.name,
        "h": dataset.h,
        "test_trajectories": [int(i) for i in dataset.test_idx],
        "dataset_config": plain,
    }
    return dataset, ds_cfg, source


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


def rollout_dataset(path: Path, model, dataset, run_cfg, run_dir, data_dir):
    """(dataset, config) a rollout file belongs to: the run's own, or the one named by the `source.json`
    next to it: the recorded (cached) dataset file, or, where it is gone, the dataset regenerated or
    re-read from its config."""
    from .data.hdf5 import load_dataset
    from .data.scenes import get_dataset

    src = load_source(path.parent)
    if src is None:
        return dataset, run_cfg
    ds_cfg = OmegaConf.create(src.get("dataset_config") or {})
    ds_path = Path(src["dataset_path"])
    if ds_path.is_file():
        other = load_dataset(ds_path)
    else:
        other, _ = get_dataset(ds_cfg, data_dir)
    check_model_fits_data(model, other, run_dir)
    merged = OmegaConf.merge(run_cfg, {})
    merged.dataset = ds_cfg
    return other, merged


__all__ = ["SOURCE_FILE", "check_model_fits_data", "other_dataset", "load_source", "rollout_dataset"]
