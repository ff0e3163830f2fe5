"""The rollout file `rollout.h5`: its one writer, reader and validator.

Format (docs/data_format.md, section "rollout.h5"):

  root attributes  steps (S: every trajectory holds S+1 poses), h, dataset_scene, group (the product
                   group's name, e.g. "SE(3) x SO(3)"; absent in files written before it was added);
                   provenance (optional, absent in older files): run_id (the id of the run that wrote
                   it), run_dir, model_name, checkpoint (file name), checkpoint_sha256, dtype (the
                   rollout's floating type before widening to float64)
  traj_index       (T,) int: the dataset trajectories rolled out (members of its test split)
  <model>/         one group per rolled-out model: `model`, and `true_scheme` when the scene has a
                   true-parameter scheme
    R              (T, S+1, B, 3, 3) float64, SE(3) bodies first
    p              (T, S+1, m, 3) float64
    converged      (T, S-1) bool: converged[:, j] flags the implicit solve that produced sample j + 2
                   (samples 0 and 1 are the given initial pair)
    iterations     (T, S-1) int
    residual_norm  (T, S-1) float64 (optional on reading)
    attributes     seconds, seconds_per_step, n_failed, first_failure (the first sample index whose
                   solve did not converge in some trajectory, -1 for none), n_trajectories
    one_step/      optional (files written before it have none): teacher-forced one-step predictions
                   of samples 2..n (n = min(S, N), N the dataset's steps), each from the TRUE pair
                   (g_{k-1}, g_k): R (T, n-1, B, 3, 3), p (T, n-1, m, 3), converged (T, n-1) bool;
                   attributes seconds, n_pairs

`write_rollout` writes a file atomically, `read_rollout` reads one and checks it is self-consistent,
`validate_rollout` checks it against the dataset it claims to roll out (including that every model
starts from the data's first two poses), and `load_rollout` does both.
Every problem is a `DatasetError` with one line naming the file and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import DatasetError
from ..lie import Pose
from ..lie.product import ProductGroup
from .io_utils import atomic_path

FILE_NAME = "rollout.h5"
REQUIRED = ("R", "p", "converged", "iterations")
"""Datasets every model group must hold (residual_norm is optional on reading)."""
PROVENANCE = ("run_id", "run_dir", "model_name", "checkpoint", "checkpoint_sha256", "dtype")
"""Optional root attributes (strings): which run, model and checkpoint wrote the file (docs/data_format.md)."""
START_RTOL = {"float64": 1e-9, "float32": 1e-6}
"""Relative tolerance of the start check (samples 0 and 1 against the data) by the rollout's recorded dtype;
files that do not record it get the float32 one (they may hold widened float32 rollouts)."""


@dataclass
class OneStep:
    """Teacher-forced one-step predictions of samples 2..n, each from the true pair (g_{k-1}, g_k)."""

    R: np.ndarray  # (T, n-1, B, 3, 3) float64
    p: np.ndarray  # (T, n-1, m, 3) float64
    converged: np.ndarray  # (T, n-1) bool
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def pose(self) -> Pose:
        return Pose(torch.from_numpy(self.R), torch.from_numpy(self.p))

    @property
    def n_failed(self) -> int:
        return int((~self.converged).sum())

    @classmethod
    def from_predictions(cls, pose: Pose, converged: torch.Tensor, seconds: float) -> OneStep:
        """From `solvers.one_step.one_step_predictions`' output (any device and dtype; stored as CPU float64)."""
        f64 = lambda t: t.detach().to(device="cpu", dtype=torch.float64).numpy()
        conv = converged.detach().cpu().numpy().astype(bool)
        return cls(
            R=f64(pose.R), p=f64(pose.p), converged=conv, attrs={"seconds": float(seconds), "n_pairs": int(conv.size)}
        )


