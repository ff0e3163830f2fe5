"""Sub-steps and a fourth-order step for the DEL models (`model.substeps`, `model.order`).

A sample interval [t_k, t_k + h] is divided into sub-steps c_1 h, ..., c_n h with sum c_j = 1:

- `substeps=s`, `order=2`: c_j = 1/s. The paper's second-order scheme at step h/s: error / s^2.
- `order=4`: each of the s parts is the triple jump (g1, g2, g1)/s with g1 = 1/(2 - 2^(1/3)),
  g2 = 1 - 2 g1 < 0 (Yoshida's composition). The sub-step map is the symmetric one (the potential at a
  pose weighted by the mean of its two sub-steps, forces as in the paper), so the composition is of
  order 4 for conservative parts and velocity-only forces such as Rayleigh damping.

The discrete Lagrangian of a sample step is the stationary value of the sum of the sub-step ones over
the internal poses z_1..z_{n-1} (z_0 = q_k, z_n = q_{k+1}), found by Newton (`internal_poses`), the
internal poses moved along the model's own DoF (the joints of a tree), so they never leave the group.
By stationarity the DEL equation at a sample pose q_k is the sub-step residual at q_k between the last
internal pose a of [k-1, k] and the first internal pose b of [k, k+1]:

    r_k = A_{c_n h}(a, q_k) + B_{c_1 h}(q_k, b)

(A: the terms of D2 L_d + F^+ of the interval before q_k, B: those of D1 L_d + F^- after it). Training
fits r_k = 0 on the data's triplets; the internal poses depend on the parameters theta through
F(z, theta) = 0, and one Newton step from the solution z* taken with theta live,
z(theta) = z* exp(-J^-1 F(z*, theta)), has the derivative -J^-1 dF/dtheta of the implicit function
theorem (F(z*) = 0 makes the derivative of J^-1 drop out). A rollout takes the momentum at q_1 from the
internal poses of [q_0, q_1] (the composite discrete Legendre transform, as accurate as the scheme) and
then runs the sub-step DEL map n times per sample.

The parameters (J_d, m, rho_COM, D, V) are continuous-time quantities: the model at h/s shares every
parameter with the model at h (`_twin`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from ...errors import ConfigError
from ...lie import Pose
from ...lie import joints as jt
from ...lie.batched import retract_increment
from ...solvers.newton import NewtonProblem
from ...solvers.options import SolverOptions
from ...solvers.rollout import Rollout, rollout_implicit
from ..base import ImplicitModel, LossOptions, TripletBatch, TripletSet, oriented_logdet
from ..del_loss import del_regularity_loss

GAMMA1 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
GAMMA2 = 1.0 - 2.0 * GAMMA1
ORDERS = (2, 4)
MAX_SUBSTEPS = 64
INTERNAL_TOL = 1e-11  # max-norm of the last Newton step of the internal poses (relative to their size)
INTERNAL_MAX_ITER = 25
MAX_HALVINGS = 8
FD_STEP = 1e-5  # central differences of the internal Jacobian (error ~FD_STEP^2 relative)


def check_steps(substeps: Any, order: Any) -> tuple[int, int]:
    """(substeps, order) as ints, or ConfigError naming the option and its allowed values."""
    try:
        s = int(substeps)
        if s != substeps or isinstance(substeps, bool):
            raise ValueError
    except (TypeError, ValueError):
        raise ConfigError(f"model.substeps={substeps!r}: an integer from 1 to {MAX_SUBSTEPS}") from None
    if not 1 <= s <= MAX_SUBSTEPS:
        raise ConfigError(f"model.substeps={substeps!r}: an integer from 1 to {MAX_SUBSTEPS}")
    if isinstance(order, bool) or order not in ORDERS:
        raise ConfigError(f"model.order={order!r}: 2 (the paper's scheme) or 4 (a triple-jump composition)")
    return s, int(order)


def step_fractions(substeps: int, order: int) -> tuple[float, ...]:
    """The sub-steps c_1..c_n of one sample step as fractions of h (sum 1, symmetric)."""
    base = (1.0,) if order == 2 else (GAMMA1, GAMMA2, GAMMA1)
    return tuple(c / substeps for _ in range(substeps) for c in base)


# ---------------------------------------------------------------------------- the model's DoF
def _reduced(m: Any) -> bool:
    """Whether `m` is an articulated model on its joints' DoF (hinge, universal or weld joints)."""
    return bool(getattr(m, "reduced", False))


def n_dof(m: Any) -> int:
    """Unknowns per pose: the tree's DoF on a reduced tree, else the group's dimension."""
    return int(m.tree.n_dof) if _reduced(m) else int(m.G.dim)


def move(m: Any, z: Pose, d: torch.Tensor) -> Pose:
    """The pose z moved by d (..., n_dof) along the model's DoF: z exp(d), or along the joints."""
    G = m.G
    if not _reduced(m):
        return retract_increment(G, z, d)  # closed form without a graph (internal-pose solves), else G.retract
    # straight through the joint coordinates: z z^-1 (...) would compound rounding off the group
    return jt.from_joint_coordinates(m.tree, jt.advance(m.tree, jt.to_joint_coordinates(m.tree, z), d))


def dof_log(m: Any, z0: Pose, z1: Pose) -> torch.Tensor:
    """d (..., n_dof) with move(z0, d) ~ z1 (exact off a reduced tree; least squares on one)."""
    G = m.G
    xi = G.log(G.increment(z0, z1))
    return jt.reduce(jt.coordinate_basis(m.tree, z0), xi) if _reduced(m) else xi


# ---------------------------------------------------------------------------- residual halves
def _project(m: Any, z: Pose, r: torch.Tensor) -> torch.Tensor:
    if not _reduced(m):
        return r
    T = jt.coordinate_basis(m.tree, z)
    return (T.transpose(-1, -2) @ r[..., None])[..., 0]


def _dof_damping(m: Any, z0: Pose, z1: Pose) -> torch.Tensor | None:
    """(h/2) tau(nu(z0, z1)) of a reduced tree's per-DoF damping (m.h the interval's step), or None."""
    half = getattr(m, "dof_half_torque", None)
    return half(z0, z1) if half is not None and _reduced(m) else None


def left_half(m: Any, z_prev: Pose, z: Pose) -> torch.Tensor:
    """A_h(z_prev, z): the residual's terms fixed by the interval before z (m.h its step), in DoF."""
    r = _project(m, z, m.residual_const(z_prev, z))
    tau = _dof_damping(m, z_prev, z)
    return r if tau is None else r + tau


