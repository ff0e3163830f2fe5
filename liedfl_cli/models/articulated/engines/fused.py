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
  (Y: the centre of mass's world velocity per column): two batched products over 3B rows each,
  accumulated into one buffer.
- Joint damping and joint-space forces through the reference's own joint maps (`lie.joints`,
  `kinetic.velocity_estimate(_jacobian)`), with T_k^T C_k^T = S(q_k)^T: no C and no T in the step; the
  damping Jacobian of joints with a constant basis block by block (`add_damping_jacobian`).
- Group operations, joint coordinates, the joints' retraction, the kinetic covectors and the warm start
  are the package's own (`ProductGroup`, `lie.joints`, `mechanics.kinetic`, `mechanics.articulated`).
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
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ....lie import Pose, ProductGroup, so3
from ....lie import joints as jt
from ....lie.tolerances import projects_poses
from ....lie.tree import Tree
from ....mechanics import articulated as art
from ....mechanics import kinetic
from ....mechanics.forces import force_jacobian_xi
from ....mechanics.potentials import GravityPotential, UniformGravityPotential
from ....solvers.newton import NewtonProblem

SUPPORTED_JOINTS = ("free", "ball", "universal", "hinge", "weld")


def applies(model) -> str | None:
    """None when the fused engine serves `model` (an `ArticulatedLieDFLNN`), else why not (one line)."""
    if not model.residual_form.closed_form:  # the engine is the closed form batched
        return f"residual={model.residual_mode}"
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

    ancestors (B, B): M[b, a] = 1 when a is b or an ancestor of b; parent_index (B,) (the root its own);
    offsets (B, 3). E, U (B, 3, n), V (3, n): the joints' maps of `lie.joints` (a body's own axes in its
    frame, a universal joint's first axis in the parent's, the free root's translation columns).
    joint_mode: the unknown moves the joints (parent-relative rotations; reduced trees, and every tree
    stored with parent rotations) rather than the world attitudes of an unreduced world-rotation tree.
    Jd (B, 3, 3), mass (B,), rho (B, 3): the kinetic parameters; rot_map (B, 9, 9): W.flatten() @
    rot_map = the body's rotational mixed-Hessian block. gamma (3,), first_moment (B, 3), gmass (B,):
    the world gravity's field and moments, or None. damping (n,) or None; forces: the joint-space forces.
    Epad, damp_index, damp_source: the damping Jacobian's blocks (`add_damping_jacobian`)."""

    tree: Tree
    h: float
    ancestors: torch.Tensor
    parent_index: torch.Tensor
    offsets: torch.Tensor
    E: torch.Tensor
    U: torch.Tensor
    V: torch.Tensor
    universal: bool
    Epad: torch.Tensor  # (B, 3, 3)
    damp_index: torch.Tensor  # flat (row * n + col) of each ball / hinge joint's block entries
    damp_source: torch.Tensor  # flat (body * 9 + i * 3 + j) of the same entries in (B, 3, 3)
    joint_mode: bool
    Jd: torch.Tensor
    mass: torch.Tensor
    rho: torch.Tensor
    rot_map: torch.Tensor
    gamma: torch.Tensor | None
    first_moment: torch.Tensor | None
    gmass: torch.Tensor | None
    damping: torch.Tensor | None
    reduced: bool
    forces: list