@dataclass
class RolloutEntry:
    """One rolled-out model: poses and per-step Newton diagnostics (numpy arrays)."""

    R: np.ndarray  # (T, S+1, B, 3, 3) float64
    p: np.ndarray  # (T, S+1, m, 3) float64
    converged: np.ndarray  # (T, S-1) bool
    iterations: np.ndarray  # (T, S-1) int
    residual_norm: np.ndarray | None = None  # (T, S-1) float64
    attrs: dict[str, Any] = field(default_factory=dict)
    one_step: OneStep | None = None  # optional: teacher-forced one-step predictions

    @property
    def steps(self) -> int:
        """S: number of time steps of the rollout."""
        return int(self.R.shape[1]) - 1

    @property
    def pose(self) -> Pose:
        """The poses as a torch `Pose` (float64)."""
        return Pose(torch.from_numpy(self.R), torch.from_numpy(self.p))

    @property
    def n_failed(self) -> int:
        """Number of implicit solves (over all trajectories and steps) that did not converge."""
        return int((~self.converged).sum())

    @property
    def first_failure(self) -> int | None:
        """The first sample index k (2..S) whose implicit solve did not converge in some trajectory."""
        bad = np.nonzero((~self.converged).any(0))[0]
        return int(bad[0]) + 2 if len(bad) else None

    @property
    def mean_iterations(self) -> float:
        return float(self.iterations.mean()) if self.iterations.size else 0.0

    @property
    def seconds_per_step(self) -> float | None:
        v = self.attrs.get("seconds_per_step")
        return float(v) if v is not None else None

    def summary(self) -> dict:
        """Timing and solver summary (what `liedfl train` records in summary.json)."""
        return {
            "seconds": float(self.attrs.get("seconds", math.nan)),
            "seconds_per_step": float(self.attrs.get("seconds_per_step", math.nan)),
            "n_failed": self.n_failed,
            "first_failure": self.first_failure,
            "mean_newton_iterations": self.mean_iterations,
        }

    @classmethod
    def from_rollout(cls, ro) -> RolloutEntry:
        """From a solver `Rollout` (pose, converged, iterations, residual_norm: tensors on any device, in
        any floating dtype; seconds): the file holds CPU float64 (float32 rollouts are widened)."""
        f64 = lambda t: t.detach().to(device="cpu", dtype=torch.float64).numpy()
        R = f64(ro.pose.R)
        entry = cls(
            R=R,
            p=f64(ro.pose.p),
            converged=ro.converged.detach().cpu().numpy().astype(bool),
            iterations=ro.iterations.detach().cpu().numpy(),
            residual_norm=f64(ro.residual_norm),
        )
        steps = entry.steps
        entry.attrs = {
            "seconds": float(ro.seconds),
            "seconds_per_step": float(ro.seconds) / max(steps - 1, 1),
            "n_failed": entry.n_failed,
            "first_failure": entry.first_failure or -1,
            "n_trajectories": int(R.shape[0]),
        }
        return entry


@dataclass
class RolloutFile:
    """The content of a rollout.h5 (see the module docstring)."""

    path: Path
    steps: int
    h: float
    traj_index: np.ndarray  # (T,) int64
    models: dict[str, RolloutEntry]
    scene: str | None = None
    group: str | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def layout(self) -> tuple[int, int]:
        """(B bodies, m SE(3) bodies) of the poses."""
        e = self.models["model"]
        return int(e.R.shape[2]), int(e.p.shape[2])

    @property
    def model(self) -> RolloutEntry:
        return self.models["model"]

    @property
    def provenance(self) -> dict[str, str]:
        """The provenance attributes the file has (empty for files written before they existed)."""
        return {k: str(self.attrs[k]) for k in PROVENANCE if self.attrs.get(k) not in (None, "")}


def _short(xs: list, n: int = 8) -> str:
    return ", ".join(map(str, xs[:n])) + (", ..." if len(xs) > n else "")


def _group_name(B: int, m: int) -> str:
    try:
        return ProductGroup(m, B - m).name
    except ValueError:
        return f"{B} bodies with {m} on SE(3)"