def right_half(m: Any, z: Pose, z_next: Pose) -> torch.Tensor:
    """B_h(z, z_next): the residual's terms of the interval after z (m.h its step), in DoF."""
    r = _project(m, z, m.residual_var(z, z_next))
    tau = _dof_damping(m, z, z_next)
    return r if tau is None else r + tau


def potential_covector(m: Any, z: Pose) -> torch.Tensor:
    """-m.h dV/d eta at z in DoF (zeros without a potential)."""
    if hasattr(m, "reduced"):  # the articulated model takes its FK and Jacobian
        from ...mechanics import articulated as art

        world, A = art.fk_and_jacobian(m.tree, z)
        return _project(m, z, m.potential_covector(z, world, A))
    return m.potential_covector(z)


def _potential_shift(ma: Any, mb: Any) -> float:
    """w with r = A_{ha} + B_{hb} + w pc_{ha}(z) weighting V at z by (ha + hb)/2 (the symmetric sub-step).
    The fast residual puts -h V' in A (weight ha), the generic one in B (weight hb)."""
    ha, hb = float(ma.h), float(mb.h)
    if ha == hb or getattr(ma, "potential", None) is None and not hasattr(ma, "reduced"):
        return 0.0
    inside = ha if ma.residual_mode == "fast" else hb
    return (0.5 * (ha + hb) - inside) / ha


def substep_residual(ma: Any, mb: Any, z_prev: Pose, z: Pose, z_next: Pose) -> torch.Tensor:
    """The DEL residual at z with step ma.h before it and mb.h after it, (..., n_dof); equals
    `ma.residual` when ma.h == mb.h."""
    r = left_half(ma, z_prev, z) + right_half(mb, z, z_next)
    w = _potential_shift(ma, mb)
    return r if w == 0.0 else r + w * potential_covector(ma, z)


