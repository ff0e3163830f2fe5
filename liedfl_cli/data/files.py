"""Your own data as scenes: `dataset=file` (an HDF5 file in liedfl's format) and `dataset=import` (a
recording in CSV or NPZ: time stamps, rotations as quaternions or matrices, positions).

Both are listed in the scene registry `scenes.SCENES` like the simulated scenes and go through the
same front door (`scenes.get_dataset`): the scene reads the user's file, keeps the trajectories and
steps the config asks for, gives the data a split when it has none, and returns a `Dataset`, which
is validated like any dataset (`hdf5.save_dataset`: shapes, rotations, time stamps, splits; the
per-step rotation checks of `checks.py`) and cached as `<data_dir>/<file|import>-<hash>.h5`. The hash
covers the config without `path` and the SHA-256 of the file's bytes: an edited file is read again,
a renamed or moved one is not. The cached copy is what a run records and reloads, so `liedfl rollout`
and `liedfl eval` see exactly the trajectories and split the run trained on.

Keys shared by both scenes (liedfl_cli/conf/dataset/file.yaml, import.yaml):

  path            the file (relative to the working directory, or absolute)
  n_trajectories  null = every trajectory; N = at most the first N (budget=smoke sets 6)
  steps           null = every step; N = the first N steps (N + 1 poses) of each trajectory
  train_steps     steps of each training trajectory that training uses (null = all)
  rollout_steps   rollout length after training (null = all)
  test_fraction, n_test, seed
                  the default split (`default_split`): with T >= 2 trajectories, n_test (or
                  round(test_fraction * T), at least 1 and at most T - 1) trajectories drawn at
                  random with `seed` are the test set, the others the training set; a single
                  trajectory is both (params["split_overlap"] = true): training uses its first
                  train_steps steps, the rollout reproduces it from its first two poses.

`file` adds `split: auto | default` (auto: the file's own split when it has one). `import` adds the
reader's options (`import_config`), documented in docs/data_format.md ("Importing a recording").
"""

from __future__ import annotations

import copy
import functools
import hashlib
import math
import warnings
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import torch

from ..errors import ConfigError, DatasetError, DataWarning
from ..lie import so3
from .dataset_config import DatasetConfig
from .hdf5 import Dataset, load_dataset
from .import_options import ColumnFinder, check_columns, check_time_unit, gravity_params, warn_if_milliseconds
from .scene_common import TRAIN_TIME_KEYS, config_hash, make_split
from .smoothing import check_window, smooth_pose
from .transforms import noise_spec, smoothing_spec

SOURCE_SCENES = ("file", "import")
"""Scenes read from a user's file (their cache name also hashes the file's content)."""

COMMON_KEYS = (
    "name",
    "path",
    "n_trajectories",
    "steps",
    "train_steps",
    "rollout_steps",
    "test_fraction",
    "n_test",
    "seed",
)
FILE_KEYS = (*COMMON_KEYS, "split", "noise", "smoothing")
IMPORT_KEYS = (
    *COMMON_KEYS,
    "noise",
    "rotation",
    "bodies",
    "time_column",
    "trajectory_column",
    "time_scale",
    "time_tolerance",
    "resample",
    "h",
    "smoothing",
    "length_scale",
    "chunk_steps",
    "time_unit",
    "columns",
    "gravity",
)
ROTATIONS = {
    "wxyz": "quaternions, scalar first (w, x, y, z)",
    "xyzw": "quaternions, scalar last (x, y, z, w)",
    "matrix": "rotation matrices (body to world), row-major",
}
QUAT_COLUMNS = ("q0", "q1", "q2", "q3")
MATRIX_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))
POSITION_COLUMNS = ("x", "y", "z")
IMPORT_VERSION = 2  # 2: the cached copy carries the file's kinematic tree
"""Bump when the import would produce different data for the same config and file (part of the hash)."""


# --------------------------------------------------------------------------- config
def _int_or_null(c: dict, key: str, low: int) -> int | None:
    v = c.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v or v < low:
        raise ConfigError(f"dataset.{key}={v!r}: must be null or an integer >= {low}")
    return int(v)


def _number(c: dict, key: str, positive: bool = True) -> float:
    v = c.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ConfigError(f"dataset.{key}={v!r}: must be a {'positive ' if positive else ''}number")
    return float(v)


