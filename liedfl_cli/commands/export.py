"""`liedfl rollout ... export=csv|npz`: the model's predicted poses of a rollout written in the layout
`dataset=import` reads (docs/data_format.md, "Importing a recording"), so that predictions go back to
the tools the recording came from, and can be imported again.

Layout: a column (CSV) / array (NPZ) `trajectory` (the recording's own trajectory name where the
dataset keeps it, `params["trajectory_names"]` of an import with a trajectory column; else the dataset's
trajectory index), `t` (seconds: the recording's own time stamps, `params["trajectory_start_s"]` + k h
for an import, the dataset's `t` otherwise), the rotation and, for SE(3) bodies, the position `x y z`
(the dataset's length unit).
Rotations are written as the dataset was imported (`params["rotation"]`: wxyz, xyzw or matrix; wxyz
for a dataset that was not imported): unit quaternions, Hamilton convention, the rotation body ->
world (x_world = R x_body, R = `so3.from_quaternion(q)`), the sign chosen with w >= 0
(`so3.to_quaternion`). One body: unprefixed columns; several: `<body name>.q0`, ... (re-import with
`dataset.bodies=[...]`, the names in the dataset's order). Written to a temporary file and renamed.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import torch

from ..config.fields import allowed
from ..config.typed import TopKeys
from ..data.files import ROTATIONS
from ..lie import so3

EXPORTS = allowed(TopKeys, "export")
"""`liedfl rollout export=...`: the formats (declared once, on `config.typed.TopKeys.export`)."""


def export_layout(dataset) -> tuple[str, list[str] | None]:
    """(rotation convention, body names or None for one body) of the exported file."""
    rotation = (dataset.params or {}).get("rotation")
    rotation = rotation if rotation in ROTATIONS else "wxyz"
    return rotation, (None if dataset.n_bodies == 1 else list(dataset.body_names))


def rotation_values(R: np.ndarray, rotation: str) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) quaternions in `rotation` order (w >= 0) or (..., 9) row-major."""
    if rotation == "matrix":
        return R.reshape(*R.shape[:-2], 9)
    q = so3.to_quaternion(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64))).numpy()
    return q if rotation == "wxyz" else q[..., [1, 2, 3, 0]]


def trajectory_labels(dataset, traj: np.ndarray) -> list[str] | None:
    """The recording's own names of the dataset trajectories `traj` (None: the dataset keeps none)."""
    names = (dataset.params or {}).get("trajectory_names")
    if not isinstance(names, list) or len(names) != dataset.n_trajectories:
        return None
    return [str(names[int(i)]) for i in traj]


def sample_times(dataset, traj: np.ndarray, h: float, n: int) -> np.ndarray:
    """(T, n) time stamps (s) of the first n samples of the dataset trajectories `traj`: the recording's
    own (`params["trajectory_start_s"]` + k h) where the dataset keeps them, else the dataset's `t`
    (k h from 0 when it stores none)."""
    k = float(h) * np.arange(n)
    starts = (dataset.params or {}).get("trajectory_start_s")
    if isinstance(starts, list) and len(starts) == dataset.n_trajectories:
        return np.asarray([float(starts[int(i)]) for i in traj])[:, None] + k[None]
    t = getattr(dataset, "t", None)
    base = np.asarray(t, dtype=np.float64)[:n] if t is not None and len(t) >= n else k
    return np.tile(base, (len(traj), 1))


def reimport_command(path: Path, rotation: str, bodies: list[str] | None) -> str:
    cmd = f"liedfl data dataset=import dataset.path={path} dataset.rotation={rotation}"
    return cmd + (f" 'dataset.bodies=[{','.join(bodies)}]'" if bodies else "")


def export_predictions(rollout_path, dataset, fmt: str, out_dir) -> Path:
    """Write the model's rollout in `rollout_path` as `<out_dir>/predictions.<fmt>`; returns the path."""
    from ..files.rollout_file import read_rollout

    fmt = TopKeys(export=fmt).export  # the values the field declares (one-line ConfigError otherwise)
    rf = read_rollout(rollout_path)
    entry = rf.model
    R, p, traj = np.asarray(entry.R), np.asarray(entry.p), np.asarray(rf.traj_index)
    t = sample_times(dataset, traj, float(rf.h), R.shape[1])  # (T, S+1)
    names = trajectory_labels(dataset, traj)
    rotation, bodies = export_layout(dataset)
    rot = rotation_values(R, rotation)  # (T, S+1, B, k)
    path = Path(out_dir) / f"predictions.{fmt}"
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:  # a crash leaves no half-written file under the final name
        if fmt == "npz":
            _write_npz(tmp, traj, names, t, rot, p, rotation, dataset.body_names)
        else:
            _write_csv(tmp, names or [str(int(i)) for i in traj], t, rot, p, rotation, bodies)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _write_npz(tmp: Path, traj, names, t, rot, p, rotation: str, body_names) -> None:
    m = p.shape[2]
    arrays = {"trajectory": traj.astype(np.int64), "t": t}
    if names is not None:
        arrays["trajectory_name"] = np.asarray(names)
    arrays["R" if rotation == "matrix" else "q"] = rot.reshape(*rot.shape[:3], 3, 3) if rotation == "matrix" else rot
    if m:
        arrays["p"] = p
    arrays["body_names"] = np.asarray([str(b) for b in body_names])
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _write_csv(tmp: Path, labels: list[str], t, rot, p, rotation: str, bodies) -> None:
    T, S1, B = rot.shape[:3]
    m = p.shape[2]
    comp = [f"r{i}{j}" for i in range(3) for j in range(3)] if rotation == "matrix" else ["q0", "q1", "q2", "q3"]
    prefixes = [""] if bodies is None else [f"{b}." for b in bodies]
    header = ["trajectory", "t"]
    for b, pre in enumerate(prefixes):
        header += [pre + c for c in comp] + ([pre + c for c in "xyz"] if b < m else [])
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(header)
        for i in range(T):
            for k in range(S1):
                row = [labels[i], repr(float(t[i, k]))]
                for b in range(B):
                    row += [repr(float(x)) for x in rot[i, k, b]]
                    if b < m:
                        row += [repr(float(x)) for x in p[i, k, b]]
                w.writerow(row)


__all__ = [
    "EXPORTS",
    "export_layout",
    "export_predictions",
    "reimport_command",
    "rotation_values",
    "sample_times",
    "trajectory_labels",
]
