"""Reload a finished run: its resolved config, model and dataset."""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from .checkpoint import load_checkpoint, load_state
from .data.errors import CheckpointError, ConfigError


def load_run(run_dir, data_dir=None):
    """-> (config, model with trained weights, dataset, run_dir)."""
    from .data.hdf5 import load_dataset
    from .data.scenes import get_dataset
    from .models.build import build_model

    if run_dir in (None, "", "???"):
        raise ConfigError("run=<run dir> is required (a directory written by `liedfl train`)")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"run={run_dir}: no such run directory")
    ckpt = run_dir / "checkpoints" / "last.pt"
    payload = load_checkpoint(ckpt)
    cfg = OmegaConf.create(payload["config"])
    ds_path = Path(payload.get("dataset_path", ""))
    if ds_path.is_file():
        dataset = load_dataset(ds_path)
    else:  # regenerate from the recorded config (deterministic given its seed)
        dataset, _ = get_dataset(cfg.dataset, data_dir or cfg.paths.data_dir)
    try:
        model = build_model(cfg, dataset)
    except Exception as e:  # noqa: BLE001
        raise CheckpointError(f"{ckpt}: field 'config' does not build a model ({e})") from None
    load_state(ckpt, model, payload)
    return cfg, model, dataset, run_dir