# --------------------------------------------------------------------------- checks
def _check(rf: RolloutFile) -> RolloutFile:
    """Self-consistency of a rollout file's content (DatasetError naming the file and field)."""
    path = rf.path
    if "model" not in rf.models:
        raise DatasetError(f"{path}: group 'model' is missing")
    if rf.steps < 2:
        raise DatasetError(f"{path}: attribute 'steps' = {rf.steps!r}: must be an integer >= 2")
    if not (math.isfinite(rf.h) and rf.h > 0):
        raise DatasetError(f"{path}: attribute 'h' = {rf.h!r}: must be a positive number")
    idx = rf.traj_index
    if idx.ndim != 1 or idx.size == 0:
        raise DatasetError(f"{path}: dataset 'traj_index' has shape {idx.shape}: need a non-empty 1-D array")
    T, S = len(idx), int(rf.steps)
    layout = None
    for name, e in rf.models.items():
        for key, arr, rank, tail in (("R", e.R, 5, (3, 3)), ("p", e.p, 4, (3,))):
            if arr.ndim != rank or arr.shape[-len(tail) :] != tail:
                dims = "(T, S+1, B, 3, 3)" if key == "R" else "(T, S+1, m, 3)"
                raise DatasetError(
                    f"{path}: dataset '{name}/{key}' has shape {arr.shape} (rank {arr.ndim}); need {dims}"
                )
            if arr.shape[0] != T:
                raise DatasetError(
                    f"{path}: dataset '{name}/{key}' holds {arr.shape[0]} trajectories but 'traj_index' lists {T}"
                )
            if arr.shape[1] != S + 1:
                raise DatasetError(
                    f"{path}: dataset '{name}/{key}' holds {arr.shape[1]} poses per trajectory but attribute "
                    f"'steps' = {S} needs {S + 1}"
                )
        B, m = int(e.R.shape[2]), int(e.p.shape[2])
        if m > B or B == 0:
            raise DatasetError(f"{path}: dataset '{name}/p' has {m} SE(3) bodies but '{name}/R' has {B} bodies")
        if layout is None:
            layout = (B, m, name)
        elif (B, m) != layout[:2]:
            raise DatasetError(
                f"{path}: group '{name}' is on {_group_name(B, m)} but group '{layout[2]}' on "
                f"{_group_name(*layout[:2])}"
            )
        for key in ("converged", "iterations", "residual_norm"):
            arr = getattr(e, key)
            if arr is not None and arr.shape != (T, S - 1):
                raise DatasetError(
                    f"{path}: dataset '{name}/{key}' has shape {arr.shape}; need (T, S-1) = {(T, S - 1)}"
                )
        if e.one_step is not None:
            _check_one_step(path, name, e.one_step, T, S, B, m)
    if rf.group is not None and layout is not None and rf.group != _group_name(*layout[:2]):
        raise DatasetError(f"{path}: attribute 'group' = {rf.group!r} but the poses are on {_group_name(*layout[:2])}")
    return rf


def _check_one_step(path: Path, name: str, o: OneStep, T: int, S: int, B: int, m: int) -> None:
    """Shapes of `<name>/one_step/`: R (T, K, B, 3, 3), p (T, K, m, 3), converged (T, K), 1 <= K <= S-1."""
    K = int(o.R.shape[1]) if o.R.ndim >= 2 else -1
    for key, arr, need, dims in (
        ("R", o.R, (T, K, B, 3, 3), "(T, K, B, 3, 3)"),
        ("p", o.p, (T, K, m, 3), "(T, K, m, 3)"),
        ("converged", o.converged, (T, K), "(T, K)"),
    ):
        if arr.shape != need or not 1 <= K <= S - 1:
            raise DatasetError(
                f"{path}: dataset '{name}/one_step/{key}' has shape {arr.shape}; need {dims} = {need} with "
                f"T = {T} trajectories, {B} bodies ({m} on SE(3)) and 1 <= K <= S-1 = {S - 1} one-step predictions"
            )


def validate_rollout(rf: RolloutFile, dataset) -> RolloutFile:
    """Check a rollout file against the dataset it rolls out: scene, h, group (body layout) and
    traj_index (each a member of the dataset's test split). DatasetError naming the file and field."""
    path = rf.path
    if rf.scene is not None and rf.scene != dataset.scene:
        raise DatasetError(
            f"{path}: attribute 'dataset_scene' = {rf.scene!r} but the dataset's scene is {dataset.scene!r}"
        )
    if not math.isclose(rf.h, dataset.h, rel_tol=1e-9):
        raise DatasetError(f"{path}: attribute 'h' = {rf.h!r} but the dataset has h = {dataset.h!r}")
    B, m = rf.layout
    if (B, m) != (dataset.n_bodies, dataset.n_se3):
        raise DatasetError(
            f"{path}: dataset 'model/R' is on {_group_name(B, m)} ({B} bodies, {m} on SE(3)) but the dataset "
            f"is on {dataset.group.name} ({dataset.n_bodies} bodies, {dataset.n_se3} on SE(3))"
        )
    test = {int(i) for i in np.asarray(dataset.test_idx)}
    for j, i in enumerate(int(i) for i in rf.traj_index):
        if i in test:
            continue
        if not 0 <= i < dataset.n_trajectories:
            why = f"the dataset has {dataset.n_trajectories} trajectories"
        else:
            why = f"it is not in the dataset's test split ({len(test)} trajectories: {_short(sorted(test))})"
        raise DatasetError(f"{path}: dataset 'traj_index' holds trajectory {i} at index {j}, but {why}")
    _check_start(rf, dataset)
    n = min(rf.steps, int(dataset.n_steps))
    for name, e in rf.models.items():
        if e.one_step is not None and e.one_step.R.shape[1] != n - 1:
            raise DatasetError(
                f"{path}: dataset '{name}/one_step/R' holds {e.one_step.R.shape[1]} one-step predictions per "
                f"trajectory; need min(steps, dataset steps) - 1 = {n - 1} (samples 2..{n})"
            )
    return rf