# ---------------------------------------------------------------------------- the wrapper model
class SubstepModel(ImplicitModel):
    """A LieDFLNN (per-body or articulated) whose sample step is `substeps` sub-steps of order 2 or 4
    (see the module docstring). Every parameter is the wrapped model's (`inner`)."""

    window = "triplet"

    def __init__(self, inner: ImplicitModel, substeps: int = 1, order: int = 2):
        super().__init__(plan=inner.plan)
        self.substeps, self.order = check_steps(substeps, order)
        self.inner = inner
        self.G, self.h = inner.G, float(inner.h)
        self.tree = getattr(inner, "tree", None)
        self.fractions = step_fractions(self.substeps, self.order)
        self.notes = list(getattr(inner, "notes", ())) + [f"step: {self.describe()}"]
        self._twins: dict[tuple[float, str], Any] = {}

    def describe(self) -> str:
        n = len(self.fractions)
        return f"{self.substeps} sub-step(s) of order {self.order} per sample ({n} DEL solves per step)"

    @classmethod
    def from_config(cls, ctx, **options: Any) -> SubstepModel:  # built by `with_substeps`
        raise ConfigError("SubstepModel is built from LieDFLNN's options model.substeps / model.order")

    # -------------------------------------------------------------- the model at a sub-step
    def _twin(self, h: float, path: str | None = None) -> Any:
        """The wrapped model at step h on `path` (default its own), every parameter shared."""
        path = path or self.inner.path
        key = (float(h), path)
        if key not in self._twins:
            twin = self.inner.with_path(path)  # type: ignore[arg-type]
            twin.h = float(h)
            self._twins[key] = twin
        return self._twins[key]

    def plan_changed(self) -> None:
        self._twins = {}  # built on the previous plan

    def _models(self, path: str | None = None) -> list[Any]:
        return [self._twin(c * self.h, path) for c in self.fractions]

    def _apply(self, fn, recurse=True):  # .to() / .double(): twins are rebuilt from the moved parameters
        self._twins = {}
        return super()._apply(fn, recurse)

    # -------------------------------------------------------------- internal poses
    def _interior(self, models: Sequence[Any], q0: Pose, z: list[Pose], q1: Pose) -> torch.Tensor:
        """The sub-step residuals at the internal poses, (N, n-1, k) (`models`: the sub-steps' models, or
        a `_LinearEngine`)."""
        full = [q0, *z, q1]
        if isinstance(models, _LinearEngine):
            return torch.stack(
                [models.residual(i - 1, i, full[i - 1], full[i], full[i + 1]) for i in range(1, len(full) - 1)], -2
            )
        return torch.stack(
            [
                substep_residual(models[i - 1], models[i], full[i - 1], full[i], full[i + 1])
                for i in range(1, len(full) - 1)
            ],
            -2,
        )

    def _interior_jacobian(self, models: Sequence[Any], q0: Pose, z: list[Pose], q1: Pose) -> torch.Tensor:
        """d residuals / d (moves of the internal poses), (N, (n-1) k, (n-1) k): block tridiagonal, by
        central differences of step FD_STEP with the poses of one colour (i mod 3) moved together:
        2 * 3 k evaluations whatever n (a row sees exactly one moved pose among i-1, i, i+1). Relative
        accuracy ~1e-9 (tested against autodiff): Newton converges as with the exact Jacobian and the
        implicit-function gradient is exact to that accuracy."""
        m, k = len(z), n_dof(self.inner)
        N = z[0].R.shape[0]
        ref = z[0].R
        J = ref.new_zeros(N, m, k, m, k)
        for c in range(min(3, m)):
            for j in range(k):
                v = ref.new_zeros(N, m, k)
                v[:, c::3, j] = FD_STEP
                plus = self._interior(models, q0, [move(self.inner, z[i], v[:, i]) for i in range(m)], q1)
                minus = self._interior(models, q0, [move(self.inner, z[i], -v[:, i]) for i in range(m)], q1)
                dF = (plus - minus) / (2.0 * FD_STEP)
                for i in range(m):
                    for col in (i - 1, i, i + 1):
                        if 0 <= col < m and col % 3 == c:
                            J[:, i, :, col, j] = dF[:, i]
        return J.reshape(N, m * k, m * k)

    def internal_poses(self, q0: Pose, q1: Pose, differentiable: bool = False) -> tuple[list[Pose], torch.Tensor]:
        """The internal poses z_1..z_{n-1} of the sample intervals (q0, q1) (leading shape (N,)) and
        whether their Newton solve converged (N,): a fourth-order step's negative sub-step can leave a
        strongly damped tree without a solution near the geodesic guess (continuation from uniform
        sub-steps did not find one either), and a rollout then reports its first step as failed.
        differentiable: their dependence on the parameters through the implicit function theorem
        (training)."""
        n, N = len(self.fractions), q0.R.shape[0]
        if n == 1:
            return [], torch.ones(N, dtype=torch.bool, device=q0.R.device)
        z, ok = self._solve_internal(q0, q1, self.fractions)
        if not differentiable:
            return z, ok
        models = self._models("reference")
        with torch.no_grad(), torch.enable_grad():
            J = self._interior_jacobian(models, q0, z, q1).detach()
        F = self._interior(models, q0, z, q1)  # live in the parameters, z fixed
        step = torch.linalg.solve(J, -F.reshape(N, -1)).reshape(F.shape)
        return [move(self.inner, z[i], step[:, i]) for i in range(len(z))], ok

    @torch.no_grad()
    def _solve_internal(
        self, q0: Pose, q1: Pose, fractions: tuple[float, ...], start: list[Pose] | None = None
    ) -> tuple[list[Pose], torch.Tensor]:
        """Damped Newton (chord iterations while they contract) for the internal poses of sub-steps
        `fractions` from `start` (default: the geodesic guess); (poses, converged (N,))."""
        models: Any = [self._twin(c * self.h, "reference") for c in fractions]
        if _LinearEngine.applies(self.inner):
            models = _LinearEngine(self, fractions)
        inner, N, n = self.inner, q0.R.shape[0], len(fractions)
        d0 = dof_log(inner, q0, q1)
        if start is None:
            z = [move(inner, q0, sum(fractions[:i]) * d0) for i in range(1, n)]
        else:
            z = list(start)
        scale = 1.0 + d0.abs().amax(-1)
        ok = torch.zeros(N, dtype=torch.bool, device=q0.R.device)
        with torch.enable_grad():
            F = self._interior(models, q0, z, q1).detach()
        J, stale = None, True
        for _ in range(INTERNAL_MAX_ITER):
            if stale or J is None:  # a chord iteration while it contracts fast, else a fresh Jacobian
                with torch.enable_grad():
                    J = self._interior_jacobian(models, q0, z, q1).detach()
            before = F.flatten(1).norm(dim=-1)
            sol, info = torch.linalg.solve_ex(J, -F.reshape(N, -1))
            step = torch.nan_to_num(sol.reshape(F.shape), nan=0.0, posinf=0.0, neginf=0.0)
            step[ok | (info != 0)] = 0.0  # converged rows stay where they are; singular ones fail
            z, F, taken = self._damped_step(models, q0, z, q1, F, step, active=~ok)
            after = F.flatten(1).norm(dim=-1)
            stale = bool(((after > 0.05 * before) & ~ok).any())
            ok = ok | (taken.abs().amax((-1, -2)) <= INTERNAL_TOL * scale)
            if bool(ok.all()):
                break
        return z, ok

    def _damped_step(
        self, models, q0: Pose, z: list[Pose], q1: Pose, F: torch.Tensor, step: torch.Tensor, active: torch.Tensor
    ):
        """The Newton step in the `active` rows (N,), halved (up to MAX_HALVINGS times) where it does not
        reduce ||F||: (poses, F there, the step taken (N, n-1, k)). Other rows are left exactly as they are
        (moving a pose by a zero step along a tree's joints is not bit-exact)."""
        norm = F.flatten(1).norm(dim=-1)
        scale = torch.ones_like(norm)
        best_z, best_F, taken = z, F, torch.zeros_like(step)
        todo = active.clone()
        for _ in range(MAX_HALVINGS + 1):
            trial = step * scale[:, None, None]
            zt = [move(self.inner, z[i], trial[:, i]) for i in range(len(z))]
            with torch.enable_grad():
                Ft = self._interior(models, q0, zt, q1).detach()
            better = todo & ((Ft.flatten(1).norm(dim=-1) <= norm) | ~torch.isfinite(norm))
            last = scale <= 0.5**MAX_HALVINGS
            accept = todo & (better | last)  # after the last halving the step is taken anyway
            if bool(accept.any()):
                best_z = [_where(accept, a, b) for a, b in zip(zt, best_z)]
                best_F = torch.where(accept[:, None, None], Ft, best_F)
                taken = torch.where(accept[:, None, None], trial, taken)
            todo = todo & ~accept
            if not bool(todo.any()):
                break
            scale = torch.where(todo, 0.5 * scale, scale)
        return best_z, best_F, taken

    # -------------------------------------------------------------- training
    def training_set(self, data: Pose, steps: int) -> TripletSet:
        ts = TripletSet(data, steps)
        ts.inner_source = (data, steps)  # type: ignore[attr-defined]  # initial_fit reads the inner model's samples
        return ts

    def loss(self, batch, opts: LossOptions):
        """w_DEL mean ||r_k||^2 of the composite residual (module docstring) + the regularity penalty of
        the sample step's mixed Hessian (the one-step model's)."""
        if opts.loss != "del":
            raise ConfigError(
                f"train.loss={opts.loss} with model.substeps/model.order: sub-steps train with train.loss=del only"
            )
        if not isinstance(batch, TripletBatch):
            raise ConfigError("model.substeps/model.order trains on triplets")
        models = self._models("reference")
        prev, cur, nxt = batch.poses()
        za, _ = self.internal_poses(prev, cur, differentiable=True)
        zb, _ = self.internal_poses(cur, nxt, differentiable=True)
        a = za[-1] if za else prev
        b = zb[0] if zb else nxt
        r = substep_residual(models[-1], models[0], a, cur, b)
        logdet = None
        if batch.reg is not None and opts.w_reg > 0:
            # the sample step's mixed Hessian, as for one step per sample: the penalty keeps the shared
            # parameters away from a degenerate Lagrangian and is not active near the truth (at the
            # shorter sub-steps a fixed threshold would bias the fit)
            inner: Any = self.inner
            logabsdet, orientation = inner.regularity_slogdet(*batch.reg)
            logdet = oriented_logdet(logabsdet, orientation, opts.epsilon)
        return del_regularity_loss(r, logdet, opts)

    def initial_fit(self, samples: Any, method: str = "auto", rollout_fit: bool = True) -> str | None:
        """The start: the wrapped model's own start (the articulated least-squares fit), then L-BFGS on
        its DEL loss with one step per sample over every training triplet (the fast path: seconds), then
        Levenberg-Marquardt on this model's own residual (`levenberg_marquardt`; L-BFGS where the model
        has too many parameters for it) and, where that ran, the model rolls out on the fused SO(3) maps
        (`_LinearEngine.applies`) and `rollout_fit`, on its rollouts over short windows of the training poses
        (`rollout_refinement`)."""
        source = getattr(samples, "inner_source", None)
        if source is None:
            return None
        inner_samples = self.inner.training_set(*source)
        notes = [self.inner.initial_fit(inner_samples, method)]
        notes.append(second_order_fit(self.inner, inner_samples))
        fit = levenberg_marquardt(self, samples)  # then the sub-step residual itself
        if fit is None and samples.n <= SUBSTEP_START_MAX_TRIPLETS:  # too many parameters for LM: L-BFGS
            fit = second_order_fit(self, samples, SUBSTEP_START_ITERATIONS)
            fit = None if fit is None else fit.replace("one-step", "sub-step")
        notes.append(fit)
        # a few physical parameters, rolled out on the fused SO(3) maps: a rollout per parameter and iteration
        # on the reference functions (SE(3) bodies, trees) would take minutes
        if rollout_fit and fit is not None and fit.startswith("Levenberg") and _LinearEngine.applies(self.inner):
            notes.append(rollout_refinement(self, *source))
        return "; ".join(n for n in notes if n)

    @torch.no_grad()
    def sample_residual(self, batch: TripletBatch) -> torch.Tensor:
        """The composite residual r_k at every triplet of `batch` (no gradient), (N, k)."""
        prev, cur, nxt = batch.poses()
        za, _ = self.internal_poses(prev, cur)
        zb, _ = self.internal_poses(cur, nxt)
        models = self._models("reference")
        with torch.enable_grad():
            r = substep_residual(models[-1], models[0], za[-1] if za else prev, cur, zb[0] if zb else nxt)
        return r.detach()

    # -------------------------------------------------------------- rollout
    def implicit_start(self, g0: Pose, g1: Pose) -> Any:  # rollouts go through `rollout`
        raise NotImplementedError("SubstepModel rolls out through rollout()")

    def implicit_problem(self, state: Any) -> NewtonProblem:
        raise NotImplementedError("SubstepModel rolls out through rollout()")

    def implicit_advance(self, state: Any, x: Any) -> tuple[Any, Pose]:
        raise NotImplementedError("SubstepModel rolls out through rollout()")

    @torch.no_grad()
    def rollout(self, g0: Pose, g1: Pose, steps: int, opts: SolverOptions | None = None, progress=None) -> Rollout:
        """Predict q_2..q_steps from (q_0, q_1): the internal poses of [q_0, q_1] give the sub-step
        before q_1, then n sub-steps per sample (the uniform ones on the wrapped model's own rollout)."""
        opts = opts or SolverOptions()
        n = len(self.fractions)
        z, ok = self.internal_poses(g0, g1)
        a = z[-1] if z else g0
        sub_steps = 1 + n * max(steps - 1, 0)
        sub_progress = None if progress is None else (lambda k: progress(k // n) if k % n == 0 else None)
        if self.order == 2:
            ro = self._twin(self.h / self.substeps).rollout(a, g1, sub_steps, opts, sub_progress)
        elif _LinearEngine.applies(self.inner):
            from .engines import columns as fused_columns

            start = [g0, *z, g1]  # the start cycle: the predictor's first history
            compiled = self.plan.wants_compile("rollout", g0.R.shape[0] * sub_steps)
            if fused_columns.applies(self.inner, a) and not compiled:
                ro = _columns_cycle(_LinearEngine(self), start, sub_steps, opts, sub_progress)
            else:
                ro = _rows_cycle(_LinearEngine(self), start, sub_steps, opts, sub_progress)
        else:
            ro = rollout_implicit(_Cycle(self), a, g1, sub_steps, opts, sub_progress)
        T = g0.R.shape[0]
        pose = Pose(
            torch.cat((g0.R[:, None], ro.pose.R[:, 1::n]), 1), torch.cat((g0.p[:, None], ro.pose.p[:, 1::n]), 1)
        )
        S = max(steps - 1, 0)
        conv = ro.converged.reshape(T, S, n).all(-1)
        if S:
            conv[:, 0] &= ok
        return Rollout(
            pose,
            conv,
            ro.iterations.reshape(T, S, n).sum(-1),
            ro.residual_norm.reshape(T, S, n).amax(-1) if S else ro.residual_norm,
            ro.seconds,
        )

    # -------------------------------------------------------------- the contract's other hooks
    def components(self) -> list[str]:
        return [*self.inner.components(), f"step: {self.describe()}"]

    def force_terms(self) -> list[nn.Module]:
        return self.inner.force_terms()

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        return self.inner.physical_parameters()

    def parameter_recovery(self, reference, physics):
        return self.inner.parameter_recovery(getattr(reference, "inner", reference), physics)

    def damping_stiffness(self) -> float | None:
        """h' lambda_max(M^-1 D) at the shortest sub-step h' (the step the damping is integrated with)."""
        h_min = min(abs(c) for c in self.fractions) * self.h
        return self._twin(h_min).damping_stiffness()

    def multibody(self):
        return self.inner.multibody()

    def joint_record(self):
        return self.inner.joint_record()


START_ITERATIONS = 300
START_REG_PAIRS = 1000
SUBSTEP_START_ITERATIONS = 60  # L-BFGS iterations on the sub-step loss (each solves every triplet's internal poses)
SUBSTEP_START_MAX_TRIPLETS = 20000  # above this the sub-step stage is left to the epochs


def second_order_fit(model: Any, samples: Any, iterations: int = START_ITERATIONS) -> str | None:
    """L-BFGS (strong Wolfe) on `model`'s DEL + regularity loss (the default weights) over all of its
    training `samples` at once, with a fixed draw of regularity pairs; returns what it did."""
    params = [p for p in model.parameters() if p.requires_grad]
    if not params or samples.n == 0:
        return None
    gen = torch.Generator().manual_seed(0)
    opts = LossOptions(reg_points=min(START_REG_PAIRS, samples.n))
    batch = samples.batch(torch.arange(samples.n, device=params[0].device), gen, opts.reg_points)
    opt = torch.optim.LBFGS(
        params, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-16
    )
    first: list[float] = []

    def closure():
        opt.zero_grad()
        loss, _ = model.loss(batch, opts)
        if not first:
            first.append(float(loss.detach()))
        loss.backward()
        return loss

    with contextlib.suppress(RuntimeError, ValueError):  # a failed line search leaves the best point reached
        opt.step(closure)
    with torch.no_grad():
        last = float(model.loss(batch, opts)[0])
    if not math.isfinite(last):
        return None
    return f"L-BFGS on the one-step DEL loss over {samples.n} triplets: {first[0]:.3e} -> {last:.3e}"


LM_MAX_PARAMETERS = 64  # Levenberg-Marquardt with a finite-difference Jacobian up to this many parameters
LM_ITERATIONS = 30
LM_MAX_TRIPLETS = 4096


def _kinetic_scale(model: Any) -> torch.Tensor | None:
    inertia = getattr(getattr(model, "inner", model), "inertia", None)
    return None if inertia is None else inertia.Jd().diagonal(dim1=-2, dim2=-1).mean()


def _trainable(model: Any) -> tuple[list[torch.Tensor], int]:
    params = [p for p in model.parameters() if p.requires_grad]
    return params, sum(p.numel() for p in params)


def _flat_parameters(params: list[torch.Tensor]):
    """(get, put): the parameters as one vector, and written back from one."""

    def get() -> torch.Tensor:
        return torch.cat([p.detach().reshape(-1) for p in params])

    def put(theta: torch.Tensor) -> None:
        with torch.no_grad():
            i = 0
            for p in params:
                p.copy_(theta[i : i + p.numel()].view_as(p))
                i += p.numel()

    return get, put


def _lm(theta: torch.Tensor, res, iterations: int, stop: float = 1e-10) -> tuple[torch.Tensor, float, float]:
    """Levenberg-Marquardt (Marquardt's diagonal scaling) on the residual vector res(theta), with a
    forward-difference Jacobian of relative step 1e-7: (theta, first cost, last cost), cost = |res|^2.
    Only steps that lower the cost are taken (a non-finite residual counts as no decrease), so the cost
    never rises; it stops after `iterations`, when no step within 10 damping increases lowers it, or when
    a step gains less than `stop` relative."""
    r = res(theta)
    first = cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        eps = 1e-7 * torch.clamp(theta.abs(), min=1.0)
        J = torch.stack([(res(theta + eps[j] * _unit(theta, j)) - r) / eps[j] for j in range(theta.numel())], -1)
        A, g = J.T @ J, J.T @ r
        improved = done = False
        for _ in range(10):
            step = torch.linalg.solve(A + lam * torch.diag(A.diagonal().clamp(min=1e-30)), -g)
            r_new = res(theta + step)
            c_new = float(r_new @ r_new)
            if math.isfinite(c_new) and c_new < cost:
                theta, r, improved = theta + step, r_new, True
                done = cost - c_new <= stop * cost
                cost, lam = c_new, max(lam / 3.0, 1e-12)
                break
            lam *= 4.0
        if not improved or done:
            break
    return theta, first, cost


def levenberg_marquardt(model: SubstepModel, samples: Any, iterations: int = LM_ITERATIONS) -> str | None:
    """Levenberg-Marquardt on the composite residual of every training triplet divided by the kinetic
    scale (mean diagonal of J_d: the residual is homogeneous in the parameters, so this removes the
    scale, which the LM damping then holds), with a forward-difference Jacobian in the raw parameters.
    None where the model has more than LM_MAX_PARAMETERS trainable numbers (then L-BFGS)."""
    params, n_par = _trainable(model)
    if not params or n_par > LM_MAX_PARAMETERS or _kinetic_scale(model) is None:
        return None
    gen = torch.Generator().manual_seed(0)
    n = min(samples.n, LM_MAX_TRIPLETS)  # a fixed random subset: a few parameters need few triplets
    idx = torch.randperm(samples.n, generator=gen)[:n] if n < samples.n else torch.arange(n, device=params[0].device)
    batch = samples.batch(idx, gen, 0)
    get, put = _flat_parameters(params)

    def res(theta: torch.Tensor) -> torch.Tensor:
        put(theta)
        with torch.no_grad():
            scale = _kinetic_scale(model)
        assert scale is not None  # checked above
        return (model.sample_residual(batch) / scale).reshape(-1)

    theta, first, cost = _lm(get(), res, iterations)
    put(theta)
    return f"Levenberg-Marquardt on the sub-step residual of {n} triplets: {first:.3e} -> {cost:.3e}"


ROLLOUT_FIT_LENGTH = 10  # samples predicted per window of the rollout refinement
ROLLOUT_FIT_WINDOWS = 128  # at most this many windows, spread evenly over the training trajectories
ROLLOUT_FIT_PASSES = 3  # reweighted least-squares passes (each a Levenberg-Marquardt run)
ROLLOUT_FIT_ITERATIONS = 5  # Levenberg-Marquardt iterations per pass
ROLLOUT_FIT_SOLVER = SolverOptions(tol=1e-10, max_iter=20)  # solutions to rounding: a smooth residual in theta


def rollout_windows(data: Pose, steps: int, length: int = ROLLOUT_FIT_LENGTH, most: int | None = None):
    """Windows of length + 1 samples from the first `steps` steps of trajectories (T, N+1, ...): start
    samples k = 0, s, 2 s, ... (the stride s the smallest that keeps at most `most` windows in all,
    default ROLLOUT_FIT_WINDOWS), stacked as (W, length + 1, ...); None where no trajectory has
    length + 1 samples."""
    most = ROLLOUT_FIT_WINDOWS if most is None else most
    steps = min(int(steps), data.R.shape[1] - 1)
    if steps < length or length < 2:
        return None
    T, per = data.R.shape[0], steps - length + 1  # start samples per trajectory
    stride = max(1, math.ceil(T * per / most))
    starts = range(0, per, stride)
    R = torch.cat([data.R[:, k : k + length + 1] for k in starts])
    p = torch.cat([data.p[:, k : k + length + 1] for k in starts])
    return Pose(R, p)


class WindowErrors:
    """The model's rollouts over `windows` (W, length + 1, ...) from each window's first two samples:
    `errors()` the differences of the predicted poses' entries (rotation and position) from the data
    at samples 2..length, (W, n) (+inf in a window whose Newton solve failed), and
    `log_mean_square()` the objective of `rollout_refinement`, mean_w log(mean_n errors^2), (a float)."""

    def __init__(self, model: Any, windows: Pose):
        self.model, self.windows = model, windows
        self.length = windows.R.shape[1] - 1
        self.g0, self.g1 = windows.index((slice(None), 0)), windows.index((slice(None), 1))

    @torch.no_grad()
    def errors(self) -> torch.Tensor:
        ro = self.model.rollout(self.g0, self.g1, self.length, ROLLOUT_FIT_SOLVER)
        w = self.windows
        d = torch.cat(((ro.pose.R - w.R)[:, 2:].flatten(1), (ro.pose.p - w.p)[:, 2:].flatten(1)), 1)
        failed = ~ro.converged.all(1)
        return torch.where(failed[:, None], math.inf, d) if bool(failed.any()) else d

    def log_mean_square(self) -> float:
        return float(torch.log(self.errors().square().mean(1)).mean())


def rollout_refinement(
    model: Any, data: Pose, steps: int, passes: int | None = None, length: int = ROLLOUT_FIT_LENGTH
) -> str | None:
    """Fits the parameters to the model's own rollouts over short windows of the training poses (from
    each window's first two samples, `length` steps): minimises the mean over windows of the log of
    the window's mean square pose error. Fitting the DEL residual on exact samples lets the parameters
    absorb the scheme's truncation error (a residual of zero is not a rollout of zero error); this fits
    what a rollout is judged by. The log makes every window count alike: a plain sum of squares is
    ruled by the few windows whose motion is most sensitive (a rotor near its unstable axis), where
    the error says least about the parameters.

    Majorise-minimise: log c <= log c0 + (c - c0) / c0, so each pass (`passes`, default
    ROLLOUT_FIT_PASSES) minimises sum_w c_w / c0_w, the squared errors divided by their window's mean
    square c0_w at the pass's start, by Levenberg-Marquardt (forward differences: one rollout per
    parameter; steps only where the weighted cost falls), and the objective never rises. Models with at
    most LM_MAX_PARAMETERS trainable numbers; None where it does not apply (or no window fits in `steps`)."""
    params, n_par = _trainable(model)
    windows = rollout_windows(data, steps, length)
    if not params or n_par > LM_MAX_PARAMETERS or windows is None:
        return None
    get, put = _flat_parameters(params)
    we = WindowErrors(model, windows)
    weight = torch.ones(windows.R.shape[0], 1, dtype=windows.R.dtype, device=windows.R.device)

    def res(theta: torch.Tensor) -> torch.Tensor:
        put(theta)
        return (weight * we.errors()).reshape(-1)

    theta = get()
    first = last = we.log_mean_square()
    if not math.isfinite(first):
        return None
    for _ in range(ROLLOUT_FIT_PASSES if passes is None else passes):
        put(theta)
        rms = we.errors().square().mean(1, keepdim=True).sqrt()
        weight = 1.0 / rms.clamp(min=torch.finfo(rms.dtype).tiny)
        theta, _, _ = _lm(theta, res, ROLLOUT_FIT_ITERATIONS, stop=1e-6)
        put(theta)
        now = we.log_mean_square()
        done = last - now < 1e-3  # the geometric mean of the windows' errors gains < 0.1 %
        last = now
        if done:
            break
    put(theta)
    n = windows.R.shape[0]
    return (
        f"Levenberg-Marquardt on the rollouts of {n} windows of {length} steps: geometric mean of their RMS "
        f"pose error {math.exp(0.5 * first):.3e} -> {math.exp(0.5 * last):.3e}"
    )


def _unit(like: torch.Tensor, j: int) -> torch.Tensor:
    e = torch.zeros_like(like)
    e[j] = 1.0
    return e


def _where(rows: torch.Tensor, a: Pose, b: Pose) -> Pose:
    """Pose a in `rows` (N,) bool, else b."""
    return Pose(torch.where(rows[:, None, None, None], a.R, b.R), torch.where(rows[:, None, None], a.p, b.p))


class _Cycle:
    """The sub-step DEL map with the steps c_1 h, ..., c_n h in turn, for `rollout_implicit`: each step
    is the wrapped model's Newton problem at the step after the pose, its fixed part moved to the step
    before it (and the potential to the symmetric weight)."""

    path = "fused"  # the batched Newton loop (the problems are the reference path's)

    def native_rollout(self, *args, **kwargs) -> None:  # (`ImplicitModel`'s hook) the loop serves
        return None

    def __init__(self, outer: SubstepModel):
        self.models = outer._models("reference")
        self.n = len(self.models)

    def implicit_start(self, g0: Pose, g1: Pose) -> Any:
        return (g0, g1, 0, None)

    def implicit_problem(self, state: Any) -> NewtonProblem:
        g_prev, g, j, _ = state
        ma, mb = self.models[(j - 1) % self.n], self.models[j % self.n]
        base = mb.implicit_start(g_prev, g)
        ratio = float(mb.h) / float(ma.h)
        if ratio != 1.0:  # warm start: the last increment scaled to this sub-step
            G = mb.G
            inc = G.exp(ratio * G.log(G.increment(g_prev, g)))
            base = mb.scaled_start(base, inc, ratio)
        prob = mb.implicit_problem(base)
        state_out = (g_prev, g, j, base)
        self._last = state_out
        if ratio == 1.0:
            return prob
        with torch.enable_grad():
            shift = left_half(ma, g_prev, g) - left_half(mb, g_prev, g)
            w = _potential_shift(ma, mb)
            if w != 0.0:
                shift = shift + w * potential_covector(ma, g)
        shift = shift.detach()
        f = prob.f
        return NewtonProblem(lambda x: f(x) + shift, prob.jac, prob.x0, prob.retract)

    def implicit_advance(self, state: Any, x: Any) -> tuple[Any, Pose]:
        g_prev, g, j, _ = self._last
        mb = self.models[j % self.n]
        _, g_next = mb.implicit_advance(self._last[3], x)
        return (g, g_next, j + 1, None), g_next


PREDICTOR_DEGREE = 3
"""Degree of the polynomial that predicts a sub-step's increment from its last cycles (`_Predictor`)."""
EXTRAPOLATION = ((1.0,), (2.0, -1.0), (3.0, -3.0, 1.0), (4.0, -6.0, 4.0, -1.0))
"""Weights of the last d + 1 values (newest first) that extrapolate a polynomial of degree d one step on."""


def cycle_period(fractions: Sequence[float]) -> int:
    """The smallest p with fractions[i] == fractions[i + p] for all i (3 for the triple jumps, 1 uniform)."""
    n = len(fractions)
    return next(p for p in range(1, n + 1) if n % p == 0 and all(fractions[i] == fractions[i % p] for i in range(n)))


class _SineRotations:
    """Rotations of angle below pi/2 by their sine vector v = vee((W - W^T) / 2) = sin(t) n, in one layout:
    rows (W (..., 3, 3), v (..., 3)) or columns (W (9, T) row-major entries, v (3, T)). The inverse is
    closed and exactly orthogonal in exact arithmetic, W = c I + hat(v) + v v^T / (1 + c), c = sqrt(1 - |v|^2)
    (= cos t; 1 / (1 + c) = (1 - c) / |v|^2 without the division by |v|^2)."""

    def __init__(self, columns: bool, like: torch.Tensor):
        self.columns = columns
        S = like.new_zeros(9, 3)  # W.flatten() @ S = v
        for k, (a, b) in enumerate(((7, 5), (2, 6), (3, 1))):  # v = (W21 - W12, W02 - W20, W10 - W01) / 2
            S[a, k], S[b, k] = 0.5, -0.5
        H = (2.0 * S).T.contiguous()  # v @ H = hat(v).flatten() (hat(v) is skew: its skew part is itself)
        self.S, self.H = (S.T.contiguous(), H.T.contiguous()) if columns else (S, H)

    def sine(self, W: torch.Tensor) -> torch.Tensor:
        return self.S @ W if self.columns else W.flatten(-2) @ self.S

    def rotation(self, v: torch.Tensor) -> torch.Tensor:
        if self.columns:
            c = (v * v).sum(0).neg_().add_(1.0).sqrt_()
            W = (v[:, None] * (v / (1.0 + c))[None]).view(9, -1)
            W.addmm_(self.H, v)
            W[0::4] += c
            return W
        c = (v * v).sum(-1, keepdim=True).neg_().add_(1.0).sqrt_()
        W = (v[..., :, None] * (v / (1.0 + c))[..., None, :]).flatten(-2)
        W += v @ self.H
        W[..., 0::4] += c
        return W.unflatten(-1, (3, 3))


class _Predictor:
    """Warm starts of the cycle's Newton solves. The increment W_j(t) of the sub-step of phase j (its place
    in the periodic fractions) is a smooth function of the time t of its cycle, and so is its sine vector
    v_j(t) (`_SineRotations`), so the sine vectors of the same phase in the last d + 1 cycles, extrapolated
    as a polynomial of degree d, predict the increment to O(h^(d+1)) c_j h (the previous warm start, the last
    increment scaled to the sub-step: O(h) c_j h, two Newton iterations at the default tolerance, three at
    1e-12). The prediction is a rotation to rounding (closed form from v), so the Newton solve is that of a
    start on the group and converges to the same solution. `rot`: the layout's `_SineRotations`."""

    def __init__(self, period: int, rot: _SineRotations, degree: int | None = None):
        self.period, self.rot = period, rot
        self.degree = PREDICTOR_DEGREE if degree is None else degree  # < 0: no prediction (the fallback guess)
        self.hist: list[list[torch.Tensor]] = [[] for _ in range(period)]

    def record(self, j: int, W: torch.Tensor) -> None:
        """The solved (cleaned) increment W of sub-step j (its sine vector is kept)."""
        h = self.hist[j % self.period]
        h.append(self.rot.sine(W))
        if len(h) > max(self.degree, 0) + 1:
            del h[0]

    def guess(self, j: int) -> torch.Tensor | None:
        """The predicted increment of sub-step j, or None before any cycle of that phase or where the
        prediction turns by more than 45 degrees (the caller's fallback guess then)."""
        h = self.hist[j % self.period]
        if not h or self.degree < 0:
            return None
        d = min(len(h) - 1, self.degree)
        w = EXTRAPOLATION[d]
        v = torch.mul(h[-1], w[0])
        for i in range(1, d + 1):
            v.add_(h[-1 - i], alpha=w[i])
        # |v| = sin(angle) must stay below 1 for a rotation to exist; a sub-step turning more than 45 degrees
        # is outside where a polynomial in the cycles predicts anything: the fallback guess instead
        if bool(((v * v).sum(0 if self.rot.columns else -1) > 0.5).any()):
            return None
        return self.rot.rotation(v)


class _LinearEngine:
    """The sub-step residual and DEL map of an SO(3)-only LieDFLNN with constant Rayleigh damping at most,
    on the fused rollout's linear maps (`fused_rollout.RolloutMaps.linear`, built once per rollout and
    sub-step length): A_h(z_prev, z) = W_prev lin_const_h + cov_h(z), B_h(z, z_next) = W lin_f_h.
    Equal to `substep_residual` to rounding (tested); used where nothing needs a gradient."""

    def __init__(self, outer: SubstepModel, fractions: tuple[float, ...] | None = None):
        from .engines.rollout import rollout_maps

        fractions = fractions or outer.fractions
        self.models = [outer._twin(c * outer.h, "fused") for c in fractions]
        self.maps = [rollout_maps(m) for m in self.models]
        self.n = len(self.models)
        self.period = cycle_period(fractions)
        # the potential's weight at a pose between sub-steps a and b: (h_a + h_b) / 2 over the -h_a of A_{h_a}
        self.weight = [[0.5 * (float(ma.h) + float(mb.h)) / float(ma.h) for mb in self.models] for ma in self.models]

    @staticmethod
    def applies(model: Any) -> bool:
        from ...mechanics.forces import RayleighForce

        return (
            bool(getattr(type(model), "has_rollout_maps", False))
            and model._fused()
            and model.G.n_se3 == 0
            and all(isinstance(f, RayleighForce) for f in model.forces)
        )

    def const(self, ia: int, ib: int, z_prev: Pose, z: Pose) -> torch.Tensor:
        """A_{h_a}(z_prev, z) with the potential at z weighted (h_a + h_b) / 2, (N, dim)."""
        return self.const_of(ia, ib, z_prev.R.transpose(-1, -2) @ z.R, z)

    def const_of(self, ia: int, ib: int, W_prev: torch.Tensor, z: Pose) -> torch.Tensor:
        """`const` from the increment W_prev = z_prev^-1 z (N, B, 3, 3)."""
        ma = self.models[ia]
        out = W_prev.flatten(-3) @ self.maps[ia].linear[2]  # type: ignore[index]
        if ma.potential is not None:
            from ...mechanics.potentials import GravityPotential, UniformGravityPotential
            from .engines.maps import potential_covector as cov

            if isinstance(ma.potential, (UniformGravityPotential, GravityPotential)):  # closed form
                c = -float(ma.h) * ma.potential.left_gradient(z).detach()
            else:
                c = cov(ma, z).detach()
            out = out + self.weight[ia][ib] * c
        return out

    def residual(self, ia: int, ib: int, z_prev: Pose, z: Pose, z_next: Pose) -> torch.Tensor:
        W = (z.R.transpose(-1, -2) @ z_next.R).flatten(-3)
        return self.const(ia, ib, z_prev, z) + W @ self.maps[ib].linear[0]  # type: ignore[index]


def _cycle_guess(engine: _LinearEngine, ia: int, ib: int, W_prev: torch.Tensor) -> torch.Tensor:
    """The fallback warm start (no cycle of this phase yet): the last increment W_prev (..., 3, 3) scaled
    to the sub-step through its first-order log (vee of the skew part: cheap, a guess only)."""
    ratio = float(engine.models[ib].h) / float(engine.models[ia].h)
    if ratio == 1.0:
        return W_prev
    from ...lie import so3

    return so3.exp(ratio * so3.vee(W_prev))


@torch.no_grad()
def _rows_cycle(
    engine: _LinearEngine, start: Sequence[Pose], steps: int, opts: SolverOptions, progress=None
) -> Rollout:
    """The fourth-order cycle's rollout on the linear maps in row layout, from the poses of the start
    cycle `start` (q_0, its internal poses, q_1; leading shape (T,)): per sub-step the fixed part of the
    sub-step before the pose (the potential weighted (h_a + h_b) / 2), the fused Newton step of the sub-step
    after it (`FusedStep`) warm-started by `_Predictor`, the Newton-Schulz-cleaned increment. Poses
    (T, steps + 1, B, 3, 3) from (start[-2], start[-1]) on, as `rollout_implicit` gives them."""
    import time

    from ...solvers import newton
    from .engines.rollout import FusedStep, RolloutState, rollout_advance

    t0 = time.perf_counter()
    n = engine.n
    predictor = _Predictor(engine.period, _SineRotations(False, start[0].R))
    for i in range(len(start) - 1):
        W_prev = start[i].R.transpose(-1, -2) @ start[i + 1].R
        predictor.record(i, W_prev)
    g_prev, g = start[-2], start[-1]
    Rs, ps = [g_prev.R, g.R], [g_prev.p, g.p]
    conv, its, res = [], [], []
    for k in range(1, steps):
        ia, ib = (k - 2) % n, (k - 1) % n
        mb, maps = engine.models[ib], engine.maps[ib]
        W0 = predictor.guess(ib)
        if W0 is None:
            W0 = _cycle_guess(engine, ia, ib, W_prev)
        step = FusedStep.from_parts(mb, maps, g, engine.const_of(ia, ib, W_prev, g))
        sol = newton.solve(step.problem(Pose(W0, g.p.new_zeros(*g.p.shape))), opts)
        state, g_next = rollout_advance(mb, RolloutState(g_prev, g, sol.x, maps), sol.x)
        W_prev = state.inc.R
        predictor.record(ib, W_prev)
        g_prev, g = g, g_next
        Rs.append(g.R)
        ps.append(g.p)
        conv.append(sol.converged)
        its.append(sol.iterations)
        res.append(sol.residual_norm)
        if progress is not None:
            progress(k)
    T = g.R.shape[0]

    def stacked(xs, dtype):
        return torch.stack(xs, 1) if xs else torch.zeros(T, 0, dtype=dtype, device=g.R.device)

    return Rollout(
        Pose(torch.stack(Rs, 1), torch.stack(ps, 1)),
        stacked(conv, torch.bool),
        stacked(its, torch.long),
        stacked(res, g.R.dtype),
        time.perf_counter() - t0,
    )


@torch.no_grad()
def _columns_cycle(
    engine: _LinearEngine, start: Sequence[Pose], steps: int, opts: SolverOptions, progress=None
) -> Rollout:
    """`_rows_cycle` in the column layout of `fused_columns` (32 trajectories and more: the same steps,
    fewer kernel calls per trajectory)."""
    import time

    from .engines import columns as fc

    t0 = time.perf_counter()
    g0, g1 = start[-2], start[-1]
    T, n = g0.R.shape[0], engine.n
    cols = [fc.ColumnMaps(m, mp) for m, mp in zip(engine.models, engine.maps)]
    n_poses = max(steps, 1) + 1
    out = g0.R.new_empty(n_poses, 9, T)
    out[0], out[1] = fc.to_columns(g0.R).view(9, T), fc.to_columns(g1.R).view(9, T)
    predictor = _Predictor(engine.period, _SineRotations(True, g0.R))
    for i in range(len(start) - 1):
        W_prev = fc.to_columns(start[i].R.transpose(-1, -2) @ start[i + 1].R).view(9, T)
        predictor.record(i, W_prev)
    conv, its, res = [], [], []
    for k in range(1, steps):
        ia, ib = (k - 2) % n, (k - 1) % n
        ma = engine.models[ia]
        g = out[k]
        const = cols[ia].c @ W_prev
        cov = fc.potential_columns(ma, engine.maps[ia], g)
        if cov is not None:
            const = const + engine.weight[ia][ib] * cov
        W0 = predictor.guess(ib)
        if W0 is None:  # the guess in rows: a fallback, at most once per phase
            W0 = fc.to_columns(_cycle_guess(engine, ia, ib, W_prev.T.reshape(T, 1, 3, 3))).view(9, T)
        step = fc.ColumnStep(cols[ib], const, g)
        r = step.f(W0)
        W, r, converged, iterations = fc.solve(step, W0, r, fc.norm(r), opts, opts.max_iter)
        W_prev = fc.newton_schulz(W)
        predictor.record(ib, W_prev)
        out[k + 1].view(3, 3, T).copy_(fc.matmul(out[k].view(3, 3, T), W_prev.view(3, 3, T)))
        conv.append(converged)
        its.append(iterations)
        res.append(r.abs().amax(0))
        if progress is not None:
            progress(k)
    m = max(steps - 1, 0)
    R = out.permute(2, 0, 1).reshape(T, n_poses, 1, 3, 3)

    def stacked(xs, dtype):
        return torch.stack(xs, 1) if xs else torch.zeros(T, m, dtype=dtype, device=g0.R.device)

    return Rollout(
        Pose(R, g0.p.new_zeros(T, n_poses, 0, 3)),
        stacked(conv, torch.bool),
        stacked(its, torch.long),
        stacked(res, g0.R.dtype),
        time.perf_counter() - t0,
    )


def with_substeps(model: ImplicitModel, substeps: Any = 1, order: Any = 2) -> ImplicitModel:
    """`model` itself for one second-order step per sample (the paper's scheme), else a `SubstepModel`."""
    s, o = check_steps(substeps, order)
    if s == 1 and o == 2:
        return model
    return SubstepModel(model, s, o)


def same_step(reference: ImplicitModel, model: Any) -> ImplicitModel:
    """`reference` (the true-parameter scheme) with `model`'s sub-steps and order, so the two compare on
    the same step."""
    if isinstance(model, SubstepModel) and not isinstance(reference, SubstepModel):
        return SubstepModel(reference, model.substeps, model.order)
    return reference


def measured_order(errors: Sequence[float], steps: Sequence[float]) -> float:
    """The slope of log(error) against log(step) between the last two points."""
    return math.log(errors[-2] / errors[-1]) / math.log(steps[-2] / steps[-1])
