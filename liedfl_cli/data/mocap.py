"""Real recordings: BVH motion capture imported onto SE(3) x SO(3)^n.

Listed in the scene registry `scenes.SCENES`.

Scene `cmu_cartwheel` (config conf/dataset/cmu_cartwheel.yaml, paper Experiment 4): CMU subject 49,
cartwheel trials 06 and 07 (BVH files shipped inside the package, liedfl_cli/data/cmu_mocap/, with
their ATTRIBUTION.md and PROVENANCE.md; `data/cmu_mocap/` of the repository links there).
The import, per file:

1. read the BVH (`bvh.read_bvh`), drop the first `skip_frames` motion lines (1: the T-pose frame the
   BVH converter put in front of the recording);
2. body 0 (SE(3)) is the world pose of the `root` joint (Hips): rotation and position from forward
   kinematics; bodies 1..n (SO(3)) are the *local* rotations of the `joints` listed in the config
   (relative to the BVH parent, Euler channels converted in the order each joint declares);
   every selected joint's BVH parent must itself be selected (root or joint);
3. world frame: BVH is y-up; with `z_up: true` the world is turned by +90 degrees about x (so that
   e3 points up, as docs/data_format.md requires): R_root <- Q R_root, p <- Q p;
4. root positions are multiplied by `length_scale` (1.0 keeps the file unit: for the CMU files one
   CMU ASF unit = 1/0.45 inch = 0.0564444 m, `unit_m`);
5. optional Savitzky-Golay smoothing (`smoothing: {window, order}`, see smoothing.py) on the whole
   recording, rotations in the local tangent space, positions plain;
6. keep every `subsample`-th frame (h = Frame Time x subsample);
7. crop every sequence to its first `steps + 1` frames (the format needs equal lengths; `steps` at
   most the shortest available length minus one); original lengths are kept in params["sources"].

Trajectories: one per file; `n_trajectories` must equal len(files), unless `cap_trajectories: true`
(set by conf/experiment/exp4_mocap.yaml), which makes it an upper bound: the first
min(n_trajectories, len(files)) files are used (budgets written for simulated scenes, e.g.
conf/budget/smoke.yaml, ask for more trajectories than there are recordings).

Split: `split: reproduce` (paper) puts every sequence in both "train" and "test" and sets
params["split_overlap"] = true, which tells the HDF5 validation that the overlap is intended;
`split: holdout` makes the last `n_test` (or round(test_fraction * T)) sequences the test set.
The raw (unsmoothed, but cropped) poses are kept as extras `R_raw`, `p_raw` for evaluation.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import ConfigError, DatasetError, DataWarning
from ..lie import so3
from ..lie.product import Pose
from ..lie.tree import Tree
from .bvh import BVH, forward_kinematics, read_bvh
from .hdf5 import Dataset
from .scene_common import REQUIRED_KEYS, check_config, dataset_params, to_dict
from .smoothing import check_window, smooth_pose

REPO_ROOT = Path(__file__).resolve().parents[2]
"""Relative BVH paths in a config are looked up here first (then in the working directory, then in
the installed package: `PACKAGE_ROOT`)."""
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
"""liedfl_cli/: the shipped recordings are `data/cmu_mocap/*.bvh` under it, so the configs' paths
(`data/cmu_mocap/49_06.bvh`) resolve in a wheel install too."""
MOCAP_DIR = PACKAGE_ROOT / "data" / "cmu_mocap"
"""The CMU recordings shipped with liedfl (49_06.bvh, 49_07.bvh, ATTRIBUTION.md, PROVENANCE.md)."""

ASF_UNIT_M = 0.0254 / 0.45
"""One CMU ASF length unit (skeleton `length 0.45`: 1/0.45 inch) in metres, 0.0564444 m."""

Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Rotation by +90 degrees about x: maps the BVH up axis y to z."""

