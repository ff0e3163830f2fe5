"""`liedfl rollout ... export=csv|npz`: the model's predicted poses of a rollout written in the layout
`dataset=import` reads (docs/data_format.md, "Importing a recording"), so that predictions go back to
the tools the recording came from, and can be imported again.

Layout: a column (CSV) / array (NPZ) `trajectory` (the dataset's trajectory index), `t` (seconds,
k h from 0), the rotation and, for SE(3) bodies, the position `x y z` (the dataset's length unit).
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

from ..data.files import ROTATIONS
from ..errors import ConfigError
from ..lie import so3

EXPORTS = ("csv", "npz")


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


def reimport_command(path: Path, rotation: str, bodies: list[str] | None) -> str:
    cmd = f"liedfl data dataset=import dataset.path={path} dataset.rotation={rotation}"
    return cmd + (f" 'dataset.bodies=[{','.join(bodies)}]'" if bodies else "")


def export_predictions(rollout_path, dataset, fmt: str, out_dir) -> Path:
    """Write the model's rollout in `rollout_path` as `<out_dir>/predictions.<fmt>`; returns the path."""
    from ..files.rollout_file import read_rollout

    if fmt not in EXPORTS:
        raise ConfigError(f"export={fmt!r}: choose csv or npz (or null for none)")
    rf = read_rollout(rollout_path)
    entry = rf.model
    R, p, traj = np.asarray(entry.R), np.asarray(entry.p), np.asarray(rf.traj_index)
    t = float(rf.h) * np.arange(R.shape[1])
    rotation, bodies = export_layout(dataset)
    rot = rotation_values(R, rotation)  # (T, S+1, B, k)
    path = Path(out_dir) / f"predictions.{fmt}"
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:  # a crash leaves no half-written file under the final name
        if fmt == "npz":
            _write_npz(tmp, traj, t, rot, p, rotation, dataset.body_names)
        else:
            _write_csv(tmp, traj, t, rot, p, rotation, bodies)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _write_npz(tmp: Path, traj, t, rot, p, rotation: str, body_names) -> None:
    T, m = rot.shape[0], p.shape[2]
    arrays = {"trajectory": traj.astype(np.int64), "t": np.tile(t, (T, 1))}
    arrays["R" if rotation == "matrix" else "q"] = rot.reshape(*rot.shape[:3], 3, 3) if rotation == "matrix" else rot
    if m:
        arrays["p"] = p
    arrays["body_names"] = np.asarray([str(b) for b in body_names])
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _write_csv(tmp: Path, traj, t, rot, p, rotation: str, bodies) -> None:
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
                row = [str(int(traj[i])), repr(float(t[k]))]
                for b in range(B):
                    row += [repr(float(x)) for x in rot[i, k, b]]
                    if b < m:
                        row += [repr(float(x)) for x in p[i, k, b]]
                w.writerow(row)


__all__ = ["EXPORTS", "export_layout", "export_predictions", "reimport_command", "rotation_values"]