def _paths(c: dict) -> list[Path]:
    raw = c.get("path")
    if raw in (None, "", "???"):
        kind = "an HDF5 file in liedfl's format" if c["name"] == "file" else "a .csv or .npz recording"
        raise ConfigError(f"dataset.path is required for dataset={c['name']}: {kind} (dataset.path=<file>)")
    items = list(raw) if isinstance(raw, (list, tuple)) else [raw]
    if c["name"] == "file" and len(items) != 1:
        raise ConfigError(f"dataset.path={raw!r}: dataset=file reads one HDF5 file")
    if not items or not all(isinstance(x, str) and x.strip() for x in items):
        raise ConfigError(f"dataset.path={raw!r}: must be a file path (or, for dataset=import, a list of them)")
    out = []
    for x in items:
        p = Path(x).expanduser()
        if not p.is_file():
            raise ConfigError(f"dataset.path={x}: no such file" + (" (a directory)" if p.is_dir() else ""))
        out.append(p)
    return out


@functools.cache
def _shipped_defaults(name: str) -> dict:
    """The values of liedfl_cli/conf/dataset/<name>.yaml, without `defaults` and the required (???) keys."""
    import yaml

    out = yaml.safe_load((Path(__file__).resolve().parent.parent / "conf" / "dataset" / f"{name}.yaml").read_text())
    assert isinstance(out, dict)
    return {k: v for k, v in out.items() if k != "defaults" and v != "???" and k not in TRAIN_TIME_KEYS}


def check_source_config(c: dict) -> dict:
    """Check a `file` / `import` dataset config (plain dict); returns it, keys it leaves out taken from
    the shipped conf/dataset/<name>.yaml (so `{"name": "file", "path": ...}` will do from Python).
    ConfigError naming the key."""
    name = c.get("name")
    keys = FILE_KEYS if name == "file" else IMPORT_KEYS
    unknown = sorted(set(c) - set(keys) - {"defaults", "source_sha256"})
    if unknown:
        raise ConfigError(f"unknown config key 'dataset.{unknown[0]}' for scene '{name}' (allowed: {', '.join(keys)})")
    c = {**copy.deepcopy(_shipped_defaults(str(name))), **c}
    missing = [k for k in keys if k not in c and k not in ("path", "rotation")]
    if missing:
        raise ConfigError(f"dataset config of scene '{name}' is missing {missing}")
    _int_or_null(c, "n_trajectories", 1)
    _int_or_null(c, "steps", 1)
    _int_or_null(c, "train_steps", 1)
    _int_or_null(c, "rollout_steps", 2)
    _int_or_null(c, "n_test", 0)
    seed = c.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"dataset.seed={seed!r}: must be an integer")
    tf = c.get("test_fraction")
    if isinstance(tf, bool) or not isinstance(tf, (int, float)) or not 0.0 <= tf < 1.0:
        raise ConfigError(f"dataset.test_fraction={tf!r}: must lie in [0, 1)")
    if name == "file":
        if c["split"] not in ("auto", "default"):
            raise ConfigError(f"dataset.split={c['split']!r}: choose auto (the file's split, if any) or default")
        smoothing_spec(c.get("smoothing"))  # applied after the scene, like for every scene (transforms.py)
    else:
        _check_import_options(c)
    noise_spec(c.get("noise"))
    _paths(c)
    return c


