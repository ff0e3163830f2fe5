"""Up-front validation of a composed config: every problem is one `ConfigError` line naming the key.

`validate(cfg)` runs before anything is written (the CLI calls it from a Hydra callback, before
Hydra creates the run directory, and again when the job starts):

- **unknown keys** at every level (the top level, every section, `dataset` and its blocks, `force`,
  `model`) are rejected, naming the key and the closest valid one (difflib);
- **types** of the sections owned by liedfl (their dataclasses in `config/typed.py`, which also
  builds the typed objects the commands pass on);
- **values**: positive epochs / batch size / learning rate, an integer seed, rollout lengths,
  a usable `paths.data_dir`, `model._target_` restricted to liedfl's own classes, the dataset's
  numbers and a non-empty train (and, with a rollout, test) split.

The allowed keys of a dataset are those of the scene's reference file `conf/dataset/<scene>.yaml`
(the generators accept exactly those), of a model those of `conf/model/<name>.yaml`, of a
force those of `conf/force/<kind>.yaml`: a new option file extends the allowed set by itself.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import os
import typing
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from ..errors import ConfigError
from ..solvers.runtime import DEVICE_CHOICES, DTYPES
from . import resolvers  # noqa: F401  (registers the config resolvers)
from .fields import check_values, required_keys
from .typed import SECTIONS as TYPED_SECTIONS
from .typed import PathsConfig, TopKeys, section, wrong_type_line

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # the configs ship inside the package


SECTIONS: dict[str, Any] = {k: v for k, v in TYPED_SECTIONS.items() if k != "paths"}
"""The sections whose keys and types are checked against their dataclass (config/typed.py)."""
CHOICES = {
    # The options whose allowed values are not on a field of config/typed.py: each reads the one list
    # its owner declares (the runtime's in solvers/runtime.py; a model's on its `Options` fields).
    ("runtime", "device"): DEVICE_CHOICES,
    ("runtime", "dtype"): tuple(DTYPES),
}
_TRAIN_KEYS = ("task_name", "seed", "epoch_scale", "train", "rollout", "eval", "ui", "paths")
TOP_LEVEL: dict[str, tuple[str, ...]] = {
    # `budgets`: per-model budget tables of the experiment files; `resume`: resume=<run dir> (train.py)
    "train": (
        *_TRAIN_KEYS,
        "group",
        "dataset",
        "model",
        "force",
        "baseline",
        "solver",
        "budgets",
        "resume",
        "runtime",
        "logger",
    ),
    # budget files also set train/rollout/epoch_scale, which `liedfl data` ignores
    "data": ("task_name", "ui", "paths", "group", "dataset", "train", "rollout", "epoch_scale", "seed"),
    # rollout run=<run> dataset=<scene>: other data (the dataset file selects its group)
    "rollout": (
        *("task_name", "run", "checkpoint", "steps", "rollout", "eval", "ui", "paths", "solver", "runtime"),
        "accept_changed_dataset",
        *("dataset", "group", "split", "export"),
    ),
    "eval": (
        *("task_name", "run", "checkpoint", "rollout", "eval", "ui", "paths", "solver", "runtime"),
        "accept_changed_dataset",
    ),
    "report": ("task_name", "sweep", "plots"),
    "export": (
        *("task_name", "run", "format", "out", "checkpoint", "accept_changed_dataset", "timestep"),
        *("dataset", "runtime", "ui", "paths"),
    ),
    "resume": ("task_name", "resume", "epochs", "ui", "accept_changed_dataset"),
}
_OTHER_REQUIRED: dict[tuple[str, str], tuple[str, ...]] = {
    # (command, section) -> the required keys that are not fields of a checked dataclass (those say
    # it on the field: `option(required=...)`): listed after that section's own ("": before every
    # section); the config groups a command reads come after `paths`
    ("train", ""): ("seed",),
    ("train", "paths"): ("dataset", "model", "force", "model.name"),
    ("data", "paths"): ("dataset",),
}


def required(command: str) -> tuple[str, ...]:
    """The keys `command` reads (an override such as ~train.epochs removes them), in the order they
    are reported: the fields declared `required` for it (config/typed.py) and `_OTHER_REQUIRED`."""
    keys = [*required_keys(TopKeys, command, ""), *_OTHER_REQUIRED.get((command, ""), ())]
    for name, schema in TYPED_SECTIONS.items():
        keys += required_keys(schema, command, name)
        keys += _OTHER_REQUIRED.get((command, name), ())
    return tuple(keys)


DEFAULT_MODEL_TARGET = "liedfl_cli.models.liedflnn.LieDFLNN"
TARGET_PREFIX = "liedfl_cli."


# ----------------------------------------------------------------------------- helpers
def closest(key: str, valid) -> str:
    """' (did you mean X?)' for the closest valid key, else ' (valid keys: ...)'."""
    valid = sorted(str(v) for v in valid)
    match = difflib.get_close_matches(str(key), valid, n=1, cutoff=0.6)
    if match:
        return f" (did you mean '{match[0]}'?)"
    return f" (valid keys: {', '.join(valid)})" if valid else " (this section takes no keys)"


def _unknown(path: str, key: str, valid, where: str = "") -> ConfigError:
    full = f"{path}.{key}" if path else str(key)
    valid = [v for v in valid if v != "hydra"]
    hint = closest(key, valid)
    if "did you mean" in hint:
        prefix = f"{path}." if path else ""
        hint = hint.replace("'", f"'{prefix}", 1)
    return ConfigError(f"unknown config key '{full}'{where}{hint}")


def _check_keys(node, valid, path: str, where: str = "") -> None:
    if not isinstance(node, (DictConfig, dict)):
        return
    for k in node:
        if k not in valid:
            raise _unknown(path, str(k), valid, where)


def _check_dataclass_keys(node, schema, path: str) -> None:
    """Unknown keys of `node` against the fields of `schema` (recursing into nested dataclasses)."""
    if not isinstance(node, (DictConfig, dict)):
        return
    hints = typing.get_type_hints(schema)
    names = [f.name for f in dataclasses.fields(schema)]
    _check_keys(node, names, path)
    for name in names:
        sub = hints[name]
        if dataclasses.is_dataclass(sub) and name in node:
            _check_dataclass_keys(_get(node, name, f"{path}.{name}"), sub, f"{path}.{name}")


def _get(node, key: str, full: str):
    """node[key] with its interpolations resolved, errors as ConfigError naming `full`."""
    try:
        return node[key]
    except OmegaConfBaseException as e:
        raise ConfigError(f"config key '{full}': {_first_line(e)}") from None


def _plain(node, full: str):
    """A config subtree as plain Python (interpolations resolved)."""
    if isinstance(node, (DictConfig, ListConfig)):
        try:
            return OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException as e:
            key = getattr(e, "full_key", None)
            raise ConfigError(
                f"config key '{full}': {_first_line(e)}" + (f" (key {key})" if key and key != full else "")
            ) from None
    return node


def _has(cfg, dotted: str) -> bool:
    node = cfg
    for part in dotted.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return False
        try:
            node = node[part]
        except OmegaConfBaseException:
            return True  # present; its value is checked (and reported) later
    return True


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _value(cfg, dotted: str):
    """The resolved value at `dotted` (None when absent)."""
    try:
        v = OmegaConf.select(cfg, dotted, throw_on_missing=False)
    except OmegaConfBaseException as e:
        raise ConfigError(f"config key '{dotted}': {_first_line(e)}") from None
    return _plain(v, dotted)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _int(cfg, key: str, minimum: int, nullable: bool = False, what: str | None = None, maximum: int | None = None):
    v = _value(cfg, key)
    if v is None and nullable:
        return None
    if not _is_int(v) or v < minimum or (maximum is not None and v > maximum):
        need = what or ("a positive integer" if minimum == 1 else f"an integer >= {minimum}")
        raise ConfigError(f"{key}={v!r}: must be {need}" + (" or null" if nullable else ""))
    return v


def _float(cfg, key: str, positive: bool = False, nonnegative: bool = False):
    v = _value(cfg, key)
    if not _is_number(v) or not math.isfinite(v) or (positive and v <= 0) or (nonnegative and v < 0):
        need = "a positive number" if positive else "a number >= 0" if nonnegative else "a finite number"
        raise ConfigError(f"{key}={v!r}: must be {need}")
    return v


@functools.cache
def _reference(group: str, option: str):
    """Plain content of conf/<group>/<option>.yaml (None when there is no such file)."""
    import yaml

    path = CONF_DIR / group / f"{option}.yaml"
    if not path.is_file():
        return None
    data = yaml.safe_load(path.read_text()) or {}
    if isinstance(data, dict):
        data.pop("defaults", None)
    return data


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


# ----------------------------------------------------------------------------- sections
def _check_types(cfg, name: str, schema, values=None, build: bool = False) -> None:
    """The section `cfg[name]` (or `values`, a plain mapping of its values) merged into the dataclass
    `schema`: a wrong type is one line naming the key; with `build`, the dataclass is built, so the
    values its fields declare are checked too (one line naming the key)."""
    values = _plain(cfg[name], name) if values is None else values
    _check_shapes(values, schema, name)
    if build:  # the dataclass built: its fields' checks run (fields.Checked.__post_init__)
        section(schema, values, name)
        return
    try:
        OmegaConf.merge(OmegaConf.structured(schema), values)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or ""
        ours = wrong_type_line(e, f"{name}.{key}" if key else "")  # e.g. train.optimizer.lr=abc: must be a number
        raise ConfigError(
            ours or f"config section '{name}': {_first_line(e)}" + (f" (key {name}.{key})" if key else "")
        ) from None


def _check_shapes(values, schema, where: str) -> None:
    """What OmegaConf's merge would coerce or word obscurely, in one line: a flag given a number or
    text (`eval.plots=2` is not `true`), a section given a scalar (`train.early_stopping=5`)."""
    import typing

    if not isinstance(values, dict) or not dataclasses.is_dataclass(schema):
        return
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if f.name not in values:
            continue
        v, kind = values[f.name], hints.get(f.name)
        key = f"{where}.{f.name}"
        if kind is bool and not isinstance(v, bool):
            raise ConfigError(f"{key}={v!r}: must be true or false")
        if isinstance(kind, type) and dataclasses.is_dataclass(kind):
            if v is not None and not isinstance(v, dict):
                names = ", ".join(g.name for g in dataclasses.fields(kind))
                raise ConfigError(
                    f"{key}={v!r}: must be a mapping of {names} (e.g. {key}.{dataclasses.fields(kind)[0].name}=...)"
                )
            _check_shapes(v, kind, key)


def _check_reference_keys(node, ref, path: str, where: str) -> None:
    """Keys of `node` against the reference mapping `ref`, recursing where both are mappings."""
    if not isinstance(node, (DictConfig, dict)) or not isinstance(ref, dict):
        return
    _check_keys(node, list(ref), path, where)
    for k in node:
        sub = ref.get(k)
        if isinstance(sub, dict) and sub:
            try:
                child = node[k]
            except OmegaConfBaseException:
                continue
            _check_reference_keys(child, sub, f"{path}.{k!s}", where)


def _check_dataset_keys(cfg) -> None:
    ds = cfg.get("dataset")
    if not isinstance(ds, DictConfig):
        if ds is not None:
            raise ConfigError(f"dataset must be a mapping, got {ds!r}")
        return
    name = _value(cfg, "dataset.name")
    if not isinstance(name, str):
        raise ConfigError(f"dataset.name={name!r}: must be a scene name ({', '.join(_options('dataset'))})")
    ref = _reference("dataset", name)
    if ref is None:  # a scene registered by user code: its generator checks its keys
        return
    _check_reference_keys(ds, ref, "dataset", f" for scene '{name}'")


def _check_force(cfg) -> None:
    force = cfg.get("force")
    if force is None:
        return
    if not isinstance(force, DictConfig):
        raise ConfigError(f"force must be a mapping of force kinds, got {force!r}")
    kinds = [o for o in _options("force") if o != "none"]
    for kind in force:
        if kind not in kinds:
            raise ConfigError(f"unknown force 'force.{kind!s}'{closest(str(kind), kinds).replace('keys', 'forces')}")
        params = force[kind]
        if params is None:
            continue
        if not isinstance(params, DictConfig):
            raise ConfigError(f"force.{kind} must be a mapping of options, got {params!r}")
        _check_keys(params, list(_reference("force", kind) or {}), f"force.{kind}")


def _check_model(cfg) -> None:
    """`model._target_` names a model class of this package (`factory.model_class`); the keys are
    those of the model's `Options` dataclass (LieDFLNN's: models/liedflnn/model.py), else of its reference
    file conf/model/<name>.yaml."""
    model = cfg.get("model")
    if model is None:
        return
    if not isinstance(model, DictConfig):
        raise ConfigError(f"model must be a mapping, got {model!r}")
    target = _value(cfg, "model._target_")
    if not isinstance(target, str) or not target.startswith(TARGET_PREFIX):
        raise ConfigError(
            f"model._target_={target!r}: only liedfl's own model classes may be instantiated "
            f"(a name starting with '{TARGET_PREFIX}models.', e.g. {DEFAULT_MODEL_TARGET})"
        )
    from .factory import model_class

    cls = model_class(target)
    name = _value(cfg, "model.name")
    if cls.Options is not None:  # the model's own options dataclass (models/<family>.py)
        _check_keys(model, ["_target_", "name", *(f.name for f in dataclasses.fields(cls.Options))], "model")
        options = {k: v for k, v in (_plain(model, "model") or {}).items() if k not in ("_target_", "name")}
        _check_types(cfg, "model", cls.Options, values=options)
        check_values(options, cls.Options, "model")  # the values its fields declare (models/<family>/model.py)
    else:
        # A model whose config lives in this package is checked against that file here; one added on
        # Hydra's search path (hydra.searchpath) is checked by its own from_config (`config_options`).
        reference = _reference("model", name) if name in _options("model") else None
        if reference is not None:
            _check_keys(model, list(reference), "model", f" for model '{name}'")
    _check_model_size(cfg)


def _check_model_size(cfg) -> None:
    """`model.mlp_width` x `model.mlp_depth`: refused when one MLP's weights, gradients and the
    optimiser's two moments (4 float64 copies of width^2 (depth - 1) + width weights) cannot fit."""
    from ..data.memory import check_fits

    width, depth = _value(cfg, "model.mlp_width"), _value(cfg, "model.mlp_depth")
    if not _is_int(width) or width < 1:
        return
    depth = depth if _is_int(depth) and depth >= 1 else 1
    check_fits(f"model.mlp_width={width} (model.mlp_depth={depth})", 4 * 8 * (float(width) ** 2 * (depth - 1) + width))


