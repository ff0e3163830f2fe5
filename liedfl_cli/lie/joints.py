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

import functools

import torch

from . import se3, so3
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


@functools.lru_cache(maxsize=64)
def _maps(tree: Tree, dtype: torch.dtype, device: torch.device) -> dict[str, torch.Tensor]:
    """Constant matrices of a tree's joints (cached per tree, dtype, device):
    E (B, 3, n): each body's right rotation tangent R_b exp(E_b d); U (B, 3, n): a universal joint's
    first axis (parent frame), its left factor exp(U_b d) R_b; V (3, n): the free root's translation
    columns; S0 (dim, n): the motion basis where it is constant (every joint but the universal's first
    column); S0_pinv (n, dim) its pseudo-inverse when no joint is universal."""
    B, n, G = tree.n_bodies, tree.n_dof, tree.group
    ax = torch.tensor(tree.axes_array(), dtype=dtype, device=device)
    E = torch.zeros(B, 3, n, dtype=dtype, device=device)
    U = torch.zeros(B, 3, n, dtype=dtype, device=device)
    V = torch.zeros(3, n, dtype=dtype, device=device)
    S0 = torch.zeros(G.dim, n, dtype=dtype, device=device)
    eye = torch.eye(3, dtype=dtype, device=device)
    rows = G.body_slices()
    for b, (kind, c) in enumerate(zip(tree.joint_kinds, joint_slices(tree))):
        r0, c0 = rows[b].start, c.start
        if kind in ("free", "ball"):
            E[b, :, c0 : c0 + 3] = eye
            S0[r0 : r0 + 3, c0 : c0 + 3] = eye
            if kind == "free":
                V[:, c0 + 3 : c0 + 6] = eye
                S0[r0 + 3 : r0 + 6, c0 + 3 : c0 + 6] = eye
        elif kind == "hinge":
            E[b, :, c0] = ax[b, 0]
            S0[r0 : r0 + 3, c0] = ax[b, 0]
        elif kind == "universal":
            U[b, :, c0] = ax[b, 0]
            E[b, :, c0 + 1] = ax[b, 1]
            S0[r0 : r0 + 3, c0 + 1] = ax[b, 1]
    out = {"E": E, "U": U, "V": V, "S0": S0}
    if "universal" not in tree.joint_kinds:
        out["S0_pinv"] = torch.linalg.pinv(S0)
    return out


def _universal(tree: Tree) -> list[tuple[int, int, int]]:
    """(body, its basis row, its first reduced column) of every universal joint."""
    rows, cols = tree.group.body_slices(), joint_slices(tree)
    return [(b, rows[b].start, cols[b].start) for b, k in enumerate(tree.joint_kinds) if k == "universal"]


def motion_basis(tree: Tree, q: Pose) -> torch.Tensor:
    """S(q) (..., dim, n): the joints' motion subspaces in joint coordinates q (parent-relative
    rotations), block diagonal over bodies in the layout of `tree.group` (rows) and `joint_slices`
    (columns). Constant unless a joint is universal (its first column R_rel^T a1)."""
    R = q.R
    S0 = _maps(tree, R.dtype, R.device)["S0"]
    uni = _universal(tree)
    if not uni:
        return S0.expand(*R.shape[:-3], *S0.shape)
    S = S0.expand(*R.shape[:-3], *S0.shape).clone()
    ax = torch.tensor(tree.axes_array(), dtype=R.dtype, device=R.device)
    for b, r0, c0 in uni:
        S[..., r0 : r0 + 3, c0] = so3.act(R[..., b, :, :].transpose(-1, -2), ax[b, 0])
    return S


def advance(tree: Tree, q: Pose, d: torch.Tensor) -> Pose:
    """Move joint coordinates q along the joints by d (..., n) (module docstring): exact on every
    joint's manifold; a free root by SE(3)'s exponential (R exp(w), p + R V(w) v)."""
    maps = _maps(tree, d.dtype, d.device)
    R = q.R @ so3.exp(torch.einsum("bin,...n->...bi", maps["E"], d))
    if _universal(tree):
        R = so3.exp(torch.einsum("bin,...n->...bi", maps["U"], d)) @ R
    p = q.p
    if tree.free_root:
        w, v = d[..., 0:3], d[..., 3:6]
        root = p[..., 0, :] + so3.act(q.R[..., 0, :, :], so3.act(se3.V_matrix(w), v))
        p = torch.cat((root[..., None, :], p[..., 1:, :]), -2)
    return Pose(R, p)