def _check_import_options(c: dict) -> None:
    rot = c.get("rotation")
    if rot in (None, "", "???"):
        raise ConfigError(
            "dataset.rotation is required for dataset=import: "
            + "; ".join(f"{k} = {v}" for k, v in ROTATIONS.items())
            + " (e.g. dataset.rotation=wxyz)"
        )
    if rot not in ROTATIONS:
        raise ConfigError(f"dataset.rotation={rot!r}: choose one of {', '.join(ROTATIONS)}")
    bodies = c.get("bodies")
    if bodies is not None and (
        not isinstance(bodies, (list, tuple))
        or not bodies
        or not all(isinstance(b, str) and b for b in bodies)
        or len(set(bodies)) != len(bodies)
    ):
        raise ConfigError(f"dataset.bodies={bodies!r}: must be null (one body) or a list of distinct body names")
    for key in ("time_column", "trajectory_column"):
        if not isinstance(c.get(key), str) or not c[key]:
            raise ConfigError(f"dataset.{key}={c.get(key)!r}: must be a column name")
    _number(c, "time_scale")
    _number(c, "time_tolerance")
    _number(c, "length_scale")
    if not isinstance(c.get("resample"), bool):
        raise ConfigError(f"dataset.resample={c.get('resample')!r}: must be true or false")
    if c.get("h") is not None:
        _number(c, "h")
    _int_or_null(c, "chunk_steps", 2)
    check_time_unit(c)
    check_columns(c)
    gravity_params(c)
    sm = c.get("smoothing")
    if sm is not None:
        if not isinstance(sm, dict) or set(sm) != {"window", "order"}:
            raise ConfigError(f"dataset.smoothing={sm!r}: must be null or {{window: <odd int>, order: <int>}}")
        try:
            check_window(sm["window"], sm["order"])
        except ValueError as e:
            raise ConfigError(f"dataset.smoothing: {e}") from None


def file_digest(paths: list[Path]) -> str:
    """SHA-256 over the bytes of the files, in order."""
    h = hashlib.sha256()
    for p in paths:
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def hashed_config(c: dict) -> dict:
    """The part of a source scene's config that names its cached copy: the config without `path`,
    plus the SHA-256 of the file(s) and the import version."""
    out = {k: v for k, v in c.items() if k not in ("path", "source_sha256")}
    out["source_sha256"] = c.get("source_sha256") or file_digest(_paths(c))
    out["import_version"] = IMPORT_VERSION
    return out


# --------------------------------------------------------------------------- after loading
def complete_steps(cfg_dataset: DatasetConfig, ds: Dataset) -> None:
    """Fill `train_steps` / `rollout_steps` left null (a `file` or `import` scene: "all the steps")
    with the dataset's step count, in place; ConfigError when train_steps exceeds it."""
    n = ds.n_steps
    for key in ("train_steps", "rollout_steps"):
        if key in cfg_dataset.present and getattr(cfg_dataset, key) is None:
            setattr(cfg_dataset, key, n)
    train = cfg_dataset.get("train_steps")
    if train is not None and int(train) > n:
        raise ConfigError(f"dataset.train_steps={train}: the dataset has only {n} steps per trajectory")


def default_split(T: int, test_fraction: float, n_test: int | None, seed: int) -> tuple[dict[str, np.ndarray], bool]:
    """(split, overlap) for data without a split; see the module docstring."""
    if T == 1:
        idx = np.zeros(1, dtype=np.int64)
        return {"train": idx, "test": idx.copy()}, True
    if n_test is not None:
        if n_test >= T:
            raise ConfigError(f"dataset.n_test={n_test}: leaves no training trajectory out of {T}")
        k = n_test
    else:
        k = min(max(1, int(round(test_fraction * T))), T - 1)
    return make_split(T, 0.0, k, int(seed)), False


def _select(c: dict, R, p, t, where: str):
    """The first n_trajectories trajectories and first steps + 1 samples."""
    T, N1 = R.shape[:2]
    n = min(int(c["n_trajectories"]), T) if c.get("n_trajectories") is not None else T
    if c.get("steps") is not None:
        if int(c["steps"]) > N1 - 1:
            raise ConfigError(f"dataset.steps={c['steps']}: {where} has only {N1 - 1} steps per trajectory")
        N1 = int(c["steps"]) + 1
    return n, N1, R[:n, :N1], p[:n, :N1], (None if t is None else t[:N1])


def _params(c: dict, **fields) -> dict:
    """`params` of the dataset: the config (json-native), its hash (the one in the cache name), the file's digest."""
    import json

    hc = hashed_config(c)
    return {
        "config": json.loads(json.dumps({k: v for k, v in c.items() if k != "source_sha256"})),
        "config_hash": config_hash(hc),
        "source_sha256": hc["source_sha256"],
        **fields,
    }


