"""Reload a finished run: its config (typed once, at load), model and dataset (`LoadedRun`)."""

from __future__ import annotations

import contextlib
import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from ..errors import CheckpointError, ConfigError, DatasetError
from ..files.checkpoint import checkpoint_path, checkpoint_record, load_checkpoint, load_state
from ..files.dataset_identity import check_unchanged
from . import resolvers  # noqa: F401  (registers the config resolvers)
from .typed import RunConfig, typed


@dataclass
class LoadedRun:
    """A finished run as `load_run_checkpoint` loads it: the run's saved config typed once (the
    `RunConfig` of its `liedfl train`; the file format is unchanged), the model with its trained
    weights, the dataset, the run's folder and the record of the checkpoint loaded. `rollout`,
    `eval`, `export` and the API receive this, never the saved config itself."""

    config: RunConfig
    model: Any
    dataset: Any
    run_dir: Path
    checkpoint: dict = field(default_factory=dict)

    @property
    def model_name(self) -> str | None:
        """`model.name` of the run's config (None when it has none)."""
        name = (self.config.model or {}).get("name")
        return None if name is None else str(name)


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


def _one_line(e: Exception) -> str:
    """An exception's text on one line (omegaconf's messages add `full_key: ...` lines)."""
    return "; ".join(ln.strip() for ln in str(e).splitlines() if ln.strip()) or type(e).__name__


def load_run(run_dir, data_dir=None, checkpoint: str = "best"):
    """-> (typed config, model with trained weights on the runtime's device and dtype, dataset, run_dir).
    checkpoint: `best` (checkpoints/best.pt, the selected model, when the run has one; else last.pt)
    or `last`. The checkpoint is loaded with `map_location` = that device."""
    run = load_run_checkpoint(run_dir, data_dir, checkpoint)
    return run.config, run.model, run.dataset, run.run_dir


def saved_config(payload: dict, ckpt: Path) -> RunConfig:
    """The run's config saved in its checkpoint (`payload["config"]`, a plain mapping), typed once.
    Its dataset section is not checked again (the run's data are the recorded file; the section is
    checked where the data are generated again from it: `scenes.get_dataset`)."""
    if not isinstance(payload["config"], dict):
        raise CheckpointError(f"{ckpt}: field 'config' is not a mapping (got {type(payload['config']).__name__})")
    try:
        cfg = OmegaConf.create(payload["config"])
    except Exception as e:
        raise CheckpointError(
            f"{ckpt}: field 'config' is not a valid config ({type(e).__name__}: {_one_line(e)})"
        ) from None
    try:
        # what the model is built from must be in the saved config (the typed sections fill in
        # defaults, which would hide a damaged checkpoint)
        _ = (cfg.seed, cfg.train.epsilon, cfg.model)
        return typed(cfg, "train", check_dataset=False)
    except Exception as e:
        raise CheckpointError(f"{ckpt}: field 'config' does not build a model ({_one_line(e)})") from None


def load_run_checkpoint(
    run_dir, data_dir=None, checkpoint: str = "best", accept_changed_dataset: bool = False
) -> LoadedRun:
    """`load_run` as a `LoadedRun`, with the record of the checkpoint loaded (`checkpoint.checkpoint_record`:
    file, epoch, selection metric and value). The run's config comes from checkpoints/last.pt, which
    is always loaded and checked (a broken last.pt is a broken run); best.pt then replaces the weights.
    The recorded dataset file must be the one trained on (its SHA-256, `dataset_identity`) unless
    `accept_changed_dataset`; the model must give finite values at the data's first step."""
    from ..data.hdf5 import load_dataset
    from ..data.scenes import get_dataset
    from .factory import build_model, placement

    if run_dir in (None, "", "???"):
        raise ConfigError("run=<run dir> is required (a directory written by `liedfl train`)")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"run={run_dir}: no such run directory")
    selected = checkpoint_path(run_dir, checkpoint)
    ckpt = run_dir / "checkpoints" / "last.pt"
    payload = load_checkpoint(ckpt, map_location=placement()[0])
    cfg = saved_config(payload, ckpt)
    ds_path = _recorded_dataset(run_dir, payload.get("dataset_path"))
    if ds_path is not None:
        with _naming_the_users_file(cfg, ds_path):
            check_unchanged(ckpt, payload.get("dataset_sha256"), ds_path, accept_changed_dataset)
            dataset = load_dataset(ds_path)
    else:  # regenerate from the recorded config (deterministic given its seed; checked there)
        assert cfg.dataset is not None
        dataset, _ = get_dataset(cfg.dataset, data_dir or cfg.paths.data_dir)
    try:
        model = build_model(cfg, dataset)
    except Exception as e:
        raise CheckpointError(f"{ckpt}: field 'config' does not build a model ({_one_line(e)})") from None
    load_state(ckpt, model, payload)
    if selected != ckpt:
        ckpt, payload = selected, load_checkpoint(selected, map_location=placement()[0])
        load_state(ckpt, model, payload)
    check_finite_first_step(ckpt, model, dataset)
    return LoadedRun(cfg, model, dataset, run_dir, checkpoint_record(ckpt, payload))


