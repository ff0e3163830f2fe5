"""Checkpoints: state dict + resolved config + versions, written atomically, loaded with checks.

Checkpoints are loaded with `torch.load(..., weights_only=True)`: the safe unpickler accepts tensors
and plain Python containers (dict, list, tuple, str, int, float, bool, None) and refuses anything
else, so a crafted `last.pt` cannot run code. `save_checkpoint` therefore stores plain types only:
it converts what has an obvious plain form (str subclasses such as `torch.__version__`, numpy arrays
and scalars, paths) and refuses the rest with a `CheckpointError` naming the field, and it re-reads
the written file with the safe loader before renaming it into place.

Resume payloads (optimizer / scheduler `state_dict()`s, `capture_rng_state()`, an epoch number)
are plain already and round-trip unchanged.
"""

from __future__ import annotations

import platform
import random
from collections import OrderedDict
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import torch

from .. import __version__
from ..errors import CheckpointError
from .io_utils import atomic_path

REQUIRED = ("state_dict", "config", "versions")


# ----------------------------------------------------------------------------- plain types
def to_plain(x: Any, where: str = "checkpoint") -> Any:
    """`x` converted to types the weights_only unpickler accepts; CheckpointError naming `where` otherwise.

    Tensors are detached (and moved to the CPU); numpy arrays become tensors; numpy scalars,
    str / int / float subclasses (e.g. `torch.__version__`, a TorchVersion) and paths become the
    plain builtin; dicts (keys str/int/float/bool/None), lists and tuples are converted element-wise.
    """
    if x is None or type(x) in (bool, int, float, str):
        return x
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    if isinstance(x, np.ndarray):
        if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == np.bool_):
            raise CheckpointError(f"cannot store field '{where}': numpy array of dtype {x.dtype}")
        return torch.from_numpy(np.ascontiguousarray(x).copy())
    if isinstance(x, np.generic):
        return to_plain(x.item(), where)
    if isinstance(x, int):  # bool subclasses are not possible; IntEnum and friends are
        return int(x)
    if isinstance(x, float):
        return float(x)
    if isinstance(x, str):
        return str.__str__(x)
    if isinstance(x, PurePath):
        return str(x)
    if isinstance(x, (dict, OrderedDict)):
        out = {}
        for k, v in x.items():
            key = to_plain(k, f"{where}.<key>")
            if not (key is None or type(key) in (bool, int, float, str)):
                raise CheckpointError(f"cannot store field '{where}': key {k!r} of type {type(k).__name__}")
            out[key] = to_plain(v, f"{where}.{k}")
        return out
    if isinstance(x, (list, tuple)):
        items = [to_plain(v, f"{where}[{i}]") for i, v in enumerate(x)]
        return items if isinstance(x, list) else tuple(items)
    raise CheckpointError(
        f"cannot store field '{where}' of type {type(x).__module__}.{type(x).__qualname__} in a checkpoint "
        "(only tensors, numbers, strings, None, lists, tuples and dicts)"
    )


def _safe_load(path, what: str = "checkpoint", map_location: Any = "cpu"):
    """torch.load with weights_only=True, tensors moved to `map_location`; TorchVersion (a str
    subclass) is allowed so that checkpoints written before versions were stored as plain strings
    stay readable."""
    import warnings

    safe_globals = getattr(torch.serialization, "safe_globals", None)
    with warnings.catch_warnings():
        # a plain (non-zip) pickle: torch warns about its protocol over two lines before the refusal
        warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
        if safe_globals is not None:
            from torch.torch_version import TorchVersion

            with safe_globals([TorchVersion]):
                return torch.load(path, map_location=map_location, weights_only=True)
        return torch.load(path, map_location=map_location, weights_only=True)  # pragma: no cover (torch < 2.5)


