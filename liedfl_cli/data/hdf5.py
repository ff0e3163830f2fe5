"""The `Dataset` container and its HDF5 file format (see docs/data_format.md).

A dataset holds T trajectories of N+1 poses of a product group SE(3)^m x SO(3)^n, sampled every h:
R (T, N+1, B, 3, 3) with the m SE(3) bodies first, p (T, N+1, m, 3).  Models may only see R, p, t and
h; `extras` (ground-truth velocities, torques, ...) are for evaluation only.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from .. import __version__
from ..errors import DatasetError, DataWarning
from ..files.io_utils import clean_orphans, deferred_signals, temporary_name
from ..lie import so3
from ..lie.product import Pose, ProductGroup
from ..lie.tolerances import tol
from ..lie.tree import ROTATIONS, Tree
from .attributes import BODY_KINDS, FORMAT_VERSION, read_root_attributes


@dataclass(eq=False)
class Dataset:
    """Trajectories of a product group plus metadata (all arrays numpy, float64)."""

    R: np.ndarray  # (T, N+1, B, 3, 3)
    p: np.ndarray  # (T, N+1, m, 3)
    h: float
    scene: str
    body_names: list[str]
    body_kinds: list[str]  # "se3" bodies first, then "so3"
    params: dict[str, Any] = field(default_factory=dict)
    seed: int = -1
    split: dict[str, np.ndarray] = field(default_factory=dict)
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    t: np.ndarray | None = None  # (N+1,); defaults to h * arange(N+1)
    tree: Tree | None = None  # kinematic tree (parents, joint offsets, rotation convention), if any

    def __post_init__(self):
        self.R = np.asarray(self.R, dtype=np.float64)
        self.p = np.asarray(self.p, dtype=np.float64)
        self.h = float(self.h)
        self.seed = int(self.seed)
        self.body_names = [str(b) for b in self.body_names]
        self.body_kinds = [str(b) for b in self.body_kinds]
        if self.t is None and self.R.ndim >= 2:
            self.t = self.h * np.arange(self.R.shape[1], dtype=np.float64)
        elif self.t is not None:
            self.t = np.asarray(self.t, dtype=np.float64)
        if not self.split and self.R.ndim >= 1:
            self.split = {"train": np.arange(self.R.shape[0]), "test": np.zeros(0, dtype=np.int64)}
        self.split = {k: np.asarray(v, dtype=np.int64).reshape(-1) for k, v in self.split.items()}

    # ------------------------------------------------------------------ layout
    @property
    def group(self) -> ProductGroup:
        return ProductGroup(self.n_se3, self.n_so3)

    @property
    def n_se3(self) -> int:
        return sum(k == "se3" for k in self.body_kinds)

    @property
    def n_so3(self) -> int:
        return sum(k == "so3" for k in self.body_kinds)

    @property
    def n_bodies(self) -> int:
        return len(self.body_kinds)

    @property
    def n_trajectories(self) -> int:
        """T."""
        return int(self.R.shape[0])

    @property
    def n_steps(self) -> int:
        """N: number of time steps (each trajectory holds N+1 poses)."""
        return int(self.R.shape[1]) - 1

    @property
    def train_idx(self) -> np.ndarray:
        return self.split["train"]

    @property
    def test_idx(self) -> np.ndarray:
        return self.split["test"]

    def pose(self, traj_idx=None, dtype: torch.dtype = torch.float64, device=None) -> Pose:
        """Torch `Pose` of the selected trajectories: R (..., N+1, B, 3, 3), p (..., N+1, m, 3).

        traj_idx: None (all), an int, a slice or an integer array / list; "train" / "test" select a split.
        """
        if isinstance(traj_idx, str):
            traj_idx = self.split[traj_idx]
        R, p = (self.R, self.p) if traj_idx is None else (self.R[traj_idx], self.p[traj_idx])
        return Pose(
            torch.as_tensor(np.ascontiguousarray(R), dtype=dtype, device=device),
            torch.as_tensor(np.ascontiguousarray(p), dtype=dtype, device=device),
        )

    def validate(self, source: str = "<in-memory dataset>") -> Dataset:
        """Run the load-time checks on this dataset (projects slightly-off rotations in place)."""
        self.R = _validate(self, source)
        return self

    def __repr__(self) -> str:
        return (
            f"Dataset(scene={self.scene!r}, group={self.group.name}, T={self.n_trajectories}, "
            f"N={self.n_steps}, h={self.h}, train={len(self.train_idx)}, test={len(self.test_idx)}, "
            f"extras={sorted(self.extras)})"
        )


# ---------------------------------------------------------------------- writing
def save_dataset(ds: Dataset, path) -> Path:
    """Write `ds` to `path` atomically (write `<path>.tmp.<host>.<pid>.<token>`, then os.replace).
    Returns the path.

    The temporary name carries the host, the process id and a random token, so parallel sweep jobs
    that generate the same dataset (on one machine or on several sharing the file system) never write
    into one temporary file; the last rename wins with identical content. Temporary files of writers
    of this host that died (killed between writing and renaming) are removed first; another host's
    are left alone (`io_utils.clean_orphans`)."""
    path = Path(path)
    _validate(ds, str(path), project=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_orphans(path.parent)
    tmp = temporary_name(path.with_suffix(".h5"), hidden=False)
    # SIGINT/SIGTERM are held while the file is written and renamed, then delivered (a Ctrl-C
    # exits with "interrupted" and leaves no temporary file)
    with deferred_signals():
        _write(ds, path, tmp)
    return path


def _write(ds: Dataset, path: Path, tmp: Path) -> None:
    try:
        with h5py.File(tmp, "w") as f:
            a = f.attrs
            a["format_version"] = FORMAT_VERSION
            a["scene"] = ds.scene
            a["h"] = float(ds.h)
            a["body_names"] = json.dumps(list(ds.body_names))
            a["body_kinds"] = json.dumps(list(ds.body_kinds))
            a["n_se3"] = ds.n_se3
            a["n_so3"] = ds.n_so3
            a["params"] = json.dumps(ds.params, sort_keys=True)
            a["seed"] = int(ds.seed)
            a["liedfl_version"] = __version__
            a["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.create_dataset("R", data=ds.R)
            f.create_dataset("p", data=ds.p)
            t = ds.h * np.arange(ds.R.shape[1]) if ds.t is None else ds.t  # (the documented default)
            f.create_dataset("t", data=np.asarray(t, dtype=np.float64))
            g = f.create_group("split")
            for k in ("train", "test"):
                g.create_dataset(k, data=np.asarray(ds.split[k], dtype=np.int64))
            if ds.tree is not None:
                a["parents"] = json.dumps(list(ds.tree.parents))
                a["rotations"] = ds.tree.rotations
                f.create_dataset("joint_offsets", data=np.asarray(ds.tree.offsets, dtype=np.float64))
                if ds.tree.joints is not None:
                    a["joints"] = json.dumps(list(ds.tree.joints))
                    f.create_dataset("joint_axes", data=np.asarray(ds.tree.axes_array(), dtype=np.float64))
            e = f.create_group("extras")
            for k, v in ds.extras.items():
                e.create_dataset(k, data=np.asarray(v))
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


# ---------------------------------------------------------------------- reading
def _array(f, name: str, src: str):
    obj = f.get(name)
    if obj is None:
        return None
    if not isinstance(obj, h5py.Dataset):
        raise DatasetError(f"{src}: '{name}' must be an HDF5 dataset, found a group")
    return obj[()]


def load_dataset(path, require_split: bool = True) -> Dataset:
    """Read and validate an HDF5 dataset file; every problem raises `DatasetError`.

    Rotations off SO(3) by more than the warn tolerance (1e-9 float64 / 1e-5 float32) but less than
    the reject tolerance (1e-3) are projected by SVD with a single warning. `R`, `p` and `t` are
    returned as float64 whatever their stored precision (float32 data are checked with the float32
    tolerances; float16 is refused); extras keep their dtype, in native byte order.

    require_split: the file must hold the `split` group with a non-empty `split/train` (what
    training needs; the default). With False, a file without it loads with every trajectory in
    `train` and an empty `test`.
    """
    path = Path(path)
    src = str(path)
    if not path.exists():
        raise DatasetError(f"{src}: file does not exist")
    if not path.is_file() or not h5py.is_hdf5(path):
        raise DatasetError(f"{src}: not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            a = read_root_attributes(f.attrs, src)
            h, kinds, names = a["h"], a["body_kinds"], a["body_names"]
            if names is None:
                names = [f"body{i}" for i in range(len(kinds))]
            for key, expected in (("n_se3", kinds.count("se3")), ("n_so3", kinds.count("so3"))):
                if a[key] is not None and a[key] != expected:
                    raise DatasetError(
                        f"{src}: attribute '{key}' is {a[key]} but 'body_kinds' lists {expected} such bodies"
                    )
            if len(names) != len(kinds):
                raise DatasetError(
                    f"{src}: attribute 'body_names' has {len(names)} entries but 'body_kinds' has {len(kinds)}"
                )
            scene = path.stem if a["scene"] is None else a["scene"]
            params = {} if a["params"] is None else a["params"]
            seed = -1 if a["seed"] is None else a["seed"]
            parents, rotations, joints = a["parents"], a["rotations"], a["joints"]
            offsets = _array(f, "joint_offsets", src)
            joint_axes = _array(f, "joint_axes", src)
            R = _array(f, "R", src)
            if R is None:
                raise DatasetError(f"{src}: dataset 'R' is missing")
            p = _array(f, "p", src)
            t = _array(f, "t", src)
            split = None
            if "split" in f:
                split = {}
                for k in ("train", "test"):
                    a = _array(f, f"split/{k}", src)
                    if a is None:
                        raise DatasetError(f"{src}: dataset 'split/{k}' is missing")
                    split[k] = a
            extras = {}
            if "extras" in f:
                for k in f["extras"]:
                    extras[k] = _native(_array(f, f"extras/{k}", src))
    except DatasetError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:  # RuntimeError: h5py, corrupt metadata
        raise DatasetError(f"{src}: cannot read file ({type(exc).__name__}: {exc})") from None

    R = _float_array(R, "R", src)
    m = kinds.count("se3") if all(k in BODY_KINDS for k in kinds) else 0
    if p is None:
        if m > 0:
            raise DatasetError(f"{src}: dataset 'p' is missing (required with {m} SE(3) bodies)")
        p = np.zeros(R.shape[:2] + (0, 3)) if R.ndim == 5 else np.zeros((0, 0, 0, 3))
    p = _float_array(p, "p", src)
    for k in ("train", "test") if split is not None else ():
        if not np.issubdtype(np.asarray(split[k]).dtype, np.integer):
            raise DatasetError(f"{src}: dataset 'split/{k}' must hold integers, got dtype {np.asarray(split[k]).dtype}")
        if np.asarray(split[k]).ndim != 1:  # a 2-D split would be flattened into other trajectories
            raise DatasetError(
                f"{src}: dataset 'split/{k}' must be a 1-D list of trajectory indices, got shape "
                f"{tuple(np.asarray(split[k]).shape)}"
            )
    input_dtype = torch.float32 if R.dtype == np.float32 else torch.float64
    tree = read_tree(parents, offsets, rotations, kinds, src, joints, joint_axes)
    if "physics" in params and all(k in BODY_KINDS for k in kinds):
        from .checks import check_physics

        n_so3 = len(kinds) - m
        check_physics(params["physics"], len(kinds), 6 * m + 3 * n_so3, tree, src)
    ds = Dataset(
        R=R,
        p=p,
        h=float(h),
        scene=str(scene),
        body_names=list(names),
        body_kinds=list(kinds),
        params=params,
        seed=int(seed),
        split=split or {},
        extras=extras,
        t=None if t is None else _float_array(t, "t", src),
        tree=tree,
    )
    if split is None and require_split:
        raise DatasetError(
            f"{src}: group 'split' is missing (it must hold 'split/train' and 'split/test', the trajectory "
            "indices to train and to test on; see docs/data_format.md)"
        )
    if split is None and ds.R.ndim >= 1:
        ds.split = {"train": np.arange(ds.R.shape[0]), "test": np.zeros(0, dtype=np.int64)}
    ds.R = _validate(ds, src, input_dtype=input_dtype, t_dtype=None if t is None else np.asarray(t).dtype)
    if tree is not None and tree.joints is not None:
        check_joint_motion(ds, src, input_dtype)
    if require_split and ds.split["train"].size == 0:
        raise DatasetError(f"{src}: dataset 'split/train' is empty: there is nothing to train on")
    return ds


def read_tree(parents, offsets, rotations, kinds: list, src: str, joints=None, joint_axes=None) -> Tree | None:
    """The kinematic tree of a file from its raw fields (root attributes `parents` (JSON list),
    `rotations`, optional `joints` (JSON list), datasets `joint_offsets` (B, 3) and optional
    `joint_axes` (B, 2, 3)), or None when the file has none. Every problem is a one-line
    DatasetError naming the field; `kinds` (the body kinds) fix B and the root's kind."""
    if parents is None and offsets is None and (joints is not None or joint_axes is not None):
        what = "attribute 'joints'" if joints is not None else "dataset 'joint_axes'"
        raise DatasetError(f"{src}: {what} needs a tree (attribute 'parents' and dataset 'joint_offsets')")
    if rotations is not None and (not isinstance(rotations, str) or rotations not in ROTATIONS):
        raise DatasetError(f"{src}: attribute 'rotations' is {rotations!r}; use one of {list(ROTATIONS)}")
    if parents is None and offsets is None:
        if rotations == "parent":
            raise DatasetError(
                f"{src}: attribute 'rotations' is 'parent' but the file has no tree: parent-relative "
                "rotations need the attribute 'parents' and the dataset 'joint_offsets'"
            )
        return None
    if parents is None or offsets is None:
        have, missing = ("joint_offsets", "parents") if parents is None else ("parents", "joint_offsets")
        what = "attribute" if missing == "parents" else "dataset"
        raise DatasetError(
            f"{src}: {what} '{missing}' is missing (a tree needs both 'parents' and 'joint_offsets'; "
            f"the file has '{have}')"
        )
    B = len(kinds)
    if not isinstance(parents, list) or not all(isinstance(q, int) and not isinstance(q, bool) for q in parents):
        raise DatasetError(f"{src}: attribute 'parents' must be a JSON list of integers, got {parents!r}")
    if len(parents) != B:
        raise DatasetError(f"{src}: attribute 'parents' has {len(parents)} entries but 'body_kinds' has {B}")
    if parents[0] != -1:
        raise DatasetError(f"{src}: attribute 'parents' must start with -1 (body 0 is the root), got {parents[0]}")
    for b, q in enumerate(parents[1:], start=1):
        if not 0 <= q < b:
            raise DatasetError(
                f"{src}: attribute 'parents' has parent {q} for body {b}; every parent must be an earlier "
                f"body (0..{b - 1}), i.e. parents come before their children"
            )
    offsets = _float_array(offsets, "joint_offsets", src)
    if offsets.shape != (B, 3):
        raise DatasetError(f"{src}: dataset 'joint_offsets' has shape {offsets.shape}, expected ({B}, 3)")
    fin = np.isfinite(offsets)
    if not fin.all():
        raise DatasetError(f"{src}: dataset 'joint_offsets' has non-finite value at index {_first(~fin)}")
    n_se3 = sum(k == "se3" for k in kinds)
    if n_se3 > 1:
        raise DatasetError(
            f"{src}: attribute 'parents' describes a tree but 'body_kinds' lists {n_se3} SE(3) bodies; a tree has "
            "exactly one (body 0, the free root) or none (all SO(3), the root pinned at joint_offsets[0])"
        )
    if n_se3 == 1 and np.any(offsets[0] != 0):
        raise DatasetError(
            f"{src}: dataset 'joint_offsets' row 0 is {offsets[0].tolist()}; the free (SE(3)) root's row must be zeros"
        )
    free = n_se3 == 1
    if joints is None:
        if joint_axes is not None:
            raise DatasetError(f"{src}: dataset 'joint_axes' is given but attribute 'joints' is missing")
        return Tree.from_lists(parents, offsets, rotations or "world", free_root=free)
    return Tree.from_lists(
        parents, offsets, rotations or "world", free, *_read_joints(joints, joint_axes, B, free, src)
    )