@functools.lru_cache(maxsize=32)
def _static(tree: Tree, dtype: torch.dtype, device: torch.device) -> dict:
    """The parameter-free constants of `TreeMaps` (cached per tree, dtype and device). The unknown's
    columns are the joints' DoF (`lie.joints.joint_slices`); on an unreduced tree every joint is a ball
    and they are the coordinates' tangent layout."""
    B = tree.n_bodies
    anc = torch.zeros(B, B, dtype=dtype, device=device)
    for b in range(B):
        a = b
        while a >= 0:
            anc[b, a] = 1.0
            a = tree.parents[a]
    maps = jt._maps(tree, dtype, device)
    # every ball or hinge joint's rotational block of d nu / d delta: its axes padded to three columns (Epad)
    # and where the block's entries go in the n x n matrix (a universal joint's basis moves: not here)
    ax = torch.tensor(tree.axes_array(), dtype=dtype, device=device)
    Epad = torch.zeros(B, 3, 3, dtype=dtype, device=device)
    idx, src = [], []
    n = tree.n_dof
    for b, (kind, c) in enumerate(zip(tree.joint_kinds, jt.joint_slices(tree))):
        k = {"free": 3, "ball": 3, "hinge": 1}.get(kind, 0)
        Epad[b, :, :k] = torch.eye(3, dtype=dtype, device=device)[:, :k] if kind != "hinge" else ax[b, 0][:, None]
        idx += [(c.start + i) * n + c.start + j for i in range(k) for j in range(k)]
        src += [b * 9 + i * 3 + j for i in range(k) for j in range(k)]
    return {
        "Epad": Epad,
        "damp_index": torch.tensor(idx, dtype=torch.long, device=device),
        "damp_source": torch.tensor(src, dtype=torch.long, device=device),
        "ancestors": anc,
        "parent_index": torch.tensor([max(q, 0) for q in tree.parents], dtype=torch.long, device=device),
        "offsets": tree.offsets_tensor(anc),
        "E": maps["E"],
        "U": maps["U"],
        "V": maps["V"],
        "universal": "universal" in tree.joint_kinds,
    }


def build_maps(model, like: torch.Tensor) -> TreeMaps:
    """The engine's constants for `model` on `like`'s dtype and device (its parameters detached)."""
    tree, h = model.tree, float(model.h)
    dt, dev = like.dtype, like.device
    B = tree.n_bodies
    reduced = bool(model.reduced)
    st = _static(tree, dt, dev)
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
        forces=list(model.forces),
        **st,
    )


# ---------------------------------------------------------------------------- kinematics
def world_rotations(maps: TreeMaps, R: torch.Tensor) -> torch.Tensor:
    """The tree's stored attitudes R (N, B, 3, 3) -> world attitudes (N, B, 3, 3)."""
    return R if maps.tree.rotations == "world" else jt.world_from_parent(maps.tree, R)


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


def _cross_columns(a: torch.Tensor, v: torch.Tensor, base: torch.Tensor | None = None) -> torch.Tensor:
    """a x v column by column (+ base): a (..., 3, n), v (..., 3), base (..., 3, n) -> (..., 3, n).
    Written row by row into one buffer (a multiply and a fused multiply-subtract per row): no
    temporaries and no stack, 1.3x the stacked form at batch 1,000 (docs/benchmarks.md)."""
    a0, a1, a2 = a.unbind(-2)
    v0, v1, v2 = (x[..., None] for x in v.unbind(-1))
    out = torch.empty_like(a) if base is None else base.clone()
    o0, o1, o2 = out.unbind(-2)
    for o, x, y, z, w in ((o0, a1, v2, a2, v1), (o1, a2, v0, a0, v2), (o2, a0, v1, a1, v0)):
        if base is None:
            torch.mul(x, y, out=o)
        else:
            o.addcmul_(x, y)
        o.addcmul_(z, w, value=-1.0)
    return out


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
        V[:, 0] = Rw[:, 0] @ maps.V
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


def body_covector(d: Callable, maps: TreeMaps, a: Frame, b: Frame) -> torch.Tensor:
    """`kinetic.kinetic_d1` or `kinetic_d2` (d) of every body as a free SE(3) body over the world
    increments FK(a)^-1 FK(b), (N, B, 6) (w, v)."""
    N, B = a.Rw.shape[0], a.Rw.shape[1]
    Gw = ProductGroup(B, 0)  # `mechanics.articulated.world_group`
    inc = Gw.increment(Pose(a.Rw, a.pw), Pose(b.Rw, b.pw))
    return d(Gw, inc, maps.Jd, maps.mass, maps.rho, maps.h).reshape(N, B, 6)


