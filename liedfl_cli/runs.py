"""Reload a finished run: its resolved config, model and dataset."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from .checkpoint import load_checkpoint, load_state
from .errors import CheckpointError, ConfigError


def _recorded_dataset(run_dir: Path, recorded) -> Path | None:
    """The dataset file recorded in the checkpoint, if it still exists. A relative path is relative
    to the directory `liedfl train` ran in (Hydra's runtime.cwd in <run>/.hydra/hydra.yaml), which
    need not be the current one."""
    if not recorded:
        return None
    path = Path(str(recorded))
    candidates = [path]
    if not path.is_absolute():
        hydra_yaml = run_dir / ".hydra" / "hydra.yaml"
        try:
            cwd = OmegaConf.select(OmegaConf.load(hydra_yaml), "hydra.runtime.cwd", default=None)
        except Exception:
            cwd = None
        if cwd:
            candidates.append(Path(str(cwd)) / path)
    return next((c for c in candidates if c.is_file()), None)


def load_run(run_dir, data_dir=None):
    """-> (config, model with trained weights, dataset, run_dir)."""
    from .data.hdf5 import load_dataset
    from .data.scenes import get_dataset
    from .factory import build_model

    if run_dir in (None, "", "???"):
        raise ConfigError("run=<run dir> is required (a directory written by `liedfl train`)")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"run={run_dir}: no such run directory")
    ckpt = run_dir / "checkpoints" / "last.pt"
    payload = load_checkpoint(ckpt)
    if not isinstance(payload["config"], dict):
        raise CheckpointError(f"{ckpt}: field 'config' is not a mapping (got {type(payload['config']).__name__})")
    try:
        cfg = OmegaConf.create(payload["config"])
    except Exception as e:
        raise CheckpointError(f"{ckpt}: field 'config' is not a valid config ({type(e).__name__}: {e})") from None
    ds_path = _recorded_dataset(run_dir, payload.get("dataset_path"))
    if ds_path is not None:
        dataset = load_dataset(ds_path)
    else:  # regenerate from the recorded config (deterministic given its seed)
        dataset, _ = get_dataset(cfg.dataset, data_dir or cfg.paths.data_dir)
    try:
        model = build_model(cfg, dataset)
    except Exception as e:
        raise CheckpointError(f"{ckpt}: field 'config' does not build a model ({e})") from None
    load_state(ckpt, model, payload)
    return cfg, model, dataset, run_dir