def _refusal(e: Exception) -> str:
    """The informative line of torch's (multi-line) weights_only refusal."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    for key in ("GLOBAL", "Unsupported", "unsupported", "error"):
        for ln in lines:
            if key in ln and "Weights only load failed" not in ln:
                return ln.rstrip(".")
    return lines[-1] if lines else type(e).__name__


# ----------------------------------------------------------------------------- save / load
def save_checkpoint(path, model, config: dict, extra: dict | None = None) -> None:
    """Write `{state_dict, config, versions, **extra}` atomically; every value must be plain (see
    `to_plain`). Extra keys used for resume: `optimizer`, `scheduler` (their `state_dict()`),
    `rng` (`capture_rng_state()`), `epoch` (int)."""
    extra = dict(extra or {})
    clash = sorted(set(extra) & set(REQUIRED))
    if clash:
        raise CheckpointError(f"{path}: extra field(s) {clash} would overwrite the checkpoint's own fields")
    payload = {
        "state_dict": to_plain(model.state_dict(), "state_dict"),
        "config": to_plain(config, "config"),
        "versions": {"liedfl": __version__, "torch": str(torch.__version__), "python": platform.python_version()},
    }
    for k, v in extra.items():
        payload[str(k)] = to_plain(v, str(k))
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
        try:  # what is written must load with the safe loader
            _safe_load(tmp)
        except Exception as e:
            raise CheckpointError(
                f"{path}: the checkpoint would not load with weights_only=True ({_refusal(e)})"
            ) from None


def load_checkpoint(path, map_location: Any = "cpu") -> dict:
    """Load a checkpoint with the safe unpickler (weights_only=True); CheckpointError on any problem.

    map_location: where its tensors go (`torch.load`'s argument: "cpu", a device such as the
    runtime's, ...). Training state (RNG states) must stay on the CPU: resume loads with the default."""
    import pickle

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        payload = _safe_load(path, map_location=map_location)
    except pickle.UnpicklingError as e:
        if "GLOBAL" in str(e):  # a reference to a class or function: what runs code on unpickling
            raise CheckpointError(
                f"{path}: refused: the file holds Python objects other than tensors and plain data "
                f"({_refusal(e)}); only checkpoints written by liedfl are loaded"
            ) from None
        raise CheckpointError(f"{path}: not a readable checkpoint (UnpicklingError: {_refusal(e)})") from None
    except Exception as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {_refusal(e)})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: checkpoint is not a dict")
    for k in REQUIRED:
        if k not in payload:
            raise CheckpointError(f"{path}: checkpoint has no field '{k}'")
    return payload


def check_training_state(path, payload: dict) -> int:
    """The checkpoint's `epoch` (an integer >= 0) after checking that `history` is its list of
    per-epoch rows (dicts with numbers `epoch` = 1, 2, ..., epoch, `loss` and `seconds`); CheckpointError
    naming the field otherwise (a tampered file would train "epochs" -4..2 or crash mid-resume)."""
    epoch, history = payload.get("epoch"), payload.get("history")
    if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
        raise CheckpointError(f"{path}: field 'epoch' must be an integer >= 0, got {epoch!r}")
    if not isinstance(history, list):
        raise CheckpointError(f"{path}: field 'history' must be a list of per-epoch rows, got {type(history).__name__}")
    if len(history) != epoch:
        raise CheckpointError(f"{path}: field 'history' has {len(history)} rows for epoch {epoch} (one per epoch)")
    for i, row in enumerate(history):
        if not isinstance(row, dict):
            raise CheckpointError(f"{path}: field 'history[{i}]' is not a mapping (got {type(row).__name__})")
        if row.get("epoch") != i + 1 or isinstance(row.get("epoch"), bool):
            raise CheckpointError(f"{path}: field 'history[{i}].epoch' must be {i + 1}, got {row.get('epoch')!r}")
        for key in ("loss", "seconds"):
            v = row.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise CheckpointError(f"{path}: field 'history[{i}].{key}' must be a number, got {v!r}")
    return epoch


