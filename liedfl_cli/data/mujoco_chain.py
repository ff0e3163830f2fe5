"""Articulated chains and trees simulated by MuJoCo: an independent engine to test liedfl's trees,
joints and articulated models against (docs/data_format.md, "MuJoCo chains and trees"; script
`scripts/mujoco_chain.py`).

`chain_spec(...)` draws a serial chain of 2..5 links from a seed: link masses, inertias about the centre
of mass with off-diagonal terms (box-like principal moments about principal axes turned by a random
rotation in the body frame), centres of mass off the joint, joint offsets, hinge axes. `tree_spec(...)`
draws any tree (`parents`, or a name in `TREES`) with a joint per body among ball / hinge / universal
(two MJCF hinges in one body) / weld (no joint element), a free or pinned root (its joint any of
those), per-DoF damping and an optional heavy root with light links. `chain_mjcf` writes the MJCF
(contacts disabled, MuJoCo's RK4 integrator, gravity along -e3), `simulate_chain` integrates random
initial states with `mj_step` and samples every h, `chain_dataset` makes a liedfl `Dataset` of it: the
coordinates R (T, N+1, B, 3, 3) (world or parent-relative attitudes) and p (T, N+1, 1 or 0, 3) (the
free root's position), the kinematic tree (parents, joint offsets: the MJCF body `pos` in the parent
frame; every joint sits at its body's origin) with its joints and axes, `params["physics"]` declaring
the truth (schema below) and the engine's world poses, velocities, energies and momenta under `extras/`
(evaluation only), lengths in metres or, `unit="mm"`, millimetres.

Body frames: every MJCF body has the identity `quat`, so its frame at the reference configuration is
parallel to its parent's, and MuJoCo's `xmat` (body -> world) is the world attitude Rw_b; a ball
joint's quaternion (w, x, y, z) is then R_rel = R_parent^T R_b, a hinge's rotation is exp(theta a) with
the axis a in the body frame, a universal joint's exp(t1 a1) exp(t2 a2) (a1 fixed in the parent frame,
a2 in the body frame; liedfl's `Tree.axes` rows 0 and 1), a weld's the identity. MuJoCo's joint damping
d acts per degree of freedom on the relative angular velocity of the child w.r.t. its parent in the
child frame: torque = -d * w_rel (a hinge's: along its axis).

params["physics"] = {
    "kind": "articulated", "g": <gravity magnitude along -e3>,
    "bodies": [{"name", "mass", "com": body frame, from the joint, "inertia": 3x3 about the COM, body frame}],
    "joint_damping": [d per non-root body (its DoF's, their mean if they differ, 0 for a weld)],
    "root_damping": <a pinned root's joint damping, 0.0>,
    "joints": ["free" | "ball" | "hinge" | "universal" | "weld" per body (the root: "free" or its pinned joint)],
    "hinge_axes": [[3] or null per body] (body frame) or null when there is no hinge,
    "joint_axes": (B, 2, 3) as `Tree.axes`, "dof_damping": [[per-DoF damping] per body] (6/3/2/1/0 values),
    "length_unit_m": 1.0 | 0.001, "engine": "mujoco <version>", "dt": dt, "integrator": "RK4"}
(lengths, inertias, damping and g in the file's length unit).

mujoco is imported inside the functions (`pip install mujoco`, or the `test` extra).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..errors import ConfigError
from ..lie import so3
from ..lie.tree import Tree
from .files import default_split
from .hdf5 import Dataset

JOINTS = ("ball", "hinge")
TREE_JOINTS = ("ball", "hinge", "universal", "weld")
UNITS = {"m": 1.0, "mm": 1e-3}
ROOTS = ("free", "pinned")
JOINT_DOF = {"free": 6, "ball": 3, "universal": 2, "hinge": 1, "weld": 0}
GENERATOR_VERSION = 1


def require_mujoco():
    """The `mujoco` module, or a one-line ConfigError saying how to install it."""
    try:
        import mujoco
    except ImportError:
        raise ConfigError(
            "MuJoCo chains need the mujoco package: pip install mujoco (or the test extra: pip install -e '.[test]')"
        ) from None
    return mujoco


@dataclass
class Link:
    """One rigid link: its joint sits at the body origin, `offset` in the parent frame (the root: the
    pivot of a pinned root, zeros for a free one)."""

    name: str
    mass: float
    com: np.ndarray  # (3,) body frame, from the joint
    inertia: np.ndarray  # (3, 3) about the COM, body frame
    offset: np.ndarray  # (3,)
    axis: np.ndarray | None = None  # hinge axis (body frame), None for ball / free; a universal's first (parent frame)
    length: float = 0.0  # for drawing: the capsule from the joint along `direction`
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    axis2: np.ndarray | None = None  # a universal joint's second axis (body frame)
    damping: list[float] | None = None  # per DoF of its joint (`tree_spec`); None: the spec's joint_damping


@dataclass
class ChainSpec:
    links: list[Link]
    joint: str  # "ball" | "hinge" (every non-root joint; a pinned root too); "mixed" for `tree_spec`
    root: str  # "free" | "pinned"
    gravity: float
    joint_damping: float
    dt: float
    tree_parents: list[int] | None = None  # a tree (`tree_spec`); None: a serial chain
    kinds: list[str] | None = None  # every body's joint (`tree_spec`); None: `joint` everywhere

    @property
    def parents(self) -> list[int]:
        if self.tree_parents is not None:
            return list(self.tree_parents)
        return [-1] + list(range(len(self.links) - 1))

    def joint_kinds(self) -> list[str]:
        if self.kinds is not None:
            return list(self.kinds)
        return [("free" if self.root == "free" else self.joint)] + [self.joint] * (len(self.links) - 1)

    def joint_axes(self) -> list[list[list[float]]]:
        """(B, 2, 3) in liedfl's layout (`lie.tree.Tree.axes`): a hinge's axis (body frame) in row 0; a
        universal joint's a1 (parent frame) in row 0 and a2 (body frame) in row 1; zeros otherwise."""
        z = [0.0, 0.0, 0.0]
        out = []
        for link, kind in zip(self.links, self.joint_kinds()):
            if kind == "hinge" and link.axis is not None:
                out.append([[float(x) for x in link.axis], z])
            elif kind == "universal" and link.axis is not None and link.axis2 is not None:
                out.append([[float(x) for x in link.axis], [float(x) for x in link.axis2]])
            else:
                out.append([z, z])
        return out

    def dof_damping(self) -> list[list[float]]:
        """Per body, the damping of each DoF of its joint (6 / 3 / 2 / 1 / 0 values; the root's zeros
        unless given)."""
        out = []
        for b, (link, kind) in enumerate(zip(self.links, self.joint_kinds())):
            if link.damping is not None:
                out.append([float(x) for x in link.damping])
            else:
                out.append([0.0 if b == 0 else self.joint_damping] * JOINT_DOF[kind])
        return out


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    return so3.from_quaternion(torch.from_numpy(q / np.linalg.norm(q))).numpy()


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _draw_link(rng: np.random.Generator, m: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """One link of mass m drawn from rng (the draws of `chain_spec` and `tree_spec` alike): (length
    U(0.25, 0.5) m, unit direction d, centre of mass at U(0.35, 0.65) L d plus up to 0.03 m sideways,
    inertia about it (3, 3) of a box L x a x c, a, c U(0.15, 0.25) m, whose principal axes are the link's
    turned by a random rotation of 0.2 to 0.6 rad)."""
    L = float(rng.uniform(0.25, 0.5))
    d = _unit(rng)
    side = _unit(rng)
    side -= side.dot(d) * d
    side /= np.linalg.norm(side)
    com = rng.uniform(0.35, 0.65) * L * d + rng.uniform(0.0, 0.03) * side
    a, c = rng.uniform(0.15, 0.25, 2)  # a box L x a x c: a physical inertia (triangle inequalities hold)
    moments = m / 12 * np.array([a * a + c * c, L * L + c * c, L * L + a * a])
    frame = np.stack([d, side, np.cross(d, side)], -1)
    Q = so3.exp(torch.from_numpy(_unit(rng) * rng.uniform(0.2, 0.6))).numpy() @ frame
    return L, d, com, Q @ np.diag(moments) @ Q.T


def chain_spec(
    links: int = 3,
    joint: str = "ball",
    root: str = "free",
    gravity: float = 0.0,
    joint_damping: float = 0.05,
    dt: float = 1e-3,
    seed: int = 0,
) -> ChainSpec:
    """A random but physical serial chain of `links` links (body b's parent is b - 1).

    Each link: mass U(1, 3) kg, length U(0.25, 0.5) m along a random direction d (the next joint at
    L d plus a sideways offset up to 0.05 m), centre of mass at U(0.35, 0.65) L d plus up to 0.03 m
    sideways, the inertia of a box L x a x c (a, c U(0.15, 0.25) m) about the COM whose principal axes
    are the link's axes turned by a random rotation of 0.2 to 0.6 rad (off-diagonal terms in the
    body frame). Links this thick keep the joint damping non-stiff: h lambda_max(M^-1 D) stays below
    about 1 at h = 0.05 with d = 0.05 (slender links, small moments about the long axis, make
    lambda_max large; `chain_dataset` records the figure)."""
    if not 2 <= int(links) <= 5:
        raise ConfigError(f"links={links}: a MuJoCo chain has 2 to 5 links")
    if joint not in JOINTS:
        raise ConfigError(f"joint={joint!r}: use one of {list(JOINTS)}")
    if root not in ROOTS:
        raise ConfigError(f"root={root!r}: use one of {list(ROOTS)}")
    if not (math.isfinite(gravity) and gravity >= 0):
        raise ConfigError(f"gravity={gravity}: the magnitude along -e3 must be >= 0")
    if not (math.isfinite(joint_damping) and joint_damping >= 0):
        raise ConfigError(f"joint_damping={joint_damping}: must be >= 0")
    if not (math.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt={dt}: must be > 0")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    out: list[Link] = []
    for b in range(int(links)):
        m = float(rng.uniform(1.0, 3.0))
        L, d, com, inertia = _draw_link(rng, m)
        if b == 0:
            offset = np.zeros(3) if root == "free" else rng.uniform(-0.5, 0.5, 3)
        else:
            prev = out[-1]
            side2 = _unit(rng)
            offset = prev.length * prev.direction + rng.uniform(0.0, 0.05) * side2
        axis = _unit(rng) if (joint == "hinge" and (b > 0 or root == "pinned")) else None
        out.append(Link(f"link{b}", m, com, 0.5 * (inertia + inertia.T), offset, axis, L, d))
    return ChainSpec(out, joint, root, float(gravity), float(joint_damping), float(dt))


TREES = {
    "chain3": [-1, 0, 1],
    "chain5": [-1, 0, 1, 2, 3],
    "branched5": [-1, 0, 0, 0, 1],  # a root with three branches, the first two links long
    "branched7": [-1, 0, 0, 0, 1, 2, 3],  # a root with three branches of two links
    "binary7": [-1, 0, 0, 1, 1, 2, 2],  # every body two children, two levels deep
}
"""Named trees for `chain_dataset(parents=...)` and `scripts/mujoco_chain.py --tree NAME`: parents (B,)."""


def _damping_per_dof(joint_damping, kinds: list[str]) -> list[list[float]]:
    """Per body, the damping of each DoF of its joint (B lists of 6/3/2/1/0 values): `joint_damping` a
    float (every non-root DoF; the root's joint undamped) or a list of B entries, each a float (every
    DoF of that joint) or a list with one value per DoF (a ball: 1 value, as MJCF has one per joint)."""
    B = len(kinds)
    if isinstance(joint_damping, (int, float)):
        entries: list = [0.0] + [float(joint_damping)] * (B - 1)
    else:
        entries = list(joint_damping)
        if len(entries) != B:
            raise ConfigError(
                f"joint_damping has {len(entries)} entries for {B} bodies (one per body, the root's first)"
            )
    out = []
    for b, (e, kind) in enumerate(zip(entries, kinds)):
        n = JOINT_DOF[kind]
        vals = [float(x) for x in (e if isinstance(e, (list, tuple, np.ndarray)) else [e])]
        if kind == "ball" and len(vals) == 3 and len(set(vals)) == 1:
            vals = vals[:1]
        if len(vals) == 1:
            vals = vals * n
        elif len(vals) != n or kind == "ball":
            raise ConfigError(
                f"joint_damping[{b}] has {len(vals)} values for a {kind} joint ({n} DoF; a ball takes one value)"
            )
        if not all(math.isfinite(x) and x >= 0 for x in vals):
            raise ConfigError(f"joint_damping[{b}]={vals}: every value must be finite and >= 0")
        if kind == "free" and any(vals):
            raise ConfigError("joint_damping[0]: a free root is undamped (use 0)")
        out.append(vals)
    return out


def tree_spec(
    parents,
    joints,
    gravity: float = 0.0,
    joint_damping: float | Sequence = 0.05,
    dt: float = 1e-3,
    seed: int = 0,
    heavy_root: bool = False,
    root_mass: float = 4.0,
    link_mass: tuple[float, float] = (0.5, 0.7),
) -> ChainSpec:
    """A random but physical kinematic tree of B = len(parents) bodies (2 to 12).

    parents (B,): -1 for body 0, then every parent an earlier body (or a name in `TREES`). joints (B,):
    body 0 "free" (a free root) or its joint to the world (a pinned root: "ball", "hinge", "universal"
    or "weld"), then "ball", "hinge", "universal" or "weld" per body. joint_damping: see
    `_damping_per_dof` (a float: every non-root DoF; or per body a float or per-DoF values).
    Links are drawn as in `chain_spec` (mass U(1, 3) kg, length U(0.25, 0.5) m along a random direction,
    box inertias turned off their axes, so off-diagonal in the body frame, centres of mass off the
    joint); a child's joint sits at U(0.6, 1) of its parent's length along the parent's direction plus
    a random offset up to 0.05 m (siblings apart). A hinge axis is a random unit vector; a universal
    joint's two axes are random unit vectors between pi/4 and 3pi/4 apart (not orthogonal, well away
    from parallel). heavy_root: the root's mass is `root_mass` (4 kg; the inertia of its box) and every
    other link's U(link_mass) kg (0.5-0.7 kg; inertias ~0.004-0.02 kg m^2): a robot base with light
    links."""
    if isinstance(parents, str):
        if parents not in TREES:
            raise ConfigError(f"parents={parents!r}: a list or one of {list(TREES)}")
        parents = TREES[parents]
    parents = [int(q) for q in parents]
    joints = [str(j) for j in joints]
    B = len(parents)
    if not 2 <= B <= 12:
        raise ConfigError(f"parents: a MuJoCo tree has 2 to 12 bodies, got {B}")
    if parents[0] != -1 or any(not 0 <= q < b for b, q in enumerate(parents[1:], start=1)):
        raise ConfigError(f"parents={parents}: -1 first, then every parent an earlier body")
    if len(joints) != B:
        raise ConfigError(f"joints has {len(joints)} entries for {B} bodies")
    root = "free" if joints[0] == "free" else "pinned"
    for b, j in enumerate(joints):
        ok = TREE_JOINTS + (("free",) if b == 0 else ())
        if j not in ok:
            raise ConfigError(f"joints[{b}]={j!r}: use one of {list(ok)}")
    if sum(JOINT_DOF[j] for j in joints) == 0:
        raise ConfigError(f"joints={joints}: every joint a weld leaves nothing to move")
    if not (math.isfinite(gravity) and gravity >= 0):
        raise ConfigError(f"gravity={gravity}: the magnitude along -e3 must be >= 0")
    if not (math.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt={dt}: must be > 0")
    if heavy_root and not (math.isfinite(root_mass) and root_mass > 0 and 0 < link_mass[0] <= link_mass[1]):
        raise ConfigError(f"root_mass={root_mass}, link_mass={link_mass}: masses must be > 0")
    damping = _damping_per_dof(joint_damping, joints)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 3]))
    out: list[Link] = []
    for b in range(B):
        if heavy_root:
            m = float(root_mass) if b == 0 else float(rng.uniform(*link_mass))
        else:
            m = float(rng.uniform(1.0, 3.0))
        L, d, com, inertia = _draw_link(rng, m)
        if b == 0:
            offset = np.zeros(3) if root == "free" else rng.uniform(-0.5, 0.5, 3)
        else:
            par = out[parents[b]]
            offset = rng.uniform(0.6, 1.0) * par.length * par.direction + rng.uniform(0.0, 0.05) * _unit(rng)
        axis = axis2 = None
        if joints[b] == "hinge":
            axis = _unit(rng)
        elif joints[b] == "universal":
            axis = _unit(rng)
            while True:
                axis2 = _unit(rng)
                if abs(float(axis.dot(axis2))) < math.cos(math.pi / 4):
                    break
        out.append(Link(f"link{b}", m, com, 0.5 * (inertia + inertia.T), offset, axis, L, d, axis2, damping[b]))
    mean = [float(np.mean(v)) if v else 0.0 for v in damping]
    uniform = float(joint_damping) if isinstance(joint_damping, (int, float)) else float(np.mean(mean[1:]))
    return ChainSpec(out, "mixed", root, float(gravity), uniform, float(dt), parents, joints)


