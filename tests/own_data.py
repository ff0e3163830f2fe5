"""Small recordings for the tests of `dataset=file` and `dataset=import`: a heavy rigid body on SE(3)
(constant angular velocity about a tilted axis, a thrown centre of mass), written as liedfl HDF5 files,
CSV logs (quaternions scalar-first or scalar-last, or rotation matrices) and NPZ archives."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch

from liedfl_cli.data.hdf5 import Dataset, save_dataset
from liedfl_cli.lie import so3

H = 0.05


def motion(
    n_traj: int = 4, n_samples: int = 21, h: float = H, seed: int = 0, times: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t (n,), R (T, n, 3, 3), p (T, n, 3)): uniform rotation and a ballistic centre per trajectory,
    sampled every h (or at `times` (T, n))."""
    rng = np.random.default_rng(seed)
    R, p = [], []
    for i in range(n_traj):
        t = times[i] if times is not None else h * np.arange(n_samples)
        R0 = so3.exp(torch.from_numpy(rng.normal(size=3))).numpy()
        w = rng.normal(size=3)
        steps = so3.exp(torch.from_numpy(t[:, None] * w[None])).numpy()
        R.append(R0 @ steps)
        p0, v0 = rng.normal(size=3), rng.normal(size=3)
        p.append(p0 + t[:, None] * v0 - 0.5 * 9.81 * t[:, None] ** 2 * np.array([0.0, 0.0, 1.0]))
    return h * np.arange(n_samples), np.stack(R), np.stack(p)


def write_h5(path: Path, n_traj: int = 6, n_samples: int = 21, split: bool = True) -> Path:
    """A liedfl dataset file on SE(3) (with a split, or with none)."""
    t, R, p = motion(n_traj, n_samples)
    ds = Dataset(
        R=R[:, :, None],
        p=p[:, :, None],
        h=H,
        scene="my_recording",
        body_names=["box"],
        body_kinds=["se3"],
        split={"train": np.arange(1, n_traj), "test": np.array([0])} if split else {},
    )
    save_dataset(ds, path)
    if not split:
        import h5py

        with h5py.File(path, "a") as f:
            del f["split"]
    return path


def write_csv(
    path: Path,
    n_traj: int = 3,
    n_samples: int = 21,
    rotation: str = "wxyz",
    t0: float = 100.0,
    jitter: float = 0.0,
    bodies: list[str] | None = None,
) -> tuple[Path, np.ndarray, np.ndarray]:
    """A CSV log: columns trajectory, t, the rotation (q0..q3 in the `rotation` order or r00..r22) and x, y, z
    (with `bodies`, one SE(3) body per name, columns prefixed `<name>.`). Returns (path, R, p) of the truth."""
    t, R, p = motion(n_traj, n_samples)
    rng = np.random.default_rng(1)
    stamps = np.tile(t, (n_traj, 1))
    if jitter:  # the samples are taken at jittered times (the ends stay put)
        stamps[:, 1:-1] += jitter * H * rng.uniform(-1, 1, size=(n_traj, n_samples - 2))
    _, Rs, ps = motion(n_traj, n_samples, times=stamps)
    q = so3.to_quaternion(torch.from_numpy(Rs)).numpy()  # w, x, y, z
    names = bodies or [""]
    header = ["trajectory", "t"]
    for b in names:
        pre = f"{b}." if b else ""
        rot = [f"r{i}{j}" for i in range(3) for j in range(3)] if rotation == "matrix" else ["q0", "q1", "q2", "q3"]
        header += [pre + c for c in rot] + [pre + c for c in ("x", "y", "z")]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for i in range(n_traj):
            for k in range(n_samples):
                row = [f"take{i}", f"{t0 + stamps[i, k]:.9f}"]
                for _ in names:
                    if rotation == "matrix":
                        rot = Rs[i, k].reshape(-1)
                    elif rotation == "wxyz":
                        rot = q[i, k]
                    else:
                        rot = q[i, k][[1, 2, 3, 0]]
                    row += [f"{v:.12f}" for v in rot] + [f"{v:.12f}" for v in ps[i, k]]
                w.writerow(row)
    return path, R, p


# the `dataset` section of `dataset=import` (conf/dataset/import.yaml's keys; tests/test_own_data.py checks
# them against the import's key list), for calling `get_dataset` directly
IMPORT = {
    "name": "import",
    "rotation": "wxyz",
    "bodies": None,
    "time_column": "t",
    "trajectory_column": "trajectory",
    "time_scale": 1.0,
    "time_tolerance": 0.01,
    "resample": False,
    "h": None,
    "smoothing": None,
    "noise": {"rotation": 0.0, "position": 0.0},
    "length_scale": 1.0,
    "chunk_steps": None,
    "time_unit": None,
    "columns": None,
    "gravity": None,
    "n_trajectories": None,
    "steps": None,
    "train_steps": None,
    "rollout_steps": None,
    "test_fraction": 0.2,
    "n_test": None,
    "seed": 0,
}