CMU_BODY_JOINTS = (
    "LHipJoint",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "RHipJoint",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "LowerBack",
    "Spine",
    "Spine1",
    "Neck",
    "Neck1",
    "Head",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
)
"""The paper's 22 body joints under their names in the CMU BVH conversion (PROVENANCE.md)."""

BVH_TO_ASF = {
    "Hips": "root",
    "LHipJoint": "lhipjoint",
    "RHipJoint": "rhipjoint",
    "LeftUpLeg": "lfemur",
    "RightUpLeg": "rfemur",
    "LeftLeg": "ltibia",
    "RightLeg": "rtibia",
    "LeftFoot": "lfoot",
    "RightFoot": "rfoot",
    "LeftToeBase": "ltoes",
    "RightToeBase": "rtoes",
    "LowerBack": "lowerback",
    "Spine": "upperback",
    "Spine1": "thorax",
    "Neck": "lowerneck",
    "Neck1": "upperneck",
    "Head": "head",
    "LeftShoulder": "lclavicle",
    "RightShoulder": "rclavicle",
    "LeftArm": "lhumerus",
    "RightArm": "rhumerus",
    "LeftForeArm": "lradius",
    "RightForeArm": "rradius",
    "LeftHand": "lwrist",
    "RightHand": "rwrist",
    "LeftFingerBase": "lhand",
    "RightFingerBase": "rhand",
    "LeftHandIndex1": "lfingers",
    "RightHandIndex1": "rfingers",
    "LThumb": "lthumb",
    "RThumb": "rthumb",
}

IMPORT_VERSION = 2  # 2: the dataset carries its kinematic tree (parents, joint_offsets, rotations="parent")
"""Bump (here and in conf/dataset/cmu_cartwheel.yaml) when the import would change the data for the same
config: the config, hence `import_version`, is part of the cache hash."""

SCENE_KEYS = (
    "import_version",
    "files",
    "skip_frames",
    "subsample",
    "root",
    "joints",
    "length_scale",
    "unit_m",
    "z_up",
    "smoothing",
    "split",
    "cap_trajectories",
)
"""Scene-specific keys of the cmu_cartwheel config (besides the common ones, scene_common.REQUIRED_KEYS)."""

REAL_DATA_SCENES = ("cmu_cartwheel",)
"""Scenes imported from recordings: no physics/initial/solver fields, fixed number of trajectories."""

ATTRIBUTION = (
    "The data used in this project was obtained from mocap.cs.cmu.edu. "
    "The database was created with funding from NSF EIA-0196217."
)


# --------------------------------------------------------------------------- metrics
def moving_joints(ds: Dataset, tol: float = 1e-9) -> list[int]:
    """Indices (0 = the first joint, i.e. body n_se3) of the joints that rotate somewhere in the data:
    the geodesic distance of some sample from the joint's first sample exceeds `tol` (rad) in some
    trajectory. In the CMU cartwheels LHipJoint, RHipJoint, LeftShoulder and RightShoulder have
    constant BVH channels, so 18 of the 22 joints move."""
    m = ds.n_se3
    R = torch.as_tensor(ds.R[:, :, m:])  # (T, N+1, n, 3, 3)
    d = so3.geodesic_distance(R, R[:, :1].expand_as(R))  # (T, N+1, n)
    return [int(j) for j in torch.nonzero(d.amax((0, 1)) > tol).flatten()]


