"""Joints of a kinematic tree: the motion each joint allows, as a basis of the coordinates' tangent space
and an exact retraction that keeps every joint on its constraint manifold.

Joint coordinates q (the tree's coordinates with parent-relative rotations, `mechanics.articulated.
joint_coordinates`): the root's pose and each body's relative rotation R_rel = R_parent^T R_b. A
joint of type (`lie.tree.JOINT_TYPES`, axes as `Tree.axes`)

    ball       R_rel anywhere in SO(3)                  S = I_3                     3 DoF
    universal  R_rel = exp(t1 a1) C exp(t2 a2)          S(R_rel) = [R_rel^T a1, a2]  2 DoF
    hinge      R_rel = C exp(t a)                       S = a                       1 DoF
    weld       R_rel = C                                S = (3, 0)                  0 DoF

(a1 fixed in the parent frame, a and a2 in the body frame; C constant), a free root has S = I_6.
S is the motion subspace in the left trivialisation: a variation of q that respects the joint is
q exp(S delta), and `advance` moves along the joint exactly:

    ball R exp(d),  hinge R exp(d a),  universal exp(d1 a1) R exp(d2 a2),  weld R,  root g exp(d)

so d/dd advance(q, d) at 0 is S(q) d in the left trivialisation (tested against autodiff), and a
hinge stays a hinge to rounding error however many steps are taken.

In the tree's own coordinates g (world or parent rotations), the admissible variations are
g exp(T(g) delta) with T = C(g)^{-1} S(q(g)), C the joint-velocity map (`mechanics.articulated.
joint_velocity_map`, the identity for parent rotations). T has full column rank n = `tree.n_dof`.
"""

from __future__ import annotations

import torch

from . import so3
from .product import Pose
from .tree import JOINT_DOF, Tree


def joint_slices(tree: Tree) -> list[slice]:
    """Each body's columns of the reduced coordinates (root first; free root 6, ball 3, universal 2,
    hinge 1, weld 0)."""
    out, s = [], 0
    for k in tree.joint_kinds:
        out.append(slice(s, s + JOINT_DOF[k]))
        s += JOINT_DOF[k]
    return out


def _axes(tree: Tree, like: torch.Tensor) -> torch.Tensor:
    """The joint axes as a (B, 2, 3) tensor of `like`'s dtype and device."""
    return torch.tensor(tree.axes_array(), dtype=like.dtype, device=like.device)


def motion_basis(tree: Tree, q: Pose) -> torch.Tensor:
    """S(q) (..., dim, n): the joints' motion subspaces in joint coordinates q (parent-relative
    rotations), block diagonal over bodies in the layout of `tree.group` (rows) and `joint_slices`
    (columns)."""
    R = q.R
    lead, dt, dev = R.shape[:-3], R.dtype, R.device
    G = tree.group
    ax = _axes(tree, R)
    S = R.new_zeros(*lead, G.dim, tree.n_dof)
    rows, cols = G.body_slices(), joint_slices(tree)
    eye = torch.eye(6, dtype=dt, device=dev)
    for b, kind in enumerate(tree.joint_kinds):
        r0, c0 = rows[b].start, cols[b].start
        if kind == "free":
            S[..., r0 : r0 + 6, c0 : c0 + 6] = eye
        elif kind == "ball":
            S[..., r0 : r0 + 3, c0 : c0 + 3] = eye[:3, :3]
        elif kind == "hinge":
            S[..., r0 : r0 + 3, c0] = ax[b, 0]
        elif kind == "universal":
            S[..., r0 : r0 + 3, c0] = so3.act(R[..., b, :, :].transpose(-1, -2), ax[b, 0])
            S[..., r0 : r0 + 3, c0 + 1] = ax[b, 1]
    return S