def _read_joints(joints, joint_axes, B: int, free: bool, src: str) -> tuple[list[str], list | None]:
    """(joint types, axes or None) of a file, checked: one-line DatasetErrors naming the field and body."""
    from ..lie.tree import JOINT_TYPES

    if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
        raise DatasetError(f"{src}: attribute 'joints' must be a JSON list of joint types, got {joints!r:.80}")
    if len(joints) != B:
        raise DatasetError(f"{src}: attribute 'joints' has {len(joints)} entries but 'body_kinds' has {B}")
    for b, j in enumerate(joints):
        allowed = ("free",) if (b == 0 and free) else JOINT_TYPES
        if j not in allowed:
            where = "the free (SE(3)) root" if (b == 0 and free) else f"body {b}"
            why = " ('free' is only the free root's, body 0)" if j == "free" else ""
            raise DatasetError(f"{src}: attribute 'joints' has {j!r} for {where}{why}; use one of {list(allowed)}")
    needs = [b for b, j in enumerate(joints) if j in ("hinge", "universal")]
    if joint_axes is None:
        if needs:
            raise DatasetError(
                f"{src}: dataset 'joint_axes' is missing (body {needs[0]} is a {joints[needs[0]]} joint, "
                "which needs its axes)"
            )
        return list(joints), None
    axes = _float_array(joint_axes, "joint_axes", src)
    if axes.shape != (B, 2, 3):
        raise DatasetError(f"{src}: dataset 'joint_axes' has shape {axes.shape}, expected ({B}, 2, 3)")
    fin = np.isfinite(axes)
    if not fin.all():
        raise DatasetError(f"{src}: dataset 'joint_axes' has non-finite value at index {_first(~fin)}")
    for b in needs:
        for r in (0,) if joints[b] == "hinge" else (0, 1):
            n = float(np.linalg.norm(axes[b, r]))
            if abs(n - 1.0) > 1e-6:
                raise DatasetError(
                    f"{src}: dataset 'joint_axes' row [{b}, {r}] of the {joints[b]} joint has norm {n:.6g}; "
                    "axes must be unit vectors"
                )
    return list(joints), axes.tolist()