# --------------------------------------------------------------------------- scene "file"
def from_file(c: dict, progress: Callable[[float], None] | None = None) -> Dataset:
    """Scene `file`: an HDF5 file in liedfl's format (docs/data_format.md)."""
    c = check_source_config(dict(c))
    (path,) = _paths(c)
    if Path(path).suffix.lower() in (".csv", ".txt", ".npz") and not h5py.is_hdf5(path):
        raise DatasetError(
            f"{path}: a recording, not an HDF5 dataset; dataset=file reads liedfl's HDF5 files, a CSV or NPZ "
            f"recording is read with dataset=import dataset.path={path} dataset.rotation=wxyz (or xyzw, matrix)"
        )
    ds = load_dataset(path, require_split=False)
    with h5py.File(path, "r") as f:
        has_split = "split" in f
    T0, N0 = ds.n_trajectories, ds.n_steps
    n, N1, R, p, t = _select(c, ds.R, ds.p, ds.t, str(path))
    extras = {}
    for k, v in ds.extras.items():
        v = np.asarray(v)
        if v.ndim >= 2 and v.shape[:2] == (T0, N0 + 1):
            v = v[:n, :N1]
        elif v.shape[:1] == (T0,):
            v = v[:n]
        extras[k] = v
    params = dict(ds.params or {})
    overlap = bool(params.get("split_overlap") is True)
    if c["split"] == "auto" and has_split:
        split = {k: np.asarray([i for i in ds.split[k] if i < n], dtype=np.int64) for k in ("train", "test")}
        if split["train"].size == 0:
            raise DatasetError(
                f"{path}: dataset 'split/train' lists none of the first {n} trajectories (dataset.n_trajectories={n}); "
                "use dataset.split=default"
            )
        how = "the file's split"
    else:
        split, overlap = default_split(n, float(c["test_fraction"]), c["n_test"], int(c["seed"]))
        how = "default split" + (" (no split in the file)" if not has_split else "")
    params.update(
        _params(
            c,
            source={"file": str(path), "trajectories": T0, "steps": N0, "scene": ds.scene},
            split_source=how,
            split_overlap=overlap,
        )
    )
    return Dataset(
        R=R,
        p=p,
        h=ds.h,
        scene=ds.scene,
        body_names=ds.body_names,
        body_kinds=ds.body_kinds,
        params=params,
        seed=ds.seed,
        split=split,
        extras=extras,
        t=t,
        tree=ds.tree,
    )


# --------------------------------------------------------------------------- scene "import"
class _Track:
    """One recording read from a file: time stamps (n,), rotations (n, B, 3, 3), positions (n, m, 3)."""

    def __init__(self, t, R, p, source: str, columns: dict[str, str] | None = None, name: str | None = None,
                 t0: float = 0.0):  # fmt: skip
        self.t, self.R, self.p, self.source = t, R, p, source
        self.columns = columns  # CSV: {canonical name: the file's column} (import_options.ColumnFinder)
        self.name, self.t0 = name, t0  # the CSV's trajectory value; the first stamp in seconds (the export's)


def _rotations(values: np.ndarray, rotation: str, where: str, first_row: int = 0) -> np.ndarray:
    """(n, B, 4) quaternions or (n, B, 9) row-major matrices -> rotations (n, B, 3, 3)."""
    if rotation == "matrix":
        M = values.reshape(*values.shape[:-1], 3, 3)
        # huge finite entries overflow to inf or NaN (inf - inf): both are bad, hence `not <=`
        with np.errstate(over="ignore", invalid="ignore"):
            E = np.swapaxes(M, -1, -2) @ M - np.eye(3)
            err = np.sqrt((E * E).sum((-1, -2)))
            det = np.linalg.det(M)
        bad = ~(err <= 1e-3) | ~(det >= 0)
        if bad.any():
            i, b = (int(x) for x in np.argwhere(bad)[0])
            raise DatasetError(
                f"{where}: row {first_row + i}, body {b}: not a rotation matrix (||R^T R - I||_F = {err[i, b]:.3g}, "
                f"det = {det[i, b]:.4g}); dataset.rotation=matrix expects r00..r22 row by row"
            )
        return so3.project(torch.from_numpy(np.ascontiguousarray(M))).numpy()
    with np.errstate(over="ignore"):  # huge entries: an infinite norm, refused below
        norm = np.linalg.norm(values, axis=-1)
    bad = ~(np.abs(norm - 1.0) <= 1e-2)
    if bad.any():
        i, b = (int(x) for x in np.argwhere(bad)[0])
        raise DatasetError(
            f"{where}: row {first_row + i}, body {b}: quaternion norm {norm[i, b]:.4g} is not 1 (tolerance 1e-2): "
            "not a unit quaternion"
        )
    q = values if rotation == "wxyz" else values[..., [3, 0, 1, 2]]
    return so3.from_quaternion(torch.from_numpy(np.ascontiguousarray(q))).numpy()


