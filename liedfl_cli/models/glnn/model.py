"""GLNN baselines (paper Exp 2): continuous forced Euler-Poincare equations on SO(3),

    w' = A(R, w) = J^{-1} (tau - w x J w),   R' = R hat(w),   tau = -D w + tau_V(R),

with a learned SPD J (`Inertia.J()`), a learned SPSD D and, when the scene has gravity, a learned
potential V(R) (MLP on the 9 entries of R) whose torque is tau_V = -d/d(eta) V(R exp(eta)) at 0.
The three variants differ only in how the equations are discretised:

- `dopri5` (glnn_rk4): torchdiffeq's adaptive RK4(5) on the 9 entries of R and w. Nothing keeps
  R on SO(3); the drift is kept as the result.
- `heun` (glnn_lie_heun): explicit Lie-Heun / RKMK2. From (R, w): A1 = A(R, w), w* = w + h A1,
  R* = R exp(h w), w' = w + h/2 (A1 + A(R*, w*)), R' = R exp(h (w + w*)/2). (The paper's
  formula has no potential; with one, the predictor's rotation R* is where A is evaluated.)
- `midpoint` (glnn_lie_midpoint): implicit Lie midpoint. Solve
  w' = w + h A(R exp(h/2 wbar), wbar), wbar = (w + w')/2, then R' = R exp(h wbar). (With a
  potential, A is evaluated at the midpoint rotation; the paper's free-body A does not need R.)

Initial velocity (every variant, training windows and rollouts alike): w0 = log(R0^T R1)/h.
Training unrolls the integrator from (R0, w0) over the window and minimises the mean squared
error of the predicted rotation entries R_1..R_L (R_0 is given). With window "triplet" (the
midpoint default) each sample (R_{k-1}, R_k, R_{k+1}) is one length-2 window: start at R_{k-1}
with w = log(R_{k-1}^T R_k)/h, take two steps, compare both predictions -- the paper's "single
two-step update per training sample", built exactly like the first two steps of a rollout.

Rollout from (g0, g1): integrate from (R0, w0) and return g0, g1 followed by the predictions
R_2..R_S. In training the implicit midpoint equation is solved by `train_newton_iters`
differentiable Newton iterations whose Jacobian I - h/2 dA/dw omits the potential's dependence
on R (exact without a potential); rollouts use the damped Newton solver with the full autodiff
Jacobian, tolerance and iteration limit of `solver`, and report real convergence flags.

Without a potential (the Exp 2 scenes) the model takes the fused path of `models.glnn.engines.fused` when
`runtime.fused` is on (the default): dopri5 as one autograd node per solve (`solvers.dopri5`:
the same steps as torchdiffeq's dopri5, the backward the solve's discrete adjoint; rollouts too), Heun and
Midpoint with their velocities first and every step's exp in one call. Same losses and gradients to
rounding (tests/test_fused_baselines.py, tests/test_dopri5.py); `runtime.fused=false` runs the
reference path above (torchdiffeq, autograd through every step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ...errors import ConfigError
from ...lie import Pose, ProductGroup, so3
from ...mechanics.parameterizations import Inertia, SPSDMatrix
from ...mechanics.potentials import MLPPotential
from ...solvers import dopri5
from ...solvers.newton import NewtonProblem, NewtonResult, solve
from ...solvers.options import SolverOptions
from ..base import (
    Batch,
    BuildContext,
    ExplicitModel,
    LossOptions,
    LossParts,
    config_options,
    require_single_so3,
    so3_pose,
)
from .engines import fused as fused_glnn

INTEGRATORS = ("dopri5", "heun", "midpoint")
# config options common to every integrator, and those of one integrator only
COMMON_OPTIONS = ("integrator", "window", "potential", "damping", "mlp_width", "mlp_depth", "init_jitter")
INTEGRATOR_OPTIONS = {
    "dopri5": ("rtol", "atol", "max_num_steps"),
    "heun": (),
    "midpoint": ("train_newton_iters",),
}

# (J (3, 3), J^{-1} (3, 3), D (3, 3) or None): the learned parameters, evaluated once per loss/rollout
Params = tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]
# rollout state: (R (N, 3, 3), w (N, 3), Params)
State = tuple[torch.Tensor, torch.Tensor, Params]


@dataclass
class GLNNOptions:
    """GLNN's config options (conf/model/glnn_*.yaml), every integrator's: the schema `config/schema.py`
    checks the `model` section's keys and types against (`Model.Options`); `from_config` checks that
    an integrator-specific option (`INTEGRATOR_OPTIONS`) belongs to the chosen integrator."""

    integrator: str = "dopri5"  # dopri5 | heun | midpoint
    window: str = "trajectory"  # trajectory | triplet
    potential: Any = "auto"  # auto | mlp | none
    damping: Any = "auto"  # auto | true | false
    mlp_width: int = 64
    mlp_depth: int = 3
    init_jitter: float = 0.1
    rtol: float = 1e-7  # dopri5
    atol: float = 1e-9  # dopri5
    max_num_steps: int = 100000  # dopri5
    train_newton_iters: int = 4  # midpoint


class GLNN(ExplicitModel):
    """Continuous-time rigid body on SO(3) with learned J, D (and V), integrated by `integrator`.

    Args:
        G: the dataset's group (must be one SO(3) body). h: time step. integrator: dopri5 | heun |
        midpoint. window: "trajectory" (unroll the whole training window) or "triplet".
        potential / damping: build V and D. rtol, atol, max_num_steps: dopri5 settings.
        train_newton_iters: Newton iterations of the midpoint solve in training.
    """

    Options = GLNNOptions

    def __init__(
        self,
        G: ProductGroup,
        h: float,
        integrator: str = "dopri5",
        window: str = "trajectory",
        potential: bool = False,
        damping: bool = True,
        mlp_width: int = 64,
        mlp_depth: int = 3,
        init_jitter: float = 0.1,
        rtol: float = 1e-7,
        atol: float = 1e-9,
        max_num_steps: int = 100000,
        train_newton_iters: int = 4,
        seed: int = 0,
    ):
        super().__init__()
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        self.G, self.h, self.integrator, self.window = G, float(h), integrator, window
        self.adaptive = integrator == "dopri5"
        self.rtol, self.atol, self.max_num_steps = float(rtol), float(atol), int(max_num_steps)
        self.train_newton_iters = int(train_newton_iters)
        gen = torch.Generator().manual_seed(int(seed))
        # The equations are invariant under a common scale of (J, D, V): start at J ~ I.
        self.inertia = Inertia(1, scale=1.0, jitter=init_jitter, generator=gen)
        self.damping = SPSDMatrix(3, init_diag=0.01) if damping else None
        self.potential = MLPPotential(G, mlp_width, mlp_depth) if potential else None

    @classmethod
    def from_config(cls, ctx: BuildContext, **options) -> GLNN:
        """Options of conf/model/glnn_*.yaml; `potential`/`damping: auto` follow the scene."""
        integrator = options.get("integrator", "dopri5")
        if integrator not in INTEGRATORS:
            raise ConfigError(f"model.integrator={integrator!r}: choose one of {', '.join(INTEGRATORS)}")
        opt = config_options(cls, options, COMMON_OPTIONS + INTEGRATOR_OPTIONS[integrator])
        require_single_so3(ctx.group, f"GLNN ({integrator})")
        if opt.get("window", "trajectory") not in ("triplet", "trajectory"):
            raise ConfigError(f"model.window={opt['window']!r}: choose one of triplet, trajectory")
        opt["potential"] = ctx.resolve_potential(opt.get("potential", "auto")) == "mlp"
        opt["damping"] = ctx.resolve_damping(opt.get("damping", "auto"))
        return cls(ctx.group, ctx.h, seed=ctx.seed, **opt)

    def components(self) -> list[str]:
        """["J", "D"?, "V:MLPPotential"?, "integrator:<name>"]."""
        out = ["J"]
        if self.damping is not None:
            out.append("D")
        if self.potential is not None:
            out.append("V:MLPPotential")
        return out + [f"integrator:{self.integrator}"]

    # ------------------------------------------------------------------ vector field
    def _params(self) -> Params:
        J = self.inertia.J()[0]
        D = self.damping() if self.damping is not None else None
        return J, torch.linalg.inv(J), D

    def potential_torque(self, R: torch.Tensor) -> torch.Tensor:
        """tau_V = -d V(R exp(eta)) / d eta at 0: R (..., 3, 3) -> (..., 3); differentiable when grad
        mode is on. Only for a model with a potential."""
        assert self.potential is not None, "potential_torque needs a learned potential"
        create = torch.is_grad_enabled()
        with torch.enable_grad():
            eta = R.new_zeros(*R.shape[:-2], 3).requires_grad_(True)
            V = self.potential(so3_pose(R @ so3.exp(eta)))
            (dV,) = torch.autograd.grad(V.sum(), eta, create_graph=create)
        return -dV

    def fused_training(self) -> bool:
        """Whether `loss` takes the fused path (`models.glnn.engines.fused`): the model's path (fixed when it
        was built) is "fused" and it has no potential."""
        return self.path == "fused" and self.potential is None

    def accel(self, R: torch.Tensor, w: torch.Tensor, params: Params, fused: bool = False) -> torch.Tensor:
        """A(R, w) = J^{-1}(tau - w x J w), tau = -D w + tau_V(R): R (..., 3, 3), w (..., 3) -> (..., 3).
        fused: one autograd node (`fused_glnn.accel`, w (N, 3) only, no potential)."""
        J, Jinv, D = params
        if fused:
            return fused_glnn.accel(w, J, Jinv, D)
        tau = torch.cross(J @ w[..., None], w[..., None], dim=-2)[..., 0]  # (J w) x w
        if D is not None:
            tau = tau - w @ D.T
        if self.potential is not None:
            tau = tau + self.potential_torque(R)
        return tau @ Jinv.T

    def accel_jacobian_w(self, w: torch.Tensor, params: Params) -> torch.Tensor:
        """dA/dw = J^{-1}(-D + hat(J w) - hat(w) J) (potential part omitted): w (..., 3) -> (..., 3, 3)."""
        J, Jinv, D = params
        M = so3.hat(w @ J.T) - so3.hat(w) @ J
        if D is not None:
            M = M - D
        return Jinv @ M

    # ------------------------------------------------------------------ integrators
    def heun_step(self, R: torch.Tensor, w: torch.Tensor, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
        """One Lie-Heun (RKMK2) step: R (..., 3, 3), w (..., 3) -> (R' (..., 3, 3), w' (..., 3)) with
        w' = w + h/2 (A(R, w) + A(R exp(h w), w*)), w* = w + h A(R, w), R' = R exp(h (w + w*)/2)."""
        A1 = self.accel(R, w, params)
        w_star = w + self.h * A1
        A2 = self.accel(R @ so3.exp(self.h * w), w_star, params)
        return R @ so3.exp(0.5 * self.h * (w + w_star)), w + 0.5 * self.h * (A1 + A2)

    def midpoint_residual(
        self, R: torch.Tensor, w: torch.Tensor, w_next: torch.Tensor, params: Params, fused: bool = False
    ) -> torch.Tensor:
        """w' - w - h A(R exp(h/2 wbar), wbar), wbar = (w + w')/2: R (..., 3, 3), w, w' (..., 3) -> (..., 3);
        zero at the implicit Lie midpoint step."""
        wbar = 0.5 * (w + w_next)
        if fused:  # no potential: A does not read the midpoint rotation
            return w_next - w - self.h * self.accel(R, wbar, params, fused)
        return w_next - w - self.h * self.accel(R @ so3.exp(0.5 * self.h * wbar), wbar, params)

    def midpoint_step_train(
        self, R: torch.Tensor, w: torch.Tensor, params: Params
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable midpoint step: explicit Euler guess + `train_newton_iters` Newton steps.

        R (..., 3, 3), w (..., 3) -> (R' = R exp(h (w + w')/2) (..., 3, 3), w' (..., 3)).
        """
        w_next = self.midpoint_velocity_train(R, w, params)
        return R @ so3.exp(0.5 * self.h * (w + w_next)), w_next

    def midpoint_velocity_train(self, R: torch.Tensor, w: torch.Tensor, params: Params, fused: bool = False):
        """w' of `midpoint_step_train`: R (..., 3, 3), w (..., 3) -> (..., 3); fused: no potential, R unused."""
        w_next = w + self.h * self.accel(R, w, params, fused)
        eye = torch.eye(3, dtype=w.dtype, device=w.device)
        for _ in range(self.train_newton_iters):
            F = self.midpoint_residual(R, w, w_next, params, fused)
            Jac = eye - 0.5 * self.h * self.accel_jacobian_w(0.5 * (w + w_next), params)
            w_next = w_next - torch.linalg.solve(Jac, F[..., None])[..., 0]
        return w_next

    def _unroll_fused(self, R0: torch.Tensor, w0: torch.Tensor, steps: int, params: Params) -> torch.Tensor:
        """heun / midpoint training unroll without a potential: the velocities first (A does not read
        R), then every step's exp in one call, then the products R_{k+1} = R_k exp(h (w_k + w_k')/2) --
        the reference steps' operations, regrouped. R0 (N, 3, 3), w0 (N, 3) -> (N, steps+1, 3, 3)."""
        phis, w = [], w0
        for _ in range(steps):
            if self.integrator == "heun":
                A1 = self.accel(R0, w, params, True)
                w_star = w + self.h * A1
                w_next = w + 0.5 * self.h * (A1 + self.accel(R0, w_star, params, True))
                phis.append(0.5 * self.h * (w + w_star))
            else:
                w_next = self.midpoint_velocity_train(R0, w, params, True)
                phis.append(0.5 * self.h * (w + w_next))
            w = w_next
        E = so3.exp(torch.stack(phis, 1))
        Rs = [R0]
        for k in range(steps):
            Rs.append(Rs[-1] @ E[:, k])
        return torch.stack(Rs, 1)

    def midpoint_step_solve(
        self, R: torch.Tensor, w: torch.Tensor, params: Params, opts: SolverOptions
    ) -> tuple[torch.Tensor, torch.Tensor, NewtonResult]:
        """Rollout midpoint step by damped Newton (autodiff Jacobian) with convergence flags.

        R (N, 3, 3), w (N, 3) -> (R' (N, 3, 3), w' (N, 3), the solver's result for w').
        """
        guess = self.heun_step(R, w, params)[1]
        sol = solve(NewtonProblem.euclidean(lambda x: self.midpoint_residual(R, w, x, params), guess.detach()), opts)
        w_next = sol.x.detach()
        return R @ so3.exp(0.5 * self.h * (w + w_next)), w_next, sol

    def _odeint(
        self, R0: torch.Tensor, w0: torch.Tensor, steps: int, params: Params, fused: bool = False
    ) -> torch.Tensor:
        """dopri5 on (R entries, w): R0 (N, 3, 3), w0 (N, 3) -> R (N, steps+1, 3, 3)."""
        from torchdiffeq import odeint

        n = R0.shape[0]
        t = self.h * torch.arange(steps + 1, dtype=R0.dtype, device=R0.device)

        def f(t, y):
            R, w = y[:, :9].reshape(n, 3, 3), y[:, 9:]
            return torch.cat(((R @ so3.hat(w)).reshape(n, 9), self.accel(R, w, params)), -1)

        y0 = torch.cat((R0.reshape(n, 9), w0), -1)
        if fused:  # the whole solve as one autograd node (solvers/dopri5.py), torchdiffeq's steps
            ys = dopri5.odeint(  # feature major: (12, N) states (fused_glnn.Dopri5Field)
                fused_glnn.Dopri5Field(),
                y0.T.contiguous(),
                t.tolist(),
                params,
                self.rtol,
                self.atol,
                self.max_num_steps,
            )
            return ys[:, :9].permute(2, 0, 1).reshape(n, steps + 1, 3, 3)
        ys = odeint(
            f, y0, t, rtol=self.rtol, atol=self.atol, method="dopri5", options={"max_num_steps": self.max_num_steps}
        )
        return ys[..., :9].reshape(steps + 1, n, 3, 3).transpose(0, 1)

    def integrate_rotations(self, R0: torch.Tensor, w0: torch.Tensor, steps: int, fused: bool = False) -> torch.Tensor:
        """Differentiable prediction (N, steps+1, 3, 3) from R0 (N, 3, 3), w0 (N, 3); fused: the
        training path of `models.glnn.engines.fused` (no potential)."""
        params = self._params()
        if self.integrator == "dopri5":
            return self._odeint(R0, w0, steps, params, fused)
        if fused:
            return self._unroll_fused(R0, w0, steps, params)
        Rs, R, w = [R0], R0, w0
        step = self.heun_step if self.integrator == "heun" else self.midpoint_step_train
        for _ in range(steps):
            R, w = step(R, w, params)
            Rs.append(R)
        return torch.stack(Rs, 1)

    def initial_velocity(self, R0: torch.Tensor, R1: torch.Tensor) -> torch.Tensor:
        """w0 = log(R0^T R1) / h (the paper's finite-difference estimate): R0, R1 (..., 3, 3) -> (..., 3)."""
        return so3.log(R0.transpose(-1, -2) @ R1) / self.h

    # ------------------------------------------------------------------ training
    def loss(self, batch: Batch, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
        """Unroll from (R_0, w_0) over each window (a triplet is a length-2 window) -> (mean squared
        error of the predicted R entries, {"mse": ...}).

        batch: windows R (N, L+1, 1, 3, 3) (`as_sequence`) -> (scalar (), {"mse": scalar ()}).
        """
        R = batch.as_sequence().R[:, :, 0]
        w0 = self.initial_velocity(R[:, 0], R[:, 1])
        pred = self.integrate_rotations(R[:, 0], w0, R.shape[1] - 1, self.fused_training())
        mse = ((pred[:, 1:] - R[:, 1:]) ** 2).mean()
        return mse, {"mse": mse}

    # ------------------------------------------------------------------ rollout (solvers.rollout_explicit)
    def initial_state(self, g0: Pose, g1: Pose) -> State:
        """g0, g1 with R (N, 1, 3, 3) -> (R0 (N, 3, 3), w0 = log(R0^T R1)/h (N, 3), params)."""
        R0 = g0.R[:, 0]
        return R0, self.initial_velocity(R0, g1.R[:, 0]), self._params()

    def state_pose(self, state: State) -> Pose:
        """State -> Pose R (N, 1, 3, 3), p (N, 0, 3)."""
        return so3_pose(state[0])

    def step(self, state: State, opts: SolverOptions) -> tuple[State, NewtonResult | None]:
        """One heun or midpoint step of length h: (R (N, 3, 3), w (N, 3), params) -> the same
        shapes, plus the midpoint's Newton result (None for heun)."""
        R, w, params = state
        if self.integrator == "heun":
            R, w = self.heun_step(R, w, params)
            return (R, w, params), None
        R, w, sol = self.midpoint_step_solve(R, w, params, opts)
        return (R, w, params), sol

    def integrate(self, state: State, steps: int) -> Pose:
        """dopri5 over the whole grid: state (R0 (N, 3, 3), w0 (N, 3), params) -> Pose R (N, steps+1, 1, 3, 3),
        p (N, steps+1, 0, 3)."""
        R0, w0, params = state
        return so3_pose(self._odeint(R0, w0, steps, params, self.fused_training()))