def load_state(path, model, payload: dict) -> None:
    """Load the state dict, naming the first missing/unexpected/mis-shaped key."""
    sd = payload["state_dict"]
    if not isinstance(sd, dict):
        raise CheckpointError(f"{path}: field 'state_dict' is not a mapping (got {type(sd).__name__})")
    own = model.state_dict()
    for k, v in sd.items():
        if not isinstance(v, torch.Tensor):
            raise CheckpointError(f"{path}: field 'state_dict.{k}' is not a tensor (got {type(v).__name__})")
        if k not in own:
            raise CheckpointError(f"{path}: field 'state_dict' has unexpected key '{k}' for this model config")
        if v.is_complex() or v.is_floating_point() != own[k].is_floating_point():  # torch would cast silently
            raise CheckpointError(f"{path}: field 'state_dict.{k}' has dtype {v.dtype}, model expects {own[k].dtype}")
        if own[k].shape != v.shape:
            raise CheckpointError(
                f"{path}: field 'state_dict.{k}' has shape {tuple(v.shape)}, model expects {tuple(own[k].shape)}"
            )
        if v.is_floating_point() and not torch.isfinite(v).all():
            raise CheckpointError(f"{path}: field 'state_dict.{k}' has non-finite values")
    for k in own:
        if k not in sd:
            raise CheckpointError(f"{path}: field 'state_dict' lacks key '{k}'")
    model.load_state_dict(sd)


# ----------------------------------------------------------------------------- which checkpoint
CHECKPOINTS = ("best", "last")
"""`checkpoint=best|last` of `liedfl rollout` / `liedfl eval` and `api.load_run`."""
CHECKPOINT_FILE = "checkpoint.json"
"""Next to a rollout.h5: the checkpoint that produced it (`checkpoint_record`)."""


def checkpoint_path(run_dir, which: str = "best") -> Path:
    """`<run>/checkpoints/best.pt` for which=best when it exists (the selected model, see
    docs/validation.md), else `<run>/checkpoints/last.pt` (runs trained with `train.select=last` or
    before validation existed)."""
    from ..errors import ConfigError

    if which not in CHECKPOINTS:
        raise ConfigError(f"checkpoint={which!r}: choose one of {', '.join(CHECKPOINTS)}")
    folder = Path(run_dir) / "checkpoints"
    if which == "best" and (folder / "best.pt").is_file():
        return folder / "best.pt"
    return folder / "last.pt"


def checkpoint_record(path, payload: dict) -> dict:
    """What a loaded checkpoint is: {checkpoint: file name, checkpoint_epoch, [selected_by, value]}."""
    epoch = payload.get("epoch")
    if epoch is not None and (
        isinstance(epoch, bool) or not isinstance(epoch, (int, float)) or not float(epoch).is_integer()
    ):
        raise CheckpointError(f"{path}: field 'epoch' must be an integer, got {epoch!r:.60}")
    record: dict[str, Any] = {"checkpoint": Path(path).name, "checkpoint_epoch": None if epoch is None else int(epoch)}
    metric = payload.get("selected_by")
    if isinstance(metric, str):
        record["selected_by"] = metric
        val = payload.get("val")
        value = val.get(metric) if isinstance(val, dict) else None
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise CheckpointError(f"{path}: field 'val.{metric}' must be a number, got {value!r:.60}")
        record["value"] = None if value is None else float(value)
    return record


def file_sha256(path) -> str | None:
    """The SHA-256 (hex) of a file's bytes, None when it cannot be read."""
    import hashlib

    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
    except OSError:
        return None
    return digest.hexdigest()


def new_run_id() -> str:
    """A run's stable id (written into its checkpoints, summary.json and rollout files)."""
    import uuid

    return uuid.uuid4().hex


def run_provenance(run_dir, run_id: str | None, model_name: str | None, used: dict) -> dict:
    """The provenance attributes of a rollout file written by the run `run_dir` from the checkpoint `used`
    (`checkpoint_record`, its file in `<run>/checkpoints/`); see `rollout_file.PROVENANCE`."""
    name = used.get("checkpoint")
    return {
        "run_id": run_id,
        "run_dir": str(Path(run_dir).resolve()),
        "model_name": model_name,
        "checkpoint": name,
        "checkpoint_sha256": file_sha256(Path(run_dir) / "checkpoints" / name) if name else None,
    }


