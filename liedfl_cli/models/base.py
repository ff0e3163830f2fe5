"""The one model contract: what every model (LieDFLNN and each baseline) gives training,
rollout and evaluation, and the typed pieces exchanged with them.

A model is an `nn.Module` subclass of `Model` that provides

    Model.from_config(ctx, **options)   build from the scene (`BuildContext`) and its config options
    model.window                        "triplet" | "trajectory": what one training sample is
    model.training_set(data, steps)     the samples of a train split (`TripletSet` | `TrajectorySet`)
    model.loss(batch, opts)             (scalar loss, {part name: scalar}) for one batch
    model.rollout(g0, g1, steps, opts)  `solvers.rollout.Rollout` predicted from the first two poses
    model.components()                  human-readable list of the active parts

Rollouts are run by one loop per kind of model (`solvers.rollout`): `ImplicitModel`s (the DEL
models: LieDFLNN, Euler-angle and Euclidean DFLNN) describe one implicit step as a Newton
problem; `ExplicitModel`s (GLNN, Neural ODE) describe an integrator step, or integrate the
whole time grid at once when their integrator is adaptive.

Nothing here knows about Hydra: the pipeline (`liedfl_cli.config.factory`) turns configs into a
`BuildContext` and plain keyword options.
"""

from __future__ import annotations

import abc
import copy
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import torch
from torch import nn

from ..errors import ConfigError
from ..lie import Pose, ProductGroup
from ..lie.tree import Tree
from ..solvers.execution import ExecutionPlan, ModelPath
from ..solvers.newton import NewtonProblem, NewtonResult
from ..solvers.options import SolverOptions
from ..solvers.rollout import Rollout, rollout_explicit, rollout_implicit

WINDOWS = ("triplet", "trajectory")
"""Which implementation serves an `ImplicitModel` (`ImplicitModel.path`)."""


def initial_scale(h: float, epsilon: float, n: int) -> float:
    """Kinetic scale s with n log(s / h) = epsilon.

    A discrete Lagrangian whose mixed Hessian is ~ -(s/h) I_n then starts exactly at the
    regularity threshold log|det H| = epsilon, so neither loss term dominates at the start.
    """
    return h * math.exp(epsilon / n)


def so3_pose(R: torch.Tensor) -> Pose:
    """Rotations (..., 3, 3) of one SO(3) body -> Pose R (..., 1, 3, 3), p (..., 0, 3)."""
    return Pose(R[..., None, :, :], R.new_zeros(*R.shape[:-2], 0, 3))


def require_single_so3(G: ProductGroup, what: str) -> None:
    if G.n_se3 != 0 or G.n_so3 != 1:
        raise ConfigError(f"{what} models a single rigid body on SO(3); this dataset's group is {G.name}")


# ---------------------------------------------------------------------------- build context
POTENTIAL_PARTS = ("mlp", "uniform_gravity")
"""Potential parts a LieDFLNN can sum (`model.potential` is one of them, a list of them, none or auto)."""