def mocap_errors(pred: Pose, true: Pose, relative_position: bool = False, joints=None) -> dict[str, torch.Tensor]:
    """Errors of the paper's Table (Exp 4) between two pose tracks of SE(3)^m x SO(3)^n (m >= 1).

    pred, true: R (..., K, B, 3, 3), p (..., K, m, 3) with K time samples; body 0 is the root (SE(3)),
    bodies m.. are the joints (SO(3)).  joints: indices of the joints (0 = body m) the mean joint error
    runs over (None: all; evaluations pass `moving_joints`).  Returns tensors:
      root_rot   (...)       mean over time of the root rotation geodesic distance |log(R^_0^T R_0)| (rad)
      joint_rot  (...)       mean over time and over the selected joints of the joint geodesic distances (rad)
      joint_rot_all (...)    the same over all n joints
      root_pos   (...)       mean over time of |p^_0 - p_0| (length unit of the data)
      root_rot_t, joint_rot_t, joint_rot_all_t, root_pos_t   (..., K)   the same per time sample
      joint_rot_per_joint    (..., n)       per joint, mean over time
    relative_position: measure each root position from the track's first sample (p_k - p_0).  Makes no
    difference for a rollout started from the true initial poses; for two different recordings (which
    start at different places) it is the convention that reproduces the paper's "ground truth
    discrepancy" root position (6.64 ASF units here vs 6.624 in the paper; 28.2 without it).
    """
    R1, R2 = pred.R, true.R
    p1, p2 = pred.p, true.p
    if R1.shape != R2.shape or p1.shape != p2.shape:
        raise ValueError(
            f"mocap_errors: shapes differ: R {tuple(R1.shape)} vs {tuple(R2.shape)}, "
            f"p {tuple(p1.shape)} vs {tuple(p2.shape)}"
        )
    m = p1.shape[-2]
    if m < 1 or R1.shape[-3] <= m or R1.ndim < 4:
        raise ValueError(
            f"mocap_errors: need a time axis, >= 1 SE(3) root and >= 1 SO(3) joint; "
            f"got R {tuple(R1.shape)}, p {tuple(p1.shape)}"
        )
    d = so3.geodesic_distance(R1, R2)  # (..., K, B)
    root_rot_t = d[..., 0]
    dj = d[..., m:]
    n = dj.shape[-1]
    sel = list(range(n)) if joints is None else [int(j) for j in joints]
    if not sel or min(sel) < 0 or max(sel) >= n:
        raise ValueError(f"mocap_errors: joints {list(joints)} must be a non-empty subset of 0..{n - 1}")
    joint_rot_t = dj[..., sel].mean(-1)
    joint_all_t = dj.mean(-1)
    q1, q2 = p1[..., 0, :], p2[..., 0, :]  # (..., K, 3)
    if relative_position:
        q1, q2 = q1 - q1[..., :1, :], q2 - q2[..., :1, :]
    root_pos_t = torch.linalg.vector_norm(q1 - q2, dim=-1)
    return {
        "root_rot": root_rot_t.mean(-1),
        "joint_rot": joint_rot_t.mean(-1),
        "joint_rot_all": joint_all_t.mean(-1),
        "root_pos": root_pos_t.mean(-1),
        "root_rot_t": root_rot_t,
        "joint_rot_t": joint_rot_t,
        "joint_rot_all_t": joint_all_t,
        "root_pos_t": root_pos_t,
        "joint_rot_per_joint": dj.mean(-2),
    }


def recording_discrepancy(
    ds: Dataset, raw: bool = False, a: int = 0, b: int = 1, relative_position: bool = True, joints="moving"
) -> dict[str, float]:
    """`mocap_errors` between trajectories a and b of a mocap dataset (the reference scale of Exp 4).

    raw: use the unsmoothed extras `R_raw`/`p_raw` instead of R/p.  relative_position: see
    `mocap_errors` (default True, the paper's convention).  joints: "moving" (`moving_joints(ds)`, the
    default), None (all) or a list of joint indices; `joint_rot_all` is over all joints either way.
    Adds root_pos_m (metres) when the dataset records its length unit in params["length_unit_m"].
    """
    R = ds.extras["R_raw"] if raw else ds.R
    p = ds.extras["p_raw"] if raw else ds.p
    if isinstance(joints, str) and joints == "moving":
        joints = moving_joints(ds)
    e = mocap_errors(
        Pose(torch.as_tensor(R[a]), torch.as_tensor(p[a])),
        Pose(torch.as_tensor(R[b]), torch.as_tensor(p[b])),
        relative_position,
        joints=joints,
    )
    out = {k: float(e[k]) for k in ("root_rot", "joint_rot", "joint_rot_all", "root_pos")}
    unit = ds.params.get("length_unit_m")
    if unit is not None:
        out["root_pos_m"] = out["root_pos"] * float(unit)
    return out