def describe_checkpoint(used: dict) -> str:
    """`checkpoint: best.pt (epoch 340, val_one_step_error 1.2e-04)`."""
    text = f"checkpoint: {used['checkpoint']} (epoch {used.get('checkpoint_epoch')}"
    if used.get("selected_by"):
        value = used.get("value")
        text += f", {used['selected_by']} {float('nan') if value is None else float(value):.2e}"
    if used.get("note"):
        text += f"; {used['note']}"
    return text + ")"


def rollout_checkpoint(rollout_path, loaded: dict) -> dict:
    """The checkpoint record of a rollout file: its `checkpoint.json` (written next to it by `liedfl
    train` / `liedfl rollout`) when there is a readable one, else `loaded` (the checkpoint just loaded;
    runs written before checkpoint.json existed rolled out last.pt)."""
    import json

    path = Path(rollout_path).parent / CHECKPOINT_FILE
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return loaded
    return record if isinstance(record, dict) and "checkpoint" in record else loaded


# ----------------------------------------------------------------------------- RNG state
def capture_rng_state(generators: dict[str, torch.Generator] | None = None) -> dict:
    """The global RNG states of torch (CPU, and CUDA when available), numpy and Python's `random`,
    plus the states of named `torch.Generator`s, as weights_only-safe types (tensors, ints, floats).
    `restore_rng_state` puts them back."""
    np_state: Any = np.random.get_state(legacy=True)  # noqa: NPY002 (the global legacy state is what is saved)
    py_version, py_state, py_gauss = random.getstate()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "bit_generator": str(np_state[0]),
            "key": torch.from_numpy(np.asarray(np_state[1], dtype=np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gaussian": float(np_state[4]),
        },
        "python": {
            "version": int(py_version),
            "state": torch.tensor(py_state, dtype=torch.int64),
            "gauss_next": None if py_gauss is None else float(py_gauss),
        },
        "generators": {k: g.get_state() for k, g in (generators or {}).items()},
    }
    if torch.cuda.is_available():  # pragma: no cover (no GPU in CI)
        state["cuda"] = list(torch.cuda.get_rng_state_all())
    return state


def restore_rng_state(state: dict, generators: dict[str, torch.Generator] | None = None) -> None:
    """Inverse of `capture_rng_state` (CheckpointError on a malformed state)."""
    try:
        torch.set_rng_state(state["torch"])
        n = state["numpy"]
        key = n["key"].numpy().astype(np.uint32)
        legacy = (n["bit_generator"], key, int(n["pos"]), int(n["has_gauss"]), float(n["cached_gaussian"]))
        np.random.set_state(legacy)  # noqa: NPY002
        p = state["python"]
        gauss = p["gauss_next"]
        random.setstate((int(p["version"]), tuple(int(v) for v in p["state"].tolist()), gauss))
        saved = state.get("generators", {})
        for k, g in (generators or {}).items():
            if k not in saved:
                raise KeyError(f"generators.{k}")
            g.set_state(saved[k])
        if "cuda" in state and torch.cuda.is_available():  # pragma: no cover
            torch.cuda.set_rng_state_all(state["cuda"])
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as e:
        raise CheckpointError(f"field 'rng' is not a valid RNG state ({type(e).__name__}: {e})") from None


__all__ = [
    "REQUIRED",
    "CHECKPOINTS",
    "CHECKPOINT_FILE",
    "checkpoint_path",
    "checkpoint_record",
    "describe_checkpoint",
    "rollout_checkpoint",
    "file_sha256",
    "new_run_id",
    "run_provenance",
    "save_checkpoint",
    "load_checkpoint",
    "load_state",
    "to_plain",
    "capture_rng_state",
    "restore_rng_state",
]