def _v(x) -> str:
    return " ".join(repr(float(a)) for a in np.asarray(x).reshape(-1))


def chain_mjcf(spec: ChainSpec) -> str:
    """The MJCF of the chain or tree: nested bodies with the identity `quat`, explicit inertials (no mass
    from geoms), massless capsule geoms for drawing only, contacts disabled, RK4 at `dt`, energy on. A
    universal joint is two hinge joints in one body (axis a1 then a2: R_rel = exp(t1 a1) exp(t2 a2)); a
    weld body has no joint."""
    lines = [
        '<mujoco model="liedfl_chain">',
        '  <compiler angle="radian" inertiafromgeom="false"/>',
        f'  <option timestep="{spec.dt!r}" integrator="RK4" gravity="0 0 {-spec.gravity!r}">',
        '    <flag contact="disable" energy="enable"/>',
        "  </option>",
        "  <worldbody>",
    ]
    parents, kinds = spec.parents, spec.joint_kinds()

    damping = spec.dof_damping()

    def body(b: int, depth: int) -> None:
        link, kind, d = spec.links[b], kinds[b], damping[b]
        ind = "    " + "  " * depth
        lines.append(f'{ind}<body name="{link.name}" pos="{_v(link.offset)}">')
        if kind == "free":
            lines.append(f'{ind}  <freejoint name="root"/>')
        elif kind in ("ball", "hinge"):
            axis = f' axis="{_v(link.axis)}"' if kind == "hinge" and link.axis is not None else ""
            lines.append(f'{ind}  <joint name="j{b}" type="{kind}" damping="{d[0]!r}"{axis}/>')
        elif kind == "universal":
            for tag, ax, db in (("a", link.axis, d[0]), ("b", link.axis2, d[1])):
                lines.append(f'{ind}  <joint name="j{b}{tag}" type="hinge" damping="{db!r}" axis="{_v(ax)}"/>')
        # a weld body has no joint: MuJoCo attaches it rigidly to its parent
        I = link.inertia
        full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        lines.append(f'{ind}  <inertial pos="{_v(link.com)}" mass="{link.mass!r}" fullinertia="{_v(full)}"/>')
        lines.append(
            f'{ind}  <geom type="capsule" size="0.02" fromto="0 0 0 {_v(link.length * link.direction)}" '
            'mass="0" contype="0" conaffinity="0"/>'
        )
        for c in range(len(spec.links)):
            if parents[c] == b:
                body(c, depth + 1)
        lines.append(f"{ind}</body>")

    body(0, 0)
    lines += ["  </worldbody>", "</mujoco>"]
    return "\n".join(lines)