def check_joint_motion(ds: Dataset, src: str, dtype: torch.dtype = torch.float64) -> None:
    """Refuse a file whose motion R (T, N+1, B, 3, 3) violates its declared joints by more than
    `lie.joint_constraints.violation_tolerance(dtype)` (1e-6 rad for float64 files, 1e-4 for float32;
    `dtype`: the stored precision of R), with a one-line DatasetError naming the file, the body (index
    and name), the joint, the trajectory and the largest violation."""
    from ..lie.joint_constraints import joint_violation, violation_tolerance
    from ..lie.joints import to_joint_coordinates

    tree = ds.tree
    assert tree is not None
    R = torch.as_tensor(np.asarray(ds.R), dtype=torch.float64)
    if R.ndim != 5 or R.shape[1] < 1:
        return
    tol = violation_tolerance(dtype)
    q = to_joint_coordinates(tree, Pose(R, torch.zeros(*R.shape[:2], 0, 3, dtype=torch.float64)))
    axes = torch.tensor(tree.axes_array(), dtype=torch.float64)
    for b, kind in enumerate(tree.joint_kinds):
        v = joint_violation(kind, axes[b], q.R[:, :, b])  # (T,)
        if v.numel() and not bool((v <= tol).all()):
            i = int(torch.nan_to_num(v, nan=float("inf")).argmax())
            raise DatasetError(
                f"{src}: body {b} ({ds.body_names[b]}) is declared a {kind} joint but trajectory {i} violates it by "
                f"{float(v[i]):.3g} rad (> {tol:g}); fix 'joints'/'joint_axes' or leave 'joints' out "
                "(model.joints=auto infers them)"
            )


