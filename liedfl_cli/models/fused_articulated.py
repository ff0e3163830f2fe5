"""The articulated model's fused rollout engine: the implicit DEL step of a kinematic tree with no
Python per body or per joint.

The same step as `ArticulatedLieDFLNN`'s reference problem (`implicit_problem`, `_reduced_problem`):
the same residual, Jacobian, retraction, warm start and unknown (the coordinate increment
g_k^{-1} g_{k+1}), so the Newton iterates agree to rounding. What changes is how they are computed:

- Forward kinematics through the ancestor matrix M (B, B) (M[b, a] = 1 when a is b or one of its
  ancestors): body positions pw = M u with u_b = Rw_parent o_b the world bone vectors, so the only
  loop over depth levels is the product of parent-relative attitudes (trees stored that way).
- The FK Jacobian in the world frame, built directly in the n columns of the unknown (the joints'
  DoF on a reduced tree): rotation rows Theta = M own with own_b = Rw_b E_b (the world axes of b's
  joint), position rows P = M V with V_b = Theta_parent(b) x u_b. The reference builds A (dim
  columns, body frame) body by body, then multiplies by T(g) (dim x n).
- Residual and Jacobian with the body-frame kinetic terms moved to the world frame: covectors rotated
  per body (R_b c), r = X_k^T c_world; each body's 6 x 6 mixed-Hessian block conjugated to the world
  frame is [[R_k H_rot(W) R_n^T + s hat(a) hat(b), -s hat(a)], [s hat(b), -s I]] (a = R_k rho,
  b = R_n rho, s = m / h; `kinetic.se3_mixed_hessian`, H_rot linear in W), so
      J = sum_b Theta_k^T R_k H_rot R_n^T Theta_n - s Y_k^T Y_n,   Y = P - (R rho) x Theta
  (Y: the centre of mass's world velocity per column): one batched product over 6B rows.
- Joint damping: the reduced velocity estimate and its Jacobian per body (a joint's DoF move only its
  own relative rotation, so d nu / d delta is block diagonal), scattered into the n x n matrix.
- The Newton loop is `solvers.newton.solve`'s (with `restrict`, so at large batch the last
  iterations run on the rows still iterating); the poses and FK of the last retracted iterate are
  reused by the residual and the Jacobian at that iterate.

Applies (`applies`) to the fast residual, world potentials of uniform gravity (learned or declared)
and/or an MLP of the coordinates, every joint type (free, ball, universal, hinge, weld; a universal
joint's first axis turns with its parent, so its damping and forces take the least-squares rates of the
reference, `_joint_terms_moving_basis`), and joint-space forces on trees whose unknown moves the joints
(reduced, or stored with parent rotations). Other models keep the reference problem. Shapes: N
trajectories, B bodies, n the unknown's columns (the reduced DoF, or the coordinates' tangent dim on an
unreduced tree), m = 1 (free root) or 0.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from ..lie import Pose, se3, so3
from ..lie import joints as jt
from ..lie.tolerances import projects_poses
from ..lie.tree import Tree
from ..mechanics import kinetic
from ..mechanics.forces import force_jacobian_xi
from ..mechanics.potentials import GravityPotential, UniformGravityPotential
from ..solvers.newton import NewtonProblem
from . import mlp_derivatives

SUPPORTED_JOINTS = ("free", "ball", "universal", "hinge", "weld")


def applies(model) -> str | None:
    """None when the fused engine serves `model` (an `ArticulatedLieDFLNN`), else why not (one line)."""
    if model.residual_mode != "fast":
        return "residual=generic"
    if len(model.forces) and not (model.reduced or model.tree.rotations == "parent"):
        return "joint-space forces on an unreduced tree with world rotations"
    bad = [k for k in model.tree.joint_kinds if k not in SUPPORTED_JOINTS]
    if bad:
        return f"{bad[0]} joints (a motion basis that varies with the pose)"
    Vw = model.potential_world
    if Vw is not None and not isinstance(Vw, (UniformGravityPotential, GravityPotential)):
        return f"world potential {type(Vw).__name__}"
    return None


@dataclass
class TreeMaps:
    """What a rollout builds once (detached, on the data's dtype and device).

    ancestors (B, B): M[b, a] = 1 when a is b or an ancestor of b; parent_index (B,) (the root its own).
    levels: (bodies, their parents) per depth level below the root (long tensors). offsets (B, 3).
    E (B, 3, n): body b's rotation variation R_b exp(E_b d) in its moving coordinates; Vsel (3, n):
    the free root's translation columns. joint_mode: the unknown moves the joints (parent-relative
    rotations; reduced trees, and every tree stored with parent rotations) rather than the world
    attitudes of an unreduced world-rotation tree. Jd (B, 3, 3), mass (B,), rho (B, 3): the kinetic
    parameters; rot_map (B, 9, 9): W.flatten() @ rot_map = the body's rotational mixed-Hessian block.
    gamma (3,), first_moment (B, 3), gmass (B,): the world gravity's field and moments, or None.
    damping (n,) or None; Epad (B, 3, 3): each joint's columns padded to three; damp_index /
    damp_source: where the entries of every joint's own block of d nu / d delta go in the n x n matrix,
    and where they come from in (B, 3, 3)."""

    tree: Tree
    h: float
    ancestors: torch.Tensor
    parent_index: torch.Tensor
    levels: list[tuple[torch.Tensor, torch.Tensor]]
    offsets: torch.Tensor
    E: torch.Tensor
    Vsel: torch.Tensor
    U: torch.Tensor  # (B, 3, n): a universal joint's first axis, fixed in the parent's frame
    universal: bool  # some joint is universal (its motion basis depends on the pose)
    joint_mode: bool
    Jd: torch.Tensor
    mass: torch.Tensor
    rho: torch.Tensor
    rot_map: torch.Tensor
    gamma: torch.Tensor | None
    first_moment: torch.Tensor | None
    gmass: torch.Tensor | None
    damping: torch.Tensor | None
    Epad: torch.Tensor
    damp_index: torch.Tensor  # flat (row * n + col) of every rotational entry of a joint's own block
    damp_source: torch.Tensor  # flat (body * 9 + i * 3 + j) of the same entries in (B, 3, 3)
    reduced: bool
    mlp: object | None
    S0: torch.Tensor  # (dim, n): the joints' motion basis (orthonormal columns), I on an unreduced tree
    forces: list  # the model's joint-space forces (joint mode only)


def _columns(tree: Tree, reduced: bool) -> list[tuple[str, int]]:
    """(joint kind, first column) per body: the reduced DoF, or the coordinates' tangent layout."""
    if reduced:
        return [(k, s.start) for k, s in zip(tree.joint_kinds, jt.joint_slices(tree))]
    kinds = ("free" if tree.free_root else "ball",) + ("ball",) * (tree.n_bodies - 1)
    return [(k, s.start) for k, s in zip(kinds, tree.group.body_slices())]