def _read_csv(path: Path, c: dict) -> list[_Track]:
    import csv

    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a UTF-8 text file") from None
    rows = [r for r in rows if any(x.strip() for x in r)]
    if len(rows) < 3:
        raise DatasetError(f"{path}: needs a header line and at least 2 rows of values, found {len(rows)} line(s)")
    header = [h.strip() for h in rows[0]]
    bodies = c["bodies"]
    prefixes = [""] if bodies is None else [f"{b}." for b in bodies]
    names = ["body"] if bodies is None else list(bodies)
    rot_cols = MATRIX_COLUMNS if c["rotation"] == "matrix" else QUAT_COLUMNS
    cols = ColumnFinder(header, c, path)
    t_col = cols.time(c["time_column"])
    r_cols = [cols.rotation_columns(pre) for pre in prefixes]
    p_cols = []
    for pre, body in zip(prefixes, names):
        found = cols.position_columns(pre)
        if any(i is not None for i in found) and not all(i is not None for i in found):
            missing = [pre + k for k, i in zip(POSITION_COLUMNS, found) if i is None]
            raise DatasetError(f"{path}: body '{body}' has some position columns but not {', '.join(missing)}")
        p_cols.append([int(i) for i in found if i is not None] if found[0] is not None else None)
    traj_col = cols.trajectory(c["trajectory_column"])
    used = [t_col, *(i for r in r_cols for i in r), *(i for q in p_cols if q for i in q)]
    values = np.empty((len(rows) - 1, len(used)))
    for n, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise DatasetError(f"{path}: line {n} has {len(r)} fields, the header has {len(header)}")
        for j, i in enumerate(used):
            try:
                values[n - 2, j] = float(r[i])
            except ValueError:
                raise DatasetError(f"{path}: line {n}, column '{header[i]}': {r[i]!r} is not a number") from None
    bad = ~np.isfinite(values)
    if bad.any():
        n, j = (int(x) for x in np.argwhere(bad)[0])
        raise DatasetError(f"{path}: line {n + 2}, column '{header[used[j]]}': {rows[n + 1][used[j]]!r} is not finite")
    ids = [r[traj_col].strip() for r in rows[1:]] if traj_col is not None else ["" for _ in rows[1:]]
    B, k = len(prefixes), len(rot_cols)
    tracks = []
    for tid in dict.fromkeys(ids):
        sel = np.asarray([i for i, x in enumerate(ids) if x == tid])
        v = values[sel]
        where = f"{path}" + (f" (trajectory {tid})" if traj_col is not None else "")
        R = _rotations(v[:, 1 : 1 + B * k].reshape(len(sel), B, k), c["rotation"], where, int(sel[0]) + 2)
        ps = []
        off = 1 + B * k
        for q in p_cols:
            if q is not None:
                ps.append(v[:, off : off + 3])
                off += 3
        p = np.stack(ps, 1) if ps else np.zeros((len(sel), 0, 3))
        tracks.append(_Track(v[:, 0], R, p, where, columns=cols.used, name=tid if traj_col is not None else None))
    return _order_bodies(tracks, names, [q is not None for q in p_cols], str(path))


def _order_bodies(tracks: list[_Track], names: list[str], has_p: list[bool], where: str):
    """SE(3) bodies (those with positions) first, as the format requires; returns (tracks, names, kinds)."""
    order = [i for i, h in enumerate(has_p) if h] + [i for i, h in enumerate(has_p) if not h]
    for tr in tracks:
        tr.R = tr.R[:, order]
    names = [names[i] for i in order]
    kinds = ["se3" if has_p[i] else "so3" for i in order]
    return tracks, names, kinds