@contextlib.contextmanager
def _naming_the_users_file(cfg: RunConfig, cached: Path):
    """Errors and warnings about the cached copy of a user's file (dataset=file / import) also name
    the user's file (`dataset.path`), which is the one they know."""
    import warnings

    from ..errors import DataWarning

    source = cfg.dataset.get("path") if cfg.dataset is not None else None
    if not isinstance(source, str) or not source:
        yield
        return
    note = f" (the cached copy of {source})"
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", DataWarning)
            try:
                yield
            except DatasetError as e:
                raise DatasetError(f"{e}{note}") from None
    finally:  # re-emitted once the recording has ended
        for w in caught:
            if issubclass(w.category, DataWarning):
                warnings.warn(f"{w.message}{note}", w.category, stacklevel=3)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def check_finite_first_step(ckpt, model, dataset) -> None:
    """CheckpointError when the model, from the first pair of the first test (else train) trajectory,
    predicts a non-finite pose or residual: weights such as a diverged run's (finite but huge) would
    otherwise roll out as a table of Newton failures, or fail inside a linear-algebra library."""
    import numpy as np
    import torch

    from ..solvers.options import SolverOptions
    from .factory import data_pose

    idx = np.asarray(dataset.test_idx if len(dataset.test_idx) else dataset.train_idx)[:1]
    if len(idx) == 0 or dataset.n_steps < 2:
        return
    truth = data_pose(dataset, idx)
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            ro = model.rollout(g0, g1, 3, SolverOptions())
    except (ArithmeticError, ValueError, RuntimeError) as e:
        bad = f"{type(e).__name__}: {e}"
    else:
        finite = bool(torch.isfinite(ro.pose.R).all() and torch.isfinite(ro.pose.p).all())
        finite = finite and bool(torch.isfinite(ro.residual_norm).all())
        bad = "" if finite else "non-finite values"
    finally:
        model.train(was_training)
    if bad:
        big = max(((float(v.abs().max()), k) for k, v in model.state_dict().items() if v.numel()), default=(0.0, ""))
        raise CheckpointError(
            f"{ckpt}: the model's predictions are non-finite from the data's first pair ({bad}; largest "
            f"|weight| {big[0]:.3g} in state_dict.{big[1]}): the weights are unusable"
        )


# ----------------------------------------------------------------------------- other run files
def read_train_metrics(path) -> list[dict]:
    """`train_metrics.csv` -> rows of floats; DatasetError naming the file, row and column when garbled."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames
            if not header or any(not h or not h.strip() for h in header):
                raise DatasetError(f"{path}: missing or empty column name in the header line")
            for col in ("epoch", "loss"):
                if col not in header:
                    raise DatasetError(f"{path}: column '{col}' is missing (header: {', '.join(header)})")
            rows = []
            for i, r in enumerate(reader, start=2):
                if None in r:
                    raise DatasetError(f"{path}: line {i} has more fields than the header")
                row = {}
                for k, v in r.items():
                    if v in (None, ""):
                        continue
                    try:
                        x = float(v)
                    except ValueError:
                        raise DatasetError(f"{path}: line {i}, column '{k}': {v!r} is not a number") from None
                    if k == "epoch" and not (math.isfinite(x) and x == int(x) and x >= 1):
                        raise DatasetError(f"{path}: line {i}, column 'epoch': {v!r} is not a positive integer")
                    row[k] = x
                rows.append(row)
    except (UnicodeDecodeError, csv.Error) as e:
        raise DatasetError(f"{path}: not a CSV text file ({type(e).__name__})") from None
    return rows


def read_json_object(path) -> dict:
    """A JSON file holding an object; DatasetError naming the file when garbled."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a UTF-8 text file") from None
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    if not isinstance(obj, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(obj).__name__}")
    return obj


def check_run_files(run_dir) -> None:
    """The files `liedfl eval` reads besides the checkpoint and the rollout (`train_metrics.csv`,
    `recovery.json`), checked before anything is recomputed: a garbled one is a one-line error."""
    run_dir = Path(str(run_dir))
    if (run_dir / "train_metrics.csv").is_file():
        read_train_metrics(run_dir / "train_metrics.csv")
    if (run_dir / "recovery.json").is_file():
        read_json_object(run_dir / "recovery.json")