def body_ids(spec: ChainSpec, model) -> list[int]:
    """MuJoCo's body id of every link, in liedfl's order (MuJoCo numbers a tree's bodies depth first)."""
    mujoco = require_mujoco()
    return [int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, link.name)) for link in spec.links]


def declared_physics(spec: ChainSpec, model) -> dict[str, Any]:
    """params["physics"] from the compiled MuJoCo model (masses, COMs and inertias as MuJoCo uses them;
    damping per DoF from `model.dof_damping`), in metres (`chain_dataset` rescales for other units)."""
    mujoco = require_mujoco()
    ids = body_ids(spec, model)
    bodies = []
    for b, link in enumerate(spec.links):
        i = ids[b]  # MuJoCo numbers bodies depth first after the world (0)
        q = model.body_iquat[i]  # (w, x, y, z): principal frame -> body frame
        Rq = so3.from_quaternion(torch.tensor(np.asarray(q), dtype=torch.float64)).numpy()  # liedfl: (w, x, y, z) too
        inertia = Rq @ np.diag(model.body_inertia[i]) @ Rq.T
        bodies.append(
            {
                "name": link.name,
                "mass": float(model.body_mass[i]),
                "com": [float(x) for x in model.body_ipos[i]],
                "inertia": [[float(x) for x in row] for row in 0.5 * (inertia + inertia.T)],
            }
        )
    kinds = spec.joint_kinds()
    hinge = "hinge" in kinds
    # per DoF as MuJoCo compiled it: a body's DoF are its joints' (a universal: two hinges; a weld: none)
    dof_damping = [
        [float(x) for x in model.dof_damping[model.body_dofadr[i] : model.body_dofadr[i] + model.body_dofnum[i]]]
        for i in ids
    ]

    def one(v: list[float]) -> float:  # a joint's damping as one number: its DoF's value, or their mean
        return 0.0 if not v else (v[0] if len(set(v)) == 1 else float(np.mean(v)))

    return {
        "kind": "articulated",
        "g": spec.gravity,
        "bodies": bodies,
        "joint_damping": [one(v) for v in dof_damping[1:]],
        "root_damping": one(dof_damping[0]),
        "joints": kinds,
        "hinge_axes": (
            [
                [float(x) for x in k.axis] if kd == "hinge" and k.axis is not None else None
                for k, kd in zip(spec.links, kinds)
            ]
            if hinge
            else None
        ),
        "joint_axes": spec.joint_axes(),
        "dof_damping": dof_damping,
        "engine": f"mujoco {mujoco.__version__}",
        "dt": spec.dt,
        "integrator": "RK4",
    }


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    return so3.to_quaternion(torch.from_numpy(R)).numpy()  # (w, x, y, z), as MuJoCo