def _read_npz(path: Path, c: dict):
    import zipfile
    import zlib

    try:
        # the file is opened here, so that it is closed when numpy fails half-way through the archive
        with open(path, "rb") as fh:
            z = np.load(fh, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):  # a bare .npy array under an .npz name
                raise DatasetError(f"{path}: not an .npz archive (a single .npy array)")
            arrays = {k: z[k] for k in z.files}
    except DatasetError:
        raise
    # zipfile: NotImplementedError for an unknown compression method, RuntimeError for an encrypted entry
    except (
        OSError,
        ValueError,
        EOFError,
        KeyError,
        NotImplementedError,
        RuntimeError,
        zipfile.BadZipFile,
        zlib.error,
    ) as e:
        raise DatasetError(f"{path}: not a readable .npz file ({type(e).__name__}: {e})") from None
    for k, v in check_columns(c).items():  # dataset.columns renames arrays: {q: quat, t: time}
        if k in ("t", "q", "R", "p", "body_names"):
            if v not in arrays:
                raise DatasetError(f"{path}: dataset.columns.{k}={v}: no such array ({', '.join(sorted(arrays))})")
            arrays[k] = arrays.pop(v)
    key = "R" if c["rotation"] == "matrix" else "q"
    for k in ("t", key):
        if k not in arrays:
            raise DatasetError(f"{path}: array '{k}' is missing (arrays: {', '.join(sorted(arrays)) or 'none'})")
    t = np.asarray(arrays["t"])
    if t.ndim not in (1, 2) or t.shape[-1] < 2:
        raise DatasetError(f"{path}: array 't' has shape {t.shape}; need (N+1,) or (T, N+1)")
    lead = t.shape
    rot = np.asarray(arrays[key])
    tail = (3, 3) if key == "R" else (4,)
    if (
        rot.shape[: len(lead)] != lead
        or rot.shape[-len(tail) :] != tail
        or rot.ndim
        not in (
            len(lead) + len(tail),
            len(lead) + len(tail) + 1,
        )
    ):
        dims = ", ".join(map(str, lead))
        want = "3, 3" if key == "R" else "4"
        raise DatasetError(f"{path}: array '{key}' has shape {rot.shape}; need ({dims}, {want}) or ({dims}, B, {want})")
    if rot.ndim == len(lead) + len(tail):  # one body: add the body axis
        rot = np.expand_dims(rot, len(lead))
    B = rot.shape[len(lead)]
    p = arrays.get("p")
    if p is None:
        p = np.zeros((*lead, 0, 3))
    else:
        p = np.asarray(p)
        if p.shape == (*lead, 3):
            p = p[..., None, :]
        if p.shape[: len(lead)] != lead or p.ndim != len(lead) + 2 or p.shape[-1] != 3 or p.shape[-2] > B:
            dims = ", ".join(map(str, lead))
            raise DatasetError(
                f"{path}: array 'p' has shape {p.shape}; need ({dims}, 3) or ({dims}, m, 3) with m <= B={B}"
            )
    for name, a in (("t", t), (key, rot), ("p", p)):
        if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
            raise DatasetError(f"{path}: array '{name}' must hold real numbers, got dtype {a.dtype}")
        bad = ~np.isfinite(a)
        if bad.any():
            raise DatasetError(
                f"{path}: array '{name}' has a non-finite value at index {tuple(int(i) for i in np.argwhere(bad)[0])}"
            )
    if t.ndim == 1:
        t, rot, p = t[None], rot[None], p[None]
    m = p.shape[-2]
    given = arrays.get("body_names")
    if given is not None and given.ndim != 1:
        raise DatasetError(f"{path}: array 'body_names' has shape {given.shape}; need ({B},), one name per body")
    names = [str(x) for x in given] if given is not None else [f"body{i}" for i in range(B)]
    if len(names) != B:
        raise DatasetError(f"{path}: array 'body_names' has {len(names)} entries for {B} bodies")
    tracks = []
    for i in range(t.shape[0]):
        where = f"{path}" + (f" (trajectory {i})" if t.shape[0] > 1 else "")
        vals = rot[i].astype(np.float64).reshape(*rot.shape[1:3], -1)
        R = _rotations(vals, c["rotation"], where)
        tracks.append(_Track(t[i].astype(np.float64), R, p[i].astype(np.float64), where))
    return tracks, names, ["se3"] * m + ["so3"] * (B - m)