@functools.lru_cache(maxsize=32)
def _static(tree: Tree, reduced: bool, dtype: torch.dtype, device: torch.device) -> dict:
    """The parameter-free constants of `TreeMaps` (cached per tree, layout, dtype and device)."""
    B = tree.n_bodies
    n = tree.n_dof if reduced else tree.group.dim
    ax = torch.tensor(tree.axes_array(), dtype=dtype, device=device)
    E = torch.zeros(B, 3, n, dtype=dtype, device=device)
    Epad = torch.zeros(B, 3, 3, dtype=dtype, device=device)
    U = torch.zeros(B, 3, n, dtype=dtype, device=device)
    Vsel = torch.zeros(3, n, dtype=dtype, device=device)
    eye = torch.eye(3, dtype=dtype, device=device)
    dof_body, dof_row = [], []
    for b, (kind, c) in enumerate(_columns(tree, reduced)):
        if kind in ("free", "ball"):
            E[b, :, c : c + 3] = eye
            Epad[b] = eye
            dof_body += [b] * 3
            dof_row += [0, 1, 2]
            if kind == "free":
                Vsel[:, c + 3 : c + 6] = eye
                dof_body += [b] * 3  # translation columns: never damped (a free root is undamped)
                dof_row += [-1, -1, -1]
        elif kind == "hinge":
            E[b, :, c] = ax[b, 0]
            Epad[b, :, 0] = ax[b, 0]
            dof_body.append(b)
            dof_row.append(0)
        elif kind == "universal":  # exp(d1 a1) R exp(d2 a2): a1 in the parent's frame, a2 in the body's
            U[b, :, c] = ax[b, 0]
            E[b, :, c + 1] = ax[b, 1]
            dof_body += [b, b]
            dof_row += [-1, -1]  # its basis moves: damping and forces take the general path
    # the rotational entries of every joint's own block of d nu / d delta (the damping's Jacobian)
    idx, src = [], []
    for i in range(n):
        for j in range(n):
            if dof_body[i] == dof_body[j] and dof_row[i] >= 0 and dof_row[j] >= 0:
                idx.append(i * n + j)
                src.append(dof_body[i] * 9 + dof_row[i] * 3 + dof_row[j])
    levels = [
        (
            torch.tensor(level, dtype=torch.long, device=device),
            torch.tensor([tree.parents[b] for b in level], dtype=torch.long, device=device),
        )
        for level in tree.levels[1:]
    ]
    anc = torch.zeros(B, B, dtype=dtype, device=device)
    for b in range(B):
        a = b
        while a >= 0:
            anc[b, a] = 1.0
            a = tree.parents[a]
    S0 = jt._maps(tree, dtype, device)["S0"] if reduced else torch.eye(n, dtype=dtype, device=device)
    return {
        "S0": S0,
        "ancestors": anc,
        "parent_index": torch.tensor([max(q, 0) for q in tree.parents], dtype=torch.long, device=device),
        "levels": levels,
        "offsets": torch.tensor(tree.offsets, dtype=dtype, device=device),
        "E": E,
        "Vsel": Vsel,
        "U": U,
        "universal": "universal" in [k for k, _ in _columns(tree, reduced)],
        "Epad": Epad,
        "damp_index": torch.tensor(idx, dtype=torch.long, device=device),
        "damp_source": torch.tensor(src, dtype=torch.long, device=device),
    }