def _initial_state(spec: ChainSpec, model, data, rng: np.random.Generator, speed: float):
    """Random qpos, qvel: every joint at a random rotation (hinges: a random angle), the free root at
    a random attitude and a position in [-1, 1]^3; velocities: Gaussian directions (every joint's
    relative angular velocity, the root's linear velocity at a tenth of the scale in m/s), scaled so
    that the kinetic energy is E = 1/2 speed^2 sum_b tr(I_b)/3, the energy of every link spinning at
    `speed` rad/s about its centre of mass (a fixed energy bounds how fast the light links can whip)."""
    qpos = np.zeros(model.nq)
    qvel = np.zeros(model.nv)
    for i in body_ids(spec, model):
        first, count = int(model.body_jntadr[i]), int(model.body_jntnum[i])
        for jid in range(first, first + count):  # none for a weld body, two for a universal joint
            qa, va, kind = model.jnt_qposadr[jid], model.jnt_dofadr[jid], int(model.jnt_type[jid])
            if kind == 0:  # free
                qpos[qa : qa + 3] = rng.uniform(-1.0, 1.0, 3)
                qpos[qa + 3 : qa + 7] = _quat_wxyz(_rotation(rng))
                qvel[va : va + 3] = rng.normal(0.0, 0.1, 3)  # world frame
                qvel[va + 3 : va + 6] = rng.normal(0.0, 1.0, 3)  # body frame
            elif kind == 1:  # ball
                qpos[qa : qa + 4] = _quat_wxyz(_rotation(rng))
                qvel[va : va + 3] = rng.normal(0.0, 1.0, 3)
            else:  # hinge
                qpos[qa] = rng.uniform(-math.pi, math.pi)
                qvel[va] = rng.normal(0.0, 1.0)
    mujoco = require_mujoco()
    data.qpos[:], data.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, data)
    target = 0.5 * speed**2 * float(model.body_inertia[1:].sum()) / 3.0
    kinetic = float(data.energy[1])
    if kinetic > 0:
        data.qvel[:] = qvel * math.sqrt(target / kinetic)