def _check_data_dir(cfg, must_write: bool) -> None:
    raw = _value(cfg, "paths.data_dir")
    if not isinstance(raw, str) or not raw.strip():
        raise ConfigError(f"paths.data_dir={raw!r}: must be a directory path")
    path = Path(raw).expanduser()
    if path.exists():
        if not path.is_dir():
            raise ConfigError(f"paths.data_dir={raw}: exists and is not a directory")
        if must_write and not os.access(path, os.W_OK | os.X_OK):
            raise ConfigError(f"paths.data_dir={raw}: directory is not writable")
        return
    parent = path.absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"paths.data_dir={raw}: cannot be created ({parent} is not a directory)")
    if must_write and not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"paths.data_dir={raw}: cannot be created ({parent} is not writable)")


SEED_MAX = 2**63 - 1  # torch's generators take a signed 64-bit seed


def _check_scalars(cfg, command: str) -> None:
    """Top-level scalars (checked first: section values interpolate them)."""
    if "seed" in cfg:
        _int(cfg, "seed", 0, what=f"an integer from 0 to {SEED_MAX} (2**63 - 1)", maximum=SEED_MAX)
    if "epoch_scale" in cfg and command == "train":
        _float(cfg, "epoch_scale", positive=True)


def _check_values(cfg, command: str) -> None:
    """What no field can say: the optional TensorBoard extra is installed, `paths.data_dir` is usable."""
    # the optional extra: refused before the run starts
    if command == "train" and "train" in cfg and _value(cfg, "logger.name") == "tensorboard":
        from ..loggers import require_tensorboard

        require_tensorboard()
    if "paths" in cfg and command in ("train", "data", "rollout", "eval"):
        _check_data_dir(cfg, must_write=command in ("train", "data"))


