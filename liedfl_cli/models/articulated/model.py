"""Articulated LieDFLNN: a learned discrete Lagrangian on a kinematic tree (`model.kinetic=articulated`).

Beyond the paper. The paper's multibody model gives each body its own kinetic term in its own
coordinates, which is exact for bodies that interact at a distance and wrong for bodies joined by
joints: a link's centre-of-mass velocity depends on every parent's motion, and forces (which enter
the DEL equation at two time levels) cannot supply that acceleration coupling. Here

    L_d(g_k, g_{k+1}) = sum_b K_b(FK_b(g_k)^{-1} FK_b(g_{k+1}); m_b, rho_b, J_b) - h V(g_k)

over every body's world pose from forward kinematics of the data's tree (`lie.tree`), learned
m_b > 0, centre of mass rho_b (body frame, from the joint) and physical inertia J_b about it;
V = uniform gravity sum_b m_b g e3.c_b (sharing m_b, rho_b) and/or an MLP of the coordinates;
forces act in joint space (the root's twist and each joint's relative angular velocity;
`mechanics.articulated`), so `force=rayleigh` is joint (+ root) damping.

residual_k = A(g_k)^T [D2 K(k-1, k) + D1 K(k, k+1) - h dV_world] - h dV_coord
             + (h/2) [C^T F(g_{k-1}, nu_{k-1}) + C^T F(g_k, nu_k)].
`residual="generic"` computes the same residual by autodiff of L_d through FK (the reference; the
fast path is tested against it). The regularity term penalises each body's world SE(3) block of the
mixed Hessian (as the per-body model does for its SE(3) bodies): the coordinates' mixed Hessian is
A_k^T blockdiag(H_b) A_{k+1}, regular when the blocks are and A has full rank.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import nn
from torch.func import grad

from ...errors import ConfigError
from ...lie import Pose, so3
from ...lie import joints as jt
from ...lie.tolerances import projects_poses
from ...lie.tree import Tree, forward_kinematics
from ...mechanics import articulated as art
from ...mechanics import kinetic
from ...mechanics.forces import RayleighForce, build_forces, force_jacobian_xi
from ...mechanics.parameterizations import Inertia, PositiveVector
from ...mechanics.potentials import STANDARD_GRAVITY, GravityPotential, MLPPotential, UniformGravityPotential
from ...solvers import native_build
from ...solvers.newton import NewtonProblem
from ...solvers.rollout import Rollout
from .. import mlp_derivatives
from ..base import Batch, ImplicitModel, LossOptions, TrajectoryBatch, TripletBatch, TripletSet, oriented_logdet
from ..components import component_tagger, force_parameters
from ..del_loss import del_regularity_loss
from ..liedflnn.model import DEFAULT_RESIDUAL, LieDFLNNOptions, check_options
from .engines import fused as fused_articulated
from .engines import native as native_articulated
from .engines.fused import FusedArticulatedState
from .residual import residual_form

NATIVE_CHUNK_ROW_STEPS = 100_000
"""Trajectory-steps per call of the native rollout (~1 s on the 5-body tree): how often it reports progress
and how soon a signal (Ctrl-C, SIGTERM) is handled, between calls."""


def geometric_start(tree: Tree) -> tuple[torch.Tensor, torch.Tensor]:
    """Where training starts, read off the tree's geometry: (rho (B, 3), l (B,)). A link with children
    has its centre of mass at half the mean of its children's joint offsets and a length l = the
    longest of them; a leaf continues its parent's link (rho = o_b / 2, l = |o_b|). Lengths below a
    tenth of the median (or 0) are raised to it, so no link starts massless in rotation."""
    o = torch.tensor(tree.offsets, dtype=torch.float64)
    B = tree.n_bodies
    rho, length = torch.zeros(B, 3, dtype=torch.float64), torch.zeros(B, dtype=torch.float64)
    for b in range(B):
        kids = [c for c in range(B) if tree.parents[c] == b]
        if kids:
            rho[b] = 0.5 * o[kids].mean(0)
            length[b] = o[kids].norm(dim=-1).max()
        elif b > 0:
            rho[b] = 0.5 * o[b]
            length[b] = o[b].norm()
    positive = length[length > 0]
    floor = 0.1 * float(positive.median()) if len(positive) else 1.0
    return rho, length.clamp_min(floor)


def articulated_parameters(physics: dict, n_bodies: int) -> dict[str, torch.Tensor]:
    """The declared truth of an articulated scene (params["physics"] with kind "articulated"):
    {"mass": (B,), "rho": (B, 3), "J": (B, 3, 3), "joint_damping": (B-1,), "root_damping": ()}."""
    bodies = physics.get("bodies")
    if not isinstance(bodies, list) or len(bodies) != n_bodies:
        raise ValueError(f"physics.bodies must list {n_bodies} bodies (mass, com, inertia)")
    f64 = lambda x: torch.as_tensor(x, dtype=torch.float64)
    mass = f64([float(b["mass"]) for b in bodies])
    rho = f64([b["com"] for b in bodies]).reshape(n_bodies, 3)
    J = f64([b["inertia"] for b in bodies]).reshape(n_bodies, 3, 3)
    jd = physics.get("joint_damping") or [0.0] * (n_bodies - 1)
    if len(jd) != n_bodies - 1:
        raise ValueError(f"physics.joint_damping must have {n_bodies - 1} entries (one per joint)")
    return {
        "mass": mass,
        "rho": rho,
        "J": J,
        "joint_damping": f64([float(d) for d in jd]),
        "root_damping": f64(float(physics.get("root_damping") or 0.0)),
        "g": f64(float(physics.get("g") or 0.0)),
    }


def joint_damping_matrix(tree: Tree, truth: dict[str, torch.Tensor]) -> torch.Tensor:
    """Block-diagonal joint-space damping (dim, dim): root_damping I on the root, d_b I per joint."""
    G = tree.group
    diag = torch.zeros(G.dim, dtype=torch.float64)
    sl = G.body_slices()
    diag[sl[0]] = truth["root_damping"]
    for b in range(1, tree.n_bodies):
        diag[sl[b]] = truth["joint_damping"][b - 1]
    return torch.diag(diag)


class DofDamping(nn.Module):
    """Joint damping per degree of freedom: tau = -d * nu (d = lambda^2 >= 0, one per damped DoF),
    acting on the reduced joint velocities nu (..., n) of a tree (`lie.joints`: the root's DoF first).
    The free root's six DoF are not damped (`damped` marks the columns that are)."""

    name = "dof_damping"
    damped: torch.Tensor  # (n,) bool buffer

    def __init__(self, tree: Tree, scale: float = 1.0, init: float = 0.01):
        super().__init__()
        cols = jt.joint_slices(tree)
        mask = torch.ones(tree.n_dof, dtype=torch.bool)
        if tree.free_root:
            mask[cols[0]] = False
        self.register_buffer("damped", mask)
        self.lam = nn.Parameter(torch.full((int(mask.sum()),), math.sqrt(init * scale), dtype=torch.float64))

    def coefficients(self) -> torch.Tensor:
        """d (n,): the damping of every reduced coordinate (0 on a free root's)."""
        d = self.lam.new_zeros(self.damped.shape[0])
        return d.masked_scatter(self.damped, self.lam**2)

    @torch.no_grad()
    def set_coefficients(self, d: torch.Tensor) -> None:
        """Set the damped DoF's coefficients from d (n,) (entries >= 0)."""
        self.lam.copy_(d.to(self.lam)[self.damped].clamp_min(0.0).sqrt())

    def forward(self, nu: torch.Tensor) -> torch.Tensor:
        return -self.coefficients() * nu

    def describe(self) -> str:
        return f"joint damping per DoF ({int(self.damped.sum())} coefficients)"


def reduced_velocity(tree: Tree, q: Pose, q_next: Pose, h: float) -> torch.Tensor:
    """nu (..., n): the reduced joint velocities of the interval (q, q_next) (joint coordinates): the
    velocity estimate of the joint-coordinate increment in the least-squares coordinates of the mean
    of the motion bases at both ends (`lie.joints.reduce_joint_velocity`; sin(dtheta)/h on a hinge)."""
    G = tree.group
    return jt.reduce_joint_velocity(tree, q, q_next, kinetic.velocity_estimate(G, G.increment(q, q_next), h))


def reduced_velocity_jacobian(tree: Tree, q: Pose, q_next: Pose, h: float) -> torch.Tensor:
    """d nu / d delta (..., n, n) under q_next -> advance(q_next, delta) (the bases held fixed)."""
    G = tree.group
    dnu = kinetic.velocity_estimate_jacobian(G, G.increment(q, q_next), h)  # (..., dim, dim)
    S_next = jt.motion_basis(tree, q_next)
    return jt.reduce_joint_velocity(tree, q, q_next, dnu @ S_next, columns=True)


def joint_summary(tree: Tree) -> str:
    """E.g. "free, 3 hinge, 1 ball (10 DoF)": the joint types of a tree with their counts."""
    kinds = tree.joint_kinds
    counts: dict[str, int] = {}
    for k in kinds[1:]:
        counts[k] = counts.get(k, 0) + 1
    parts = [kinds[0] if tree.free_root else f"root {kinds[0]}"] + [f"{n} {k}" for k, n in counts.items()]
    return ", ".join(parts) + f" ({tree.n_dof} DoF)"


def true_dof_damping(tree: Tree, physics: dict, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The declared damping per reduced coordinate (n,): physics["dof_damping"] (a list per body of
    per-DoF values) when present, else each joint's `joint_damping` on all its DoF (root_damping on a
    pinned root's); 0 on a free root."""
    cols = jt.joint_slices(tree)
    d = torch.zeros(tree.n_dof, dtype=dtype)
    per_dof = physics.get("dof_damping")
    jd = physics.get("joint_damping") or [0.0] * (tree.n_bodies - 1)
    for b, c in enumerate(cols):
        if tree.free_root and b == 0:
            continue
        if per_dof is not None and per_dof[b] is not None and len(per_dof[b]) == c.stop - c.start:
            d[c] = torch.tensor([float(x) for x in per_dof[b]], dtype=dtype)
        else:
            d[c] = float(jd[b - 1]) if b > 0 else float(physics.get("root_damping") or 0.0)
    return d


# ---------------------------------------------------------------------------- training samples
@dataclass
class ArticulatedBatch:
    """Triplets with forward kinematics done once: coordinate poses prev/cur (for forces and MLP
    potentials), world increments inc_prev = FK(g_{k-1})^-1 FK(g_k), inc_next = FK(g_k)^-1 FK(g_{k+1})
    (SE(3)^B), world poses of g_k, A_k (N, B, 6, dim), the joint coordinates q of g_{k-1} and g_k,
    the joint-velocity estimates of both intervals (N, dim), C(g_k) (N, dim, dim; None for
    parent-relative rotations), and `reg`: world increments of the regularity pairs."""

    prev: Pose
    cur: Pose
    world_cur: Pose
    inc_prev: Pose
    inc_next: Pose
    A: torch.Tensor
    q_prev: Pose
    q_cur: Pose
    nu_prev: torch.Tensor
    nu_next: torch.Tensor
    C: torch.Tensor | None
    A_next: torch.Tensor | None = None
    inc_coord: Pose | None = None
    reg: Pose | None = None
    T: torch.Tensor | None = None  # reduced trees: T(g_k) (N, dim, n), `lie.joints.coordinate_basis`
    T_next: torch.Tensor | None = None  # T(g_{k+1}), train.loss=newton only
    nu_red_prev: torch.Tensor | None = None  # reduced joint velocities of both intervals (N, n)
    nu_red_next: torch.Tensor | None = None


class ArticulatedTriplets(TripletSet):
    """`TripletSet` plus what every epoch would otherwise recompute: FK, world increments, A."""

    def __init__(self, model: ArticulatedLieDFLNN, data: Pose, steps: int):
        super().__init__(data, steps)
        tree, G = model.tree, model.G
        Gw = art.world_group(tree)
        with torch.no_grad():
            w_prev = forward_kinematics(tree, self.prev)
            w_cur, self.A = art.fk_and_jacobian(tree, self.cur)
            w_next = forward_kinematics(tree, self.nxt)
            self.world_cur = w_cur
            self.inc_prev = Gw.increment(w_prev, w_cur)
            self.inc_next = Gw.increment(w_cur, w_next)
            q_prev, q_cur, q_next = (art.joint_coordinates(tree, x) for x in (self.prev, self.cur, self.nxt))
            self.q_prev, self.q_cur = q_prev, q_cur
            self.nu_prev = kinetic.velocity_estimate(G, G.increment(q_prev, q_cur), model.h)
            self.nu_next = kinetic.velocity_estimate(G, G.increment(q_cur, q_next), model.h)
            self.C = art.joint_velocity_map(tree, self.cur)
            self.T: torch.Tensor | None = None
            self.nu_red_prev: torch.Tensor | None = None
            self.nu_red_next: torch.Tensor | None = None
            if model.reduced:
                self.T = jt.coordinate_basis(tree, self.cur)
                self.nu_red_prev = reduced_velocity(tree, q_prev, q_cur, model.h)
                self.nu_red_next = reduced_velocity(tree, q_cur, q_next, model.h)
        self.A_next: torch.Tensor | None = None  # `enable_jacobian` (train.loss=newton only)
        self.inc_coord: Pose | None = None
        self.T_next: torch.Tensor | None = None
        self.tree = tree
        self.reduced = model.reduced

    def enable_jacobian(self) -> None:
        """Also keep A(g_{k+1}) and the coordinate increments, which the Newton-normalised loss needs."""
        with torch.no_grad():
            self.A_next = art.fk_jacobian(self.tree, self.nxt)
            self.inc_coord = self.tree.group.increment(self.cur, self.nxt)
            if self.reduced:
                self.T_next = jt.coordinate_basis(self.tree, self.nxt)

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> ArticulatedBatch:  # type: ignore[override]
        reg = None
        if reg_points > 0:
            reg_idx = torch.randint(0, self.n, (int(reg_points),), generator=generator).to(self.cur.R.device)
            reg = self.inc_next.index(reg_idx)
        i = idx.to(self.cur.R.device)
        return ArticulatedBatch(
            self.prev.index(i),
            self.cur.index(i),
            self.world_cur.index(i),
            self.inc_prev.index(i),
            self.inc_next.index(i),
            self.A[i],
            self.q_prev.index(i),
            self.q_cur.index(i),
            self.nu_prev[i],
            self.nu_next[i],
            None if self.C is None else self.C[i],
            None if self.A_next is None else self.A_next[i],
            None if self.inc_coord is None else self.inc_coord.index(i),
            reg,
            None if self.T is None else self.T[i],
            None if self.T_next is None else self.T_next[i],
            None if self.nu_red_prev is None else self.nu_red_prev[i],
            None if self.nu_red_next is None else self.nu_red_next[i],
        )


@dataclass
class ArticulatedState:
    """Rollout state: g_{k-1}, g_k, the last coordinate increment, FK(g_k), A(g_k), and the warm start's
    points: the last increment's coordinates `dof` (N, n) and the previous one's `dof_prev` (None on the
    first step; `ArticulatedLieDFLNN.increment_coordinates`)."""

    g_prev: Pose
    g: Pose
    inc: Pose
    world: Pose
    A: torch.Tensor
    dof: torch.Tensor
    dof_prev: torch.Tensor | None = None


@dataclass
class ArticulatedOptions(LieDFLNNOptions):
    """The articulated model's config options (conf/model/articulated.yaml): LieDFLNN's fields, declared
    there once (`kinetic` is articulated; per_body is refused by `from_config`)."""


class ArticulatedLieDFLNN(ImplicitModel):
    """Learned forced discrete mechanics of a kinematic tree (an `ImplicitModel` on the tree's
    coordinates; see the module docstring).

    Args:
        tree: the data's kinematic tree. h: time step.
        potential: parts among "mlp" (of the coordinates), "uniform_gravity" (on FK's world poses).
        forces: force names or {name: options}, applied in joint space.
        residual: "fast" (closed forms through the FK Jacobian) or "generic" (autodiff through FK).
        known / physics: parts set to the declared truth (params["physics"], kind "articulated") and frozen.
    """

    window = "triplet"
    needs_tree = True
    Options = ArticulatedOptions
    notes: list[str]
    tree: Tree
    joint_report: str | None = None  # the joint inference's table, when the joints were inferred
    total_mass: float | None = None  # dataset.total_mass: the scale of the least-squares start
    start_report: dict | None = None  # what the least-squares start found (recovery.json)

    def __init__(
        self,
        tree: Tree,
        h: float,
        potential=(),
        forces=("rayleigh",),
        residual: str = DEFAULT_RESIDUAL,
        mlp_width: int = 64,
        mlp_depth: int = 3,
        epsilon: float = 10.0,
        init_jitter: float = 0.1,
        seed: int = 0,
        known=(),
        physics: dict | None = None,
        gravity: float = STANDARD_GRAVITY,
        learn_gravity_direction: bool = False,
        gravity_up=None,
    ):
        super().__init__()
        known = check_options(residual, known, physics)
        self.tree, self.G, self.h = tree, tree.group, float(h)
        self.residual_form = residual_form(residual)  # closed form or autodiff, fixed here (residual.py)
        self.known = known
        self.epsilon = float(epsilon)
        B = tree.n_bodies
        gen = torch.Generator().manual_seed(seed)
        rho0, length = geometric_start(tree)
        # equal masses s, inertias s l_b^2 / 12 I (a rod of the link's length), centres of mass halfway
        # along the link; s puts the shortest link's world block at the regularity threshold:
        # 3 log(s/h) + 3 log(s l^2 / (12 h)) = epsilon
        scale = h * math.exp(epsilon / 6.0) * math.sqrt(12.0) / float(length.min())
        self.inertia = Inertia(B, scale=(scale * length**2 / 12.0).tolist(), jitter=init_jitter, generator=gen)
        self.mass = PositiveVector(B, init=scale)
        self.rho = nn.Parameter(
            rho0 + init_jitter * length[:, None] * torch.randn(B, 3, generator=gen, dtype=torch.float64)
        )
        truth = articulated_parameters(physics, B) if known and physics else None
        if truth is not None and "inertia" in known:
            self.inertia.set_J(truth["J"])
            self.mass.set_value(truth["mass"])
            with torch.no_grad():
                self.rho.copy_(truth["rho"])
            for p in (self.inertia, self.mass):
                p.requires_grad_(False)
            self.rho.requires_grad_(False)
            scale = float(truth["J"].diagonal(dim1=-2, dim2=-1).mean())
        parts = tuple(potential or ())
        Gw = art.world_group(tree)
        self.potential_world: nn.Module | None = None
        self.potential_coord: MLPPotential | None = None
        if truth is not None and "potential" in known:
            if parts:
                raise ValueError("model.potential together with model.known=[potential]: choose one")
            g_true = float(truth["g"])
            if g_true:
                self.potential_world = GravityPotential(Gw, truth["mass"], truth["rho"], g_true)
        else:
            for part in parts:
                if part == "mlp":
                    self.potential_coord = MLPPotential(self.G, mlp_width, mlp_depth)
                elif part == "uniform_gravity":
                    self.potential_world = UniformGravityPotential(
                        Gw,
                        gravity=gravity,
                        mass=self.mass,
                        rho=self.rho,
                        learn_direction=learn_gravity_direction,
                        up=gravity_up,
                    )
                else:
                    raise ValueError(f"model.potential: unknown part {part!r}")
        # a tree with hinge, universal or weld joints lives on its joints' DoF (`lie.joints`): its
        # residual, Newton unknown and damping are reduced, and rayleigh is damping per DoF
        # joint damping is per DoF on every tree (MuJoCo's and a robot's model; the free root undamped):
        # `rayleigh` in the force group becomes `DofDamping`, which needs the reduced path too
        items = dict(forces.items()) if hasattr(forces, "items") else {f: {} for f in forces}
        self.dof_damper: DofDamping | None = None
        if "rayleigh" in items:
            items.pop("rayleigh")
            self.dof_damper = DofDamping(tree, scale)
        forces = items
        self.reduced = tree.constrained or self.dof_damper is not None
        self.forces = nn.ModuleList(build_forces(self.G, forces, scale))
        if truth is not None and "damping" in known and self.dof_damper is not None:
            self.dof_damper.set_coefficients(true_dof_damping(tree, physics or {}))
            self.dof_damper.requires_grad_(False)
        elif truth is not None and "damping" in known:
            ray = [f for f in self.forces if getattr(f, "name", None) == "rayleigh"]
            if not ray:
                raise ValueError("model.known=[damping] needs the rayleigh force (joint damping)")
            assert isinstance(ray[0], RayleighForce)
            ray[0].D.set_matrix(joint_damping_matrix(tree, truth))
            ray[0].requires_grad_(False)

    # ------------------------------------------------------------------ config
    @classmethod
    def from_config(cls, ctx, **options: Any) -> ImplicitModel:
        """From its own config (`conf/model/articulated.yaml`: LieDFLNN's options, `ArticulatedOptions`) or
        from LieDFLNN's with `kinetic: articulated` (the factory picks this class for them, `variant_for`);
        the tree comes from the data (`ctx.tree`). `model.substeps` / `model.order`
        other than 1 / 2 wrap it in `models.liedflnn.substeps.SubstepModel`."""
        from ..liedflnn.model import LieDFLNN
        from ..liedflnn.substeps import with_substeps

        if options.get("kinetic", "articulated") not in ("articulated", "auto"):
            raise ConfigError(
                f"model=articulated with model.kinetic={options['kinetic']}: the articulated model is the "
                "articulated kinetic term (for the paper's per-body one: model=liedflnn model.kinetic=per_body)"
            )
        _, parts, why, opt = LieDFLNN.resolve_options(ctx, options)
        substeps, order = opt.pop("substeps", 1), opt.pop("order", 2)
        return with_substeps(build_articulated(ctx, parts, opt, why), substeps, order)

    def components(self) -> list[str]:
        tag = component_tagger()
        out = [
            f"tree ({self.tree.n_bodies} bodies, {self.tree.rotations} rotations, "
            f"{'free' if self.tree.free_root else 'pinned'} root, joints {joint_summary(self.tree)})",
            tag("J_b", self.inertia),
            tag("m_b", self.mass),
            tag("rho_b", self.rho),
        ]
        for V in (self.potential_world, self.potential_coord):
            if V is not None:
                describe = getattr(V, "describe", None)
                desc = describe() if callable(describe) else type(V).__name__
                out.append(tag(f"V:{desc}", V))
        for f in self.forces:
            describe = getattr(f, "describe", None)
            desc = describe() if describe is not None else getattr(f, "name", type(f).__name__)
            out.append(tag(f"F:{desc} in joint space", f))
        if self.dof_damper is not None:
            out.append(tag(f"F:{self.dof_damper.describe()}", self.dof_damper))
        return out

    # ------------------------------------------------------------------ contract hooks
    def force_terms(self) -> list[nn.Module]:
        return list(self.forces)

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        """Per link: `J_d` (B, 3, 3), `m` (B,), `rho_COM` (B, 3); `D` of a joint-space Rayleigh damping."""
        with torch.no_grad():
            Jd, mass, rho = self._params()
            out = {"J_d": Jd.detach(), "m": mass.detach(), "rho_COM": rho.detach(), **force_parameters(self.forces)}
            if self.dof_damper is not None:
                out["dof_damping"] = self.dof_damper.coefficients().detach()
            return out

    def initial_fit(self, samples: Any, method: str = "auto") -> str | None:
        """`Model.initial_fit`: the prediction-weighted least-squares start (`models.articulated.fit`),
        on the fast path's triplets only; the scale from dataset.total_mass when given."""
        if not self.residual_form.closed_form or not isinstance(samples, ArticulatedTriplets) or self.known:
            return None
        from .fit import least_squares_start

        saved = {k: v.detach().clone() for k, v in self.state_dict().items()}
        try:
            if method == "identify":  # least squares + Levenberg-Marquardt (models.articulated.identification)
                from .identification import identify

                return identify(self, samples, epsilon=self.epsilon, log=None).line()
            report = least_squares_start(self, samples, epsilon=self.epsilon)
            self.start_report = {
                "regressor_rank": report.rank,
                "parameters": report.n_params,
                "gauge_dimension": report.n_params - report.rank,
                "first_order_one_step_error": report.weighted_rms,
                "projected_bodies": report.projected,
                "regularity_scale": report.scale,
                "seconds": report.seconds,
            }
            return report.line()
        except (torch.linalg.LinAlgError, RuntimeError, ValueError) as e:  # never worse than no start
            self.load_state_dict(saved)
            why = f"{type(e).__name__}: {str(e).splitlines()[0][:100]}"
            return f"least-squares start failed ({why}); epochs start from the tree's geometry"

    def multibody(self) -> dict[str, Any]:
        """`Model.multibody`: per body mass, COM and inertia about the COM (J = tr(J_d) I - J_d), the
        per-DoF damping, the gravity vector of a uniform field, and the parts with no simulator form."""
        with torch.no_grad():
            Jd, mass, rho = (t.detach() for t in self._params())
            J = (
                Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=Jd.dtype, device=Jd.device)
                - Jd
            )
            d = self.dof_damping()
            gravity = mass.new_zeros(3)
            unexported: list[str] = []
            V = self.potential_world
            if isinstance(V, UniformGravityPotential):
                gravity = -V.field().detach().to(mass)  # V = m gamma.c: gravity acts along -gamma
            elif isinstance(V, GravityPotential):
                gravity = torch.tensor([0.0, 0.0, -float(V.gravity)], dtype=mass.dtype, device=mass.device)
            elif V is not None:
                unexported.append(f"the world potential {type(V).__name__}")
            if self.potential_coord is not None:
                unexported.append("the learned potential of the coordinates (mlp)")
            unexported += [f"the force {getattr(f, 'name', type(f).__name__)!r}" for f in self.forces]
        return {
            "tree": self.tree,
            "mass": mass,
            "com": rho,
            "inertia": J,
            "dof_damping": mass.new_zeros(self.tree.n_dof) if d is None else d,
            "gravity": gravity,
            "unexported": unexported,
        }

    def joint_record(self) -> dict[str, Any]:
        return {
            "kinds": list(self.tree.joint_kinds),
            "axes": self.tree.axes_array(),
            "dof": self.tree.n_dof,
            "inference": self.joint_report,
        }

    def dof_damping(self) -> torch.Tensor | None:
        """The learned joint damping per reduced coordinate (n,) (root first; 0 on a free root), or
        None when the model has no per-DoF damping (a ball-joint tree damps through `rayleigh`)."""
        return None if self.dof_damper is None else self.dof_damper.coefficients().detach()

    def parameter_recovery(self, reference, physics) -> dict | None:
        from ..recovery import articulated_recovery

        return articulated_recovery(self, reference) if isinstance(reference, ArticulatedLieDFLNN) else None

    # ------------------------------------------------------------------ pieces
    def _params(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.inertia.Jd(), self.mass(), self.rho

    def potential(self, g: Pose) -> torch.Tensor:
        """V(g), shape (...)."""
        V = g.R.new_zeros(g.R.shape[:-3])
        if self.potential_world is not None:
            V = V + self.potential_world(forward_kinematics(self.tree, g))
        if self.potential_coord is not None:
            V = V + self.potential_coord(g)
        return V

    def lagrangian(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """L_d(g, g_next) through forward kinematics, shape (...)."""
        Gw = art.world_group(self.tree)
        inc = Gw.increment(forward_kinematics(self.tree, g), forward_kinematics(self.tree, g_next))
        Jd, m, rho = self._params()
        return kinetic.kinetic_lagrangian(Gw, inc, Jd, m, rho, self.h) - self.h * self.potential(g)

    def joint_torque(self, g: Pose, g_next: Pose, q: Pose | None = None) -> torch.Tensor:
        """sum_f F(q, nu~) of the interval (g, g_next) in joint space, (..., dim): q = the joint
        coordinates of g (pass them when known), nu~ the velocity estimate of the joint-coordinate increment."""
        q = art.joint_coordinates(self.tree, g) if q is None else q
        q_next = art.joint_coordinates(self.tree, g_next)
        nu = kinetic.velocity_estimate(self.G, self.G.increment(q, q_next), self.h)
        F = torch.zeros_like(nu)
        for f in self.forces:
            F = F + f(q, nu)
        return F

    def at(self, g: Pose, tau: torch.Tensor) -> torch.Tensor:
        """C(g)^T tau: a joint-space covector as a covector of the coordinates at g, (..., dim)."""
        C = art.joint_velocity_map(self.tree, g)
        return tau if C is None else (C.transpose(-1, -2) @ tau[..., None])[..., 0]

    def half_force(self, g_from: Pose, g_to: Pose, at: Pose) -> torch.Tensor:
        """(h/2) C(at)^T F of the interval (g_from, g_to), (..., dim); zeros without forces."""
        if not len(self.forces):
            return at.R.new_zeros(*at.R.shape[:-3], self.G.dim)
        return 0.5 * self.h * self.at(at, self.joint_torque(g_from, g_to))

    def potential_covector(self, g: Pose, world: Pose, A: torch.Tensor, world_part: bool = True) -> torch.Tensor:
        """-h dV(g exp(eta))/d eta at 0, (..., dim): world potentials through A^T (world_part=False: left
        out), coordinate ones directly."""
        out = g.R.new_zeros(*g.R.shape[:-3], self.G.dim)
        Vw = self.potential_world
        if Vw is not None and world_part:
            Gw = art.world_group(self.tree)
            if isinstance(Vw, UniformGravityPotential):
                dw = Vw.left_gradient(world)
            else:
                eta = world.R.new_zeros(*world.R.shape[:-3], Gw.dim)
                dw = grad(lambda e: Vw(Gw.perturb(world, e)).sum())(eta)
            out = out - self.h * art.to_coordinates(A, dw)
        Vc = self.potential_coord
        if Vc is not None:
            # an MLP in closed form (`mlp_derivatives`): no autograd pass inside the loss, whose own
            # backward then runs once instead of through a double backward
            closed = mlp_derivatives.mlp_potential_covector(Vc, self.G, g, float(self.h))
            if closed is not None:
                return out + closed
            eta = g.R.new_zeros(*g.R.shape[:-3], self.G.dim)
            out = out - self.h * grad(lambda e: Vc(self.G.perturb(g, e)).sum())(eta)
        return out

    # ------------------------------------------------------------------ residual
    @property
    def residual_mode(self) -> str:
        """`model.residual`: "fast" (closed form) or "generic" (autodiff), the residual object's mode."""
        return self.residual_form.mode

    def residual_const(self, g_prev: Pose, g: Pose) -> torch.Tensor:
        """D2 L_d(g_prev, g) + F^+ (+ the potential): the part fixed by (g_prev, g), by the model's
        residual object (`residual.py`)."""
        return self.residual_form.const(self, g_prev, g)

    def residual_var(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """D1 L_d(g, g_next) + F^- (the part depending on g_next)."""
        return self.residual_form.var(self, g, g_next)

    def residual(self, g_prev: Pose, g: Pose, g_next: Pose) -> torch.Tensor:
        """Forced DEL residual at g in the tree's coordinates, (..., dim); on a reduced tree (hinge,
        universal or weld joints) in its joints' DoF, (..., n): T(g)^T r + (h/2)(tau_{k-1} + tau_k)."""
        r = self.residual_const(g_prev, g) + self.residual_var(g, g_next)
        if not self.reduced:
            return r
        T = jt.coordinate_basis(self.tree, g)
        return (T.transpose(-1, -2) @ r[..., None])[..., 0] + self.dof_torques(g_prev, g, g_next)

    def dof_torques(self, g_prev: Pose, g: Pose, g_next: Pose) -> torch.Tensor:
        """(h/2) (tau(g_prev, g) + tau(g, g_next)) of the per-DoF damping, (..., n); zeros without it."""
        q0, q1, q2 = (jt.to_joint_coordinates(self.tree, x) for x in (g_prev, g, g_next))
        if self.dof_damper is None:
            return q1.R.new_zeros(*q1.R.shape[:-3], self.tree.n_dof)
        nu = torch.stack((reduced_velocity(self.tree, q0, q1, self.h), reduced_velocity(self.tree, q1, q2, self.h)))
        tau = self.dof_damper(nu)
        return 0.5 * self.h * (tau[0] + tau[1])

    def dof_half_torque(self, g: Pose, g_next: Pose) -> torch.Tensor | None:
        """(h/2) tau(nu(g, g_next)) of the per-DoF damping over one interval, (..., n); None without it
        (one half of `dof_torques`, for steps of different lengths: `models.liedflnn.substeps`)."""
        if self.dof_damper is None:
            return None
        q0, q1 = jt.to_joint_coordinates(self.tree, g), jt.to_joint_coordinates(self.tree, g_next)
        return 0.5 * self.h * self.dof_damper(reduced_velocity(self.tree, q0, q1, self.h))

    def _force_jacobian(self, g: Pose, inc: Pose, fixed: tuple[Pose, torch.Tensor | None] | None = None):
        """d/d delta of (h/2) C(g)^T F(q, nu~(q, q_next)) with g_next = g inc exp(delta), (..., dim, dim):
        (h/2) C(g)^T dF/dnu dnu~/d delta_q C(g_next) (delta_q = C(g_next) delta moves the joint coordinates).
        `fixed`: (q, C) of g when already known (a rollout step's Newton iterations share them). None
        without forces."""
        if not len(self.forces):
            return None
        G = self.G
        g_next = G.compose(g, inc)
        q, C = (
            fixed if fixed is not None else (art.joint_coordinates(self.tree, g), art.joint_velocity_map(self.tree, g))
        )
        q_next = art.joint_coordinates(self.tree, g_next)
        inc_q = G.increment(q, q_next)
        nu = kinetic.velocity_estimate(G, inc_q, self.h)
        dnu = kinetic.velocity_estimate_jacobian(G, inc_q, self.h)
        dF = sum(force_jacobian_xi(f, q, nu) for f in self.forces)
        assert isinstance(dF, torch.Tensor)
        J = dF @ dnu
        C_next = art.joint_velocity_map(self.tree, g_next)
        if C_next is not None:
            J = J @ C_next
        if C is not None:
            J = C.transpose(-1, -2) @ J
        return 0.5 * self.h * J

    def jacobian_var(self, g: Pose, inc: Pose) -> torch.Tensor:
        """d residual_var(g, g inc exp(delta)) / d delta at 0, (..., dim, dim): A_k^T blockdiag(H_b) A_{k+1}
        plus the forces (closed form), or autodiff; on a reduced tree in its joints' DoF."""
        J = self.residual_form.jacobian_var(self, g, inc)
        return self.reduce_jacobian(g, inc, J) if self.reduced else J

    def reduce_jacobian(
        self, g: Pose, inc: Pose, J: torch.Tensor, damping=None, Tk: torch.Tensor | None = None, q: Pose | None = None
    ) -> torch.Tensor:
        """The Jacobian of the reduced residual from the full one J (..., dim, dim) of `residual_var`:
        T(g)^T J T(g inc) - (h/2) diag(d) d nu / d delta (..., n, n) (`lie.joints`; the damping's
        term holds a universal joint's basis fixed over the step). `damping`: d (n,) when known;
        Tk, q: T(g) and g's joint coordinates when known (a rollout step's iterations share them)."""
        tree = self.tree
        g_next = self.G.compose(g, inc)
        Tk = jt.coordinate_basis(tree, g) if Tk is None else Tk
        T_next = jt.coordinate_basis(tree, g_next)
        J = Tk.transpose(-1, -2) @ J @ T_next
        d = damping if damping is not None else (None if self.dof_damper is None else self.dof_damper.coefficients())
        if d is not None:
            q = jt.to_joint_coordinates(tree, g) if q is None else q
            q_next = jt.to_joint_coordinates(tree, g_next)
            J = J - 0.5 * self.h * d[:, None] * reduced_velocity_jacobian(tree, q, q_next, self.h)
        return J

    def step_retract(self, g: Pose, x: Pose, delta: torch.Tensor) -> Pose:
        """The Newton update of an increment x at g by delta: along the joints on a reduced tree
        (`lie.joints.retract`, delta (..., n)), else x exp(delta)."""
        return jt.retract(self.tree, g, x, delta) if self.reduced else self.G.retract(x, delta)

    # ------------------------------------------------------------------ training
    def training_set(self, data: Pose, steps: int):
        if self.residual_form.closed_form:
            return ArticulatedTriplets(self, data, steps)
        return super().training_set(data, steps)

    def regularity_slogdet(self, g: Pose, g_next: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        """(log|det H_b|, sign det(-H_b)) of each body's world SE(3) block of the mixed Hessian at the
        pairs (g, g_next), (..., B) (the regularity term's blocks; the contract of `LieDFLNN`)."""
        Gw = art.world_group(self.tree)
        return self.world_slogdet(Gw.increment(forward_kinematics(self.tree, g), forward_kinematics(self.tree, g_next)))

    def world_slogdet(self, inc_world: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        """`regularity_slogdet` from the world increments FK(g)^-1 FK(g_next) (SE(3)^B), (..., B)."""
        Jd, m, rho = self._params()
        H = art.mixed_hessian_blocks(inc_world, Jd, m, rho, self.h)
        sl = torch.linalg.slogdet(H)
        return sl.logabsdet, sl.sign  # 6 x 6 blocks: det(-H) = det H

    def loss(self, batch: Batch | ArticulatedBatch, opts: LossOptions):
        """`train.loss`: del (w_DEL mean ||r||^2), newton (w_DEL mean ||H^-1 r||^2) or rollout (the
        fine-tuning windows, `models.liedflnn.losses.rollout_window_loss`), each + w_reg mean penalty(log|det H_b|)
        -> (loss, parts). The paper's DEL loss of a precomputed batch is compiled, forward and backward, when
        the plan asks for it (`runtime.compile`; `auto` from 1e5 optimiser steps: 1.75x per Exp 4 step, about
        1.3x per epoch, after about a minute of compiling; docs/benchmarks.md, "Compilation")."""
        if (
            isinstance(batch, ArticulatedBatch)
            and opts.loss == "del"
            and torch.is_grad_enabled()
            and self.plan.wants_compile("train")
        ):
            from ...solvers import compile as compile_cache

            return compile_cache.compiled(_articulated_loss, "articulated_train_loss")(self, batch, opts)
        return self._loss(batch, opts)

    def _loss(self, batch: Batch | ArticulatedBatch, opts: LossOptions):
        """`loss` uncompiled."""
        from ..liedflnn import losses

        if opts.loss == "rollout":
            assert isinstance(batch, TrajectoryBatch), "train.loss=rollout trains on windows (losses.WindowSet)"
            return losses.rollout_window_loss(self, batch, opts, opts.solver)
        if not isinstance(batch, ArticulatedBatch):
            assert isinstance(batch, TripletBatch), "the articulated model trains on triplets"
            if opts.loss == "newton":
                return losses.newton_loss(self, batch, opts)
            logdet = None
            if batch.reg is not None and opts.w_reg > 0:
                logdet = oriented_logdet(*self.regularity_slogdet(*batch.reg), opts.epsilon)
            return del_regularity_loss(self.residual(*batch.poses()), logdet, opts)
        logdet = None
        if batch.reg is not None and opts.w_reg > 0:
            logdet = oriented_logdet(*self.world_slogdet(batch.reg), opts.epsilon)
        if opts.loss == "newton":
            x, singular, clipped = losses.newton_step(self.newton_jacobian_batch(batch), self._batch_residual(batch))
            return losses.newton_regularity_loss(x, singular, clipped, logdet, opts)
        return del_regularity_loss(self._batch_residual(batch), logdet, opts)

    def newton_jacobian_batch(self, b: ArticulatedBatch) -> torch.Tensor:
        """H_k = d r_k / d delta_{k+1} of a batch (kinetic A_k^T blockdiag(H_b) A_{k+1} + forces), (N, dim, dim)."""
        if b.A_next is None:
            raise RuntimeError("train.loss=newton needs ArticulatedTriplets.enable_jacobian()")
        Jd, m, rho = self._params()
        Hk = art.newton_jacobian(b.A, b.inc_next, b.A_next, Jd, m, rho, self.h)
        Jf = self._force_jacobian(b.cur, b.inc_coord) if b.inc_coord is not None else None
        Hk = Hk if Jf is None else Hk + Jf
        if not self.reduced:
            return Hk
        assert b.T is not None and b.T_next is not None
        Hk = b.T.transpose(-1, -2) @ Hk @ b.T_next
        if self.dof_damper is not None:
            assert b.inc_coord is not None
            q = jt.to_joint_coordinates(self.tree, b.cur)
            q_next = jt.to_joint_coordinates(self.tree, self.G.compose(b.cur, b.inc_coord))
            dnu = reduced_velocity_jacobian(self.tree, q, q_next, self.h)
            Hk = Hk - 0.5 * self.h * self.dof_damper.coefficients()[:, None] * dnu
        return Hk

    def body_covectors(self, b: ArticulatedBatch, params: tuple | None = None) -> tuple[torch.Tensor, bool]:
        """Every body's world covector of the batch's kinetic terms, D2 K + D1 K (N, 6B), and with `params`
        and a learned uniform gravity also -h dV_world (then True): the part of the residual the
        physical parameters enter, body by body (body b's covector depends on body b's parameters only:
        the identification's regressor is a forward-mode Jacobian in ten colours, `articulated_fit`)."""
        Gw = art.world_group(self.tree)
        Jd, m, rho = self._params() if params is None else params[:3]
        c = kinetic.kinetic_d2(Gw, b.inc_prev, Jd, m, rho, self.h) + kinetic.kinetic_d1(
            Gw, b.inc_next, Jd, m, rho, self.h
        )
        if params is not None and isinstance(self.potential_world, UniformGravityPotential):
            up = (b.world_cur.R * self.potential_world.field()[:, None]).sum(-2)  # (N, B, 3): R^T gamma
            dw = Gw.join(torch.cross((m[:, None] * rho).expand_as(up), up, dim=-1), m[:, None] * up)
            return c - self.h * dw, True
        return c, False

    def _batch_residual(self, b: ArticulatedBatch, params: tuple | None = None) -> torch.Tensor:
        """The residual of a batch, (N, dim) or reduced (N, n). params: (J_d (B, 3, 3), m (B,), rho (B, 3),
        d (n,) or None) to use instead of the model's (the identification's regressor: the residual is
        linear in (m, m rho, J_d + m rho rho^T) per body and in d; gravity shares m and rho)."""
        c, with_potential = self.body_covectors(b, params)
        r = art.to_coordinates(b.A, c)
        if not with_potential:
            r = r + self.potential_covector(b.cur, b.world_cur, b.A)
        elif self.potential_coord is not None:
            r = r + self.potential_covector(b.cur, b.world_cur, b.A, world_part=False)
        if len(self.forces):
            r = r + 0.5 * self.h * self._batch_torques(b)
        if not self.reduced:
            return r
        assert b.T is not None
        r = (b.T.transpose(-1, -2) @ r[..., None])[..., 0]
        if self.dof_damper is not None:
            assert b.nu_red_prev is not None and b.nu_red_next is not None
            d = self.dof_damper.coefficients() if params is None or params[3] is None else params[3]
            r = r - 0.5 * self.h * d * (b.nu_red_prev + b.nu_red_next)
        return r

    def _batch_torques(self, b: ArticulatedBatch) -> torch.Tensor:
        """C(g_k)^T [F(q_{k-1}, nu~_{k-1}) + F(q_k, nu~_k)] from the precomputed joint coordinates; each
        force is called once on both time levels stacked (half the calls of its networks)."""
        n = b.nu_prev.shape[0]
        q = Pose(torch.cat((b.q_prev.R, b.q_cur.R)), torch.cat((b.q_prev.p, b.q_cur.p)))
        nu = torch.cat((b.nu_prev, b.nu_next))
        both = torch.zeros_like(nu)
        for f in self.forces:
            both = both + f(q, nu)
        F = both[:n] + both[n:]
        return F if b.C is None else (b.C.transpose(-1, -2) @ F[..., None])[..., 0]

    # ------------------------------------------------------------------ rollout
    def implicit_start(self, g0: Pose, g1: Pose) -> ArticulatedState | FusedArticulatedState:
        """The rollout's first state: the fused engine's (`models.articulated.engines.fused`) on the fused path
        where it applies and no gradient is being recorded (it reads the parameters detached), else
        the reference problem's."""
        if self.path == "fused" and not torch.is_grad_enabled() and fused_articulated.applies(self) is None:
            return fused_articulated.ArticulatedEngine(self, g1.R).start(g0, g1)
        world, A = art.fk_and_jacobian(self.tree, g1)
        inc = self.G.increment(g0, g1)
        return ArticulatedState(g0, g1, inc, world, A, self.increment_coordinates(g0, g1, inc))

    def native_rollout(self, g0: Pose, g1: Pose, steps: int, opts, progress=None) -> Rollout | None:
        """The rollout by the native step (`models.articulated.engines.native`: the fused engine's step in
        C++, the same poses to rounding) where the plan allows it (`ExecutionPlan.wants_native`), with Newton
        or chord steps, where it serves this model and these poses; else None (the caller rolls out in torch)."""
        if steps < 2 or opts.method not in ("newton", "chord") or not self.plan.wants_native():
            return None
        if not native_articulated.usable(self, g1):
            return None
        t0 = time.perf_counter()
        engine = native_articulated.for_model(self, g1.R)
        state = engine.start(g0, g1)
        run = lambda count: engine.run(state, count, opts)
        chunks = native_build.run_in_chunks(run, g0.R.shape[0], steps, NATIVE_CHUNK_ROW_STEPS, progress)
        cat = {key: torch.cat([c[key] for c in chunks], 1) for key in chunks[0]}  # (on g1's dtype and device)
        R = torch.cat((g0.R[:, None], g1.R[:, None], cat["R"]), 1)
        p = torch.cat((g0.p[:, None], g1.p[:, None], cat["p"]), 1)
        return Rollout(
            Pose(R, p), cat["converged"].bool(), cat["iterations"], cat["residual_norm"], time.perf_counter() - t0
        )

    def scaled_start(self, state, inc: Pose, ratio: float):
        """`state` (from `implicit_start(g_prev, g)`) warm-starting a step `ratio` times as long as the last
        (`LieDFLNN.scaled_start`): the last increment `inc`, and, since a reduced tree starts from the last
        increment's DoF, those DoF scaled by `ratio` with no earlier ones to extrapolate from."""
        return replace(state, inc=inc, dof=ratio * state.dof, dof_prev=None)

    def increment_coordinates(self, g: Pose, g_next: Pose, inc: Pose) -> torch.Tensor:
        """The coordinates of the step g -> g_next = g inc, (N, n) (`mechanics.articulated.step_coordinates`):
        the warm start's points, exact so that the extrapolated start is off by O(h^3) (tested)."""
        q = q_next = None
        if self.reduced:
            q, q_next = jt.to_joint_coordinates(self.tree, g), jt.to_joint_coordinates(self.tree, g_next)
        return art.step_coordinates(self.tree, self.reduced, inc, q, q_next)

    def warm_start(self, state: ArticulatedState) -> Pose:
        """The Newton start of the step from g_k: the last two increments' coordinates extrapolated
        (`mechanics.articulated.extrapolate`: 2 d_k - d_{k-1}, about one Newton iteration in four
        fewer than the last increment alone on the 5-body tree) applied at g_k, along the joints on a
        reduced tree; on the first step the last increment."""
        if state.dof_prev is None and not self.reduced:
            return state.inc
        d = state.dof if state.dof_prev is None else art.extrapolate(state.dof, state.dof_prev)
        if not self.reduced:
            return self.G.retract(state.inc, d - state.dof)
        g = state.g
        ident = Pose(torch.eye(3, dtype=g.R.dtype, device=g.R.device).expand_as(g.R).clone(), torch.zeros_like(g.p))
        return jt.retract(self.tree, g, ident, d)

    def implicit_problem(self, state: ArticulatedState | FusedArticulatedState) -> NewtonProblem:
        """Solve the DEL residual for the coordinate increment W_k (updated by W exp(delta)); on a
        reduced tree for its joints' DoF (`_reduced_problem`); the fused engine's own problem."""
        if isinstance(state, FusedArticulatedState):
            return state.engine.problem(state)
        if self.reduced:
            return self._reduced_problem(state)
        g, form = state.g, self.residual_form
        with torch.enable_grad():
            const = form.const(self, state.g_prev, g, fk=(state.world, state.A)).detach()
        var, jac = form.step_terms(self, g, state.world, state.A)

        def f(x: Pose) -> torch.Tensor:
            return const + var(x)

        return NewtonProblem(f, jac, self.warm_start(state), self.G.retract)

    def _reduced_problem(self, state: ArticulatedState) -> NewtonProblem:
        """The DEL equations of a tree with hinge, universal or weld joints on its n DoF: residual
        T(g_k)^T r + (h/2)(tau_{k-1} + tau_k) (n,), Jacobian T_k^T H T_{k+1} (+ damping), the unknown
        the coordinate increment moved along the joints (`lie.joints.retract`), so every joint stays
        on its manifold. The warm start is the last increment's DoF applied at g_k."""
        G, tree, h = self.G, self.tree, self.h
        g = state.g
        Tk = jt.coordinate_basis(tree, g)
        Tk_t = Tk.transpose(-1, -2)
        q_prev, q = jt.to_joint_coordinates(tree, state.g_prev), jt.to_joint_coordinates(tree, g)
        damper = self.dof_damper
        with torch.enable_grad():
            const = self.residual_const(state.g_prev, g)
            const = (Tk_t @ const[..., None])[..., 0]
            if damper is not None:
                const = const + 0.5 * h * damper(reduced_velocity(tree, q_prev, q, h))
            const = const.detach()
        with torch.no_grad():
            d = None if damper is None else damper.coefficients().detach()
        var_full, jac_full = self.residual_form.step_terms(self, g, state.world, state.A)

        def f(x: Pose) -> torch.Tensor:
            r = const + (Tk_t @ var_full(x).detach()[..., None])[..., 0]
            if d is not None:
                g_next = G.compose(g, x)
                r = r - 0.5 * h * d * reduced_velocity(tree, q, jt.to_joint_coordinates(tree, g_next), h)
            return r

        def jac(x: Pose) -> torch.Tensor:
            return self.reduce_jacobian(g, x, jac_full(x).detach(), damping=d, Tk=Tk, q=q)

        return NewtonProblem(f, jac, self.warm_start(state), lambda x, delta: jt.retract(tree, g, x, delta))

    def implicit_advance(self, state, x: Pose) -> tuple[ArticulatedState | FusedArticulatedState, Pose]:
        if isinstance(state, FusedArticulatedState):
            return state.engine.advance(state, x)
        W = x.R.detach()
        W = 0.5 * W @ (3.0 * torch.eye(3, dtype=W.dtype, device=W.device) - W.transpose(-1, -2) @ W)
        inc = Pose(W, x.p.detach())
        g_next = self.G.compose(state.g, inc)
        if projects_poses(W.dtype):  # below float64 the composed poses drift off SO(3) too
            g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
        world, A = art.fk_and_jacobian(self.tree, g_next)
        dof = self.increment_coordinates(state.g, g_next, inc)
        return ArticulatedState(state.g, g_next, inc, world, A, dof, state.dof), g_next


def build_articulated(ctx, parts: tuple[str, ...], opt: dict, why: str) -> ArticulatedLieDFLNN:
    """`LieDFLNN.from_config` with `kinetic: articulated`: the tree comes from the data (`ctx.tree`)."""
    tree = getattr(ctx, "tree", None)
    if tree is None:
        raise ConfigError(
            "model.kinetic=articulated needs a kinematic tree in the data (attributes 'parents', "
            "'rotations' and dataset 'joint_offsets'; docs/data_format.md); this dataset has none"
        )
    if tree.group != ctx.group:
        raise ConfigError(f"the data's tree is on {tree.group.name} but the dataset's group is {ctx.group.name}")
    tree, joint_note, joint_report = resolve_joints(ctx, tree, opt.pop("joints", "auto"))
    known = tuple(opt.pop("known", ()) or ())
    physics = dict(ctx.physics) if known and ctx.physics else None
    try:
        model = ArticulatedLieDFLNN(
            tree,
            ctx.h,
            potential=parts,
            forces=dict(ctx.forces),
            epsilon=ctx.epsilon,
            seed=ctx.seed,
            known=known,
            physics=physics,
            **opt,
        )
    except ValueError as e:
        raise ConfigError(str(e)) from None
    model.notes = [f"potential: {why}", f"kinetic: articulated ({model.components()[0]})", joint_note]
    model.joint_report = joint_report
    model.total_mass = ctx.total_mass
    return model


def resolve_joints(ctx, tree: Tree, joints) -> tuple[Tree, str, str | None]:
    """`model.joints` against the data: (the tree with its joints, a note saying where they came from,
    the inference's table when they were inferred, else None).
    auto: the file's declared joints, else inferred from the training trajectories
    (`mechanics.joint_inference`); declared: the file's (ConfigError if none); ball: every joint a
    ball; a mapping {kinds: [...], axes: [...]}: exactly these (how a run stores what it inferred)."""
    if joints in (None, "ball"):
        return tree.with_joints(None), "joints: ball (every joint 3 DoF; model.joints=ball)", None
    if isinstance(joints, Mapping):
        kinds, axes = joints.get("kinds"), joints.get("axes")
        try:
            out = tree.with_joints(list(kinds or []), axes)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"model.joints: {e}") from None
        return out, f"joints: as given ({joint_summary(out)})", None
    if joints == "declared" or (joints == "auto" and tree.joints is not None):
        if tree.joints is None:
            raise ConfigError(
                "model.joints=declared: the data declare no joints (attribute 'joints'); use auto or ball"
            )
        return tree, f"joints: declared by the data ({joint_summary(tree)})", None
    if joints != "auto":
        raise ConfigError(f"model.joints={joints!r}: auto, declared, ball or a mapping {{kinds: [...], axes: [...]}}")
    if ctx.train_poses is None:
        return tree.with_joints(None), "joints: ball (no training data to infer joints from)", None
    from ...mechanics.joint_inference import format_inference, infer_joints

    result = infer_joints(tree, ctx.train_poses().R)
    out = tree.with_joints(list(result.kinds), [[list(r) for r in a] for a in result.axes])
    note = f"joints: inferred from the training data ({joint_summary(out)}; model.joints=ball for all balls)"
    return out, note, format_inference(result, None)


def articulated_true_model(
    tree: Tree, h: float, physics: dict, residual: str = DEFAULT_RESIDUAL
) -> ArticulatedLieDFLNN:
    """The articulated scheme with the declared truth (every part known and frozen)."""
    truth = articulated_parameters(physics, tree.n_bodies)
    damped = bool(torch.count_nonzero(joint_damping_matrix(tree, truth)))
    forces = {"rayleigh": {"coupling": "per_body"}} if damped else {}
    known = ("inertia", "potential", "damping") if damped else ("inertia", "potential")
    model = ArticulatedLieDFLNN(
        tree, h, forces=forces, residual=residual, init_jitter=0.0, known=known, physics=physics
    )
    model.requires_grad_(False)
    return model


def _articulated_loss(model: ArticulatedLieDFLNN, batch: ArticulatedBatch, opts: LossOptions):
    """`ArticulatedLieDFLNN._loss` as a module-level function: what `runtime.compile` compiles (one
    compiled function for every model, told apart by dynamo's guards)."""
    return model._loss(batch, opts)
