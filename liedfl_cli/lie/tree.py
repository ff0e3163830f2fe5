"""Kinematic trees: the coordinates of an articulated body and their forward kinematics.

A tree of B bodies is described by `parents` (one int per body, -1 for the root, which is body 0;
every parent comes before its children), `offsets` (B, 3): the origin of body b -- its joint --
in its parent's frame (the root's row is the pivot of an SO(3) root in the world, zeros for an
SE(3) root), and `rotations`: how the coordinates store a body's attitude,

    "world":  R[..., b] is body b's world attitude (x_world = R x_body);
    "parent": R[..., b] is its attitude relative to its parent, R_parent^T R_b (the BVH convention).

The coordinates are a Pose of the product group SE(3) x SO(3)^(B-1) (free-floating root) or
SO(3)^B (root pinned at offsets[0]). Forward kinematics gives every body's world SE(3) pose:
    Rw_b = R_b (world) or Rw_parent R_b (parent);  pw_b = pw_parent + Rw_parent o_b.

`fk_jacobian` is the left-trivialised Jacobian of forward kinematics: a perturbation g exp(eta) of
the coordinates moves body b's world pose to (Rw_b exp(dw_b), pw_b + Rw_b dv_b) + O(|eta|^2) with
(dw_b, dv_b) = A_b eta. In world-frame terms, with theta_b = Rw_b dw_b and P_b = Rw_b dv_b:
    theta_b = [theta_parent, parent rotations only] + Rw_b eta_b,
    P_b     = P_parent - hat(pw_b - pw_parent) theta_parent,   P_root = R_root eta_root,v (SE(3) root).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property

import torch

from . import so3
from .product import Pose, ProductGroup

ROTATIONS = ("world", "parent")
# joint types of a non-root body (and of a pinned root, its joint to the world): degrees of freedom 3, 2, 1, 0
JOINT_TYPES = ("ball", "universal", "hinge", "weld")
JOINT_DOF = {"free": 6, "ball": 3, "universal": 2, "hinge": 1, "weld": 0}


@dataclass(frozen=True)
class Tree:
    """A kinematic tree (holds no tensors): parents (B,), offsets (B, 3) as nested tuples, rotations."""

    parents: tuple[int, ...]
    offsets: tuple[tuple[float, float, float], ...]
    rotations: str = "world"
    free_root: bool = True
    # per body: "free" (the free root only) or one of JOINT_TYPES; None = every joint a ball (a free
    # root "free"). axes (B, 2, 3): a hinge's axis in the body (child) frame in row 0; a universal
    # joint's first axis fixed in the parent frame in row 0 and its second, fixed in the body frame,
    # in row 1 (R_rel = exp(t1 a1) C exp(t2 a2)); rows of other joints are zeros. `lie.joints`.
    joints: tuple[str, ...] | None = None
    axes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] | None = None

    def __post_init__(self):
        B = len(self.parents)
        if B == 0:
            raise ValueError("a tree needs at least one body")
        if self.parents[0] != -1:
            raise ValueError(f"parents[0] must be -1 (body 0 is the root), got {self.parents[0]}")
        for b, p in enumerate(self.parents[1:], start=1):
            if not (isinstance(p, int) and 0 <= p < b):
                raise ValueError(f"parents[{b}] = {p!r}: every parent must be an earlier body (0..{b - 1})")
        if len(self.offsets) != B or any(len(o) != 3 for o in self.offsets):
            raise ValueError(f"offsets must have shape ({B}, 3)")
        if self.rotations not in ROTATIONS:
            raise ValueError(f"rotations must be one of {ROTATIONS}, got {self.rotations!r}")
        if self.joints is not None:
            self._check_joints()

    def _check_joints(self) -> None:
        B = self.n_bodies
        joints = self.joints
        assert joints is not None
        if len(joints) != B:
            raise ValueError(f"joints has {len(joints)} entries for {B} bodies")
        root = "free" if self.free_root else None
        for b, kind in enumerate(joints):
            allowed = ("free",) if (b == 0 and root) else JOINT_TYPES
            if kind not in allowed:
                raise ValueError(f"joints[{b}] = {kind!r}: use one of {list(allowed)}")
        axes = self.axes
        needs_axes = any(k in ("hinge", "universal") for k in joints)
        if axes is None:
            if needs_axes:
                raise ValueError("hinge and universal joints need axes (B, 2, 3)")
            return
        if len(axes) != B or any(len(a) != 2 or any(len(r) != 3 for r in a) for a in axes):
            raise ValueError(f"axes must have shape ({B}, 2, 3)")
        for b, kind in enumerate(joints):
            rows = {"hinge": (0,), "universal": (0, 1)}.get(kind, ())
            for r in rows:
                n = sum(x * x for x in axes[b][r]) ** 0.5
                if not abs(n - 1.0) < 1e-6:
                    raise ValueError(f"axes[{b}][{r}] of the {kind} joint must be a unit vector, has norm {n:.6g}")

    @classmethod
    def from_lists(
        cls,
        parents: Sequence[int],
        offsets: Iterable[Iterable[float]],
        rotations: str = "world",
        free_root: bool = True,
        joints: Sequence[str] | None = None,
        axes: Iterable[Iterable[Iterable[float]]] | None = None,
    ) -> Tree:
        """From plain lists or arrays: parents (B,), offsets (B, 3), joints (B,) and axes (B, 2, 3) or None."""
        return cls(
            tuple(int(p) for p in parents),
            tuple(tuple(float(x) for x in o) for o in offsets),  # type: ignore[misc]
            str(rotations),
            bool(free_root),
            None if joints is None else tuple(str(j) for j in joints),
            None if axes is None else tuple(tuple(tuple(float(x) for x in r) for r in a) for a in axes),  # type: ignore[misc]
        )

    @property
    def joint_kinds(self) -> tuple[str, ...]:
        """Every body's joint: the declared `joints`, or "free"/"ball" for the root and "ball" elsewhere."""
        if self.joints is not None:
            return self.joints
        return ("free" if self.free_root else "ball",) + ("ball",) * (self.n_bodies - 1)

    @property
    def constrained(self) -> bool:
        """True when some joint has fewer degrees of freedom than a ball (hinge, universal, weld)."""
        return any(k in ("hinge", "universal", "weld") for k in self.joint_kinds)

    @property
    def n_dof(self) -> int:
        """Degrees of freedom of the tree: the sum of its joints' (6 for a free root)."""
        return sum(JOINT_DOF[k] for k in self.joint_kinds)

    def axes_array(self) -> list[list[list[float]]]:
        """axes as nested lists (B, 2, 3), zeros where none are declared."""
        if self.axes is None:
            return [[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]] for _ in range(self.n_bodies)]
        return [[list(r) for r in a] for a in self.axes]

    def with_joints(
        self, joints: Sequence[str] | None, axes: Iterable[Iterable[Iterable[float]]] | None = None
    ) -> Tree:
        """The same tree with other joints: joints (B,) or None (every joint a ball), axes (B, 2, 3) or None."""
        return Tree.from_lists(self.parents, self.offsets, self.rotations, self.free_root, joints, axes)

    @property
    def n_bodies(self) -> int:
        """B, the number of bodies."""
        return len(self.parents)

    @property
    def group(self) -> ProductGroup:
        """The coordinates' group: SE(3) x SO(3)^(B-1) for a free root, SO(3)^B for a pinned one."""
        return ProductGroup(1, self.n_bodies - 1) if self.free_root else ProductGroup(0, self.n_bodies)

    @cached_property
    def levels(self) -> list[list[int]]:
        """Bodies grouped by depth (root first): level d holds every body with d ancestors."""
        depth = [0] * self.n_bodies
        for b in range(1, self.n_bodies):
            depth[b] = depth[self.parents[b]] + 1
        out: list[list[int]] = [[] for _ in range(max(depth) + 1)]
        for b, d in enumerate(depth):
            out[d].append(b)
        return out

    def offsets_tensor(self, like: torch.Tensor) -> torch.Tensor:
        """offsets as a (B, 3) tensor of `like`'s dtype and device."""
        return torch.tensor(self.offsets, dtype=like.dtype, device=like.device)