def world_from_parent(tree: Tree, R_rel: torch.Tensor) -> torch.Tensor:
    """Parent-relative attitudes (..., B, 3, 3) -> world attitudes (..., B, 3, 3) (the root as it is),
    one batched product per depth level."""
    out = R_rel.clone()
    for level in tree.levels[1:]:
        par = [tree.parents[b] for b in level]
        out[..., level, :, :] = out[..., par, :, :] @ R_rel[..., level, :, :]
    return out


def to_joint_coordinates(tree: Tree, g: Pose) -> Pose:
    """The tree's coordinates g (R (..., B, 3, 3), p (..., m, 3)) -> joint coordinates q (parent-relative
    rotations), of the same shapes."""
    if tree.rotations == "parent":
        return g
    par = [max(q, 0) for q in tree.parents]
    Rp = g.R[..., par, :, :]
    R = torch.cat((g.R[..., :1, :, :], Rp[..., 1:, :, :].transpose(-1, -2) @ g.R[..., 1:, :, :]), -3)
    return Pose(R, g.p)


def from_joint_coordinates(tree: Tree, q: Pose) -> Pose:
    """Joint coordinates q (R (..., B, 3, 3), p (..., m, 3)) -> the tree's coordinates g of the same
    shapes (inverse of `to_joint_coordinates`)."""
    if tree.rotations == "parent":
        return q
    return Pose(world_from_parent(tree, q.R), q.p)


def coordinate_basis(tree: Tree, g: Pose) -> torch.Tensor:
    """T(g) (..., dim, n): the admissible variations g exp(T delta) of the tree's coordinates, C(g)^{-1}
    S(q(g)) with C the joint-velocity map (`mechanics.articulated.joint_velocity_map`). For parent
    rotations T = S; for world rotations a body's world-attitude variation is its parent's carried
    into its frame plus its joint's: T_b = (R_parent^T R_b)^T T_parent[rotation rows] + S_b, one
    batched product per depth level."""
    S = motion_basis(tree, to_joint_coordinates(tree, g))
    if tree.rotations == "parent":
        return S
    rows = tree.group.body_slices()
    rot = torch.tensor([r.start for r in rows], dtype=torch.long, device=g.R.device)[:, None] + torch.arange(
        3, device=g.R.device
    )
    T = S.clone()
    for level in tree.levels[1:]:
        par = [tree.parents[b] for b in level]
        rel = g.R[..., par, :, :].transpose(-1, -2) @ g.R[..., level, :, :]  # (..., L, 3, 3)
        Tp = T[..., rot[par], :]  # (..., L, 3, n): the parents' rotation rows
        T[..., rot[level], :] = T[..., rot[level], :] + rel.transpose(-1, -2) @ Tp
    return T


def retract(tree: Tree, g: Pose, x: Pose, d: torch.Tensor) -> Pose:
    """The increment x' with g x' = the joints of g x advanced by d (..., n): a Newton update of the
    increment x (tree coordinates) that keeps every joint on its manifold. d/dd (g x') at 0 is
    T(g x) d in the left trivialisation."""
    G = tree.group
    q_next = to_joint_coordinates(tree, G.compose(g, x))
    return G.increment(g, from_joint_coordinates(tree, advance(tree, q_next, d)))


def reduce(T: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """The least-squares reduced coordinates d (..., n) of a tangent vector xi (..., dim): T d ~ xi (T d = xi
    exactly, by an LU solve, when T is square: every joint a ball, where T = C^-1 is invertible)."""
    if T.shape[-1] == 0:
        return xi[..., :0]
    if T.shape[-1] == T.shape[-2]:
        return torch.linalg.solve(T, xi[..., None])[..., 0]
    return torch.linalg.lstsq(T, xi[..., None]).solution[..., 0]


def reduce_joint_velocity(tree: Tree, q: Pose, q_next: Pose, nu: torch.Tensor, columns: bool = False) -> torch.Tensor:
    """nu (..., dim) in joint coordinates -> its DoF rates (..., n) in the least-squares coordinates of
    the mean motion basis of q and q_next (a constant pseudo-inverse unless a joint is universal).
    columns=True: nu is a matrix (..., dim, k) reduced column by column -> (..., n, k)."""
    maps = _maps(tree, nu.dtype, nu.device)
    if "S0_pinv" in maps:
        return maps["S0_pinv"] @ nu if columns else nu @ maps["S0_pinv"].T
    S = 0.5 * (motion_basis(tree, q) + motion_basis(tree, q_next))
    if columns:
        return torch.linalg.lstsq(S, nu).solution
    return reduce(S, nu)


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
    "reduce_joint_velocity",
]
