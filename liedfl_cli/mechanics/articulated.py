"""The articulated discrete Lagrangian of a kinematic tree, and joint-space forces.

Coordinates g: the tree's product group (free root SE(3) x SO(3)^(B-1), or SO(3)^B on a pinned
root; `lie.tree`). Forward kinematics gives each body's world SE(3) pose FK_b(g), and

    L_d(g_k, g_{k+1}) = sum_b K_b(FK_b(g_k)^{-1} FK_b(g_{k+1}); m_b, rho_b, J_b) - h V(g_k)

with K_b the rigid-body SE(3) kinetic term of `mechanics.kinetic` (J_b about the centre of mass
rho_b, in the body frame whose origin is the body's joint). The mass matrix then couples bodies
through the joints: a link's centre-of-mass velocity depends on every parent's motion.

Because FK does not depend on parameters, every derivative of L_d in the coordinates is the
world-frame derivative mapped by the FK Jacobian A (`lie.tree.fk_jacobian`, (..., B, 6, dim)):
    D1/D2 L_d = A(g_k)^T [world covectors of K_b],     d/d delta D1 L_d(g_k, g_k W exp delta)
              = A(g_k)^T blockdiag(H_b) A(g_{k+1}),
with H_b the closed-form mixed Hessian blocks of `kinetic.mixed_hessian_blocks`. These are exact
(first derivatives of FK only: the mixed derivative of K(phi(a), psi(b)) needs none of phi's or
psi's second derivatives); tests compare them with autodiff of L_d through FK.

Joint space: forces act on the joints' own coordinates q = `joint_coordinates(g)` (the root's pose and
each joint's rotation relative to its parent) and their velocity estimate nu~ from the increments of q,
so damping on the joints is a `rayleigh` force in joint space. A joint-space covector tau enters the
residual at g_k as C(g_k)^T tau, with C the left-trivialised Jacobian of g -> q (`joint_velocity_map`:
the identity for parent-relative rotations; with world rotations it couples each body to its parent),
evaluated where the variation acts (g_k for both F^+_{k-1} and F^-_k): mapping F^+_{k-1} with
C(g_{k-1}) instead would cost an order of accuracy.
"""

from __future__ import annotations

import torch

from ..lie import Pose, ProductGroup, joints
from ..lie.tree import Tree, fk_jacobian, forward_kinematics, relative_rotations
from . import kinetic


def world_group(tree: Tree) -> ProductGroup:
    """SE(3)^B: every body of the tree as a free rigid body (the layout of FK's world poses)."""
    return ProductGroup(tree.n_bodies, 0)


def to_coordinates(A: torch.Tensor, c_world: torch.Tensor) -> torch.Tensor:
    """A^T c: world covectors c (..., 6B) in SE(3)^B layout (w_1, v_1, ...) -> coordinates (..., dim)."""
    B = A.shape[-3]
    c = c_world.reshape(*c_world.shape[:-1], B, 6)
    return torch.einsum("...bkd,...bk->...d", A, c)


def newton_jacobian(A_k: torch.Tensor, inc_next: Pose, A_next: torch.Tensor, Jd, mass, rho, h: float) -> torch.Tensor:
    """d [A_k^T D1 K(FK(g_k)^{-1} FK(g_k W exp delta))] / d delta = A_k^T blockdiag(H_b) A_next, (..., dim, dim)."""
    H = mixed_hessian_blocks(inc_next, Jd, mass, rho, h)  # (..., B, 6, 6)
    return torch.einsum("...bkd,...bkl,...ble->...de", A_k, H, A_next)


def mixed_hessian_blocks(inc: Pose, Jd, mass, rho, h: float) -> torch.Tensor:
    """Each body's world SE(3) block of the mixed Hessian, (..., B, 6, 6) (`kinetic.se3_mixed_hessian`)."""
    return kinetic.se3_mixed_hessian(inc.R, Jd, mass, rho, h)


def joint_velocity_map(tree: Tree, g: Pose) -> torch.Tensor | None:
    """C(g) (..., dim, dim) with nu = C xi: the root's twist and each joint's relative angular
    velocity w_b - R_b^T R_parent w_parent (child frame); None when C = I (parent-relative rotations).
    Built without in-place writes, so torch.func transforms (vmap, jacrev) go through it."""
    if tree.rotations == "parent":
        return None
    G, B = tree.group, tree.n_bodies
    dt, dev, lead = g.R.dtype, g.R.device, g.R.shape[:-3]
    par = [max(q, 0) for q in tree.parents]
    rel = g.R.transpose(-1, -2) @ g.R[..., par, :, :]  # (..., B, 3, 3): R_b^T R_parent
    P = torch.zeros(B, B, dtype=dt, device=dev)  # P[b, parent(b)] = 1
    P[torch.arange(1, B, device=dev), torch.tensor(par[1:], dtype=torch.long, device=dev)] = 1.0
    C_rot = -torch.einsum("bc,...bij->...bicj", P, rel).reshape(*lead, 3 * B, 3 * B)
    # into the tangent layout: every body's rotation rows/columns (S), the root's translation untouched
    rot = torch.cat([torch.arange(s.start, s.start + 3, device=dev) for s in G.body_slices()])
    S = torch.zeros(G.dim, 3 * B, dtype=dt, device=dev)
    S[rot, torch.arange(3 * B, device=dev)] = 1.0
    return torch.eye(G.dim, dtype=dt, device=dev) + S @ C_rot @ S.T


def joint_coordinates(tree: Tree, g: Pose) -> Pose:
    """The tree's coordinates with parent-relative rotations (R_parent^T R_b; the root as it is):
    the joints' own configuration, on which forces act. Identity for `rotations="parent"`."""
    return g if tree.rotations == "parent" else Pose(relative_rotations(tree, g.R), g.p)


def fk_and_jacobian(tree: Tree, g: Pose) -> tuple[Pose, torch.Tensor]:
    """(FK(g) as SE(3)^B poses, A(g) (..., B, 6, dim))."""
    world = forward_kinematics(tree, g)
    return world, fk_jacobian(tree, g, world)


def step_coordinates(tree: Tree, reduced: bool, inc: Pose, q: Pose | None, q_next: Pose | None) -> torch.Tensor:
    """The coordinates of a rollout step, (N, n): the warm start's points (`extrapolate`). log(inc) of the
    coordinate increment on an unreduced tree; on a reduced one the joints' DoF d with advance(q, d) = q_next
    from the joint coordinates q, q_next at both ends: exact for every joint but a universal one (the log
    through the constant motion basis, `lie.joints.reduce_joint_velocity`; least squares in the mean basis
    with a universal joint)."""
    G = tree.group
    if not reduced:
        return G.log(inc)
    assert q is not None and q_next is not None
    return joints.reduce_joint_velocity(tree, q, q_next, G.log(G.increment(q, q_next)))


def extrapolate(d: torch.Tensor, d_prev: torch.Tensor) -> torch.Tensor:
    """The warm start of an implicit step from the coordinates of the last two increments, (N, n):
    2 d - d_prev (exact for a constant second difference, so the guess is off by O(h^3) rather than
    the last increment's O(h^2)); d on rows where that is not finite (a failed step never seeds the
    next guess)."""
    pred = 2.0 * d - d_prev
    return torch.where(torch.isfinite(pred).all(-1, keepdim=True), pred, d)