def forward_kinematics(tree: Tree, g: Pose) -> Pose:
    """World SE(3) pose of every body: coordinates Pose (R (..., B, 3, 3), p (..., m, 3)) with
    m = 1 (free root) or 0 (pinned root) -> Pose (Rw (..., B, 3, 3), pw (..., B, 3))."""
    o = tree.offsets_tensor(g.R)
    lead = g.R.shape[:-3]
    Rw: list[torch.Tensor | None] = [None] * tree.n_bodies
    pw: list[torch.Tensor | None] = [None] * tree.n_bodies
    Rw[0] = g.R[..., 0, :, :]
    pw[0] = g.p[..., 0, :] if tree.free_root else o[0].expand(*lead, 3)
    for level in tree.levels[1:]:
        par = [tree.parents[b] for b in level]
        Rp = torch.stack([Rw[q] for q in par], -3)  # type: ignore[misc]
        pp = torch.stack([pw[q] for q in par], -2)  # type: ignore[misc]
        Rb = g.R[..., level, :, :]
        Rwb = Rp @ Rb if tree.rotations == "parent" else Rb
        pwb = pp + so3.act(Rp, o[level])
        for i, b in enumerate(level):
            Rw[b], pw[b] = Rwb[..., i, :, :], pwb[..., i, :]
    return Pose(torch.stack(Rw, -3), torch.stack(pw, -2))  # type: ignore[arg-type]