def build_maps(model, like: torch.Tensor) -> TreeMaps:
    """The engine's constants for `model` on `like`'s dtype and device (its parameters detached)."""
    tree, h = model.tree, float(model.h)
    dt, dev = like.dtype, like.device
    B = tree.n_bodies
    reduced = bool(model.reduced)
    st = _static(tree, reduced, dt, dev)
    with torch.no_grad():
        Jd, mass, rho = (t.detach().to(like) for t in model._params())
        basis = torch.eye(9, dtype=dt, device=dev).reshape(9, 1, 3, 3).expand(9, B, 3, 3)
        # the rotational block alone (massless: the translational coupling is added in the world frame)
        hess = kinetic.se3_mixed_hessian(basis, Jd, torch.zeros_like(mass), rho, h)[..., :3, :3]  # (9, B, 3, 3)
        rot_map = hess.reshape(9, B, 9).transpose(0, 1).contiguous()
        gamma = first_moment = gmass = None
        Vw = model.potential_world
        if isinstance(Vw, UniformGravityPotential):
            gamma = Vw.field().detach().to(like)
            first_moment = Vw.first_moments().detach().to(like)
            gmass = Vw.mass().detach().to(like)
        elif isinstance(Vw, GravityPotential):
            gamma = torch.tensor([0.0, 0.0, float(Vw.gravity)], dtype=dt, device=dev)
            gmass = Vw.masses.detach().to(like)
            first_moment = gmass[:, None] * Vw.rhos.detach().to(like)
        damper = model.dof_damper
        damping = None if damper is None else damper.coefficients().detach().to(like)
    return TreeMaps(
        tree=tree,
        h=h,
        joint_mode=reduced or tree.rotations == "parent",
        Jd=Jd,
        mass=mass,
        rho=rho,
        rot_map=rot_map,
        gamma=gamma,
        first_moment=first_moment,
        gmass=gmass,
        damping=damping,
        reduced=reduced,
        mlp=model.potential_coord,
        forces=list(model.forces),
        **st,
    )


# ---------------------------------------------------------------------------- kinematics
def world_rotations(maps: TreeMaps, R: torch.Tensor) -> torch.Tensor:
    """The tree's stored attitudes R (N, B, 3, 3) -> world attitudes (N, B, 3, 3)."""
    return R if maps.tree.rotations == "world" else world_rotations_from_relative(maps, R)


def world_rotations_from_relative(maps: TreeMaps, Q: torch.Tensor) -> torch.Tensor:
    """Parent-relative attitudes (the root's its own) -> world attitudes: one product per depth level."""
    if not maps.levels:
        return Q
    Rw = Q.clone()
    for idx, par in maps.levels:
        Rw[:, idx] = Rw[:, par] @ Q[:, idx]
    return Rw


