"""LieDFLNN: a learned discrete Lagrangian and discrete forces on SE(3)^m x SO(3)^n.

L_d(g_k, g_{k+1}) = sum_i K_i(W_i, z_i) - h V(g_k)   (rigid-body kinetic terms, `mechanics.kinetic`)
residual_k = D2 L_d(g_{k-1}, g_k) + D1 L_d(g_k, g_{k+1}) + (h/2)[F(g_{k-1}, xi~_{k-1}) + F(g_k, xi~_k)]
with D1/D2 the left-trivialised derivatives (left perturbation g exp(eta)). The residual is
split into a part fixed by (g_{k-1}, g_k) (`residual_const`) and a part depending on g_{k+1}
(`residual_var`) so a rollout's Newton solve only differentiates the latter.

Components are built only when configured: no potential network for a free body, no mass
or centre of mass for SO(3)-only groups, no force modules when `forces` is empty. Parts named
in `known` ("inertia": J_d and, for SE(3) bodies, m and rho_COM; "potential": the scene's
gravity + interaction potential; "damping": the Rayleigh D) are set to the scene's true values
from `physics` (a dataset's `params["physics"]`) and frozen (requires_grad False: not trained,
not counted as trainable parameters). `components()` lists every active part.

This file is the model's one meaning; what must agree with it when its physics changes (each tested to
rounding against it): `residual.py` (the residual's closed form and its autodiff reference), and the
engines chosen in `engines/choose.py` — training: `engines/training.py` (increments, the batched loss),
`engines/gradient.py` (the no-autograd gradient); rollouts: `engines/rollout.py` (the fused Newton step),
`engines/columns.py`, `engines/scalar.py`; their closed forms in `engines/maps.py`. The articulated model
(`models/articulated/`) has its own meaning and residual objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch
from torch import nn
from torch.func import grad, jacfwd, jacrev, vmap

from ...errors import ConfigError
from ...lie import Pose, ProductGroup, so3
from ...lie.batched import HISTORY, extrapolate_increments
from ...lie.tolerances import projects_poses
from ...mechanics import kinetic
from ...mechanics.forces import RayleighForce, build_forces
from ...mechanics.parameterizations import Inertia, PositiveVector
from ...mechanics.potentials import (
    STANDARD_GRAVITY,
    GravityPotential,
    MLPPotential,
    SumPotential,
    UniformGravityPotential,
)
from ...mechanics.scene_physics import body_parameters, true_potential
from ...solvers.newton import NewtonProblem
from ...solvers.options import SolverOptions
from ...solvers.rollout import Rollout, rollout_implicit
from ..base import (
    POTENTIAL_PARTS,
    Batch,
    BuildContext,
    ImplicitModel,
    LossOptions,
    ModelPath,
    TrajectoryBatch,
    TripletBatch,
    config_options,
    initial_scale,
    oriented_logdet,
)
from ..components import component_tagger, force_parameters
from ..del_loss import del_regularity_loss
from .engines import core as fused
from .engines.choose import choose_rollout_engine, choose_training_engine
from .residual import FORMS, residual_form

RESIDUAL_MODES = tuple(FORMS)  # the residual objects' names (residual.py)
DEFAULT_RESIDUAL = "fast"  # the closed form; "generic" (autodiff) is the reference it is tested against
KINETIC_KINDS = ("auto", "per_body", "articulated")
KNOWN_PARTS = ("inertia", "potential", "damping")


def check_options(residual: str, known, physics) -> tuple[str, ...]:
    """The checks every LieDFLNN (per-body or articulated) makes of its options; returns `known` as a tuple."""
    if residual not in RESIDUAL_MODES:
        raise ValueError(f"model.residual must be one of {RESIDUAL_MODES}, got {residual!r}")
    known = tuple(known or ())
    bad = [k for k in known if k not in KNOWN_PARTS]
    if bad:
        raise ValueError(f"model.known: unknown part(s) {bad}; choose from {list(KNOWN_PARTS)}")
    if known and not physics:
        raise ValueError(
            f"model.known={list(known)} needs the scene's true parameters, but the dataset "
            "has no params['physics'] (real recordings have none)"
        )
    return known


def potential_parts(potential) -> tuple[str, ...]:
    """ "none" / a part name / a list of part names (POTENTIAL_PARTS) -> the tuple of parts."""
    if potential in (None, "none"):
        return ()
    parts = (potential,) if isinstance(potential, str) else tuple(potential)
    bad = [p for p in parts if p not in POTENTIAL_PARTS]
    if bad or len(set(parts)) != len(parts):
        raise ValueError(
            f"model.potential must be none, one of {POTENTIAL_PARTS} or a list of distinct ones, got {potential!r}"
        )
    return parts


@dataclass
class LieDFLNNOptions:
    """LieDFLNN's config options (conf/model/liedflnn.yaml; also ArticulatedLieDFLNN's): the schema
    `config/schema.py` checks the `model` section's keys and types against (`Model.Options`)."""

    # auto | none | mlp | uniform_gravity | a list of mlp, uniform_gravity
    potential: Any = field(
        default="auto",
        metadata={"choices": ("auto", "none", *POTENTIAL_PARTS), "each_of": POTENTIAL_PARTS, "item": "part"},
    )
    # fast (closed-form kinetic derivatives) | generic (autodiff of L_d): the residual objects (residual.py)
    residual: str = field(default=DEFAULT_RESIDUAL, metadata={"choices": RESIDUAL_MODES})
    # auto (articulated where the data declare a tree) | per_body (the paper's) | articulated
    kinetic: str = field(default="auto", metadata={"choices": KINETIC_KINDS})
    joints: Any = "auto"  # articulated: auto (declared, else inferred) | declared | ball | {kinds, axes}
    mlp_width: int = 64
    mlp_depth: int = 3
    init_jitter: float = 0.1
    # parts set to the scene's true values and frozen
    known: list[str] = field(default_factory=list, metadata={"each_of": KNOWN_PARTS, "item": "part"})
    gravity: Any = "auto"  # field strength of uniform_gravity: auto (the data's g, else 9.81) | a number
    learn_gravity_direction: bool = False
    substeps: int = 1  # DEL sub-steps per sample step (models/liedflnn/substeps.py): error / substeps^2
    order: int = 2  # 2: the paper's step | 4: a triple-jump composition of it (models/liedflnn/substeps.py)