def _check_start(rf: RolloutFile, dataset) -> None:
    """Every model's samples 0 and 1 are the data's first two poses of the trajectory (relative tolerance
    `START_RTOL` of the pose magnitudes): a rollout starts from the true pair, so anything else is
    another dataset's, a shifted or a tampered file."""
    rtol = START_RTOL.get(str(rf.attrs.get("dtype")), START_RTOL["float32"])
    idx = [int(i) for i in rf.traj_index]
    R_true = np.asarray(dataset.R[idx][:, :2], dtype=np.float64)
    p_true = np.asarray(dataset.p[idx][:, :2], dtype=np.float64)
    for name, e in rf.models.items():
        for key, pred, true in (("R", e.R[:, :2], R_true), ("p", e.p[:, :2], p_true)):
            if true.size == 0:
                continue
            for j, i in enumerate(idx):
                scale = max(float(np.abs(true[j]).max()), 1e-300)
                for k in (0, 1):
                    err = float(np.abs(pred[j, k] - true[j, k]).max()) / scale
                    if not err <= rtol:  # NaN fails too
                        raise DatasetError(
                            f"{rf.path}: dataset '{name}/{key}' sample {k} of trajectory {i} (index {j}) is "
                            f"not the data's (relative difference {err:.3g} > {rtol:g}): a rollout starts from "
                            "the dataset's first two poses"
                        )


# --------------------------------------------------------------------------- reading
def _attr(f, key: str, path: Path):
    if key not in f.attrs:
        raise DatasetError(f"{path}: attribute '{key}' is missing")
    return f.attrs[key]


def _array(g, key: str, name: str, path: Path, kind: str) -> np.ndarray:
    import h5py

    if not isinstance(g[key], h5py.Dataset):
        raise DatasetError(f"{path}: '{name}/{key}' must be an HDF5 dataset, found a group")
    arr = np.asarray(g[key][...])
    ok = {
        "float": np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer),
        "bool": arr.dtype == bool or np.issubdtype(arr.dtype, np.integer),
        "int": np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool,
    }[kind]
    if not ok:
        raise DatasetError(f"{path}: dataset '{name}/{key}' has dtype {arr.dtype}; need {kind}")
    if kind == "float":
        return arr.astype(np.float64, copy=False)
    if kind == "bool":
        return arr.astype(bool, copy=False)
    return arr.astype(np.int64, copy=False)