def _check_top_keys(cfg) -> None:
    """The commands' own top-level keys (run, checkpoint, steps, split, export, ...) against
    `typed.TopKeys` (their fields declare the values)."""
    keys = set(cfg.keys())  # (`key in cfg` is false for a missing mandatory value such as `run: ???`)
    present = {f.name: _value(cfg, f.name) for f in dataclasses.fields(TopKeys) if f.name in keys}
    TopKeys(**present)


def _check_split_sizes(cfg, d: dict) -> None:
    """Generated scenes split by `n_test` / `test_fraction` (scenes.make_split): the train split must
    not be empty, nor the test split when the run rolls out."""
    if "split" in d or d.get("name") in ("file", "import"):  # recordings and files: data/mocap.py, data/files.py
        return
    T = int(d["n_trajectories"])
    k = int(d["n_test"]) if d.get("n_test") is not None else int(round(float(d["test_fraction"]) * T))
    if T - k < 1:
        raise ConfigError(
            f"dataset.n_test={d.get('n_test')!r} (test_fraction={d.get('test_fraction')!r}) leaves no training "
            f"trajectory out of n_trajectories={T}"
        )
    if k < 1 and bool(_value(cfg, "rollout.enabled")):
        raise ConfigError(
            f"dataset.n_test={d.get('n_test')!r} (test_fraction={d.get('test_fraction')!r}) gives an empty test "
            f"split, but rollout.enabled is true; set dataset.n_test >= 1 or rollout.enabled=false"
        )