ARTICULATED_TARGET = "liedfl_cli.models.articulated.ArticulatedLieDFLNN"
"""The articulated variant (its own package, which builds on this one: named, not imported)."""


class LieDFLNN(ImplicitModel):
    """Learned forced discrete mechanics on a product group (an `ImplicitModel`: trained on pose
    triplets, rolled out by Newton on the DEL residual for each increment).

    Args:
        G: group layout. h: time step.
        potential: "none", a part of POTENTIAL_PARTS ("mlp", "uniform_gravity") or a list of them (summed).
        forces: names in FORCES, or {name: options}.
        residual: "fast" (closed-form kinetic derivatives) or "generic" (autodiff of L_d).
        epsilon: log-det regularity threshold, also used to pick the initial scale.
        init_jitter, seed: the relative jitter of the initial inertia and rho_COM, drawn from a generator seeded
            with `seed`; the networks (potential, forces) draw from torch's global generator, which `liedfl
            train` seeds with the run's `seed` (seed it yourself for the same networks in a script).
        known / physics: parts set to the scene's true values and frozen.
        gravity: field strength of the uniform_gravity part; learn_gravity_direction: learn its direction too.
        path: "fused" (the fused hot paths of `models.liedflnn.engines.core`, with the fast residual) or "reference";
            default `runtime.fused` at construction (`ImplicitModel.path`; `with_path` for the other).
    """

    window = "triplet"
    notes: list[str]  # set by from_config: what `auto` options chose
    has_rollout_maps = True  # its fused rollout's maps (`fused_rollout.RolloutMaps`) describe its step

    def __init__(
        self,
        G: ProductGroup,
        h: float,
        potential="none",
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
        path: ModelPath | None = None,
    ):
        super().__init__(path)
        known = check_options(residual, known, physics)
        self.G, self.h = G, float(h)
        self.residual_form = residual_form(residual)  # closed form or autodiff, fixed here
        self.known = known
        gen = torch.Generator().manual_seed(seed)
        # Start with log|det H| at the regularity threshold so neither loss term dominates.
        body_scales = [initial_scale(h, epsilon, 6 if i < G.n_se3 else 3) for i in range(G.n_bodies)]
        scale = body_scales[0]
        if known:
            assert physics is not None  # checked above
            J_true, m_true, rho_true, D_true = body_parameters(G, physics)
            if "inertia" in known:  # forces are scaled like the true inertia
                scale = float(J_true.diagonal(dim1=-2, dim2=-1).mean())
        self.inertia = Inertia(G.n_bodies, scale=body_scales, jitter=init_jitter, generator=gen)
        self.mass: PositiveVector | None  # SE(3) bodies only
        self.rho: nn.Parameter | None  # SE(3) bodies only, (m, 3)
        if G.n_se3:
            self.mass = PositiveVector(G.n_se3, init=scale)
            self.rho = nn.Parameter(init_jitter * torch.randn(G.n_se3, 3, generator=gen, dtype=torch.float64))
        else:
            self.mass, self.rho = None, None
        if "inertia" in known:
            self.inertia.set_J(J_true)
            self.inertia.requires_grad_(False)
            if G.n_se3:
                assert self.mass is not None and self.rho is not None
                self.mass.set_value(m_true[: G.n_se3])
                self.mass.requires_grad_(False)
                with torch.no_grad():
                    self.rho.copy_(rho_true[: G.n_se3])
                self.rho.requires_grad_(False)
        parts = potential_parts(potential)
        if "potential" in known:
            if parts:
                raise ValueError(
                    f"model.potential={potential} together with model.known=[potential]: choose one "
                    "(the known potential replaces the learned one)"
                )
            assert physics is not None  # checked above
            self.potential = true_potential(G, physics)  # None when the scene has no potential
        else:
            terms: list[nn.Module] = []
            for part in parts:
                if part == "mlp":
                    terms.append(MLPPotential(G, mlp_width, mlp_depth))
                else:  # uniform_gravity: shares m and rho_COM with the kinetic term
                    terms.append(
                        UniformGravityPotential(
                            G,
                            gravity=gravity,
                            mass=self.mass,
                            rho=self.rho,
                            learn_direction=learn_gravity_direction,
                            up=gravity_up,
                        )
                    )
            self.potential = None if not terms else terms[0] if len(terms) == 1 else SumPotential(terms)
        self.forces = nn.ModuleList(build_forces(G, forces, scale))
        if "damping" in known:
            ray = [f for f in self.forces if getattr(f, "name", None) == "rayleigh"]
            if not ray:
                raise ValueError("model.known=[damping] needs the rayleigh force (force=[rayleigh,...])")
            assert isinstance(ray[0], RayleighForce)  # the force named "rayleigh"
            ray[0].D.set_matrix(D_true)
            ray[0].requires_grad_(False)

    Options = LieDFLNNOptions
    OPTIONS = tuple(f.name for f in fields(LieDFLNNOptions))

    @classmethod
    def resolve_options(cls, ctx: BuildContext, options) -> tuple[str, tuple[str, ...], str, dict]:
        """The config options of a LieDFLNN (this class's or the articulated one's) resolved against the
        data: (kinetic, potential parts, why, the other options with `known` and a numeric `gravity`).
        `model.potential: auto` reads the data (`BuildContext.resolve_potential_parts`); with a known
        potential it is none. `model.gravity: auto` is the data's declared g (9.81 when undeclared or 0)."""
        opt = config_options(cls, options, LieDFLNN.OPTIONS)
        kinetic_kind = opt.pop("kinetic", "per_body")
        if kinetic_kind not in KINETIC_KINDS:
            raise ConfigError(f"model.kinetic={kinetic_kind!r}: choose one of {', '.join(KINETIC_KINDS)}")
        known = tuple(opt.pop("known", None) or ())
        choice = opt.pop("potential", "auto")
        parts: tuple[str, ...]
        if choice == "auto" and "potential" in known:
            parts, why = (), "auto: none (model.known holds the true potential)"
        else:
            parts, why = ctx.resolve_potential_parts(choice)
        gravity = opt.pop("gravity", "auto")
        if gravity in (None, "auto"):
            declared = ctx.declared_gravity()
            gravity = declared if declared else STANDARD_GRAVITY
        try:
            gravity = float(gravity)
        except (TypeError, ValueError):
            raise ConfigError(f"model.gravity={gravity!r}: auto or a number") from None
        up = ctx.declared_gravity_up()
        extra = {"gravity_up": up} if up is not None and "uniform_gravity" in parts else {}
        return kinetic_kind, parts, why, {**opt, "known": known, "gravity": gravity, **extra}

    @classmethod
    def variant_for(cls, options: dict[str, Any], has_tree: bool) -> str | None:
        """Model only what the scene has: `kinetic: auto` is articulated on a scene that declares a
        kinematic tree, per body otherwise; articulated builds `ArticulatedLieDFLNN` with the same options."""
        if options.get("kinetic", "auto") == "auto":
            options["kinetic"] = "articulated" if has_tree else "per_body"
        return ARTICULATED_TARGET if options.get("kinetic") == "articulated" else None

    @classmethod
    def from_config(cls, ctx: BuildContext, **options) -> ImplicitModel:
        """The per-body model from its config options (`resolve_options`). What auto chose is kept in
        `notes` (printed by `liedfl train`). `model.kinetic: articulated` is built by the factory as
        `models.articulated.ArticulatedLieDFLNN` (same options). `model.substeps` / `model.order` other
        than 1 / 2 wrap it in `models.liedflnn.substeps.SubstepModel`."""
        from .substeps import with_substeps

        kinetic_kind, parts, why, opt = cls.resolve_options(ctx, options)
        substeps, order = opt.pop("substeps", 1), opt.pop("order", 2)
        joints = opt.pop("joints", "auto")
        if joints not in ("auto", "ball", None):
            raise ConfigError(
                f"model.joints={joints!r} needs an articulated model (model.kinetic=articulated and a tree)"
            )
        if kinetic_kind == "auto":
            kinetic_kind = "per_body"
        if kinetic_kind != "per_body":
            raise ConfigError(f"model.kinetic={kinetic_kind}: build it with ArticulatedLieDFLNN.from_config")
        known, gravity = opt.pop("known"), opt.pop("gravity")
        try:
            model = cls(
                ctx.group,
                ctx.h,
                potential=list(parts),
                forces=dict(ctx.forces),
                epsilon=ctx.epsilon,
                seed=ctx.seed,
                known=known,
                physics=dict(ctx.physics) if known and ctx.physics else None,
                gravity=gravity,
                **opt,
            )
        except ValueError as e:  # bad model/force options: one clear config error
            raise ConfigError(str(e)) from None
        model.notes = [f"potential: {why}"]
        return with_substeps(model, substeps, order)

    # ------------------------------------------------------------------ parameters
    def _params(self):
        Jd = self.inertia.Jd()
        if self.G.n_se3:
            assert self.mass is not None and self.rho is not None
            return Jd, self.mass(), self.rho
        empty = Jd.new_zeros(0)
        return Jd, empty, Jd.new_zeros(0, 3)

    @property
    def residual_mode(self) -> str:
        """`model.residual`: "fast" (closed form) or "generic" (autodiff), the residual object's mode."""
        return self.residual_form.mode

    @residual_mode.setter
    def residual_mode(self, mode: str) -> None:
        self.residual_form = residual_form(mode)

    def _fused(self) -> bool:
        """Whether the fused paths (`engines/core.py`) serve this model: its `path`, with the fast residual."""
        return self.residual_mode == "fast" and self.path == "fused"

    def training_set(self, data: Pose, steps: int):
        """The training samples of the engine `engines/choose.py` picks (precomputed increments on the
        fused path, pose triplets otherwise)."""
        return choose_training_engine(self).samples(self, data, steps)

    def loss(self, batch: Batch, opts: LossOptions):
        """w_DEL mean ||r||^2 + w_reg mean penalty(log|det H|) -> (loss, {"del_loss", "reg_loss"}), by the
        engine that serves the batch (`engines/choose.py`); `opts.loss` newton / rollout:
        `models.liedflnn.losses`."""
        if opts.loss != "del":
            from . import losses

            if opts.loss == "newton":
                return losses.newton_loss(self, batch, opts)
            assert isinstance(batch, TrajectoryBatch), "train.loss=rollout trains on windows (losses.WindowSet)"
            return losses.rollout_window_loss(self, batch, opts, opts.solver)
        return choose_training_engine(self, batch).loss(self, batch, opts)

    def triplet_loss(self, batch: TripletBatch, opts: LossOptions):
        """The DEL loss of a batch of pose triplets by the model's residual object: the meaning every
        training engine must equal (`engines/choose.py`)."""
        logdet = None
        if batch.reg is not None and opts.w_reg > 0:
            logdet = oriented_logdet(*self.regularity_slogdet(*batch.reg), opts.epsilon)
        return del_regularity_loss(self.residual(*batch.poses()), logdet, opts)

    # ------------------------------------------------------------------ contract hooks
    def force_terms(self) -> list[nn.Module]:
        return list(self.forces)

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        """`J_d` (B, 3, 3); for SE(3) bodies `m` (m,), `rho_COM` (m, 3); `D` of a constant Rayleigh
        damping, `C` (3, k) of a learned control."""
        with torch.no_grad():
            Jd, mass, rho = self._params()
            out = {"J_d": Jd.detach()}
            if self.G.n_se3:
                out.update({"m": mass.detach(), "rho_COM": rho.detach()})
            out.update(force_parameters(self.forces))
        return out

    def parameter_recovery(self, reference, physics) -> dict | None:
        from ..recovery import lie_recovery

        return lie_recovery(self, reference, physics) if isinstance(reference, LieDFLNN) else None

    def damping_stiffness(self) -> float | None:
        from ..stiffness import damping_stiffness

        return damping_stiffness(self)

    def components(self) -> list[str]:
        """Every active component, with its trainable parameter count or "known, frozen".

        E.g. ["J_d (6)", "V:MLP 64x3 (8,961)", "F:control (C 3x3 unit columns, u MLP 64x3) (9,420)"]
        or ["J_d (known, frozen)", "V:gravity+interaction:spring (known, frozen)", ...].
        """

        tag = component_tagger()
        out = [tag("J_d", self.inertia)]
        if self.G.n_se3:
            out += [tag("m", self.mass), tag("rho_COM", self.rho)]
        if self.potential is not None:
            desc = self.potential.describe() if hasattr(self.potential, "describe") else type(self.potential).__name__
            out.append(tag(f"V:{desc}", self.potential))
        for f in self.forces:
            describe = getattr(f, "describe", None)
            desc = describe() if describe is not None else getattr(f, "name", type(f).__name__)
            out.append(tag(f"F:{desc}", f))
        return out

    # ------------------------------------------------------------------ pieces of L_d and F
    def lagrangian(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """L_d(g, g_next), shape (...)."""
        Jd, m, rho = self._params()
        L = kinetic.kinetic_lagrangian(self.G, self.G.increment(g, g_next), Jd, m, rho, self.h)
        if self.potential is not None:
            L = L - self.h * self.potential(g)
        return L

    def half_force(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """(h/2) sum of forces at (g, xi~(g, g_next)), shape (..., dim)."""
        xi = kinetic.velocity_estimate(self.G, self.G.increment(g, g_next), self.h)
        out = torch.zeros_like(xi)
        for f in self.forces:
            out = out + f(g, xi)
        return 0.5 * self.h * out

    def potential_covector(self, g: Pose) -> torch.Tensor:
        """-h dV(g exp(eta))/d(eta) at 0, shape (..., dim) (zeros without a potential)."""
        eta = g.R.new_zeros(*g.R.shape[:-3], self.G.dim)
        if self.potential is None:
            return eta
        if isinstance(self.potential, (UniformGravityPotential, GravityPotential)):  # closed form (tested)
            return -self.h * self.potential.left_gradient(g)
        dV = grad(lambda e: self.potential(self.G.perturb(g, e)).sum())(eta)
        return -self.h * dV

    # ------------------------------------------------------------------ residual
    def residual_const(self, g_prev: Pose, g: Pose) -> torch.Tensor:
        """Terms of the residual at g fixed by (g_prev, g): D2 L_d(g_prev, g) + F^+ (+ potential),
        by the model's residual object (`residual.py`: closed form or autodiff, fixed at construction)."""
        return self.residual_form.const(self, g_prev, g)

    def residual_var(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """Terms depending on g_next: D1 L_d(g, g_next) + F^- (the potential is in `residual_const`
        for the closed form, inside D1 L_d for autodiff)."""
        return self.residual_form.var(self, g, g_next)

    def jacobian_var(self, g: Pose, inc: Pose) -> torch.Tensor:
        """d residual_var(g, g inc exp(delta)) / d delta at 0, shape (..., dim, dim): the kinetic mixed
        Hessian plus each force's (h/2) dF/d xi~ . d xi~/d delta (closed form), or autodiff."""
        return self.residual_form.jacobian_var(self, g, inc)

    def value_and_grad(self, samples, opts: LossOptions, params: list[nn.Parameter]):
        """`Model.value_and_grad`: the SO(3)-only fused gradient (`engines/gradient.py`) where it applies."""
        if type(self) is not LieDFLNN:  # a subclass may have other parameters
            return None
        return choose_training_engine(self).value_and_grad(self, samples, opts, params)

    # ------------------------------------------------------------------ implicit step (rollout)
    def rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions | None = None, progress=None) -> Rollout:
        """`ImplicitModel.rollout` by the engine `engines/choose.py` picks: a single SO(3) body with at
        most constant Rayleigh damping rolls out in Python floats (few trajectories) or column layout (many:
        the same steps, several times faster at large batches) on the fused path; everything else in rows."""
        engine = choose_rollout_engine(self, g0, steps)  # scalar | columns | rows (engines/choose.py)
        return engine.rollout(self, g0, g1, steps, opts or SolverOptions(), progress)

    def rollout_rows(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout:
        """The rollout in row layout (`solvers.rollout.rollout_implicit`); its fused Newton step is
        compiled when the model's plan asks for it at this rollout's size (trajectories x steps)."""
        compile_it = self._fused() and self.plan.wants_compile("rollout", g0.R.shape[0] * max(steps - 1, 0))
        return rollout_implicit(
            self, g0, g1, steps, opts, progress, start=lambda a, b: self.implicit_start(a, b, compile=compile_it)
        )

    def implicit_start(self, g0: Pose, g1: Pose, compile: bool = False):
        """State (g_{k-1}, g_k, the last increment g_{k-1}^{-1} g_k, the increments before it: a tuple,
        oldest first, at most `HISTORY` - 1 of them, the warm start's history); on the fused path a
        `fused.RolloutState` that also carries the parameters derived once for the rollout (and, with
        `compile`, the compiled Newton step)."""
        if self._fused():
            return fused.rollout_start(self, g0, g1, compile)
        return g0, g1, self.G.increment(g0, g1), ()

    def implicit_problem(self, state) -> NewtonProblem:
        """Solve the DEL residual for the increment W_k = g_k^{-1} g_{k+1}, updated by W exp(delta)
        (so it stays on the group), warm-started from the last increments extrapolated
        (`lie.batched.extrapolate_increments`: off by O(h^4) from the third step on); the part of the
        residual fixed by (g_{k-1}, g_k) is computed once."""
        if isinstance(state, fused.RolloutState):
            return fused.rollout_problem(self, state)
        g_prev, g, inc, before = state
        G = self.G
        x0 = extrapolate_increments(G, (*before, inc))
        with torch.enable_grad():  # potential gradients and autodiff Jacobians need autograd
            const = self.residual_const(g_prev, g).detach()

        def f(x):
            with torch.enable_grad():
                return const + self.residual_var(g, G.compose(g, x))

        def jac(x):
            with torch.enable_grad():
                return self.jacobian_var(g, x)

        return NewtonProblem(f, jac, x0, G.retract)

    def scaled_start(self, state, inc: Pose, ratio: float):
        """`state` (from `implicit_start(g_prev, g)`) warm-starting a step `ratio` times as long as the last:
        its last increment replaced by `inc`, that increment scaled (the sub-step cycles of
        `models.liedflnn.substeps`); no history of earlier increments."""
        if isinstance(state, fused.RolloutState):
            return replace(state, inc=inc)
        g_prev, g, _, _ = state
        return g_prev, g, inc, ()

    def implicit_advance(self, state, x: Pose):
        # Newton-Schulz step on the increment: its retractions would otherwise accumulate
        # rounding drift off SO(3) across the warm-started steps (O(k eps) instead of O(sqrt(k) eps)).
        if isinstance(state, fused.RolloutState):
            return fused.rollout_advance(self, state, x)
        _, g, last, before = state
        W = x.R.detach()
        W = 0.5 * W @ (3.0 * torch.eye(3, dtype=W.dtype, device=W.device) - W.transpose(-1, -2) @ W)
        inc = Pose(W, x.p.detach())
        g_next = self.G.compose(g, inc)
        if projects_poses(W.dtype):  # below float64 the composed poses drift off SO(3) too
            g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
        return (g, g_next, inc, (*before, last)[1 - HISTORY :]), g_next

    def residual(self, g_prev: Pose, g: Pose, g_next: Pose) -> torch.Tensor:
        """Forced DEL residual at g, shape (..., dim); zero on exact solutions of the learned scheme."""
        return self.residual_const(g_prev, g) + self.residual_var(g, g_next)

    # ------------------------------------------------------------------ regularity
    def mixed_hessian_autodiff(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """H = d^2 L_d(g exp(a), g_next exp(b)) / da db at 0 by autodiff, shape (..., dim, dim).

        Potentials depend on one time level and drop out; the kinetic part is used. Reference
        for `kinetic.mixed_hessian_blocks` (the closed form used in training).
        """
        G, h = self.G, self.h
        Jd, m, rho = self._params()
        delta = G.increment(g, g_next)
        lead = delta.R.shape[:-3]
        n = math.prod(lead)
        flat = Pose(delta.R.reshape(n, *delta.R.shape[-3:]), delta.p.reshape(n, *delta.p.shape[-2:]))

        def K(a, b, d: Pose):
            inc = G.compose(G.compose(G.exp(-a), d), G.exp(b))
            return kinetic.kinetic_lagrangian(G, inc, Jd, m, rho, h)

        zero = Jd.new_zeros(G.dim)
        H = vmap(lambda d: jacfwd(jacrev(K, argnums=1), argnums=0)(zero, zero, d))(flat)
        return H.reshape(*lead, G.dim, G.dim)

    def regularity_logdet(self, g: Pose, g_next: Pose) -> torch.Tensor:
        """log|det| of each body's diagonal block of the mixed Hessian, shape (..., B)."""
        return self.regularity_slogdet(g, g_next)[0]

    def regularity_slogdet(self, g: Pose, g_next: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        """(log|det H_b|, sign det(-H_b)) of each body's diagonal block H_b of the mixed Hessian,
        both (..., B); sign det(-H_b) = +1 is the normal orientation (`base.oriented_logdet`)."""
        blocks = self.residual_form.hessian_blocks(self, g, g_next)
        sl = [torch.linalg.slogdet(b) for b in blocks]
        sign = [s.sign if b.shape[-1] % 2 == 0 else -s.sign for s, b in zip(sl, blocks)]  # det(-H) = (-1)^n det H
        return torch.stack([s.logabsdet for s in sl], -1), torch.stack(sign, -1)