def rotational_world(maps: TreeMaps, Rk: torch.Tensor, Rn: torch.Tensor) -> torch.Tensor:
    """Every body's rotational mixed-Hessian block in the world frame, R_k H_rot(R_k^T R_n) R_n^T
    (N, B, 3, 3) (`kinetic.se3_mixed_hessian`'s massless part, linear in W: `TreeMaps.rot_map`)."""
    N, B = Rk.shape[0], Rk.shape[1]
    W = Rk.transpose(-1, -2) @ Rn
    Hrot = torch.einsum("Nbk,bkl->Nbl", W.reshape(N, B, 9), maps.rot_map).reshape(N, B, 3, 3)
    return Rk @ Hrot @ Rn.transpose(-1, -2)


# ---------------------------------------------------------------------------- joints
def moving_coordinates(maps: TreeMaps, g: Pose) -> Pose:
    """The coordinates the unknown moves: joint coordinates (parent-relative attitudes) in joint mode,
    else the tree's own."""
    return jt.to_joint_coordinates(maps.tree, g) if maps.joint_mode else g


def from_moving(maps: TreeMaps, q: Pose) -> Pose:
    """Inverse of `moving_coordinates`."""
    return jt.from_joint_coordinates(maps.tree, q) if maps.joint_mode else q


