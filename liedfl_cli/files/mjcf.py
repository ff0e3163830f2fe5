"""An articulated rigid-body model as MuJoCo MJCF (`liedfl export format=mjcf`, docs/export.md).

`MjcfSpec` holds what the file says: the kinematic tree (`lie.tree.Tree`'s parents, joint offsets in
the parent frame, joint kinds and axes), each body's mass, centre of mass (body frame, from the joint)
and inertia about the centre of mass (body frame), the joint damping per degree of freedom, the
gravity vector and the time step. `mjcf_text` writes it:

    <compiler angle="radian" inertiafromgeom="false"/>, <option timestep integrator="RK4" gravity>
    with contacts disabled; nested bodies with pos = the joint offset and no quat (every body frame
    is parallel to its parent's at qpos = 0, so MuJoCo's xmat is the world attitude and a ball
    joint's quaternion is R_parent^T R_b); the joint at the body origin: <freejoint/> (free root),
    type="ball", type="hinge" axis=a (body frame), a universal joint as two hinges a1 then a2 in one
    body (MuJoCo composes them as R_rel = exp(t1 a1) exp(t2 a2), liedfl's convention), no joint for a
    weld; <inertial pos mass fullinertia="Ixx Iyy Izz Ixy Ixz Iyz"/>; massless capsules (no contacts)
    along each link for viewing only.

Bodies are written depth first, children in index order (MuJoCo numbers them in that order, and its
qpos follows them); `replay` maps them back. MuJoCo has one damping coefficient per ball joint: the
mean of the three is written (`ball_damping_dropped` says how much that drops).

`spec_from_physics` builds a spec from a dataset's declared truth (params["physics"] of
`data/mujoco_chain.py`), `write_mjcf` writes a spec atomically, `replay` steps an MJCF with MuJoCo
(imported inside the functions) and `initial_state_from_poses` gives MuJoCo's (qpos, qvel) from the
first poses of a liedfl trajectory when the engine's own state is not known.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from ..errors import ConfigError
from ..lie.tree import JOINT_DOF, Tree

INTEGRATOR = "RK4"


@dataclass
class MjcfSpec:
    """An articulated model to write as MJCF (module docstring). Arrays are per body, in liedfl's
    order (every parent before its children). joints: "free" (the root only) / "ball" / "universal" /
    "hinge" / "weld"; axes (B, 2, 3) as `Tree.axes` (hinge axis in the body frame in row 0; universal
    a1 in the parent frame in row 0, a2 in the body frame in row 1); dof_damping: per body, one value
    per degree of freedom of its joint (ignored on a free root)."""

    names: list[str]
    parents: list[int]
    offsets: np.ndarray  # (B, 3) joint position in the parent frame (a pinned root's: in the world)
    joints: list[str]
    axes: np.ndarray  # (B, 2, 3)
    mass: np.ndarray  # (B,)
    com: np.ndarray  # (B, 3) body frame, from the joint
    inertia: np.ndarray  # (B, 3, 3) about the COM, body frame
    dof_damping: list[list[float]]
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) world acceleration
    timestep: float = 1e-3
    comment: str = ""
    model_name: str = "liedfl"


def _v(x) -> str:
    return " ".join(repr(float(a)) for a in np.asarray(x, dtype=np.float64).reshape(-1))


def _comment(text: str) -> str:
    """XML comment body: no '--' inside, none at the end."""
    text = text.replace("--", "- -")
    return text + " " if text.endswith("-") else text


def unique_names(names, n: int) -> list[str]:
    """n body names: the given ones (blank ones `body<b>`), made unique with `_<b>` suffixes."""
    names = list(names or [])
    out: list[str] = []
    for b in range(n):
        name = str(names[b]).strip() if b < len(names) and str(names[b]).strip() else f"body{b}"
        if name in out:
            name = f"{name}_{b}"
        out.append(name)
    return out


def depth_first(parents) -> list[int]:
    """Bodies in the order the MJCF lists them (depth first, children in index order): MuJoCo's body
    ids 1, 2, ... in that order."""
    parents = [int(p) for p in parents]
    order: list[int] = []

    def visit(b: int) -> None:
        order.append(b)
        for c in range(len(parents)):
            if parents[c] == b:
                visit(c)

    visit(0)
    return order


def ball_damping_dropped(values) -> float:
    """The share of a ball joint's damping that one coefficient (their mean) cannot carry:
    sum |d_i - mean| / sum d_i (0 when all three agree)."""
    d = np.asarray(values, dtype=np.float64)
    total = float(np.abs(d).sum())
    return 0.0 if total == 0 else float(np.abs(d - d.mean()).sum() / total)


def check_spec(spec: MjcfSpec) -> None:
    """ConfigError naming the body for a spec MuJoCo would refuse or mis-simulate: shapes, mass <= 0,
    an inertia that is not symmetric positive definite or violates the triangle inequality, negative
    damping, a joint axis that is not a unit vector."""
    B = len(spec.names)
    shapes = {
        "parents": (len(spec.parents),),
        "offsets": np.shape(spec.offsets),
        "joints": (len(spec.joints),),
        "axes": np.shape(spec.axes),
        "mass": np.shape(spec.mass),
        "com": np.shape(spec.com),
        "inertia": np.shape(spec.inertia),
        "dof_damping": (len(spec.dof_damping),),
    }
    want = {
        "parents": (B,),
        "offsets": (B, 3),
        "joints": (B,),
        "axes": (B, 2, 3),
        "mass": (B,),
        "com": (B, 3),
        "inertia": (B, 3, 3),
        "dof_damping": (B,),
    }
    for key, shape in shapes.items():
        if tuple(shape) != want[key]:
            raise ConfigError(f"MJCF export: {key} has shape {tuple(shape)}, expected {want[key]} ({B} bodies)")
    if not (math.isfinite(spec.timestep) and spec.timestep > 0):
        raise ConfigError(f"MJCF export: timestep={spec.timestep!r} must be a positive number")
    if not np.all(np.isfinite(np.asarray(spec.gravity, dtype=np.float64))) or np.shape(spec.gravity) != (3,):
        raise ConfigError(f"MJCF export: gravity {spec.gravity!r} must be a finite 3-vector")
    for b, name in enumerate(spec.names):
        kind = spec.joints[b]
        allowed = ("free", "ball", "universal", "hinge", "weld") if b == 0 else ("ball", "universal", "hinge", "weld")
        if kind not in allowed:
            raise ConfigError(f"MJCF export: body {name!r}: joint {kind!r} (use one of {', '.join(allowed)})")
        if b > 0 and not 0 <= int(spec.parents[b]) < b:
            raise ConfigError(f"MJCF export: body {name!r}: parent {spec.parents[b]} must be an earlier body")
        m = float(spec.mass[b])
        if not (math.isfinite(m) and m > 0):
            raise ConfigError(f"MJCF export: body {name!r}: mass {m:.6g} must be positive")
        if not np.all(np.isfinite(spec.com[b])) or not np.all(np.isfinite(spec.offsets[b])):
            raise ConfigError(f"MJCF export: body {name!r}: non-finite centre of mass or joint offset")
        J = np.asarray(spec.inertia[b], dtype=np.float64)
        scale = max(float(np.abs(J).max()), 1e-300)
        if not np.all(np.isfinite(J)) or float(np.abs(J - J.T).max()) > 1e-9 * scale:
            raise ConfigError(f"MJCF export: body {name!r}: inertia is not a finite symmetric matrix")
        lam = np.linalg.eigvalsh(0.5 * (J + J.T))
        if lam[0] <= 0:
            raise ConfigError(
                f"MJCF export: body {name!r}: inertia is not positive definite "
                f"(principal moments {lam[0]:.3g}, {lam[1]:.3g}, {lam[2]:.3g})"
            )
        if lam[2] > (lam[0] + lam[1]) * (1 + 1e-9):
            raise ConfigError(
                f"MJCF export: body {name!r}: inertia violates the triangle inequality "
                f"(principal moments {lam[0]:.3g} + {lam[1]:.3g} < {lam[2]:.3g}): no rigid body has it"
            )
        d = [float(x) for x in spec.dof_damping[b]]
        if kind != "free" and len(d) != JOINT_DOF[kind]:
            raise ConfigError(
                f"MJCF export: body {name!r}: {len(d)} damping values for a {kind} joint ({JOINT_DOF[kind]} DoF)"
            )
        if kind != "free" and any(not (math.isfinite(x) and x >= 0) for x in d):
            raise ConfigError(f"MJCF export: body {name!r}: joint damping {d} must be >= 0")
        rows = {"hinge": (0,), "universal": (0, 1)}.get(kind, ())
        for r in rows:
            n = float(np.linalg.norm(spec.axes[b][r]))
            if not abs(n - 1.0) < 1e-6:
                raise ConfigError(f"MJCF export: body {name!r}: {kind} axis {r + 1} has norm {n:.6g} (needs 1)")


def mjcf_text(spec: MjcfSpec) -> str:
    """The MJCF document of `spec` (module docstring); ConfigError naming the body when a body's
    mass, inertia, damping or axes are unusable (`check_spec`)."""
    check_spec(spec)
    names = unique_names(spec.names, len(spec.names))
    B = len(names)
    offsets = np.asarray(spec.offsets, dtype=np.float64)
    com = np.asarray(spec.com, dtype=np.float64)
    lengths = [float(np.linalg.norm(offsets[c])) for c in range(1, B)] + [2 * float(np.linalg.norm(c)) for c in com]
    positive = [x for x in lengths if x > 0]
    radius = 0.05 * float(np.median(positive)) if positive else 0.01
    lines = [f"<mujoco model={quoteattr(spec.model_name)}>"]
    for ln in spec.comment.splitlines():
        lines.append(f"  <!-- {_comment(ln)} -->")
    lines += [
        '  <compiler angle="radian" inertiafromgeom="false"/>',
        f'  <option timestep="{float(spec.timestep)!r}" integrator="{INTEGRATOR}" gravity="{_v(spec.gravity)}">',
        '    <flag contact="disable"/>',
        "  </option>",
        "  <worldbody>",
    ]
    parents = [int(p) for p in spec.parents]

    def body(b: int, depth: int) -> None:
        ind = "    " + "  " * depth
        kind, name = spec.joints[b], names[b]
        lines.append(f"{ind}<body name={quoteattr(name)} pos={quoteattr(_v(offsets[b]))}>")
        d = [float(x) for x in spec.dof_damping[b]]
        if kind == "free":
            lines.append(f"{ind}  <freejoint name={quoteattr(name + '_root')}/>")
        elif kind == "ball":
            mean = float(np.mean(d)) if d else 0.0
            lines.append(f'{ind}  <joint name={quoteattr(name + "_ball")} type="ball" damping="{mean!r}"/>')
        elif kind == "hinge":
            lines.append(
                f'{ind}  <joint name={quoteattr(name + "_hinge")} type="hinge" '
                f'axis="{_v(spec.axes[b][0])}" damping="{d[0]!r}"/>'
            )
        elif kind == "universal":  # R_rel = exp(t1 a1) exp(t2 a2): a1 (parent frame = body frame at 0) first
            for r in (0, 1):
                lines.append(
                    f'{ind}  <joint name={quoteattr(f"{name}_universal{r + 1}")} type="hinge" '
                    f'axis="{_v(spec.axes[b][r])}" damping="{d[r]!r}"/>'
                )
        J = np.asarray(spec.inertia[b], dtype=np.float64)
        J = 0.5 * (J + J.T)
        full = [J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2]]
        lines.append(f'{ind}  <inertial pos="{_v(com[b])}" mass="{float(spec.mass[b])!r}" fullinertia="{_v(full)}"/>')
        kids = [c for c in range(B) if parents[c] == b]
        ends = [offsets[c] for c in kids] if kids else [2 * com[b]]
        for end in ends:  # drawing only: massless, no contacts
            if float(np.linalg.norm(end)) > 1e-9:
                lines.append(
                    f'{ind}  <geom type="capsule" size="{radius!r}" fromto="0 0 0 {_v(end)}" '
                    'mass="0" contype="0" conaffinity="0"/>'
                )
        for c in kids:
            body(c, depth + 1)
        lines.append(f"{ind}</body>")

    body(0, 0)
    lines += ["  </worldbody>", "</mujoco>", ""]
    return "\n".join(lines)


def write_mjcf(path, spec: MjcfSpec) -> Path:
    """Write `mjcf_text(spec)` to `path` atomically: a temporary file in the same folder, then
    os.replace (a reader never sees a half-written file; an existing `path` is replaced only on
    success). ConfigError for a bad spec (nothing written); OSError when the folder is not writable."""
    from .io_utils import atomic_path

    text = mjcf_text(spec)
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
    return path


def physics_dof_damping(tree: Tree, physics: dict[str, Any]) -> list[list[float]]:
    """The declared damping per body and DoF: physics["dof_damping"] (per body, per DoF) where it
    matches the joint, else `joint_damping` (non-root bodies) / `root_damping` (a pinned root) on
    every DoF; zeros on a free root."""
    per_dof = physics.get("dof_damping")
    jd = physics.get("joint_damping") or [0.0] * (tree.n_bodies - 1)
    out = []
    for b, kind in enumerate(tree.joint_kinds):
        n = JOINT_DOF[kind]
        if kind == "free":
            out.append([0.0] * n)
            continue
        row = per_dof[b] if per_dof is not None and b < len(per_dof) else None
        if row is not None and len(row) == n:
            out.append([float(x) for x in row])
        else:
            value = float(jd[b - 1]) if b > 0 else float(physics.get("root_damping") or 0.0)
            out.append([value] * n)
    return out


def spec_from_physics(tree: Tree, physics: dict[str, Any], names, timestep: float | None = None) -> MjcfSpec:
    """The spec of a dataset's declared truth (params["physics"], kind "articulated": bodies' mass,
    com, inertia; joint_damping / dof_damping; g along -e3; dt) on `tree` (its joints and axes).
    timestep: default physics["dt"]."""
    bodies = physics.get("bodies")
    if not isinstance(bodies, list) or len(bodies) != tree.n_bodies:
        raise ConfigError(f"physics.bodies must list {tree.n_bodies} bodies (mass, com, inertia)")
    dt = timestep if timestep is not None else physics.get("dt")
    if dt is None:
        raise ConfigError("physics has no 'dt': give the MJCF timestep")
    return MjcfSpec(
        names=unique_names(names or [b.get("name") for b in bodies], tree.n_bodies),
        parents=list(tree.parents),
        offsets=np.asarray(tree.offsets, dtype=np.float64),
        joints=list(tree.joint_kinds),
        axes=np.asarray(tree.axes_array(), dtype=np.float64),
        mass=np.asarray([float(b["mass"]) for b in bodies]),
        com=np.asarray([b["com"] for b in bodies], dtype=np.float64).reshape(-1, 3),
        inertia=np.asarray([b["inertia"] for b in bodies], dtype=np.float64).reshape(-1, 3, 3),
        dof_damping=physics_dof_damping(tree, physics),
        gravity=np.array([0.0, 0.0, -float(physics.get("g") or 0.0)]),
        timestep=float(dt),
        comment="the declared physics of a dataset",
    )


def load_model(xml: str):
    """MuJoCo's compiled model of an MJCF text; ConfigError (one line) when mujoco is missing or
    refuses the file."""
    try:
        import mujoco
    except ImportError:
        raise ConfigError("this needs the mujoco package: pip install mujoco") from None
    try:
        return mujoco.MjModel.from_xml_string(xml)
    except ValueError as e:
        first = " ".join(str(e).split())
        raise ConfigError(f"MuJoCo refuses the MJCF: {first}") from None


def replay(xml: str, tree: Tree, qpos0, qvel0, h: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Step the MJCF `xml` (written by `mjcf_text` for `tree`) from MuJoCo's state (qpos0, qvel0) with
    mj_step (nstep = round(h / timestep) per sample). Returns every body's world attitude
    (steps + 1, B, 3, 3) and joint position (steps + 1, B, 3) at the samples, in the tree's order."""
    import mujoco

    model = load_model(xml)
    data = mujoco.MjData(model)
    dt = float(model.opt.timestep)
    sub = int(round(h / dt))
    if sub < 1 or abs(sub * dt - h) > 1e-9 * max(h, dt):
        raise ConfigError(f"h={h} must be a whole multiple of the MJCF timestep {dt}")
    B = tree.n_bodies
    ids = np.zeros(B, dtype=np.int64)
    for i, b in enumerate(depth_first(tree.parents)):
        ids[b] = i + 1  # (0 is the world)
    if model.nbody != B + 1:
        raise ConfigError(f"the MJCF has {model.nbody - 1} bodies, the tree {B}")
    data.qpos[:] = np.asarray(qpos0, dtype=np.float64)
    data.qvel[:] = np.asarray(qvel0, dtype=np.float64)
    mujoco.mj_forward(model, data)
    R = np.zeros((steps + 1, B, 3, 3))
    p = np.zeros((steps + 1, B, 3))
    for k in range(steps + 1):
        if k > 0:
            mujoco.mj_step(model, data, nstep=sub)
            mujoco.mj_forward(model, data)
        R[k] = data.xmat[ids].reshape(B, 3, 3)
        p[k] = data.xpos[ids]
    return R, p