# --------------------------------------------------------------------------- skeleton drawing
def skeleton_points(R: np.ndarray, p: np.ndarray, skeleton: Mapping[str, Any]):
    """World positions of a skeleton for plots.

    R (..., B, 3, 3), p (..., m, 3): a pose of the dataset (body 0 the root in world coordinates,
    the other bodies local rotations); skeleton: params["skeleton"] of a mocap dataset.
    Returns (points (..., B + P, 3), edges list[(i, j)]): the B body origins, then the P extra points
    fixed in a body (dropped children such as toes and fingers, End Sites), and the segments to draw.
    """
    R = np.asarray(R, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    parents = list(skeleton["parents"])
    off = np.asarray(skeleton["offsets"], dtype=np.float64)
    t = np.broadcast_to(off, R.shape[:-3] + off.shape).copy()
    t[..., 0, :] = p[..., 0, :]
    Rw, pw = forward_kinematics(parents, t, R)
    extra = skeleton.get("points", [])
    if extra:
        idx = [int(b) for b, _ in extra]
        o = np.asarray([x for _, x in extra], dtype=np.float64)
        pe = pw[..., idx, :] + np.einsum("...bij,bj->...bi", Rw[..., idx, :, :], o)
        pw = np.concatenate([pw, pe], axis=-2)
    B = len(parents)
    edges = [(q, j) for j, q in enumerate(parents) if q >= 0]
    edges += [(int(b), B + k) for k, (b, _) in enumerate(extra)]
    return pw, edges


# --------------------------------------------------------------------------- import
def _resolve(path: str) -> Path:
    p = Path(str(path)).expanduser()
    if p.is_absolute():
        return p
    bases = list(dict.fromkeys((REPO_ROOT, Path.cwd(), PACKAGE_ROOT)))  # a source checkout: REPO_ROOT holds liedfl_cli
    for base in bases:
        if (base / p).is_file():
            return base / p
    raise DatasetError(
        f"{path}: BVH file not found (looked in {', '.join(str(b) for b in bases)}); give an absolute path, or "
        f"a path relative to the working directory (the CMU cartwheels ship in {MOCAP_DIR})"
    )


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _scene_config(c: dict) -> dict:
    """Check the mocap-specific keys; returns them with defaults filled in (ConfigError on problems)."""
    allowed = set(SCENE_KEYS) | set(REQUIRED_KEYS) | {"defaults", "noise"}  # defaults: Hydra's list, in the yaml
    unknown = sorted(set(c) - allowed)
    if unknown:
        raise ConfigError(
            f"dataset config of scene {c['name']!r}: unknown key(s) {unknown} (allowed: {sorted(allowed)})"
        )
    if c.get("import_version") != IMPORT_VERSION:
        raise ConfigError(
            f"dataset.import_version={c.get('import_version')!r}, but this liedfl imports version "
            f"{IMPORT_VERSION}; update the dataset config"
        )
    s = {
        "files": c.get("files"),
        "skip_frames": c.get("skip_frames", 1),
        "subsample": c.get("subsample", 1),
        "root": c.get("root", "Hips"),
        "joints": c.get("joints", list(CMU_BODY_JOINTS)),
        "length_scale": c.get("length_scale", 1.0),
        "unit_m": c.get("unit_m", ASF_UNIT_M),
        "z_up": c.get("z_up", True),
        "smoothing": c.get("smoothing"),
        "split": c.get("split", "reproduce"),
        "cap_trajectories": c.get("cap_trajectories", False),
    }
    files = s["files"]
    if not isinstance(files, (list, tuple)) or not files or not all(isinstance(f, str) for f in files):
        raise ConfigError(f"dataset.files must be a non-empty list of BVH paths, got {files!r}")
    if not isinstance(s["cap_trajectories"], bool):
        raise ConfigError(f"dataset.cap_trajectories must be true or false, got {s['cap_trajectories']!r}")
    if s["cap_trajectories"]:
        # n_trajectories is an upper bound (budgets written for simulated scenes ask for more
        # trajectories than there are recordings): use the first min(n_trajectories, len(files)) files.
        s["files"] = files = list(files)[: int(c["n_trajectories"])]
    elif int(c["n_trajectories"]) != len(files):
        raise ConfigError(
            f"dataset.n_trajectories={c['n_trajectories']} must equal the number of dataset.files "
            f"({len(files)}): one trajectory per recording (or set dataset.cap_trajectories: true)"
        )

    def integer(key, low):
        v = s[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v or v < low:
            raise ConfigError(f"dataset.{key} must be an integer >= {low}, got {v!r}")
        s[key] = int(v)

    integer("skip_frames", 0)
    integer("subsample", 1)
    for key in ("length_scale", "unit_m"):
        v = s[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise ConfigError(f"dataset.{key} must be a positive number, got {v!r}")
        s[key] = float(v)
    if not isinstance(s["z_up"], bool):
        raise ConfigError(f"dataset.z_up must be true or false, got {s['z_up']!r}")
    if not isinstance(s["root"], str):
        raise ConfigError(f"dataset.root must be a joint name, got {s['root']!r}")
    joints = s["joints"]
    if not isinstance(joints, (list, tuple)) or not joints or not all(isinstance(j, str) for j in joints):
        raise ConfigError(f"dataset.joints must be a non-empty list of joint names, got {joints!r}")
    if len(set(joints)) != len(joints) or s["root"] in joints:
        raise ConfigError(f"dataset.joints must list distinct joints other than the root {s['root']!r}, got {joints}")
    s["joints"] = list(joints)
    sm = s["smoothing"]
    if sm is not None:
        if not isinstance(sm, Mapping) or set(sm) != {"window", "order"}:
            raise ConfigError(f"dataset.smoothing must be null or {{window: <odd int>, order: <int>}}, got {sm!r}")
        try:
            check_window(sm["window"], sm["order"])
        except ValueError as exc:
            raise ConfigError(f"dataset.smoothing: {exc}") from None
        s["smoothing"] = {"window": int(sm["window"]), "order": int(sm["order"])}
    if s["split"] not in ("reproduce", "holdout"):
        raise ConfigError(f"dataset.split must be 'reproduce' or 'holdout', got {s['split']!r}")
    return s


def _skeleton(b: BVH, bodies: list[int], scale: float) -> dict:
    """params["skeleton"]: per body its parent (index into the bodies), offset, extra drawing points."""
    pos = {j: k for k, j in enumerate(bodies)}
    parents, offsets, points = [-1], [[0.0, 0.0, 0.0]], []
    for j in bodies[1:]:
        parents.append(pos[b.parents[j]])
        offsets.append([float(x) * scale for x in b.offsets[j]])
    for j in range(b.n_joints):  # unselected children of a selected body: points fixed in that body
        q = b.parents[j]
        if j not in pos and q in pos:
            points.append([pos[q], [float(x) * scale for x in b.offsets[j]]])
    for j, o in b.end_sites:
        if j in pos:
            points.append([pos[j], [float(x) * scale for x in o]])
    return {"bodies": [b.names[j] for j in bodies], "parents": parents, "offsets": offsets, "points": points}


def joint_offsets(b: BVH, bodies: list[int], skip: int, scale: float, source) -> np.ndarray:
    """(B, 3) joint offsets of the kept bodies for the dataset's tree: each joint's origin in its
    parent's frame (OFFSET + position channels, which must then be constant over the frames used),
    times `scale`; the root's row is zeros (its world position is the SE(3) body's p). The z-up turn
    acts on the root's world attitude only, so the offsets are unchanged by it."""
    t = b.local_translations(bodies)[skip:]
    moving = np.abs(t - t[:1]).max(axis=0).max(axis=-1) > 0
    moving[0] = False
    if moving.any():
        j = int(np.argmax(moving))
        raise DatasetError(
            f"{source}: joint {b.names[bodies[j]]!r} has position channels that change over the recording; "
            "the dataset's kinematic tree needs fixed joint offsets"
        )
    out = t[0] * scale
    out[0] = 0.0
    return out


def import_bvh(path: Path, s: dict) -> tuple[np.ndarray, np.ndarray, dict, BVH, list[int]]:
    """One recording -> (R (F, B, 3, 3), p (F, 1, 3), source info, BVH, body joint indices), unsmoothed."""
    b = read_bvh(path)
    names = [s["root"]] + s["joints"]
    missing = [n for n in names if n not in b.names]
    if missing:
        raise DatasetError(
            f"{path}: joint(s) {missing} of dataset.root/joints are not in the hierarchy (joints: {', '.join(b.names)})"
        )
    bodies = [b.names.index(n) for n in names]
    for n, j in zip(names[1:], bodies[1:]):
        if b.parents[j] not in bodies:
            parent = b.names[b.parents[j]] if b.parents[j] >= 0 else None
            raise ConfigError(
                f"dataset.joints: the BVH parent {parent!r} of joint {n!r} is not selected; "
                f"local rotations are relative to the BVH parent, so a chain cannot skip joints"
            )
    skip = s["skip_frames"]
    if b.n_frames - skip < 2:
        raise DatasetError(f"{path}: {b.n_frames} frames leave fewer than 2 after skip_frames={skip}")
    Rw, pw = b.world_poses()
    R = np.concatenate([Rw[skip:, bodies[:1]], b.local_rotations(bodies[1:])[skip:]], axis=1)
    p = pw[skip:, bodies[:1]] * s["length_scale"]
    if s["z_up"]:
        R[:, 0] = Z_UP @ R[:, 0]
        p = p @ Z_UP.T
    info = {
        "file": str(path),
        "sha256": _sha256(path),
        "frames_in_file": b.n_frames,
        "frames_after_skip": b.n_frames - skip,
        "frame_time": b.frame_time,
    }
    return R, p, info, b, bodies


def cmu_cartwheel(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 4: BVH recordings on SE(3) x SO(3)^n (see the module docstring for every step)."""
    c = check_config(to_dict(cfg))
    s = _scene_config(c)
    sub, steps, h = s["subsample"], int(c["steps"]), float(c["h"])
    Rs, ps, raws, infos, skeleton = [], [], [], [], None
    offsets: list[np.ndarray] = []
    for i, f in enumerate(s["files"]):
        path = _resolve(f)
        R, p, info, b, bodies = import_bvh(path, s)
        h_file = b.frame_time * sub
        if abs(h - h_file) > 1e-6 * h_file:
            raise ConfigError(
                f"dataset.h={h} does not match {path}: Frame Time {b.frame_time} x subsample {sub} = {h_file}"
            )
        raw = (R[::sub], p[::sub])
        if s["smoothing"] is not None:
            try:
                R, p = smooth_pose(R, p, s["smoothing"]["window"], s["smoothing"]["order"])
            except ValueError as exc:
                raise DatasetError(f"{path}: smoothing failed: {exc}") from None
        R, p = R[::sub], p[::sub]
        info["frames_available"] = int(R.shape[0])
        Rs.append(R)
        ps.append(p)
        raws.append(raw)
        infos.append(info)
        offsets.append(joint_offsets(b, bodies, s["skip_frames"], s["length_scale"], path))
        sk = _skeleton(b, bodies, s["length_scale"])
        if skeleton is None:
            skeleton = sk
        elif not np.allclose(np.asarray(sk["offsets"]), np.asarray(skeleton["offsets"]), atol=1e-9):
            skeleton.setdefault("per_file_offsets", {})[str(i)] = sk["offsets"]
        if progress is not None:
            progress(h * steps * (i + 1) / len(s["files"]))
    available = min(r.shape[0] for r in Rs) - 1
    if steps > available:
        shortest = infos[int(np.argmin([r.shape[0] for r in Rs]))]["file"]
        raise ConfigError(
            f"dataset.steps={steps} is longer than the recordings allow: {shortest} has "
            f"{available + 1} frames after skip_frames={s['skip_frames']} and subsample={sub}, "
            f"so steps <= {available}"
        )
    n1 = steps + 1
    for info in infos:
        info["frames_used"] = n1
    T = len(Rs)
    R = np.stack([r[:n1] for r in Rs])
    p = np.stack([q[:n1] for q in ps])
    R_raw = np.stack([r[0][:n1] for r in raws])
    p_raw = np.stack([r[1][:n1] for r in raws])
    if s["split"] == "reproduce":
        split = {"train": np.arange(T), "test": np.arange(T)}
    else:
        k = int(c["n_test"]) if c["n_test"] is not None else int(round(float(c["test_fraction"]) * T))
        if not 0 < k < T:
            raise ConfigError(
                f"dataset.split=holdout with {T} recording(s) and n_test={c['n_test']}, "
                f"test_fraction={c['test_fraction']}: {k} test recording(s) leave no train or no "
                f"test recording; need 0 < test count < {T}"
            )
        split = {"train": np.arange(T - k), "test": np.arange(T - k, T)}
    unit_m = s["unit_m"] / s["length_scale"]
    tree = None
    if all(np.array_equal(o, offsets[0]) for o in offsets):
        parents = list(skeleton["parents"])  # type: ignore[index]
        tree = Tree.from_lists(parents, offsets[0], "parent", free_root=True)
    else:
        warnings.warn(
            f"{c['name']}: the recordings have different skeletons (joint offsets); the dataset gets no "
            "kinematic tree (params['skeleton']['per_file_offsets'] lists them)",
            DataWarning,
            stacklevel=2,
        )
    params = dataset_params(
        c,
        sources=infos,
        split_overlap=s["split"] == "reproduce",
        length_unit_m=unit_m,
        length_unit=(
            f"file unit x {s['length_scale']} (1 stored unit = {unit_m:.6g} m; the CMU files use "
            f"CMU ASF units, 1/0.45 inch = {ASF_UNIT_M:.6g} m)"
        ),
        world_frame=(
            "z up: world = Rx(+90 deg) applied to the BVH world (y up)" if s["z_up"] else "BVH world frame (y up)"
        ),
        bodies={
            "root": "world pose of " + s["root"],
            "joints": "rotation relative to the BVH parent (the file's attribute rotations = 'parent')",
            "asf_names": [BVH_TO_ASF.get(n, n) for n in [s["root"]] + s["joints"]],
        },
        smoothing=(
            None
            if s["smoothing"] is None
            else {
                **s["smoothing"],
                "method": "Savitzky-Golay; rotations in the tangent space at each "
                "sample, positions plain; applied before subsample/crop",
            }
        ),
        skeleton=skeleton,
        attribution=ATTRIBUTION,
    )
    return Dataset(
        R=R,
        p=p,
        h=h,
        scene=c["name"],
        body_names=[s["root"]] + s["joints"],
        body_kinds=["se3"] + ["so3"] * len(s["joints"]),
        params=params,
        seed=int(c["seed"]),
        split=split,
        extras={"R_raw": R_raw, "p_raw": p_raw},
        tree=tree,
    )


__all__ = [
    "REAL_DATA_SCENES",
    "moving_joints",
    "mocap_errors",
    "recording_discrepancy",
    "skeleton_points",
    "import_bvh",
    "cmu_cartwheel",
    "CMU_BODY_JOINTS",
    "BVH_TO_ASF",
    "ASF_UNIT_M",
    "ATTRIBUTION",
]