def _uniform(tr: _Track, c: dict, h_cfg: float | None) -> float:
    """The track's time step. Without resampling every step must be within `time_tolerance` (relative)
    of the median step (or of the configured h), and the step returned is the mean one (rounded to 10
    digits, which removes the rounding of printed time stamps); with resampling, the median step."""
    t = tr.t
    with np.errstate(over="ignore"):  # finite stamps near 1e308: differences overflow to inf (refused below)
        d = np.diff(t)
    if (d <= 0).any():
        k = int(np.argmax(d <= 0))
        raise DatasetError(
            f"{tr.source}: time stamps are not increasing at sample {k + 1}: {float(t[k])!r} then {float(t[k + 1])!r}"
        )
    median = float(np.median(d))
    if c["resample"]:
        return median
    ref = h_cfg or median
    with np.errstate(over="ignore", invalid="ignore"):
        dev = np.abs(d - ref) / ref
    if (~(dev <= c["time_tolerance"])).any():
        k = int(np.argmax(~(dev <= c["time_tolerance"])))
        raise DatasetError(
            f"{tr.source}: time stamps are not uniform: step {k} -> {k + 1} is {d[k]:.6g} s, the "
            f"{'configured' if h_cfg else 'median'} step {ref:.6g} s (off by {dev[k]:.1%}, tolerance "
            f"dataset.time_tolerance={c['time_tolerance']:g}); set dataset.resample=true to resample on the group"
        )
    with np.errstate(over="ignore"):
        return float(f"{(t[-1] - t[0]) / (len(t) - 1):.10g}")


def resample(t: np.ndarray, R: np.ndarray, p: np.ndarray, h: float, where: str = "track"):
    """Samples at t0, t0 + h, ... (within the recording) of a pose track: rotations along the geodesic
    between the neighbouring samples (R_i exp(s log(R_i^T R_(i+1)))), positions linearly.
    t (n,), R (n, B, 3, 3), p (n, m, 3) -> (t', R', p')."""
    n_new = int(math.floor((t[-1] - t[0]) / h * (1 + 1e-12))) + 1
    tn = t[0] + h * np.arange(n_new)
    i = np.clip(np.searchsorted(t, tn, side="right") - 1, 0, len(t) - 2)
    s = (tn - t[i]) / (t[i + 1] - t[i])
    Ri = torch.from_numpy(np.ascontiguousarray(R[:-1]))
    W = Ri.transpose(-1, -2) @ torch.from_numpy(np.ascontiguousarray(R[1:]))
    xi = so3.log(W)  # (n-1, B, 3)
    angle = torch.linalg.vector_norm(xi, dim=-1)
    if float(angle.max()) > 0.9 * math.pi:
        k, b = (int(x) for x in (angle > 0.9 * math.pi).nonzero()[0])
        raise DatasetError(
            f"{where}: body {b} turns by {float(angle[k, b]):.3f} rad between samples {k} and {k + 1}: too far "
            "to interpolate (above 0.9 pi); the recording is sampled too coarsely to resample"
        )
    st = torch.from_numpy(s)[:, None, None]
    Rn = Ri[i] @ so3.exp(st * xi[i])
    pn = (1 - s)[:, None, None] * p[i] + s[:, None, None] * p[i + 1]
    return tn, Rn.numpy(), pn