@dataclass
class ChainRecord:
    """What the engine reports at every sample: world poses (T, N+1, B, 3, 3) / (T, N+1, B, 3), body-frame
    angular velocities of the world attitudes (T, N+1, B, 3), qpos, qvel, energies (T, N+1), momenta."""

    Rw: np.ndarray
    pw: np.ndarray
    omega: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    kinetic: np.ndarray
    potential: np.ndarray
    linear_momentum: np.ndarray
    angular_momentum: np.ndarray
    damping_rate: float = 0.0  # lambda_max(M^-1 D) over the initial states (1/s)


def simulate_chain(
    spec: ChainSpec,
    n_trajectories: int,
    steps: int,
    h: float,
    seed: int = 0,
    speed: float = 5.0,
    progress: Callable[[float], None] | None = None,
) -> tuple[ChainRecord, Any]:
    """Integrate `n_trajectories` random initial states with mj_step at spec.dt, sampled every h
    (h must be a multiple of dt). Returns (record, compiled MjModel)."""
    mujoco = require_mujoco()
    sub = int(round(h / spec.dt))
    if sub < 1 or abs(sub * spec.dt - h) > 1e-9 * h:
        raise ConfigError(f"h={h} must be a whole multiple of dt={spec.dt}")
    model = mujoco.MjModel.from_xml_string(chain_mjcf(spec))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 2]))
    T, N1, B = int(n_trajectories), int(steps) + 1, len(spec.links)
    rec = ChainRecord(
        Rw=np.zeros((T, N1, B, 3, 3)),
        pw=np.zeros((T, N1, B, 3)),
        omega=np.zeros((T, N1, B, 3)),
        qpos=np.zeros((T, N1, model.nq)),
        qvel=np.zeros((T, N1, model.nv)),
        kinetic=np.zeros((T, N1)),
        potential=np.zeros((T, N1)),
        linear_momentum=np.zeros((T, N1, 3)),
        angular_momentum=np.zeros((T, N1, 3)),
    )
    vel = np.zeros(6)
    ids = body_ids(spec, model)
    total_mass = float(model.body_subtreemass[1])
    for i in range(T):
        mujoco.mj_resetData(model, data)
        _initial_state(spec, model, data, rng, speed)
        mujoco.mj_forward(model, data)
        M = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M)
        rate = np.linalg.eigvals(np.linalg.solve(M, np.diag(model.dof_damping))).real.max()
        rec.damping_rate = max(rec.damping_rate, float(rate))
        for k in range(N1):
            if k > 0:
                mujoco.mj_step(model, data, nstep=sub)
            mujoco.mj_forward(model, data)  # kinematics and energy of the current state
            mujoco.mj_subtreeVel(model, data)
            rec.Rw[i, k] = data.xmat[ids].reshape(B, 3, 3)
            rec.pw[i, k] = data.xpos[ids]
            for b in range(B):
                mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, ids[b], vel, 1)
                rec.omega[i, k, b] = vel[:3]
            rec.qpos[i, k], rec.qvel[i, k] = data.qpos, data.qvel
            rec.potential[i, k], rec.kinetic[i, k] = data.energy
            rec.linear_momentum[i, k] = total_mass * data.subtree_linvel[1]
            rec.angular_momentum[i, k] = data.subtree_angmom[1]  # about the chain's centre of mass
        if progress is not None:
            progress((i + 1) / T)
    return rec, model