def relative_rotations(tree: Tree, Rw: torch.Tensor) -> torch.Tensor:
    """World attitudes (..., B, 3, 3) -> each body's attitude relative to its parent, R_parent^T R_b
    (the root's as it is), (..., B, 3, 3)."""
    par = [max(q, 0) for q in tree.parents]
    Rp = Rw[..., par, :, :]
    return torch.cat((Rw[..., :1, :, :], Rp[..., 1:, :, :].transpose(-1, -2) @ Rw[..., 1:, :, :]), -3)


def coordinates(tree: Tree, world: Pose) -> Pose:
    """Inverse of `forward_kinematics` on its image: world poses (Rw (..., B, 3, 3), pw (..., B, 3))
    -> the tree's coordinates (R (..., B, 3, 3), p (..., m, 3)). Positions of non-root bodies are
    implied by the joints and are not read."""
    R = relative_rotations(tree, world.R) if tree.rotations == "parent" else world.R
    p = world.p[..., :1, :] if tree.free_root else world.p[..., :0, :]
    return Pose(R, p)


def fk_jacobian(tree: Tree, g: Pose, world: Pose | None = None) -> torch.Tensor:
    """Left-trivialised Jacobian A of forward kinematics, shape (..., B, 6, dim):
    body b's world pose moves by (dw_b, dv_b) = A[..., b, :, :] eta under g exp(eta)
    (dim = the coordinates' tangent dimension, `tree.group.dim`). `world`: FK(g) if already known."""
    G = tree.group
    world = forward_kinematics(tree, g) if world is None else world
    Rw, pw = world.R, world.p
    lead = Rw.shape[:-3]
    B, dim = tree.n_bodies, G.dim
    slices = G.body_slices()
    theta: list[torch.Tensor | None] = [None] * B  # world-frame rotation rows (..., 3, dim)
    P: list[torch.Tensor | None] = [None] * B  # world-frame position rows (..., 3, dim)

    def own_rotation(b: int) -> torch.Tensor:
        t = Rw.new_zeros(*lead, 3, dim)
        s = slices[b].start
        t[..., :, s : s + 3] = Rw[..., b, :, :]
        return t

    theta[0] = own_rotation(0)
    P0 = Rw.new_zeros(*lead, 3, dim)
    if tree.free_root:
        P0[..., :, 3:6] = Rw[..., 0, :, :]
    P[0] = P0
    for b in range(1, B):
        q = tree.parents[b]
        tq, Pq = theta[q], P[q]
        assert tq is not None and Pq is not None
        own = own_rotation(b)
        theta[b] = tq + own if tree.rotations == "parent" else own
        P[b] = Pq - so3.hat(pw[..., b, :] - pw[..., q, :]) @ tq
    Th = torch.stack(theta, -3)  # type: ignore[arg-type]
    Pt = torch.stack(P, -3)  # type: ignore[arg-type]
    RwT = Rw.transpose(-1, -2)
    return torch.cat((RwT @ Th, RwT @ Pt), -2)