def _check_dataset_values(cfg, command: str) -> None:
    """The dataset section's one check (`typed.dataset_config`, the same as the command's conversion),
    then, for training, the sizes of its split."""
    if not isinstance(cfg.get("dataset"), DictConfig):
        return
    from .typed import dataset_config

    ds = dataset_config(_plain(cfg.dataset, "dataset"), rollout=command == "rollout")  # the one check
    if command == "train":
        assert ds.checked is not None
        _check_split_sizes(cfg, ds.checked)


# ----------------------------------------------------------------------------- entry point
def validate(cfg: DictConfig, command: str | None = None) -> None:
    """Raise ConfigError for unknown keys, wrong types or invalid values (see the module docstring).

    command: the liedfl command (default: `cfg.task_name`); it selects the allowed top-level keys.
    A `hydra` node (present in Hydra callbacks) is ignored."""
    command = command or (cfg.get("task_name") if isinstance(cfg, DictConfig) else None)
    top = TOP_LEVEL.get(str(command))
    if top is not None:
        _check_keys(cfg, (*top, "hydra"), "")
    for dotted in required(str(command)):
        if not _has(cfg, dotted):
            raise ConfigError(f"config key '{dotted}' is missing (removed by an override?)")
    _check_scalars(cfg, str(command))
    # sections with a dataclass schema: keys, then types
    for name, schema in SECTIONS.items():
        if name == "rollout" and command == "eval":
            continue  # `liedfl eval rollout=<file>`: there `rollout` is a path, not this section
        if name in cfg and cfg[name] is not None:
            _check_dataclass_keys(cfg[name], schema, name)
            _check_types(cfg, name, schema, build=True)
    if "paths" in cfg:
        _check_keys(cfg.paths, [f.name for f in dataclasses.fields(PathsConfig)], "paths")
    if command != "export":  # export's `dataset` holds total_mass only (commands/export_model.py)
        _check_dataset_keys(cfg)
    _check_force(cfg)
    _check_top_keys(cfg)
    for path, allowed in CHOICES.items():
        node = _value(cfg, ".".join(path))
        if node is not None and node not in allowed:
            raise ConfigError(f"{'.'.join(path)}={node!r}: choose one of {', '.join(allowed)}")
    _check_values(cfg, str(command))
    if "model" in cfg:
        _check_model(cfg)
    if command != "export":
        _check_dataset_values(cfg, str(command))