@dataclass(frozen=True)
class BuildContext:
    """What a model needs to know about the scene and the run to be built.

    group: the dataset's group layout. h: time step. seed: initialisation seed.
    epsilon: regularity threshold (train.epsilon), also used for the initial scale.
    forces: the `force` group as {name: options} (empty: no learned force).
    physics: the scene's true parameters (a synthetic dataset's params["physics"]) or None.
    metadata: the dataset's whole `params` (declarations such as params["gravity"]) or None.
    tree: the dataset's kinematic tree (`Dataset.tree`: parents, joint offsets, rotation convention,
    free or pinned root) or None when the data declare none.
    """

    group: ProductGroup
    h: float
    seed: int = 0
    epsilon: float = 10.0
    forces: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    physics: Mapping[str, Any] | None = None
    metadata: Mapping[str, Any] | None = None
    tree: Tree | None = None
    train_poses: Callable[[], Pose] | None = None  # the training trajectories (joint inference reads them)
    total_mass: float | None = None  # dataset.total_mass: the scale gauge of an articulated model (kg)

    # -------------------------------------------------------------- what the data declare
    def declared_gravity(self) -> float | None:
        """The field strength the data declare: params["physics"]["g"] (generated scenes) or
        params["gravity"] (any file: the magnitude along -e3, 0 for none); None if undeclared."""
        physics, meta = self.physics or {}, self.metadata or {}
        value = physics.get("g") if "g" in physics else meta.get("gravity")
        if value is None or isinstance(value, bool):
            return 0.0 if value is False else None
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"dataset params: gravity={value!r} is not a number") from None

    def declared_gravity_up(self) -> tuple[float, float, float] | None:
        """The unit "up" direction the data declare (params["gravity_up"], -acceleration / |acceleration|,
        written by `dataset=import dataset.gravity=[gx,gy,gz]`); None: +e3 (gravity along -e3)."""
        up = (self.metadata or {}).get("gravity_up")
        if up is None:
            return None
        try:
            out = tuple(float(x) for x in up)
        except (TypeError, ValueError):
            raise ConfigError(f"dataset params: gravity_up={up!r} is not a 3-vector") from None
        if len(out) != 3 or not all(math.isfinite(x) for x in out) or not any(out):
            raise ConfigError(f"dataset params: gravity_up={up!r} is not a non-zero 3-vector")
        return out[0], out[1], out[2]

    def declares_no_potential(self) -> bool:
        """params["potential"] == "none": the data say there is no potential at all."""
        return str((self.metadata or {}).get("potential", "")).lower() == "none"

    def declares_interaction(self) -> bool:
        return bool((self.physics or {}).get("interaction"))

    def scene_has_potential(self) -> bool:
        """False only when the data say there is none (see `resolve_potential_parts`)."""
        return bool(self.resolve_potential_parts("auto")[0])

    def resolve_potential_parts(self, choice: Any) -> tuple[tuple[str, ...], str]:
        """`model.potential` -> (the potential parts to sum, why). `auto` reads the data:

        - none for data declaring no potential (params["potential"] = "none"), for a free body (one
          body, gravity declared 0) and for several bodies with gravity 0 and no declared interaction;
        - uniform_gravity where the data declare gravity g > 0, plus an MLP for a declared interaction;
        - none otherwise (nothing declared: real recordings, a user's file without metadata), with
          the overrides in the note: model.potential=mlp for a learned V(g), dataset.gravity to declare it.
        Other choices: a part name, a list of them, or none.
        """
        if isinstance(choice, str):
            if choice == "auto":
                return self._auto_potential()
            if choice == "none":
                return (), "model.potential=none"
            parts: tuple[str, ...] = (choice,)
        elif isinstance(choice, (list, tuple)):
            parts = tuple(str(c) for c in choice)
        else:
            raise ConfigError(f"model.potential={choice!r}: a name or a list of names")
        bad = [p for p in parts if p not in POTENTIAL_PARTS]
        if bad or not parts or len(set(parts)) != len(parts):
            what = f"unknown part {bad[0]!r}" if bad else "empty or repeated parts"
            raise ConfigError(
                f"model.potential={choice!r}: {what}; choose auto, none, one of {', '.join(POTENTIAL_PARTS)} "
                "or a list of them (e.g. [uniform_gravity,mlp])"
            )
        return parts, f"model.potential={list(parts) if len(parts) > 1 else parts[0]}"

    def _auto_potential(self) -> tuple[tuple[str, ...], str]:
        if self.declares_no_potential():
            return (), "auto: none (the data declare no potential)"
        g = self.declared_gravity()
        inter = self.declares_interaction()
        if g is None:
            return (), (
                "auto: none (the data declare no gravity or potential; model.potential=mlp learns one, "
                "dataset.gravity=9.81 declares gravity on import)"
            )
        parts = (("uniform_gravity",) if g != 0.0 else ()) + (("mlp",) if inter else ())
        why = [f"the data declare gravity g = {g:g}" if g != 0.0 else "the data declare g = 0"]
        if inter:
            why.append("and an interaction (learned by the MLP)")
        if not parts:
            what = "a free body" if self.group.n_bodies == 1 else "no interaction declared"
            why.append(f"({what})")
        return parts, f"auto: {'+'.join(parts) or 'none'} ({' '.join(why)})"

    def resolve_potential(self, choice: str) -> str:
        """For models with only an MLP potential (the baselines): `auto` -> "none" where the data have
        no potential (`resolve_potential_parts`), else "mlp"; mlp / none as given."""
        if choice not in ("auto", "mlp", "none"):
            raise ConfigError(f"model.potential={choice!r}: this model supports auto, mlp or none")
        if choice != "auto":
            return choice
        return "mlp" if self.scene_has_potential() else "none"

    def resolve_damping(self, choice: Any) -> bool:
        """`auto` -> learned Rayleigh damping iff the force group contains rayleigh."""
        if choice == "auto":
            return "rayleigh" in self.forces
        if isinstance(choice, bool):
            return choice
        raise ConfigError(f"model.damping={choice!r}: choose auto, true or false")


