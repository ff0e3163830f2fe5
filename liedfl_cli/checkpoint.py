"""Checkpoints: state dict + resolved config + versions, written atomically, loaded with checks."""

from __future__ import annotations

import platform
from pathlib import Path

import torch

from . import __version__
from .errors import CheckpointError
from .io_utils import atomic_path

REQUIRED = ("state_dict", "config", "versions")


def save_checkpoint(path, model, config: dict, extra: dict | None = None) -> None:
    payload = {
        "state_dict": model.state_dict(),
        "config": config,
        "versions": {"liedfl": __version__, "torch": torch.__version__, "python": platform.python_version()},
        **(extra or {}),
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def load_checkpoint(path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: checkpoint is not a dict")
    for k in REQUIRED:
        if k not in payload:
            raise CheckpointError(f"{path}: checkpoint has no field '{k}'")
    return payload


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
        if own[k].shape != v.shape:
            raise CheckpointError(
                f"{path}: field 'state_dict.{k}' has shape {tuple(v.shape)}, model expects {tuple(own[k].shape)}"
            )
        if not torch.isfinite(v).all():
            raise CheckpointError(f"{path}: field 'state_dict.{k}' has non-finite values")
    for k in own:
        if k not in sd:
            raise CheckpointError(f"{path}: field 'state_dict' lacks key '{k}'")
    model.load_state_dict(sd)