def _float_array(a, name: str, src: str) -> np.ndarray:
    a = np.asarray(a)
    if not np.issubdtype(a.dtype, np.floating):
        raise DatasetError(f"{src}: dataset '{name}' must hold floating-point numbers, got dtype {a.dtype}")
    if a.dtype.itemsize < 4:
        raise DatasetError(
            f"{src}: dataset '{name}' is stored as {a.dtype.name} ({np.finfo(a.dtype).precision} significant digits); "
            "store it as float32 or float64"
        )
    return a


def _native(a):
    """A numeric array in native byte order, same precision (torch refuses big-endian arrays)."""
    if isinstance(a, np.ndarray) and a.dtype.kind in "iufcb" and not a.dtype.isnative:
        return a.astype(a.dtype.newbyteorder("="))
    return a


# ---------------------------------------------------------------------- validation
def _first(mask: np.ndarray) -> tuple:
    return tuple(int(i) for i in np.argwhere(mask)[0])


def _validate(
    ds: Dataset, src: str, project: bool = True, input_dtype: torch.dtype = torch.float64, t_dtype=None
) -> np.ndarray:
    """Check `ds`; return R (projected where slightly off SO(3) if `project`). Raises DatasetError.
    t_dtype: the stored dtype of `t` (its spacing is checked to that precision)."""
    kinds, names = ds.body_kinds, ds.body_names
    bad = [i for i, k in enumerate(kinds) if k not in BODY_KINDS]
    if bad:
        raise DatasetError(
            f"{src}: attribute 'body_kinds' has unknown kind {kinds[bad[0]]!r} at index {bad[0]} (use 'se3' or 'so3')"
        )
    if not kinds:
        raise DatasetError(f"{src}: attribute 'body_kinds' is empty; a dataset needs at least one body")
    order = [i for i in range(1, len(kinds)) if kinds[i] == "se3" and kinds[i - 1] == "so3"]
    if order:
        raise DatasetError(
            f"{src}: attribute 'body_kinds' lists 'se3' after 'so3' at index {order[0]}; SE(3) bodies come first"
        )
    if len(names) != len(kinds):
        raise DatasetError(f"{src}: attribute 'body_names' has {len(names)} entries but 'body_kinds' has {len(kinds)}")
    if not np.isfinite(ds.h) or ds.h <= 0:
        raise DatasetError(f"{src}: attribute 'h' must be a positive finite number, got {ds.h!r}")
    B, m = len(kinds), kinds.count("se3")
    if ds.tree is not None:
        tr = ds.tree
        read_tree(
            list(tr.parents),
            np.asarray(tr.offsets, dtype=np.float64),
            tr.rotations,
            kinds,
            src,
            None if tr.joints is None else list(tr.joints),
            None if tr.axes is None else np.asarray(tr.axes_array(), dtype=np.float64),
        )
        if tr.free_root != (m == 1):
            raise DatasetError(
                f"{src}: field 'tree' has free_root={tr.free_root} but 'body_kinds' lists {m} SE(3) bodies"
            )

    R, p = ds.R, ds.p
    if R.ndim != 5 or R.shape[2:] != (B, 3, 3):
        raise DatasetError(
            f"{src}: dataset 'R' has shape {R.shape}, expected (T, N+1, {B}, 3, 3) for body_kinds {kinds}"
        )
    T, N1 = R.shape[:2]
    if T < 1 or N1 < 2:
        raise DatasetError(f"{src}: dataset 'R' has shape {R.shape}; need at least 1 trajectory of at least 2 poses")
    if p.shape != (T, N1, m, 3):
        raise DatasetError(f"{src}: dataset 'p' has shape {p.shape}, expected {(T, N1, m, 3)} (T, N+1, n_se3, 3)")
    for name, a in (("R", R), ("p", p)):
        fin = np.isfinite(a)
        if not fin.all():
            raise DatasetError(f"{src}: dataset '{name}' has non-finite value at index {_first(~fin)}")
    if ds.t is not None:
        t = np.asarray(ds.t)
        if t.shape != (N1,):
            raise DatasetError(f"{src}: dataset 't' has shape {t.shape}, expected ({N1},) to match 'R'")
        if not np.isfinite(t).all():
            raise DatasetError(f"{src}: dataset 't' has non-finite value at index {_first(~np.isfinite(t))}")
        spacing_tol = 1e-6 * ds.h
        if t_dtype is not None and np.dtype(t_dtype).itemsize < 8:  # rounding of the stored times
            spacing_tol = max(spacing_tol, 4 * float(np.finfo(t_dtype).eps) * float(np.abs(t).max()))
        off = np.abs(np.diff(t) - ds.h) > spacing_tol
        if off.any():
            k = _first(off)[0]
            raise DatasetError(
                f"{src}: dataset 't' is not evenly spaced by h={ds.h}: t[{k + 1}] - t[{k}] = {t[k + 1] - t[k]!r}"
            )

    if set(ds.split) != {"train", "test"}:
        raise DatasetError(f"{src}: 'split' must have exactly 'train' and 'test', got {sorted(ds.split)}")
    for k in ("train", "test"):
        idx = np.asarray(ds.split[k])
        if idx.ndim != 1:
            raise DatasetError(f"{src}: dataset 'split/{k}' has shape {idx.shape}, expected 1-D")
        out = (idx < 0) | (idx >= T)
        if out.any():
            j = _first(out)[0]
            raise DatasetError(
                f"{src}: dataset 'split/{k}' has index {int(idx[j])} out of range [0, {T}) at position {j}"
            )
        uniq, counts = np.unique(idx, return_counts=True)
        if (counts > 1).any():
            raise DatasetError(f"{src}: dataset 'split/{k}' lists trajectory {int(uniq[counts > 1][0])} twice")
    both = np.isin(ds.split["test"], ds.split["train"])
    overlap_ok = isinstance(ds.params, dict) and ds.params.get("split_overlap") is True  # reproduction data
    if both.any() and not overlap_ok:
        j = _first(both)[0]
        raise DatasetError(
            f"{src}: dataset 'split/test' shares trajectory {int(ds.split['test'][j])} with 'split/train' "
            f"(at position {j}); splits must be disjoint (unless params['split_overlap'] is true)"
        )
    for k, v in ds.extras.items():
        v = np.asarray(v)
        if v.ndim < 1 or v.shape[0] != T:
            raise DatasetError(f"{src}: dataset 'extras/{k}' has shape {v.shape}; its first axis must be T={T}")

    # rotations: ||R^T R - I||_F and det R
    warn_tol, reject_tol = tol(input_dtype, "project_warn"), tol(input_dtype, "reject")
    # huge finite entries overflow to inf (or inf - inf = NaN): both must count as gross, hence `not <=`
    with np.errstate(over="ignore", invalid="ignore"):
        E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
        err = np.sqrt((E * E).sum((-1, -2)))
        det = np.linalg.det(R)
        det_err = np.abs(det - 1.0)
    worst = np.maximum(err, det_err)
    gross = ~(worst <= reject_tol)
    if gross.any():
        i = _first(gross)
        raise DatasetError(
            f"{src}: dataset 'R' is not a rotation at index {i} (trajectory, sample, body): "
            f"||R^T R - I||_F = {err[i]:.3g}, det R = {det[i]:.6g} (reject tolerance {reject_tol:g})"
        )
    off = worst > warn_tol
    if project and off.any():
        R = R.copy()
        R[off] = so3.project(torch.from_numpy(np.ascontiguousarray(R[off]))).numpy()
        warnings.warn(
            f"{src}: projected {int(off.sum())} of {off.size} rotations in 'R' onto SO(3) by SVD "
            f"(max ||R^T R - I||_F = {err.max():.3g}, max |det R - 1| = {det_err.max():.3g}, "
            f"warn tolerance {warn_tol:g})",
            DataWarning,
            stacklevel=3,
        )
    # per-step rotation: a warning above pi/2, an error above 0.9 pi (data/checks.py)
    from .checks import check_step_rotation

    check_step_rotation(R, src, names)
    return R


__all__ = ["FORMAT_VERSION", "Dataset", "save_dataset", "load_dataset", "read_tree"]