# ---------------------------------------------------------------------------- losses
@dataclass(frozen=True)
class LossOptions:
    """Loss settings of the train config (paper: w_DEL = w_reg = 0.5, 10 regularity points).

    w_del, w_reg: weights of mean ||r||^2 and of the regularity penalty. epsilon: threshold on
    log|det H| per body block. reg_form: relu | gaussian. reg_points: pairs drawn per batch for
    the regularity term (0 = none). loss: del | newton | rollout (`models.liedflnn.losses`; w_del then
    weighs mean ||H^-1 r||^2 for newton). rollout_horizon: steps k of the rollout loss's windows;
    solver: the Newton settings of its solves (the run's `solver` section, set by the fine-tuning stage)."""

    w_del: float = 0.5
    w_reg: float = 0.5
    epsilon: float = 10.0
    reg_form: str = "relu"
    reg_points: int = 10
    loss: str = "del"
    rollout_horizon: int = 5
    solver: SolverOptions | None = None  # the rollout loss's Newton solves (None: SolverOptions())
    # built from the `train` section by liedfl_cli/config/typed.py (TrainConfig.loss_options)


def oriented_logdet(logabsdet: torch.Tensor, orientation: torch.Tensor | None, epsilon: float) -> torch.Tensor:
    """The log-det the regularity penalty sees, per body block: log|det H_b| where the block has
    its normal orientation (`orientation` = sign det(-H_b) > 0; -H_b is the body's mass matrix
    over h at small increments), and epsilon - 1 - |log|det H_b| - epsilon| where it does not
    (det(-H_b) <= 0), so a block of the wrong orientation is penalised however large |det H_b| is:
    at least as much as a right one 1 below the threshold. Finite wherever |det H_b| > 0 and equal
    to `logabsdet` (the same tensor values, the same gradient) on normally oriented blocks.
    `orientation` None: no sign information (`logabsdet` as is)."""
    if orientation is None:
        return logabsdet
    return torch.where(orientation > 0, logabsdet, epsilon - 1.0 - (logabsdet - epsilon).abs())


LossParts = dict[str, torch.Tensor]


# ---------------------------------------------------------------------------- batches
@dataclass
class TripletBatch:
    """Pose triplets (g_{k-1}, g_k, g_{k+1}), each with leading shape (N,), and optionally
    `reg`: pairs (g, g_next) with leading shape (P,) for the regularity term."""

    prev: Pose
    cur: Pose
    nxt: Pose
    reg: tuple[Pose, Pose] | None = None

    def poses(self) -> tuple[Pose, Pose, Pose]:
        return self.prev, self.cur, self.nxt

    def as_sequence(self) -> Pose:
        """The triplets as length-2 trajectories: R (N, 3, B, 3, 3), p (N, 3, m, 3)."""
        stack = lambda *xs: torch.stack(xs, 1)
        return Pose(stack(self.prev.R, self.cur.R, self.nxt.R), stack(self.prev.p, self.cur.p, self.nxt.p))