def read_rollout(path) -> RolloutFile:
    """Read and self-check a rollout file (DatasetError with one line naming the file and field)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: rollout file not found (run `liedfl rollout run=<dir>` first)")
    try:
        f = h5py.File(path, "r")
    except (OSError, RuntimeError, ValueError) as e:  # h5py: RuntimeError/ValueError on corrupt metadata
        raise DatasetError(f"{path}: not an HDF5 file ({e})") from None
    try:
        with f:
            steps = _attr(f, "steps", path)
            h = _attr(f, "h", path)
            if "traj_index" not in f or not isinstance(f["traj_index"], h5py.Dataset):
                raise DatasetError(f"{path}: dataset 'traj_index' is missing")
            idx = np.asarray(f["traj_index"][...])
            if not np.issubdtype(idx.dtype, np.integer):
                raise DatasetError(f"{path}: dataset 'traj_index' has dtype {idx.dtype}; need integers")
            if "model" not in f or not isinstance(f["model"], h5py.Group):
                raise DatasetError(f"{path}: group 'model' is missing")
            models = {}
            for name in f:
                g = f[name]
                if not isinstance(g, h5py.Group):
                    continue
                missing = [k for k in REQUIRED if k not in g]
                if missing:
                    raise DatasetError(f"{path}: group '{name}' lacks dataset '{missing[0]}'")
                models[name] = RolloutEntry(
                    R=_array(g, "R", name, path, "float"),
                    p=_array(g, "p", name, path, "float"),
                    converged=_array(g, "converged", name, path, "bool"),
                    iterations=_array(g, "iterations", name, path, "int"),
                    residual_norm=_array(g, "residual_norm", name, path, "float") if "residual_norm" in g else None,
                    attrs={k: _plain(v) for k, v in g.attrs.items()},
                    one_step=_read_one_step(g, name, path) if "one_step" in g else None,
                )
            attrs = {k: _plain(v) for k, v in f.attrs.items()}
    except DatasetError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:  # RuntimeError: h5py, corrupt metadata
        raise DatasetError(f"{path}: cannot read rollout file ({type(e).__name__}: {e})") from None
    steps, h = _plain(steps), _plain(h)
    if isinstance(steps, bool) or not isinstance(steps, (int, float)) or not float(steps).is_integer() or steps < 2:
        raise DatasetError(f"{path}: attribute 'steps' = {steps!r}: must be an integer >= 2")
    if isinstance(h, bool) or not isinstance(h, (int, float)):
        raise DatasetError(f"{path}: attribute 'h' = {h!r}: must be a positive number")
    rf = RolloutFile(
        path=path,
        steps=int(steps),
        h=float(h),
        traj_index=idx.astype(np.int64),
        models=models,
        scene=str(attrs["dataset_scene"]) if "dataset_scene" in attrs else None,
        group=str(attrs["group"]) if "group" in attrs else None,
        attrs=attrs,
    )
    return _check(rf)


def _read_one_step(g, name: str, path: Path) -> OneStep:
    import h5py

    o = g["one_step"]
    if not isinstance(o, h5py.Group):
        raise DatasetError(f"{path}: '{name}/one_step' is not a group")
    missing = [k for k in ("R", "p", "converged") if k not in o]
    if missing:
        raise DatasetError(f"{path}: group '{name}/one_step' lacks dataset '{missing[0]}'")
    where = f"{name}/one_step"
    return OneStep(
        R=_array(o, "R", where, path, "float"),
        p=_array(o, "p", where, path, "float"),
        converged=_array(o, "converged", where, path, "bool"),
        attrs={k: _plain(v) for k, v in o.attrs.items()},
    )


def _plain(v):
    """numpy scalars / bytes from h5py attributes -> Python values."""
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


def load_rollout(path, dataset) -> RolloutFile:
    """`read_rollout` + `validate_rollout` against `dataset`."""
    return validate_rollout(read_rollout(path), dataset)


# --------------------------------------------------------------------------- writing
def write_rollout(
    path, *, steps: int, h: float, scene: str, traj_index, rollouts: dict, provenance: dict | None = None
) -> RolloutFile:
    """Write `rollouts` ({name: solver `Rollout` or `RolloutEntry`}, `model` first) to `path` atomically.
    provenance: root attributes naming what wrote the file (keys of `PROVENANCE`; None values skipped).

    The content is checked as on reading before anything is written. Returns the written `RolloutFile`."""
    import h5py

    path = Path(path)
    unknown = sorted(set(provenance or {}) - set(PROVENANCE))
    if unknown:
        raise ValueError(f"write_rollout: unknown provenance key(s) {unknown}; known: {', '.join(PROVENANCE)}")
    prov = {k: str(v) for k, v in (provenance or {}).items() if v is not None}
    entries = {k: v if isinstance(v, RolloutEntry) else RolloutEntry.from_rollout(v) for k, v in rollouts.items()}
    idx = np.asarray(traj_index, dtype=np.int64)
    rf = RolloutFile(path=path, steps=int(steps), h=float(h), traj_index=idx, models=entries, scene=str(scene))
    rf.group = _group_name(*_check(rf).layout)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["steps"] = rf.steps
        f.attrs["h"] = rf.h
        f.attrs["dataset_scene"] = rf.scene
        f.attrs["group"] = rf.group
        for k, v in prov.items():
            f.attrs[k] = v
        f.create_dataset("traj_index", data=idx)
        for name, e in entries.items():
            g = f.create_group(name)
            g.create_dataset("R", data=e.R)
            g.create_dataset("p", data=e.p)
            g.create_dataset("converged", data=e.converged)
            g.create_dataset("iterations", data=e.iterations)
            if e.residual_norm is not None:
                g.create_dataset("residual_norm", data=e.residual_norm)
            g.attrs.update(e.attrs)
            if e.one_step is not None:
                o = g.create_group("one_step")
                o.create_dataset("R", data=e.one_step.R)
                o.create_dataset("p", data=e.one_step.p)
                o.create_dataset("converged", data=e.one_step.converged)
                o.attrs.update(e.one_step.attrs)
    rf.attrs = {"steps": rf.steps, "h": rf.h, "dataset_scene": rf.scene, "group": rf.group, **prov}
    return rf


__all__ = [
    "FILE_NAME",
    "PROVENANCE",
    "OneStep",
    "RolloutEntry",
    "RolloutFile",
    "read_rollout",
    "validate_rollout",
    "load_rollout",
    "write_rollout",
]