def add_damping_jacobian(maps: TreeMaps, W: torch.Tensor, J: torch.Tensor) -> torch.Tensor:
    """J (N, n, n, contiguous) += -(h/2) diag(d) d nu_red / d delta, in place, for joints with a constant
    basis: the rotational blocks (tr(W) I - W^T) / (2h) of `kinetic.velocity_estimate_jacobian` (W: the
    joints' rotation increments), each only on its own joint's DoF (E_pad^T . E_pad), added at their
    entries instead of a dense dim x dim product and sum (the hot path of a damped tree; the free root is
    not damped). Returns J."""
    assert maps.damping is not None
    h, n = maps.h, maps.damping.shape[0]
    tr = W.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    eye = torch.eye(3, dtype=W.dtype, device=W.device)
    blocks = torch.einsum("bia,Nbij,bjc->Nbac", maps.Epad, (tr * eye - W.transpose(-1, -2)) / (2 * h), maps.Epad)
    N = W.shape[0]
    values = (-0.5 * h * maps.damping)[maps.damp_index // n] * blocks.reshape(N, -1)[:, maps.damp_source]
    J.view(N, n * n).index_add_(1, maps.damp_index, values)
    return J


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
        return cls(g, moving_coordinates(maps, g) if q is None else q, Rw, pw, u)

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
            self.Y = _cross_columns(theta, arm, base=P)  # P + Theta x (Rw rho)
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
    """Rollout state: g_{k-1} and the frame of g_k, the last increment g_{k-1}^{-1} g_k, the residual's
    constant part at g_k (N, n), the engine, and the warm start's points: the last increment's
    coordinates `dof` (N, n) and the previous one's `dof_prev` (None on the first step;
    `ArticulatedLieDFLNN.increment_coordinates`)."""

    g_prev: Pose
    frame: Frame
    inc: Pose
    const: torch.Tensor
    engine: ArticulatedEngine
    dof: torch.Tensor
    dof_prev: torch.Tensor | None = None

    @property
    def g(self) -> Pose:
        return self.frame.g

    def index(self, rows: torch.Tensor) -> FusedArticulatedState:
        return FusedArticulatedState(
            self.g_prev.index(rows),
            self.frame.index(rows),
            self.inc.index(rows),
            self.const[rows],
            self.engine,
            self.dof[rows],
            None if self.dof_prev is None else self.dof_prev[rows],
        )


class ArticulatedEngine:
    """The fused rollout of one model (its parameters read once, `build_maps`)."""

    def __init__(self, model, like: torch.Tensor):
        self.model = model
        self.maps = build_maps(model, like)

    def _const(self, prev: Frame, cur: Frame) -> torch.Tensor:
        """D2 L_d(g_prev, g) + the potentials at g + (h/2) tau(g_prev, g), reduced (N, n)."""
        maps = self.maps
        c = body_covector(kinetic.kinetic_d2, maps, prev, cur)
        if maps.gamma is not None:
            assert maps.first_moment is not None and maps.gmass is not None
            up = torch.einsum("Nbji,j->Nbi", cur.Rw, maps.gamma)  # (N, B, 3): R^T gamma
            fm = maps.first_moment.expand_as(up)
            c = c - maps.h * torch.cat((torch.linalg.cross(fm, up, dim=-1), maps.gmass[:, None] * up), -1)
        r = pair(cur.jacobian(maps), covector_rows(cur.Rw, c))
        if self.model.potential_coord is not None:
            r = r + self._coordinate_potential(cur.g)
        return r + self._joint_terms(prev.q, cur.q, cur.q)

    def _joint_terms(self, q: Pose, q2: Pose, at: Pose) -> torch.Tensor | float:
        """(h/2) of the joint-space forces and damping of the interval (q, q2) on the unknown's columns at
        g_k (joint coordinates `at`), (N, n): S(q_k)^T sum_f F(q, nu~) - d nu_red (the reference's T(g_k)^T
        C(g_k)^T is S(q_k)^T; `articulated.reduced_velocity`); 0 without either."""
        maps, tree = self.maps, self.maps.tree
        if maps.damping is None and not maps.forces:
            return 0.0
        G = tree.group
        nu = kinetic.velocity_estimate(G, G.increment(q, q2), maps.h)
        tau = nu.new_zeros(nu.shape[0], maps.E.shape[-1])
        if maps.forces:
            F = maps.forces[0](q, nu)
            for force in maps.forces[1:]:
                F = F + force(q, nu)
            tau = tau + (F[:, None, :] @ jt.motion_basis(tree, at))[:, 0]
        if maps.damping is not None:
            tau = tau - maps.damping * jt.reduce_joint_velocity(tree, q, q2, nu)
        return 0.5 * maps.h * tau

    def _joint_jacobian(self, q: Pose, q2: Pose, J: torch.Tensor) -> torch.Tensor:
        """J (N, n, n, contiguous) + d `_joint_terms`(q, q2, q) / d delta with q2 advanced along the joints
        by delta: S(q)^T dF dnu S(q2) and the damping's rates with the bases held fixed
        (`articulated.reduced_velocity_jacobian`); J itself (updated in place) in the common case."""
        maps, tree = self.maps, self.maps.tree
        if maps.damping is None and not maps.forces:
            return J
        G = tree.group
        if maps.damping is not None and not maps.forces and not maps.universal:  # the common case, sparse
            return add_damping_jacobian(maps, q.R.transpose(-1, -2) @ q2.R, J)
        inc = G.increment(q, q2)
        dnu = kinetic.velocity_estimate_jacobian(G, inc, maps.h)
        S2 = jt.motion_basis(tree, q2)
        if maps.damping is not None:
            dred = jt.reduce_joint_velocity(tree, q, q2, dnu @ S2, columns=True)
            J = J - 0.5 * maps.h * maps.damping[:, None] * dred
        if maps.forces:
            nu = kinetic.velocity_estimate(G, inc, maps.h)
            dF = force_jacobian_xi(maps.forces[0], q, nu)
            for force in maps.forces[1:]:
                dF = dF + force_jacobian_xi(force, q, nu)
            J = J + 0.5 * maps.h * (jt.motion_basis(tree, q).transpose(-1, -2) @ dF @ dnu @ S2)
        return J

    def _coordinate_potential(self, g: Pose) -> torch.Tensor:
        """-h dV_coord at g of the potential of the coordinates (the model's own `potential_covector`, no
        world part), reduced by T(g)^T on a reduced tree."""
        maps = self.maps
        cov = self.model.potential_covector(g, None, None, world_part=False)
        if not maps.reduced:
            return cov
        T = jt.coordinate_basis(maps.tree, g)
        return (T.transpose(-1, -2) @ cov[..., None])[..., 0]

    def start(self, g0: Pose, g1: Pose) -> FusedArticulatedState:
        maps = self.maps
        cur, prev = Frame.at(maps, g1), Frame.at(maps, g0)
        const = self._const(prev, cur)
        inc = maps.tree.group.increment(g0, g1)
        return FusedArticulatedState(g0, cur, inc, const, self, self._coordinates(inc, prev.q, cur.q))

    def _coordinates(self, inc: Pose, q: Pose, q_next: Pose) -> torch.Tensor:
        """The step's coordinates (`mechanics.articulated.step_coordinates`) from the increment and the
        frames' moving coordinates, the joint coordinates on a reduced tree (no conversion per step)."""
        return art.step_coordinates(self.maps.tree, self.maps.reduced, inc, q, q_next)

    def _warm_start(self, s: FusedArticulatedState) -> Pose:
        """The reference's warm start (`ArticulatedLieDFLNN.warm_start`): the last two increments'
        coordinates extrapolated, 2 d_k - d_{k-1}, applied at g_k (along the joints on a reduced
        tree); on the first step the last increment alone."""
        maps, tree = self.maps, self.maps.tree
        G = tree.group
        d = s.dof if s.dof_prev is None else art.extrapolate(s.dof, s.dof_prev)
        if not maps.reduced:
            return s.inc if s.dof_prev is None else G.retract(s.inc, d - s.dof)
        return G.increment(s.g, from_moving(maps, jt.advance(tree, s.frame.q, d)))

    def problem(self, s: FusedArticulatedState, x0: Pose | None = None) -> NewtonProblem:
        maps, cur = self.maps, s.frame
        G = maps.tree.group
        last: list = [None, None]  # (x, its Frame): the last iterate made or read
        cached: list = [None]  # the Jacobian's left factor at g_k

        def frame(x: Pose) -> Frame:
            if last[0] is not x:
                last[0], last[1] = x, Frame.at(maps, G.compose(cur.g, x))
            return last[1]

        def f(x: Pose) -> torch.Tensor:
            nxt = frame(x)
            c = body_covector(kinetic.kinetic_d1, maps, cur, nxt)
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
            rot, trans = left()[1]  # two products into one buffer: 1.4x the concatenated factors at batch 1,000
            J = torch.baddbmm(torch.bmm(rot, HT.reshape(N, 3 * B, n)), trans, _rows(nxt.com_jacobian(maps)), alpha=-1)
            return self._joint_jacobian(cur.q, nxt.q, J)

        def left() -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
            """At g_k, once per step: [Theta_k; P_k]^T (the residual's, (N, n, 6B)) and the Jacobian's
            Theta_k^T and (m/h) Y_k^T (each (N, n, 3B), transposed views)."""
            if cached[0] is None:
                s_ = (maps.mass / maps.h)[:, None, None]
                theta = cur.jacobian(maps)[0]
                trans = _rows(s_ * cur.com_jacobian(maps)).transpose(-1, -2)
                cached[0] = (stacked(cur.jacobian(maps)), (_rows(theta).transpose(-1, -2), trans))
            return cached[0]

        def retract(x: Pose, delta: torch.Tensor) -> Pose:
            q_next = jt.advance(maps.tree, frame(x).q, delta)
            g_next = from_moving(maps, q_next)
            x_next = G.increment(cur.g, g_next)
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
        g_next = maps.tree.group.compose(s.g, inc)
        if projects_poses(W.dtype):
            g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
        nxt = Frame.at(maps, g_next)
        state = FusedArticulatedState(
            s.g, nxt, inc, self._const(s.frame, nxt), self, self._coordinates(inc, s.frame.q, nxt.q), s.dof
        )
        return state, g_next