@dataclass
class TrajectoryBatch:
    """Whole training windows: R (N, L+1, B, 3, 3), p (N, L+1, m, 3)."""

    traj: Pose

    def as_sequence(self) -> Pose:
        return self.traj


Batch = TripletBatch | TrajectoryBatch


class TripletSet:
    """Every triplet (g_{k-1}, g_k, g_{k+1}) with k + 1 <= steps of trajectories (T, N+1, ...),
    flattened to (T * (steps - 1), ...)."""

    def __init__(self, data: Pose, steps: int):
        steps = min(int(steps), data.R.shape[1] - 1)
        if steps < 2:
            raise ConfigError(f"dataset.train_steps={steps}: need at least 2 steps to form a triplet")

        def cut(a: int, b: int) -> Pose:
            return Pose(data.R[:, a:b].flatten(0, 1), data.p[:, a:b].flatten(0, 1))

        self.prev, self.cur, self.nxt = cut(0, steps - 1), cut(1, steps), cut(2, steps + 1)
        self.n = self.prev.R.shape[0]

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> TripletBatch:
        """Triplets `idx` plus `reg_points` random pairs drawn from `generator` (none when 0)."""
        reg = None
        if reg_points > 0:
            reg_idx = torch.randint(0, self.n, (int(reg_points),), generator=generator).to(self.cur.R.device)
            reg = (self.cur.index(reg_idx), self.nxt.index(reg_idx))
        idx = idx.to(self.cur.R.device)  # (drawn on the CPU generator of the training loop)
        return TripletBatch(self.prev.index(idx), self.cur.index(idx), self.nxt.index(idx), reg)


class TrajectorySet:
    """The first `steps` steps of every trajectory: (T, steps + 1, ...)."""

    def __init__(self, data: Pose, steps: int):
        if int(steps) < 1:
            raise ConfigError(f"dataset.train_steps={steps}: need at least 1 step")
        self.traj = data.index((slice(None), slice(0, int(steps) + 1)))
        self.n = self.traj.R.shape[0]

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> TrajectoryBatch:
        return TrajectoryBatch(self.traj.index(idx.to(self.traj.R.device)))


TrainingSet = TripletSet | TrajectorySet


# ---------------------------------------------------------------------------- the contract
ModelT = TypeVar("ModelT", bound="Model")