def _wrap(x: np.ndarray) -> np.ndarray:
    """Angles to (-pi, pi]."""
    return np.angle(np.exp(1j * x))


def _signed_angle(u: np.ndarray, v: np.ndarray, n: np.ndarray) -> float:
    """The angle turning u's component normal to the unit axis n onto v's, about n (right hand)."""
    u = u - (u @ n) * n
    v = v - (v @ n) * n
    return float(math.atan2(float(n @ np.cross(u, v)), float(u @ v)))


def _joint_angles(kind: str, axes: np.ndarray, R_rel: np.ndarray) -> tuple[list[float], float]:
    """(angles, residual) of a hinge (R_rel = exp(t a)) or universal joint (R_rel = exp(t1 a1)
    exp(t2 a2)) at one sample; residual: the angle (rad) between R_rel and the joint's rotation at
    those angles (0 when R_rel is on the joint's manifold, i.e. the rest rotation C is the identity)."""
    import torch

    from ..lie import so3

    def exp(w: np.ndarray) -> np.ndarray:
        return so3.exp(torch.as_tensor(w, dtype=torch.float64)).numpy()

    if kind == "hinge":
        a = axes[0]
        t = [float(so3.log(torch.as_tensor(R_rel)).numpy() @ a)]
        fit = exp(t[0] * a)
    else:
        a1, a2 = axes[0], axes[1]
        t2 = -_signed_angle(a1, R_rel.T @ a1, a2)  # R_rel^T a1 = exp(-t2 a2) a1
        t1 = _signed_angle(a2, R_rel @ a2, a1)  # R_rel a2 = exp(t1 a1) a2
        t = [t1, t2]
        fit = exp(t1 * a1) @ exp(t2 * a2)
    residual = float(so3.geodesic_distance(torch.as_tensor(fit), torch.as_tensor(R_rel)))
    return t, residual