def forward_kinematics(maps: TreeMaps, g: Pose) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World poses of every body and the world bone vectors: (Rw (N, B, 3, 3), pw (N, B, 3), u (N, B, 3))
    with u_b = Rw_parent o_b = pw_b - pw_parent (the root's row: its position) and pw = M u
    (`lie.tree.forward_kinematics`)."""
    Rw = world_rotations(maps, g.R)
    N = Rw.shape[0]
    u = torch.einsum("Nbij,bj->Nbi", Rw[:, maps.parent_index], maps.offsets)
    root = g.p[:, 0] if maps.tree.free_root else maps.offsets[0].expand(N, 3)
    u = torch.cat((root[:, None], u[:, 1:]), 1)
    return Rw, maps.ancestors @ u, u


def _cross_columns(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """a x v column by column: a (..., 3, n), v (..., 3) -> (..., 3, n)."""
    a0, a1, a2 = a.unbind(-2)
    v0, v1, v2 = (x[..., None] for x in v.unbind(-1))
    return torch.stack((a1 * v2 - a2 * v1, a2 * v0 - a0 * v2, a0 * v1 - a1 * v0), -2)


def world_jacobian(maps: TreeMaps, Rw: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(Theta, P), each (N, B, 3, n): body b's world-frame rotation and the velocity of its origin per
    unit of the unknown's columns; the body-frame FK Jacobian A~ = A T is blockdiag(Rw_b^T, Rw_b^T)
    [Theta; P]."""
    own = torch.einsum("Nbij,bjn->Nbin", Rw, maps.E)  # world axes of each body's own joint
    if maps.universal:  # a universal joint's first axis turns with the parent (the world's for a root)
        eye = torch.eye(3, dtype=Rw.dtype, device=Rw.device).expand(Rw.shape[0], 1, 3, 3)
        Rp = torch.cat((eye, Rw[:, maps.parent_index[1:]]), 1)
        own = own + torch.einsum("Nbij,bjn->Nbin", Rp, maps.U)
    N, B, _, n = own.shape
    theta = (maps.ancestors @ own.reshape(N, B, 3 * n)).reshape(N, B, 3, n) if maps.joint_mode else own
    V = _cross_columns(theta[:, maps.parent_index], u)  # theta_parent x u_b (the root's row replaced)
    if maps.tree.free_root:
        V[:, 0] = Rw[:, 0] @ maps.Vsel
    else:
        V[:, 0] = 0.0
    P = (maps.ancestors @ V.reshape(N, B, 3 * n)).reshape(N, B, 3, n)
    return theta, P


def _rows(X: torch.Tensor) -> torch.Tensor:
    """(N, B, 3, n) -> (N, 3B, n)."""
    return X.reshape(X.shape[0], -1, X.shape[-1])


def covector_rows(Rw: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Body-frame covectors c (N, B, 6) -> their world-frame rotation and translation parts
    (R_b c_w, R_b c_v), each (N, 3B, 1)."""
    N, B = c.shape[0], c.shape[1]
    cw = (Rw[:, :, None] @ c.reshape(N, B, 2, 3, 1)).reshape(N, B, 2, 3)
    return cw[:, :, 0].reshape(N, 3 * B, 1), cw[:, :, 1].reshape(N, 3 * B, 1)


def pair(A: tuple[torch.Tensor, torch.Tensor], c: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Theta^T c_w + P^T c_v, (N, n): a world covector on the unknown's columns."""
    return (_rows(A[0]).transpose(-1, -2) @ c[0] + _rows(A[1]).transpose(-1, -2) @ c[1])[..., 0]


def stacked(A: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """[Theta; P]^T as one (N, n, 6B) factor (one batched product per use instead of two)."""
    return torch.cat((_rows(A[0]), _rows(A[1])), 1).transpose(1, 2)


def _world_increment(Rw, pw, Rw2, pw2) -> tuple[torch.Tensor, torch.Tensor]:
    """(W, z) = FK_k^{-1} FK_{k+1} per body: W (N, B, 3, 3), z (N, B, 3)."""
    Rt = Rw.transpose(-1, -2)
    return Rt @ Rw2, (Rt @ (pw2 - pw)[..., None])[..., 0]


def kinetic_d1(maps: TreeMaps, W: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Every body's covector D1 K (N, B, 6), body frame (`kinetic.kinetic_d1` on SE(3)^B)."""
    Jd, rho, h = maps.Jd, maps.rho, maps.h
    w = so3.vee(Jd @ W.transpose(-1, -2) - W @ Jd) / h
    Wrho = (W @ rho[:, :, None])[..., 0]
    X = z + Wrho - rho
    s = (maps.mass / h)[:, None]
    w = w + s * torch.linalg.cross(X, z + Wrho, dim=-1)
    return torch.cat((w, -s * X), -1)


def kinetic_d2(maps: TreeMaps, W: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Every body's covector D2 K (N, B, 6), body frame (`kinetic.kinetic_d2` on SE(3)^B)."""
    Jd, rho, h = maps.Jd, maps.rho, maps.h
    w = so3.vee(Jd @ W - W.transpose(-1, -2) @ Jd) / h
    X = z + (W @ rho[:, :, None])[..., 0] - rho
    WtX = (W.transpose(-1, -2) @ X[..., None])[..., 0]
    s = (maps.mass / h)[:, None]
    w = w + s * torch.linalg.cross(rho.expand_as(WtX), WtX, dim=-1)
    return torch.cat((w, s * WtX), -1)


def rotational_world(maps: TreeMaps, Rk: torch.Tensor, Rn: torch.Tensor) -> torch.Tensor:
    """Every body's rotational mixed-Hessian block in the world frame, R_k H_rot(R_k^T R_n) R_n^T
    (N, B, 3, 3) (`kinetic.se3_mixed_hessian`'s massless part, linear in W: `TreeMaps.rot_map`)."""
    N, B = Rk.shape[0], Rk.shape[1]
    W = Rk.transpose(-1, -2) @ Rn
    Hrot = torch.einsum("Nbk,bkl->Nbl", W.reshape(N, B, 9), maps.rot_map).reshape(N, B, 3, 3)
    return Rk @ Hrot @ Rn.transpose(-1, -2)


# ---------------------------------------------------------------------------- joints
def moving_coordinates(maps: TreeMaps, g: Pose, Rw: torch.Tensor | None = None) -> Pose:
    """The coordinates the unknown moves: joint coordinates (parent-relative attitudes) in joint mode,
    else the tree's own. Rw: g's world attitudes when known."""
    if maps.joint_mode and maps.tree.rotations == "world":
        Rw = g.R if Rw is None else Rw
        Q = Rw[:, maps.parent_index].transpose(-1, -2) @ Rw
        return Pose(torch.cat((Rw[:, :1], Q[:, 1:]), 1), g.p)
    return g


def from_moving(maps: TreeMaps, q: Pose) -> Pose:
    """Inverse of `moving_coordinates`."""
    if maps.joint_mode and maps.tree.rotations == "world":
        return Pose(world_rotations_from_relative(maps, q.R), q.p)
    return q


def advance(maps: TreeMaps, q: Pose, d: torch.Tensor) -> Pose:
    """Move the moving coordinates q by d (N, n) (`lie.joints.advance`): R_b exp(E_b d), the free
    root's position by R_0 V(w) v."""
    N, B = q.R.shape[0], q.R.shape[1]
    w = (d @ maps.E.reshape(B * 3, -1).T).reshape(N, B, 3)
    R = q.R @ so3.exp(w)
    if maps.universal:
        R = so3.exp((d @ maps.U.reshape(B * 3, -1).T).reshape(N, B, 3)) @ R
    p = q.p
    if maps.tree.free_root:
        w0, v0 = w[:, 0], d @ maps.Vsel.T
        p = p + (q.R[:, 0] @ (se3.V_matrix(w0) @ v0[..., None]))[..., 0][:, None, :]
    return Pose(R, p)


def compose(g: Pose, x: Pose) -> Pose:
    """g x on the tree's coordinates (`ProductGroup.compose`)."""
    m = g.p.shape[1]
    return Pose(g.R @ x.R, g.p + (g.R[:, :m] @ x.p[..., None])[..., 0])


def increment(g: Pose, g2: Pose) -> Pose:
    """g^{-1} g2 on the tree's coordinates (`ProductGroup.increment`)."""
    m = g.p.shape[1]
    Rt = g.R.transpose(-1, -2)
    return Pose(Rt @ g2.R, (Rt[:, :m] @ (g2.p - g.p)[..., None])[..., 0])


def joint_velocity(maps: TreeMaps, q: Pose, q2: Pose) -> torch.Tensor:
    """The joint-coordinate velocity estimate nu~ (N, dim) of the interval (q, q2) in the coordinates'
    tangent layout (`kinetic.velocity_estimate` of the increment q^{-1} q2); its DoF rates are
    nu~ @ S0 (`articulated.reduced_velocity`: S0's columns are orthonormal)."""
    h = maps.h
    W = q.R.transpose(-1, -2) @ q2.R
    w = so3.vee(W) / h  # (N, B, 3)
    N = w.shape[0]
    if not maps.tree.free_root:
        return w.reshape(N, -1)
    z = (q.R[:, 0].transpose(-1, -2) @ (q2.p[:, 0] - q.p[:, 0])[..., None])[..., 0]
    v = (z - 0.5 * h * torch.linalg.cross(w[:, 0], z, dim=-1)) / h
    return torch.cat((w[:, 0], v, w[:, 1:].reshape(N, -1)), -1)


def damping_jacobian(maps: TreeMaps, W: torch.Tensor) -> torch.Tensor:
    """-(h/2) diag(d) d nu / d delta (N, n, n) on the damped (rotational) DoF: per body
    E_pad^T (tr(W) I - W^T) E_pad / (2h) (`kinetic.velocity_estimate_jacobian`)."""
    assert maps.damping is not None
    h = maps.h
    tr = W.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    eye = torch.eye(3, dtype=W.dtype, device=W.device)
    blocks = torch.einsum("bia,Nbij,bjc->Nbac", maps.Epad, (tr * eye - W.transpose(-1, -2)) / (2 * h), maps.Epad)
    N, n = W.shape[0], maps.damping.shape[0]
    vals = blocks.reshape(N, -1)[:, maps.damp_source]
    coeff = (-0.5 * h * maps.damping)[maps.damp_index // n]
    out = W.new_zeros(N, n * n)
    out[:, maps.damp_index] = coeff * vals
    return out.reshape(N, n, n)


# ---------------------------------------------------------------------------- the step
@dataclass
class Frame:
    """A pose of the tree and what the step reads at it: g (tree coordinates), its moving coordinates
    q, FK (Rw, pw, bone vectors u) and, once asked for, the world Jacobian X (N, B, 6, n)."""

    g: Pose
    q: Pose
    Rw: torch.Tensor
    pw: torch.Tensor
    u: torch.Tensor
    X: tuple[torch.Tensor, torch.Tensor] | None = None
    Y: torch.Tensor | None = None

    @classmethod
    def at(cls, maps: TreeMaps, g: Pose, q: Pose | None = None) -> Frame:
        Rw, pw, u = forward_kinematics(maps, g)
        return cls(g, moving_coordinates(maps, g, Rw) if q is None else q, Rw, pw, u)

    def jacobian(self, maps: TreeMaps) -> tuple[torch.Tensor, torch.Tensor]:
        """(Theta, P) at this pose (`world_jacobian`), computed once."""
        if self.X is None:
            self.X = world_jacobian(maps, self.Rw, self.u)
        return self.X

    def com_jacobian(self, maps: TreeMaps) -> torch.Tensor:
        """Y (N, B, 3, n): the world velocity of every body's centre of mass per unit column,
        P - (Rw rho) x Theta."""
        if self.Y is None:
            theta, P = self.jacobian(maps)
            arm = torch.einsum("Nbij,bj->Nbi", self.Rw, maps.rho)  # (N, B, 3): Rw rho
            self.Y = _cross_columns(theta, arm).add_(P)  # P + Theta x (Rw rho)
        return self.Y

    def index(self, rows: torch.Tensor) -> Frame:
        return Frame(
            self.g.index(rows),
            self.q.index(rows),
            self.Rw[rows],
            self.pw[rows],
            self.u[rows],
            None if self.X is None else (self.X[0][rows], self.X[1][rows]),
            None if self.Y is None else self.Y[rows],
        )


@dataclass
class FusedArticulatedState:
    """Rollout state: g_{k-1} and the frame of g_k, the last increment g_{k-1}^{-1} g_k (the warm start),
    the residual's constant part at g_k (N, n), and the engine."""

    g_prev: Pose
    frame: Frame
    inc: Pose
    const: torch.Tensor
    engine: ArticulatedEngine

    @property
    def g(self) -> Pose:
        return self.frame.g

    def index(self, rows: torch.Tensor) -> FusedArticulatedState:
        return FusedArticulatedState(
            self.g_prev.index(rows), self.frame.index(rows), self.inc.index(rows), self.const[rows], self.engine
        )


class ArticulatedEngine:
    """The fused rollout of one model (its parameters read once, `build_maps`)."""

    def __init__(self, model, like: torch.Tensor):
        self.model = model
        self.maps = build_maps(model, like)

    def _const(self, prev: Frame, cur: Frame) -> torch.Tensor:
        """D2 L_d(g_prev, g) + the potentials at g + (h/2) tau(g_prev, g), reduced (N, n)."""
        maps = self.maps
        c = kinetic_d2(maps, *_world_increment(prev.Rw, prev.pw, cur.Rw, cur.pw))
        if maps.gamma is not None:
            assert maps.first_moment is not None and maps.gmass is not None
            up = torch.einsum("Nbji,j->Nbi", cur.Rw, maps.gamma)  # (N, B, 3): R^T gamma
            fm = maps.first_moment.expand_as(up)
            c = c - maps.h * torch.cat((torch.linalg.cross(fm, up, dim=-1), maps.gmass[:, None] * up), -1)
        r = pair(cur.jacobian(maps), covector_rows(cur.Rw, c))
        if maps.mlp is not None:
            r = r + self._coordinate_potential(cur.g)
        return r + self._joint_terms(prev.q, cur.q, cur.q)

    def _joint_terms(self, q: Pose, q2: Pose, at: Pose) -> torch.Tensor | float:
        """(h/2) of the joint-space forces and damping of the interval (q, q2), on the unknown's columns
        at g_k (joint coordinates `at`), (N, n): S0^T sum_f F(q, nu~) - d nu~ S0 (T_k^T C_k^T = S(q_k)^T:
        the reference's T(g_k)^T and C(g_k)^T together); 0 without either."""
        maps = self.maps
        if maps.damping is None and not maps.forces:
            return 0.0
        if maps.universal:
            return self._joint_terms_moving_basis(q, q2, at)
        nu = joint_velocity(maps, q, q2)
        tau = nu.new_zeros(nu.shape[0], maps.S0.shape[1])
        if maps.forces:
            F = maps.forces[0](q, nu)
            for force in maps.forces[1:]:
                F = F + force(q, nu)
            tau = tau + F @ maps.S0
        if maps.damping is not None:
            tau = tau - maps.damping * (nu @ maps.S0)
        return 0.5 * maps.h * tau

    def _joint_jacobian(self, q: Pose, q2: Pose) -> torch.Tensor | float:
        """d `_joint_terms`(q, q2) / d delta (N, n, n) with q2 advanced along the joints by delta."""
        maps = self.maps
        if maps.damping is None and not maps.forces:
            return 0.0
        if maps.universal:
            return self._joint_jacobian_moving_basis(q, q2)
        W = q.R.transpose(-1, -2) @ q2.R
        J = damping_jacobian(maps, W) if maps.damping is not None else 0.0
        if maps.forces:
            G = maps.tree.group
            inc = increment(q, q2)
            nu = joint_velocity(maps, q, q2)
            dF = force_jacobian_xi(maps.forces[0], q, nu)
            for force in maps.forces[1:]:
                dF = dF + force_jacobian_xi(force, q, nu)
            dnu = kinetic.velocity_estimate_jacobian(G, inc, maps.h)
            J = J + 0.5 * maps.h * (maps.S0.T @ dF @ dnu @ maps.S0)
        return J

    def _joint_terms_moving_basis(self, q: Pose, q2: Pose, at: Pose) -> torch.Tensor:
        """`_joint_terms` with a universal joint: the forces through S(q_k)^T (T_k^T C_k^T at `at`), the
        DoF rates by least squares on the mean basis of both ends (`lie.joints.reduce_joint_velocity`)."""
        maps, tree = self.maps, self.maps.tree
        nu = joint_velocity(maps, q, q2)
        tau = nu.new_zeros(nu.shape[0], tree.n_dof)
        if maps.forces:
            F = maps.forces[0](q, nu)
            for force in maps.forces[1:]:
                F = F + force(q, nu)
            tau = tau + (F[:, None, :] @ jt.motion_basis(tree, at))[:, 0]
        if maps.damping is not None:
            tau = tau - maps.damping * jt.reduce_joint_velocity(tree, q, q2, nu)
        return 0.5 * maps.h * tau

    def _joint_jacobian_moving_basis(self, q: Pose, q2: Pose) -> torch.Tensor:
        """d `_joint_terms_moving_basis` / d delta: S(q)^T dF dnu S(q2) and the damping's least-squares
        rates with both bases held fixed (`articulated.reduced_velocity_jacobian`)."""
        maps, tree = self.maps, self.maps.tree
        dnu = kinetic.velocity_estimate_jacobian(tree.group, increment(q, q2), maps.h)
        S2 = jt.motion_basis(tree, q2)
        J = dnu.new_zeros(dnu.shape[0], tree.n_dof, tree.n_dof)
        if maps.damping is not None:
            dred = jt.reduce_joint_velocity(tree, q, q2, dnu @ S2, columns=True)
            J = J - 0.5 * maps.h * maps.damping[:, None] * dred
        if maps.forces:
            nu = joint_velocity(maps, q, q2)
            dF = force_jacobian_xi(maps.forces[0], q, nu)
            for force in maps.forces[1:]:
                dF = dF + force_jacobian_xi(force, q, nu)
            J = J + 0.5 * maps.h * (jt.motion_basis(tree, q).transpose(-1, -2) @ dF @ dnu @ S2)
        return J

    def _coordinate_potential(self, g: Pose) -> torch.Tensor:
        """-h dV_coord at g for the MLP of the coordinates, reduced by T(g)^T on a reduced tree."""
        model, maps = self.model, self.maps
        closed = mlp_derivatives.mlp_potential_covector(maps.mlp, model.G, g, maps.h)
        if closed is None:
            from torch.func import grad

            Vc = maps.mlp
            eta = g.R.new_zeros(g.R.shape[0], model.G.dim)
            with torch.enable_grad():
                closed = -maps.h * grad(lambda e: Vc(model.G.perturb(g, e)).sum())(eta)  # type: ignore[operator]
        if not maps.reduced:
            return closed
        T = jt.coordinate_basis(maps.tree, g)
        return (T.transpose(-1, -2) @ closed[..., None])[..., 0]

    def start(self, g0: Pose, g1: Pose) -> FusedArticulatedState:
        maps = self.maps
        cur = Frame.at(maps, g1)
        const = self._const(Frame.at(maps, g0), cur)
        return FusedArticulatedState(g0, cur, increment(g0, g1), const, self)

    def _warm_start(self, s: FusedArticulatedState) -> Pose:
        """The reference's warm start: the last increment (unreduced), or its DoF by least squares
        applied along the joints at g_k (`ArticulatedLieDFLNN._reduced_problem`)."""
        maps, model = self.maps, self.model
        if not maps.reduced:
            return s.inc
        xi = model.G.log(s.inc)
        tree, q = maps.tree, s.frame.q
        if tree.n_dof != tree.group.dim:  # hinge or weld joints: least squares on T(g_k)
            d0 = jt.reduce(jt.coordinate_basis(tree, s.g), xi)
        elif tree.rotations == "parent":  # every joint a ball: T = I
            d0 = xi
        else:  # every joint a ball on a world-rotation tree: T = C^{-1}, so d0 = C xi exactly
            w, v = model.G.split(xi)
            wp = (q.R.transpose(-1, -2) @ w[:, maps.parent_index][..., None])[..., 0]  # R_rel^T w_parent
            wj = torch.cat((w[:, :1], w[:, 1:] - wp[:, 1:]), 1)
            d0 = model.G.join(wj, v)
        return increment(s.g, from_moving(maps, advance(maps, q, d0)))

    def problem(self, s: FusedArticulatedState, x0: Pose | None = None) -> NewtonProblem:
        maps, cur = self.maps, s.frame
        last: list = [None, None]  # (x, its Frame): the last iterate made or read
        cached: list = [None]  # the Jacobian's left factor at g_k

        def frame(x: Pose) -> Frame:
            if last[0] is not x:
                last[0], last[1] = x, Frame.at(maps, compose(cur.g, x))
            return last[1]

        def f(x: Pose) -> torch.Tensor:
            nxt = frame(x)
            c = kinetic_d1(maps, *_world_increment(cur.Rw, cur.pw, nxt.Rw, nxt.pw))
            cw, cv = covector_rows(cur.Rw, c)
            r = s.const + (left()[0] @ torch.cat((cw, cv), 1))[..., 0]
            return r + self._joint_terms(cur.q, nxt.q, cur.q)

        def jac(x: Pose) -> torch.Tensor:
            # blockdiag(H_world) in closed form (module docstring): the rotational blocks
            # Theta_k^T R_k H_rot(W) R_n^T Theta_n, and the translational ones -(m/h) Y_k^T Y_n with Y
            # the centre of mass's world velocity per column
            nxt = frame(x)
            Tn = nxt.jacobian(maps)[0]
            N, B, _, n = Tn.shape
            HT = torch.bmm(rotational_world(maps, cur.Rw, nxt.Rw).reshape(N * B, 3, 3), Tn.reshape(N * B, 3, n))
            right = torch.cat((HT.reshape(N, 3 * B, n), _rows(nxt.com_jacobian(maps)).neg()), 1)
            return torch.bmm(left()[1], right) + self._joint_jacobian(cur.q, nxt.q)

        def left() -> tuple[torch.Tensor, torch.Tensor]:
            """At g_k, once per step: [Theta_k; P_k]^T (the residual's) and [Theta_k; (m/h) Y_k]^T (the
            Jacobian's), each (N, n, 6B)."""
            if cached[0] is None:
                s_ = (maps.mass / maps.h)[:, None, None]
                theta = cur.jacobian(maps)[0]
                cached[0] = (stacked(cur.jacobian(maps)), stacked((theta, s_ * cur.com_jacobian(maps))))
            return cached[0]

        def retract(x: Pose, delta: torch.Tensor) -> Pose:
            q_next = advance(maps, frame(x).q, delta)
            g_next = from_moving(maps, q_next)
            x_next = increment(cur.g, g_next)
            last[0], last[1] = x_next, Frame.at(maps, g_next, q_next)
            return x_next

        def restrict(rows: torch.Tensor) -> NewtonProblem:
            return self.problem(s.index(rows), x0=s.inc.index(rows))

        return NewtonProblem(f, jac, self._warm_start(s) if x0 is None else x0, retract, restrict=restrict)

    def advance(self, s: FusedArticulatedState, x: Pose) -> tuple[FusedArticulatedState, Pose]:
        """The reference's `implicit_advance`: the increment's rotations re-orthonormalised (one
        Newton-Schulz step), g_{k+1} = g_k inc, and the next step's frame and constant part."""
        maps = self.maps
        W = x.R.detach()
        W = 0.5 * W @ (3.0 * torch.eye(3, dtype=W.dtype, device=W.device) - W.transpose(-1, -2) @ W)
        inc = Pose(W, x.p.detach())
        g_next = compose(s.g, inc)
        if projects_poses(W.dtype):
            g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
        nxt = Frame.at(maps, g_next)
        return FusedArticulatedState(s.g, nxt, inc, self._const(s.frame, nxt), self), g_next
