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
"""

from __future__ import annotations

import time

import torch
from torch import nn

from ..lie import Pose, ProductGroup, so3
from ..mechanics.parameterizations import Inertia, SPSDMatrix
from ..mechanics.potentials import MLPPotential
from ..solvers.newton import damped_newton
from ..solvers.rollout import Rollout
from .baseline_common import explicit_rollout, so3_pose, triplet_sequence, with_data_start

INTEGRATORS = ("dopri5", "heun", "midpoint")


class GLNN(nn.Module):
    """Continuous-time rigid body on SO(3) with learned J, D (and V), integrated by `integrator`.

    Args:
        G: the dataset's group (must be one SO(3) body). h: time step. integrator: dopri5 | heun |
        midpoint. window: "trajectory" (unroll the whole training window) or "triplet".
        potential / damping: build V and D. rtol, atol, max_num_steps: dopri5 settings.
        train_newton_iters: Newton iterations of the midpoint solve in training.
    """

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
        self.rtol, self.atol, self.max_num_steps = float(rtol), float(atol), int(max_num_steps)
        self.train_newton_iters = int(train_newton_iters)
        gen = torch.Generator().manual_seed(int(seed))
        # The equations are invariant under a common scale of (J, D, V): start at J ~ I.
        self.inertia = Inertia(1, scale=1.0, jitter=init_jitter, generator=gen)
        self.damping = SPSDMatrix(3, init_diag=0.01) if damping else None
        self.potential = MLPPotential(G, mlp_width, mlp_depth) if potential else None

    def components(self) -> list[str]:
        out = ["J"]
        if self.damping is not None:
            out.append("D")
        if self.potential is not None:
            out.append("V:MLPPotential")
        return out + [f"integrator:{self.integrator}"]

    # ------------------------------------------------------------------ vector field
    def _params(self):
        J = self.inertia.J()[0]
        D = self.damping() if self.damping is not None else None
        return J, torch.linalg.inv(J), D

    def potential_torque(self, R: torch.Tensor) -> torch.Tensor:
        """tau_V = -d V(R exp(eta)) / d eta at 0, (..., 3); differentiable when grad mode is on."""
        create = torch.is_grad_enabled()
        with torch.enable_grad():
            eta = R.new_zeros(*R.shape[:-2], 3).requires_grad_(True)
            V = self.potential(so3_pose(R @ so3.exp(eta)))
            (dV,) = torch.autograd.grad(V.sum(), eta, create_graph=create)
        return -dV

    def accel(self, R: torch.Tensor, w: torch.Tensor, params) -> torch.Tensor:
        """A(R, w) = J^{-1}(tau - w x J w), (..., 3)."""
        J, Jinv, D = params
        tau = torch.cross(J @ w[..., None], w[..., None], dim=-2)[..., 0]  # (J w) x w
        if D is not None:
            tau = tau - w @ D.T
        if self.potential is not None:
            tau = tau + self.potential_torque(R)
        return tau @ Jinv.T

    def accel_jacobian_w(self, w: torch.Tensor, params) -> torch.Tensor:
        """dA/dw = J^{-1}(-D + hat(J w) - hat(w) J) (potential part omitted), (..., 3, 3)."""
        J, Jinv, D = params
        M = so3.hat(w @ J.T) - so3.hat(w) @ J
        if D is not None:
            M = M - D
        return Jinv @ M

    # ------------------------------------------------------------------ integrators
    def heun_step(self, R, w, params):
        A1 = self.accel(R, w, params)
        w_star = w + self.h * A1
        A2 = self.accel(R @ so3.exp(self.h * w), w_star, params)
        return R @ so3.exp(0.5 * self.h * (w + w_star)), w + 0.5 * self.h * (A1 + A2)

    def midpoint_residual(self, R, w, w_next, params):
        wbar = 0.5 * (w + w_next)
        return w_next - w - self.h * self.accel(R @ so3.exp(0.5 * self.h * wbar), wbar, params)

    def midpoint_step_train(self, R, w, params):
        """Differentiable midpoint step: explicit Euler guess + `train_newton_iters` Newton steps."""
        w_next = w + self.h * self.accel(R, w, params)
        eye = torch.eye(3, dtype=w.dtype)
        for _ in range(self.train_newton_iters):
            F = self.midpoint_residual(R, w, w_next, params)
            Jac = eye - 0.5 * self.h * self.accel_jacobian_w(0.5 * (w + w_next), params)
            w_next = w_next - torch.linalg.solve(Jac, F[..., None])[..., 0]
        return R @ so3.exp(0.5 * self.h * (w + w_next)), w_next

    def midpoint_step_solve(self, R, w, params, tol, max_iter, max_halvings):
        """Rollout midpoint step by damped Newton (autodiff Jacobian) with convergence flags."""
        guess = self.heun_step(R, w, params)[1]
        sol = damped_newton(
            lambda x: self.midpoint_residual(R, w, x, params),
            guess.detach(),
            tol=tol,
            max_iter=max_iter,
            max_halvings=max_halvings,
        )
        w_next = sol.x.detach()
        return R @ so3.exp(0.5 * self.h * (w + w_next)), w_next, sol

    def _odeint(self, R0, w0, steps, params):
        from torchdiffeq import odeint

        n = R0.shape[0]

        def f(t, y):
            R, w = y[:, :9].reshape(n, 3, 3), y[:, 9:]
            return torch.cat(((R @ so3.hat(w)).reshape(n, 9), self.accel(R, w, params)), -1)

        t = self.h * torch.arange(steps + 1, dtype=R0.dtype)
        y0 = torch.cat((R0.reshape(n, 9), w0), -1)
        ys = odeint(
            f, y0, t, rtol=self.rtol, atol=self.atol, method="dopri5", options={"max_num_steps": self.max_num_steps}
        )
        return ys[..., :9].reshape(steps + 1, n, 3, 3).transpose(0, 1)

    def integrate(self, R0: torch.Tensor, w0: torch.Tensor, steps: int) -> torch.Tensor:
        """Differentiable prediction (N, steps+1, 3, 3) from R0 (N, 3, 3), w0 (N, 3)."""
        params = self._params()
        if self.integrator == "dopri5":
            return self._odeint(R0, w0, steps, params)
        Rs, R, w = [R0], R0, w0
        step = self.heun_step if self.integrator == "heun" else self.midpoint_step_train
        for _ in range(steps):
            R, w = step(R, w, params)
            Rs.append(R)
        return torch.stack(Rs, 1)

    def initial_velocity(self, R0: torch.Tensor, R1: torch.Tensor) -> torch.Tensor:
        """w0 = log(R0^T R1) / h (the paper's finite-difference estimate), (..., 3)."""
        return so3.log(R0.transpose(-1, -2) @ R1) / self.h

    # ------------------------------------------------------------------ training
    def loss(self, batch, *args):
        """window "trajectory": loss(traj (B, L+1, ...), cfg_train); "triplet": loss((prev, cur, nxt),
        reg_pairs, cfg_train). -> (mean squared error of predicted R entries, {"mse": ...})."""
        seq = triplet_sequence(batch) if isinstance(batch, tuple) and not isinstance(batch, Pose) else batch
        R = seq.R[:, :, 0]
        pred = self.integrate(R[:, 0], self.initial_velocity(R[:, 0], R[:, 1]), R.shape[1] - 1)
        mse = ((pred[:, 1:] - R[:, 1:]) ** 2).mean()
        return mse, {"mse": mse}

    # ------------------------------------------------------------------ rollout
    @torch.no_grad()
    def rollout(self, g0: Pose, g1: Pose, steps: int, solver=None, progress=None) -> Rollout:
        s = solver or {}
        t0 = time.perf_counter()
        R0, R1 = g0.R[:, 0], g1.R[:, 0]
        w = self.initial_velocity(R0, R1)
        params = self._params()
        T = R0.shape[0]
        if self.integrator != "midpoint":
            Rs = self.integrate(R0, w, steps)
            if progress is not None:
                progress(steps - 1)
            pose = with_data_start(so3_pose(Rs), g0, g1)
            return explicit_rollout(pose, time.perf_counter() - t0)
        tol, max_iter = float(s.get("tol", 1e-5)), int(s.get("max_iter", 10))
        halvings = int(s.get("max_halvings", 6))
        Rs, R = [R0], R0
        conv, its, res = [], [], []
        for k in range(steps):
            R, w, sol = self.midpoint_step_solve(R, w, params, tol, max_iter, halvings)
            Rs.append(R)
            conv.append(sol.converged)
            its.append(sol.iterations)
            res.append(sol.residual_norm)
            if progress is not None and k >= 1:
                progress(k)
        pose = with_data_start(so3_pose(torch.stack(Rs, 1)), g0, g1)
        if steps < 2:
            e = torch.zeros(T, 0)
            return Rollout(pose, e.bool(), e.long(), e.double(), time.perf_counter() - t0)
        conv, its, res = torch.stack(conv, 1), torch.stack(its, 1), torch.stack(res, 1)
        # The first step (to R_1) is replaced by the observed g1 but feeds the later ones: fold
        # its diagnostics into those of the step to R_2.
        converged, iterations, residual = conv[:, 1:].clone(), its[:, 1:].clone(), res[:, 1:].clone()
        converged[:, 0] &= conv[:, 0]
        iterations[:, 0] += its[:, 0]
        residual[:, 0] = torch.maximum(residual[:, 0], res[:, 0])
        return Rollout(pose, converged, iterations, residual, time.perf_counter() - t0)