class Model(nn.Module, abc.ABC):
    """Base class of every model. Subclasses set `G`, `h` and `window` and implement the
    abstract methods; `name` is the config option that built the model (e.g. "glnn_rk4")."""

    G: ProductGroup
    h: float
    window: str = "triplet"
    name: str = ""
    notes: Sequence[str] = ()
    """What the model's `auto` options chose and why (printed by `liedfl train`, kept in the run)."""
    tree: Tree | None = None
    """The kinematic tree the model runs forward kinematics with (None: the model has none)."""
    needs_tree: bool = False
    """Whether the model can only be built on data that declare a kinematic tree (the articulated one)."""
    Options: type | None = None
    """A dataclass of the model's config options (keys and types checked against it before a run
    starts, `config/schema.py`); None: its `from_config` checks them (`config_options`)."""
    plan: ExecutionPlan
    """How the model is computed (`solvers.execution.ExecutionPlan`): its path ("fused" | "reference":
    its fast engines where they apply, or the reference paths) and compile policy. Defaults to the
    fused paths; the pipeline gives every model it builds the command's plan (`set_plan`, from the
    `runtime` section); nothing is read from a process global. `with_path` gives the same model,
    parameters shared, on the other path."""

    def __init__(self, path: ModelPath | None = None, plan: ExecutionPlan | None = None):
        super().__init__()
        plan = plan if plan is not None else ExecutionPlan()
        self.plan = plan.on_path(path) if path is not None else plan

    @property
    def path(self) -> ModelPath:
        """The plan's path, fixed until `set_plan`: which implementation serves training and rollouts."""
        return self.plan.path

    def set_plan(self, plan: ExecutionPlan) -> None:
        """Run under `plan` from now on: this model and every model it holds (a wrapped model, twins)."""
        for module in self.modules():
            if isinstance(module, Model):
                module.plan = plan
                module.plan_changed()

    def plan_changed(self) -> None:
        """Hook: drop what was built for the previous plan (cached twins, engines)."""

    def with_path(self: ModelT, path: ModelPath) -> ModelT:
        """A copy of this model on `path` sharing every parameter, buffer and submodule (a step of an
        optimiser on one moves the other)."""
        twin = copy.copy(self)
        # the copy's own registries (so attributes set on one do not appear on the other), same tensors
        twin._parameters = dict(self._parameters)
        twin._buffers = dict(self._buffers)
        twin._modules = dict(self._modules)
        twin.plan = self.plan.on_path(path)
        return twin

    @classmethod
    def variant_for(cls, options: dict[str, Any], has_tree: bool) -> str | None:
        """The `_target_` of the model to build instead of this class for `options` on a scene with
        (`has_tree`) or without a declared kinematic tree, or None for this class; may set an `auto`
        option in `options` to what it chose (the factory asks before `from_config`)."""
        return None

    @classmethod
    @abc.abstractmethod
    def from_config(cls, ctx: BuildContext, **options: Any) -> Model:
        """Build for the scene `ctx` from the model's config options (unknown keys: TypeError)."""

    def training_set(self, data: Pose, steps: int) -> TrainingSet:
        """Training samples of trajectories `data` (T, N+1, ...) over their first `steps` steps."""
        if self.window == "triplet":
            return TripletSet(data, steps)
        if self.window == "trajectory":
            return TrajectorySet(data, steps)
        raise ConfigError(f"model window {self.window!r} is not one of {', '.join(WINDOWS)}")

    @abc.abstractmethod
    def loss(self, batch: Batch, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
        """Scalar training loss of one batch and its named parts (for the metrics table)."""

    @abc.abstractmethod
    def rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions | None = None, progress=None) -> Rollout:
        """Predict g_2..g_steps from g0, g1 (leading batch dim T); the result starts with g0, g1."""

    @abc.abstractmethod
    def components(self) -> list[str]:
        """Active components, e.g. ["J_d (6)", "F:rayleigh D (6)"]."""

    # -------------------------------------------------------------- optional hooks
    def force_terms(self) -> list[nn.Module]:
        """The learned non-conservative force terms (each with a `name`: rayleigh, control, ...);
        [] for a model without separate force terms."""
        return []

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        """Interpretable learned parameters by name (`api.parameters`): e.g. `J_d` (B, 3, 3), `m` (m,),
        `rho_COM` (m, 3), `D` (dim, dim), `C` (3, k); {} for a model without any."""
        return {}

    def parameter_recovery(self, reference: Model, physics: Mapping[str, Any]) -> dict | None:
        """Learned against true parameters: `reference` is the true-parameter model of the scene
        (`true_scheme.true_model`), `physics` the scene's declared physics. None where the model has
        no parameters comparable with the reference's."""
        return None

    def damping_stiffness(self) -> float | None:
        """h lambda_max(M^-1 D) of a constant learned damping (`models.stiffness`); None where the
        model has none or it is not checked."""
        return None

    def value_and_grad(
        self, samples: Any, opts: LossOptions, params: list[nn.Parameter]
    ) -> Callable[[Any, LossOptions], tuple[Any, dict[str, float], list | None]] | None:
        """A training batch's loss and the gradients of `params` without autograd, where the model has
        a fused gradient for `samples` under `opts`: a callable (batch, opts) -> (loss, parts, grads;
        grads None when the loss is not finite: loss is then what it became); None: autograd's backward."""
        return None

    def initial_fit(self, samples: Any, method: str = "auto") -> str | None:
        """Fit the model to its training samples (`training_set`) before the first epoch, where the
        model has a closed-form or second-order start (`train.start`: auto, or identify where the model
        has a second-order fit); returns a line saying what it did, or None where it has none."""
        return None

    def multibody(self) -> dict[str, Any] | None:
        """The model as a multibody simulator reads it (`liedfl export`), or None where the model is not
        a kinematic tree: {"tree": Tree (its joints), "mass" (B,), "com" (B, 3) body frame from the joint,
        "inertia" (B, 3, 3) about the COM, "dof_damping" (n,) per DoF, "gravity" (3,) the field's vector
        (zeros without one), "unexported": [what a simulator model cannot carry]}; tensors on the model's device."""
        return None

    def joint_record(self) -> dict[str, Any] | None:
        """The joints a tree model runs with, to store with the run: {"kinds", "axes", "dof", "inference"
        (the inference's table or None)}; None for a model without a tree."""
        return None