def initial_state_from_poses(
    tree: Tree, R, p, h: float, method: str = "central", tol: float = 1e-6
) -> tuple[np.ndarray, np.ndarray, int]:
    """MuJoCo's state (qpos (nq,), qvel (nv,)) of an MJCF written by `mjcf_text` for `tree`, from the
    first poses of a liedfl trajectory, for a replay (`replay`) when the engine's own velocities are
    not known.

    R (T, B, 3, 3): the tree's coordinates (world or parent-relative attitudes, `tree.rotations`);
    p (T, m, 3): the free root's position (m = 1) or (T, 0, 3) for a pinned root; h: the sample
    interval; T >= 3 for method="central", >= 2 for "forward". Returns (qpos, qvel, k0): the state at
    sample k0 (central: 1, forward: 0), bodies in MuJoCo's (depth-first) order.

    qpos: a free root's world position and attitude quaternion (w, x, y, z); a ball joint's
    quaternion of R_rel = R_parent^T R_b; a hinge's angle t with R_rel = exp(t a); a universal's
    (t1, t2) with R_rel = exp(t1 a1) exp(t2 a2); a weld has none. Exact (the poses are the state).
    qvel: from the relative rotations' increments: per body and interval the mean body-frame angular
    velocity w_{k+1/2} = log(R_rel,k^T R_rel,k+1) / h (ball joints, a free root's attitude), the
    wrapped differences of a hinge's t or a universal joint's (t1, t2) over h, and the free root's
    world velocity (p_{k+1} - p_k) / h.
    "forward": the interval (0, 1) at sample 0: first-order, the error is h/2 times the acceleration
    (w(t0) + h/2 w'(t0) + O(h^2)), which a replay carries as a drift growing linearly in time;
    "central": the mean of the intervals (0, 1) and (1, 2) at sample 1: second order, error
    h^2/6 w'' + O(h^2) commutator terms. ConfigError (one line, naming the body) when a hinge or universal
    joint's relative rotation is more than `tol` rad off its manifold (a rest rotation C != I, which
    the MJCF written without `quat` cannot hold)."""
    import torch

    from ..lie import so3
    from ..lie.joints import to_joint_coordinates
    from ..lie.product import Pose

    if method not in ("central", "forward"):
        raise ConfigError(f"initial state method={method!r}: use central or forward")
    R = np.asarray(R, dtype=np.float64)
    P = np.asarray(p, dtype=np.float64)
    need = 3 if method == "central" else 2
    B = tree.n_bodies
    if R.ndim != 4 or R.shape[1:] != (B, 3, 3) or R.shape[0] < need:
        raise ConfigError(f"initial state ({method}): R must be (T >= {need}, {B}, 3, 3), got {R.shape}")
    m = 1 if tree.free_root else 0
    if tree.free_root and (P.ndim != 3 or P.shape[0] < need or P.shape[1] < 1 or P.shape[2] != 3):
        raise ConfigError(f"initial state ({method}): p must be (T >= {need}, 1, 3) for a free root, got {P.shape}")
    k0 = 1 if method == "central" else 0
    frames = [k0 - 1, k0, k0 + 1] if method == "central" else [k0, k0 + 1]
    Rt = torch.as_tensor(R[frames])
    Pt = torch.as_tensor(P[frames, :m] if m else np.zeros((len(frames), 0, 3)))
    rel = to_joint_coordinates(tree, Pose(Rt, Pt)).R.numpy()  # (F, B, 3, 3): root's world, others R_rel
    # mean body-frame angular velocity over each interval (F - 1, B, 3)
    inc = np.einsum("fbji,fbjk->fbik", rel[:-1], rel[1:])
    w = so3.log(torch.as_tensor(inc)).numpy() / h
    w_mid = w.mean(axis=0)  # central: (w_{1/2} + w_{3/2}) / 2; forward: w_{1/2}
    ax = np.asarray(tree.axes_array(), dtype=np.float64)
    c = 1 if method == "central" else 0  # the state's frame among `frames`
    qpos: list[float] = []
    qvel: list[float] = []
    for b in depth_first(tree.parents):
        kind = tree.joint_kinds[b]
        Rb = rel[c, b]
        if kind in ("free", "ball"):
            quat = so3.to_quaternion(torch.as_tensor(Rb)).numpy()
            if kind == "free":
                pos = P[frames, 0]
                v = (pos[-1] - pos[0]) / (h * (len(frames) - 1))
                qpos += [*pos[c], *quat]
                qvel += [*v, *w_mid[b]]
            else:
                qpos += list(quat)
                qvel += list(w_mid[b])
        elif kind in ("hinge", "universal"):
            angles = []
            for f in range(len(frames)):
                t, residual = _joint_angles(kind, ax[b], rel[f, b])
                if residual > tol:
                    raise ConfigError(
                        f"initial state: body {b}: its {kind} rotation is {residual:.3g} rad off "
                        f"exp(t a){' exp(t2 a2)' if kind == 'universal' else ''} at sample {frames[f]}: a rest "
                        "rotation C != I, which the MJCF (no body quat) cannot hold"
                    )
                angles.append(t)
            A = np.asarray(angles)  # (F, dof)
            rate = _wrap(A[1:] - A[:-1]).mean(axis=0) / h
            qpos += list(A[c])
            qvel += list(rate)
    return np.asarray(qpos), np.asarray(qvel), k0


__all__ = [
    "INTEGRATOR",
    "MjcfSpec",
    "ball_damping_dropped",
    "check_spec",
    "depth_first",
    "initial_state_from_poses",
    "load_model",
    "mjcf_text",
    "physics_dof_damping",
    "replay",
    "spec_from_physics",
    "unique_names",
    "write_mjcf",
]