def step_rotations(R: np.ndarray) -> np.ndarray:
    """Geodesic angle of every increment R_k^T R_(k+1): (T, N+1, B, 3, 3) -> (T, N, B)."""
    W = np.swapaxes(R[:, :-1], -1, -2) @ R[:, 1:]
    c = np.clip((np.trace(W, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(c)


def chain_coordinates(
    rec: ChainRecord, rotations: str, free_root: bool, parents: list[int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) of the dataset from the engine's world poses: world attitudes or R_parent^T R_b
    (`parents`: the tree's; None: a serial chain)."""
    R = rec.Rw.copy()
    if rotations == "parent":
        B = R.shape[2]
        par = list(range(-1, B - 1)) if parents is None else list(parents)
        R[:, :, 1:] = np.swapaxes(rec.Rw[:, :, par[1:]], -1, -2) @ rec.Rw[:, :, 1:]
    p = rec.pw[:, :, :1] if free_root else rec.pw[:, :, :0]
    return R, p


def _tree_joints(parents: list[int], joints, joint: str, root: str) -> list[str]:
    """Every body's joint (B,) from `joints`: None (the root "free" or, pinned, `joint`; `joint` elsewhere),
    B entries, or B - 1 entries for the non-root bodies (the root's from `root` and `joint`)."""
    B = len(parents)
    first = "free" if root == "free" else joint
    if joints is None:
        return [first] + [joint] * (B - 1)
    joints = [str(j).strip() for j in joints]
    if len(joints) == B - 1:
        return [first] + joints
    return joints


def chain_dataset(
    links: int = 3,
    joint: str = "ball",
    rotations: str = "world",
    root: str = "free",
    gravity: float = 0.0,
    joint_damping: float | Sequence = 0.05,
    n_trajectories: int = 128,
    steps: int = 100,
    h: float = 0.05,
    dt: float = 1e-3,
    seed: int = 0,
    speed: float = 5.0,
    test_fraction: float = 0.1,
    max_step_rotation: float = 0.5 * math.pi / 2,
    progress: Callable[[float], None] | None = None,
    parents: Sequence[int] | str | None = None,
    joints: Sequence[str] | None = None,
    heavy_root: bool = False,
    unit: str = "m",
    declare_joints: bool = True,
    root_mass: float = 4.0,
) -> Dataset:
    """A liedfl dataset of a random MuJoCo chain or tree (module docstring; docs/data_format.md "MuJoCo
    chains"): R (T, N+1, B, 3, 3), p (T, N+1, 1 or 0, 3), the tree with its joints, params["physics"],
    MuJoCo's poses under extras. ConfigError when the largest per-step rotation of the coordinates or of
    a world attitude exceeds `max_step_rotation` (default pi/4: well below the pi/2 at which liedfl
    warns; lower `speed` or h).

    A serial chain of `links` ball or hinge joints (`chain_spec`, as before) unless one of the tree
    options is given, then `tree_spec`: `parents` (B,) or a name in `TREES`; `joints` per body (B, or
    B - 1 with the root's from `root`: "free", or pinned with `joint`) among ball / hinge / universal /
    weld; `joint_damping` a float or per body (per DoF); `heavy_root` (a `root_mass` kg root, 0.5-0.7 kg
    links); `joint` universal/weld. `unit` "m" or "mm": MuJoCo simulates in metres, the file stores
    lengths (p, joint_offsets, COMs, world positions) in the unit, inertias in kg unit^2, gravity in
    unit/s^2, damping in kg unit^2/s, energies in kg unit^2/s^2; params["length_unit_m"] says which.
    declare_joints=False leaves the tree's joints out (every joint then reads as a ball)."""
    if rotations not in ("world", "parent"):
        raise ConfigError(f"rotations={rotations!r}: use 'world' or 'parent'")
    if int(n_trajectories) < 1 or int(steps) < 1:
        raise ConfigError(f"n_trajectories={n_trajectories}, steps={steps}: need at least 1 of each")
    if unit not in UNITS:
        raise ConfigError(f"unit={unit!r}: use one of {list(UNITS)}")
    if root not in ROOTS:
        raise ConfigError(f"root={root!r}: use one of {list(ROOTS)}")
    as_tree = (
        parents is not None
        or joints is not None
        or heavy_root
        or joint not in JOINTS
        or not isinstance(joint_damping, (int, float))
    )
    if as_tree:
        if parents is None:
            parents = [-1] + list(range(int(links) - 1))
        elif isinstance(parents, str):
            if parents not in TREES:
                raise ConfigError(f"parents={parents!r}: a list or one of {list(TREES)}")
            parents = TREES[parents]
        parents = [int(q) for q in parents]
        kinds_in = _tree_joints(parents, joints, joint, root)
        spec = tree_spec(parents, kinds_in, gravity, joint_damping, dt, seed, heavy_root, root_mass)
        root = spec.root
    else:
        assert isinstance(joint_damping, (int, float))
        spec = chain_spec(links, joint, root, gravity, float(joint_damping), dt, seed)
    rec, model = simulate_chain(spec, n_trajectories, steps, h, seed, speed, progress)
    free = root == "free"
    kinds = spec.joint_kinds()
    R, p = chain_coordinates(rec, rotations, free, spec.parents)
    for b, kind in enumerate(kinds):  # a weld's R_rel is C = I (identity body quats): exactly, not to rounding
        if kind == "weld" and b > 0:
            R[:, :, b] = np.eye(3) if rotations == "parent" else R[:, :, spec.parents[b]]
    scale = 1.0 / UNITS[unit]  # file units per metre
    tree = Tree.from_lists(
        spec.parents,
        [scale * k.offset for k in spec.links],
        rotations,
        free_root=free,
        joints=kinds if declare_joints else None,
        axes=spec.joint_axes() if declare_joints else None,
    )
    coord_rot, world_rot = step_rotations(R), step_rotations(rec.Rw)
    worst = max(float(coord_rot.max()), float(world_rot.max()))
    largest = {
        "coordinates": float(coord_rot.max()),
        "world": float(world_rot.max()),
        "where": [int(i) for i in np.unravel_index(int(np.argmax(coord_rot)), coord_rot.shape)],
    }
    if worst > max_step_rotation:
        raise ConfigError(
            f"the largest per-step rotation is {worst:.3f} rad (> {max_step_rotation:.3f}): lower speed={speed} "
            f"or h={h}"
        )
    T = int(n_trajectories)
    split, overlap = default_split(T, float(test_fraction), None, int(seed))
    physics = declared_physics(spec, model)
    energy_scale = scale * scale  # kg m^2 -> kg unit^2 (inertias, damping, energies, angular momenta)
    if scale != 1.0:  # the same motion in other length units
        for body in physics["bodies"]:
            body["com"] = [scale * x for x in body["com"]]
            body["inertia"] = [[energy_scale * x for x in row] for row in body["inertia"]]
        physics["g"] = scale * physics["g"]
        physics["dof_damping"] = [[energy_scale * x for x in row] for row in physics["dof_damping"]]
        physics["joint_damping"] = [energy_scale * x for x in physics["joint_damping"]]
        physics["root_damping"] = energy_scale * physics["root_damping"]
        p = scale * p
    physics["length_unit_m"] = UNITS[unit]
    config = {
        "links": len(spec.links),
        "joint": joint,
        "rotations": rotations,
        "root": root,
        "gravity": float(gravity),
        "joint_damping": (
            float(joint_damping) if isinstance(joint_damping, (int, float)) else physics_damping_config(joint_damping)
        ),
        "parents": spec.parents,
        "joints": kinds,
        "heavy_root": bool(heavy_root),
        "root_mass": float(root_mass) if heavy_root else None,
        "unit": unit,
        "declare_joints": bool(declare_joints),
        "n_trajectories": T,
        "steps": int(steps),
        "h": float(h),
        "dt": float(dt),
        "seed": int(seed),
        "speed": float(speed),
        "test_fraction": float(test_fraction),
    }
    params: dict[str, Any] = {
        "physics": physics,
        "gravity": float(gravity) * scale,
        "config": config,
        "generator": "liedfl_cli.data.mujoco_chain",
        "generator_version": GENERATOR_VERSION,
        "mjcf": chain_mjcf(spec),  # in metres, whatever `unit`
        "split_overlap": overlap,
        "step_rotation": largest,
        "length_unit_m": UNITS[unit],
        "bodies": {
            "root": "free (SE(3)) root, world pose" if free else "root pinned at joint_offsets[0] (SO(3))",
            "rotations": rotations,
        },
        "simulation": {
            "substeps_per_sample": int(round(h / dt)),
            "initial_speed_rad_s": float(speed),
            "h_lambda_max_damping": h * rec.damping_rate,
        },
    }
    if gravity == 0:
        params["potential"] = "none"
    extras = {  # in the file's unit, but qpos / qvel: MuJoCo's own state, in metres (params["mjcf"])
        "body_R_world": rec.Rw,
        "body_p_world": scale * rec.pw,
        "body_omega": rec.omega,
        "qpos": rec.qpos,
        "qvel": rec.qvel,
        "kinetic_energy": energy_scale * rec.kinetic,
        "potential_energy": energy_scale * rec.potential,
        "energy": energy_scale * (rec.kinetic + rec.potential),
        "linear_momentum": scale * rec.linear_momentum,
        "angular_momentum": energy_scale * rec.angular_momentum,
    }
    return Dataset(
        R=R,
        p=p,
        h=float(h),
        scene="mujoco_chain",
        body_names=[k.name for k in spec.links],
        body_kinds=(["se3"] if free else ["so3"]) + ["so3"] * (len(spec.links) - 1),
        params=params,
        seed=int(seed),
        split=split,
        extras=extras,
        tree=tree,
    )


def physics_damping_config(joint_damping) -> list:
    """`joint_damping` given per body (floats or per-DoF lists) as plain JSON lists."""
    out: list = []
    for e in joint_damping:
        out.append([float(x) for x in e] if isinstance(e, (list, tuple, np.ndarray)) else float(e))
    return out


__all__ = [
    "JOINTS",
    "ROOTS",
    "Link",
    "ChainSpec",
    "ChainRecord",
    "require_mujoco",
    "chain_spec",
    "tree_spec",
    "TREE_JOINTS",
    "TREES",
    "JOINT_DOF",
    "UNITS",
    "body_ids",
    "chain_mjcf",
    "declared_physics",
    "simulate_chain",
    "step_rotations",
    "chain_coordinates",
    "chain_dataset",
]