class ImplicitModel(Model):
    """A model whose step solves an implicit equation r(g_{k-1}, g_k, g_{k+1}) = 0 (the DEL
    models). `state` is whatever the model carries from step to step.

    Its `path` (see `Model`) also picks the Newton loop of its rollouts (`solvers.newton.solve`,
    `reference=True` on the reference path)."""

    def __init__(self, path: ModelPath | None = None, plan: ExecutionPlan | None = None):
        super().__init__(path, plan)

    @abc.abstractmethod
    def implicit_start(self, g0: Pose, g1: Pose) -> Any:
        """State before the first implicit step (the pair g0, g1 in the model's coordinates)."""

    @abc.abstractmethod
    def implicit_problem(self, state: Any) -> NewtonProblem:
        """The Newton problem whose root gives the next configuration."""

    @abc.abstractmethod
    def implicit_advance(self, state: Any, x: Any) -> tuple[Any, Pose]:
        """(next state, predicted pose g_{k+1}) from the solution x of `implicit_problem`."""

    def native_rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout | None:
        """The whole rollout in native code where the model has it and it serves these inputs, else None
        (the default: `rollout_implicit`'s loop of `implicit_problem` / `implicit_advance` serves)."""
        return None

    def rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions | None = None, progress=None) -> Rollout:
        return rollout_implicit(self, g0, g1, steps, opts or SolverOptions(), progress)


class ExplicitModel(Model):
    """A continuous-time model advanced by an integrator (GLNN, Neural ODE). Fixed-step
    integrators implement `step`; adaptive ones (`adaptive = True`) implement `integrate`."""

    adaptive: bool = False

    @abc.abstractmethod
    def initial_state(self, g0: Pose, g1: Pose) -> Any:
        """State at t = 0 (g0 and a velocity estimated from g0, g1)."""

    @abc.abstractmethod
    def state_pose(self, state: Any) -> Pose:
        """The configuration of a state, leading shape (T,)."""

    def step(self, state: Any, opts: SolverOptions) -> tuple[Any, NewtonResult | None]:
        """One step of length h; implicit integrators return their Newton diagnostics."""
        raise NotImplementedError(f"{type(self).__name__} integrates adaptively (see integrate)")

    def integrate(self, state: Any, steps: int) -> Pose:
        """Configurations at t = 0, h, ..., steps h: leading shape (T, steps + 1)."""
        raise NotImplementedError(f"{type(self).__name__} integrates step by step (see step)")

    def rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions | None = None, progress=None) -> Rollout:
        return rollout_explicit(self, g0, g1, steps, opts or SolverOptions(), progress)


def tensor_placement(module: Any) -> dict[str, Any]:
    """{"device", "dtype"} of a module's first floating-point parameter or buffer, for `Tensor.to(**...)`
    of the inputs given to it ({} for anything else: inputs stay as they are). The pipeline decides
    where models live (`factory.place`); code that feeds them data of its own reads it here."""
    if isinstance(module, nn.Module):
        for t in itertools.chain(module.parameters(), module.buffers()):
            if t.is_floating_point():
                return {"device": t.device, "dtype": t.dtype}
    return {}


def config_options(cls: type, options: Mapping[str, Any], allowed: tuple[str, ...]) -> dict[str, Any]:
    """`options` checked against the names a model's config accepts (one-line error otherwise)."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], allowed, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(
            f"model ({cls.__name__}): unknown key '{unknown[0]}'{hint}; expected some of {', '.join(sorted(allowed))}"
        )
    return dict(options)