def advance(tree: Tree, q: Pose, d: torch.Tensor) -> Pose:
    """Move joint coordinates q along the joints by d (..., n) (module docstring): exact on every
    joint's manifold; the root by its group's exponential (SE(3): (R exp(w), p + R V(w) v))."""
    from .product import ProductGroup

    R, p = q.R, q.p
    ax = _axes(tree, R)
    cols = joint_slices(tree)
    Rs, ps = [], p
    for b, kind in enumerate(tree.joint_kinds):
        Rb = R[..., b, :, :]
        c = cols[b]
        if kind == "free":
            root = ProductGroup(1, 0).retract(Pose(Rb[..., None, :, :], p[..., :1, :]), d[..., c])
            Rs.append(root.R[..., 0, :, :])
            ps = torch.cat((root.p, p[..., 1:, :]), -2)
        elif kind == "ball":
            Rs.append(Rb @ so3.exp(d[..., c]))
        elif kind == "hinge":
            Rs.append(Rb @ so3.exp(d[..., c] * ax[b, 0]))
        elif kind == "universal":
            Rs.append(
                so3.exp(d[..., c.start : c.start + 1] * ax[b, 0])
                @ Rb
                @ so3.exp(d[..., c.start + 1 : c.stop] * ax[b, 1])
            )
        else:
            Rs.append(Rb)
    return Pose(torch.stack(Rs, -3), ps)


def world_from_parent(tree: Tree, R_rel: torch.Tensor) -> torch.Tensor:
    """Parent-relative attitudes (..., B, 3, 3) -> world attitudes (..., B, 3, 3) (the root as it is)."""
    out: list[torch.Tensor | None] = [None] * tree.n_bodies
    out[0] = R_rel[..., 0, :, :]
    for b in range(1, tree.n_bodies):
        parent = out[tree.parents[b]]
        assert parent is not None
        out[b] = parent @ R_rel[..., b, :, :]
    return torch.stack(out, -3)  # type: ignore[arg-type]


def to_joint_coordinates(tree: Tree, g: Pose) -> Pose:
    """The tree's coordinates g -> joint coordinates q (parent-relative rotations)."""
    if tree.rotations == "parent":
        return g
    par = [max(q, 0) for q in tree.parents]
    Rp = g.R[..., par, :, :]
    R = torch.cat((g.R[..., :1, :, :], Rp[..., 1:, :, :].transpose(-1, -2) @ g.R[..., 1:, :, :]), -3)
    return Pose(R, g.p)


def from_joint_coordinates(tree: Tree, q: Pose) -> Pose:
    """Joint coordinates q -> the tree's coordinates g (inverse of `to_joint_coordinates`)."""
    if tree.rotations == "parent":
        return q
    return Pose(world_from_parent(tree, q.R), q.p)


def coordinate_basis(tree: Tree, g: Pose, C: torch.Tensor | None) -> torch.Tensor:
    """T(g) = C(g)^{-1} S(q(g)) (..., dim, n): the admissible variations g exp(T delta) of the tree's
    coordinates; C = `joint_velocity_map(tree, g)` (None: the identity, parent rotations)."""
    S = motion_basis(tree, to_joint_coordinates(tree, g))
    return S if C is None else torch.linalg.solve(C, S)


def retract(tree: Tree, g: Pose, x: Pose, d: torch.Tensor) -> Pose:
    """The increment x' with g x' = the joints of g x advanced by d (..., n): a Newton update of the
    increment x (tree coordinates) that keeps every joint on its manifold. d/dd (g x') at 0 is
    T(g x) d in the left trivialisation."""
    G = tree.group
    q_next = to_joint_coordinates(tree, G.compose(g, x))
    return G.increment(g, from_joint_coordinates(tree, advance(tree, q_next, d)))


def reduce(T: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """The least-squares reduced coordinates d (..., n) of a tangent vector xi (..., dim): T d ~ xi."""
    if T.shape[-1] == 0:
        return xi[..., :0]
    return torch.linalg.lstsq(T, xi[..., None]).solution[..., 0]


__all__ = [
    "joint_slices",
    "motion_basis",
    "advance",
    "world_from_parent",
    "to_joint_coordinates",
    "from_joint_coordinates",
    "coordinate_basis",
    "retract",
    "reduce",
]