def import_recording(c: dict, progress: Callable[[float], None] | None = None) -> Dataset:
    """Scene `import`: a CSV or NPZ recording converted to the dataset format (see the module docstring
    and docs/data_format.md, "Importing a recording")."""
    c = check_source_config(dict(c))
    paths = _paths(c)
    tracks: list[_Track] = []
    layout = None
    for path in paths:
        suffix = path.suffix.lower()
        if suffix == ".npz":
            ts, names, kinds = _read_npz(path, c)
        elif suffix in (".csv", ".txt"):
            ts, names, kinds = _read_csv(path, c)
        else:
            raise DatasetError(f"{path}: unknown recording format '{suffix}' (dataset=import reads .csv and .npz)")
        if layout is None:
            layout = (names, kinds, str(path))
        elif (names, kinds) != layout[:2]:
            raise DatasetError(
                f"{path}: bodies {list(zip(names, kinds))} differ from those of {layout[2]} {list(zip(*layout[:2]))}"
            )
        tracks += ts
    assert layout is not None  # _paths returns at least one file
    names, kinds, _ = layout
    scale_t, scale_p = float(c["time_scale"]) * check_time_unit(c), float(c["length_scale"])
    for tr in tracks:
        tr.t0 = float(tr.t[0]) * scale_t
        tr.t = (tr.t - tr.t[0]) * scale_t
        tr.p = tr.p * scale_p
        if len(tr.t) < 3:
            raise DatasetError(f"{tr.source}: {len(tr.t)} samples; a trajectory needs at least 3")
    h_cfg = float(c["h"]) if c.get("h") is not None else None
    steps = [_uniform(tr, c, h_cfg) for tr in tracks]
    h = h_cfg or float(np.median(steps))
    warn_if_milliseconds(c, h, [tr.t for tr in tracks], ", ".join(map(str, paths)))
    if not c["resample"] and h_cfg is None:
        off = [i for i, s in enumerate(steps) if abs(s - h) > c["time_tolerance"] * h]
        if off:
            raise DatasetError(
                f"{tracks[off[0]].source}: time step {steps[off[0]]:.6g} s differs from the other trajectories' "
                f"{h:.6g} s; set dataset.resample=true (and dataset.h) to resample them all at one step"
            )
    sources = []
    for tr in tracks:
        info = {"source": tr.source, "samples": len(tr.t), "duration_s": float(tr.t[-1])}
        if c["resample"]:
            tr.t, tr.R, tr.p = resample(tr.t, tr.R, tr.p, h, tr.source)
            info["resampled_samples"] = len(tr.t)
        if c.get("smoothing"):
            w, o = int(c["smoothing"]["window"]), int(c["smoothing"]["order"])
            if w > len(tr.t):
                raise ConfigError(f"dataset.smoothing.window={w} is longer than {tr.source} ({len(tr.t)} samples)")
            try:
                tr.R, tr.p = smooth_pose(tr.R, tr.p, w, o)
            except ValueError as e:
                raise DatasetError(f"{tr.source}: {e}") from None
        sources.append(info)
    if c.get("chunk_steps"):
        n = int(c["chunk_steps"]) + 1
        pieces = []
        for tr in tracks:
            k = len(tr.t) // n
            if k == 0:
                raise ConfigError(f"dataset.chunk_steps={n - 1}: {tr.source} has only {len(tr.t) - 1} steps")
            pieces += [
                _Track(
                    tr.t[j * n : (j + 1) * n],
                    tr.R[j * n : (j + 1) * n],
                    tr.p[j * n : (j + 1) * n],
                    tr.source,
                    tr.columns,
                    tr.name,
                    tr.t0 + float(tr.t[j * n]),
                )
                for j in range(k)
            ]
        tracks = pieces
    lengths = [len(tr.t) for tr in tracks]
    N1 = min(lengths)
    if max(lengths) > N1:
        warnings.warn(
            f"{paths[0]}{' ...' if len(paths) > 1 else ''}: trajectories have {N1} to {max(lengths)} samples; "
            f"all are cropped to their first {N1} (the format needs equal lengths)",
            DataWarning,
            stacklevel=2,
        )
    R = np.stack([tr.R[:N1] for tr in tracks])
    p = np.stack([tr.p[:N1] for tr in tracks])
    n, N1, R, p, _ = _select(c, R, p, None, ", ".join(map(str, paths)))
    split, overlap = default_split(n, float(c["test_fraction"]), c["n_test"], int(c["seed"]))
    params = _params(
        c,
        sources=sources,
        rotation=c["rotation"],
        resampled=bool(c["resample"]),
        split_source="default split",
        split_overlap=overlap,
        **({"columns": tracks[0].columns} if tracks[0].columns else {}),
        # per trajectory: the recording's name and first time stamp (s), which `export=csv|npz` writes back
        **({"trajectory_names": [str(tr.name) for tr in tracks[:n]]} if tracks[0].name is not None else {}),
        trajectory_start_s=[tr.t0 for tr in tracks[:n]],
        **gravity_params(c),
    )
    return Dataset(
        R=R,
        p=p,
        h=h,
        scene=Path(paths[0]).stem,
        body_names=names,
        body_kinds=kinds,
        params=params,
        seed=int(c["seed"]),
        split=split,
    )


__all__ = [
    "SOURCE_SCENES",
    "ROTATIONS",
    "check_source_config",
    "hashed_config",
    "file_digest",
    "complete_steps",
    "default_split",
    "resample",
    "from_file",
    "import_recording",
]
