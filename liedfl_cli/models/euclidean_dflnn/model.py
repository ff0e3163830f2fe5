"""Euclidean DFLNN (paper Exp 3): the rigid-body discrete Lagrangian written on the entries of
(R, p) as free coordinates x in R^12 (R^9 for an SO(3) body), ignoring R^T R = I.

With finite-difference velocities Rd = (R1 - R0)/h, pd = (p1 - p0)/h:
    L_d(x0, x1) = h [ 1/2 tr(Rd J_d Rd^T) + 1/2 m |pd + Rd rho|^2 - V(x0) ],
which equals LieDFLNN's kinetic discrete Lagrangian whenever R0, R1 are rotations, so the two
models share the same variational structure and differ only in the configuration space. J_d is
the matrix-representation inertia of a learned SPD J (`Inertia.Jd()`, SPD), m > 0, rho free, V an
MLP on x (only when the scene has a potential). Damping: the Rayleigh function
1/2 xi^T D xi of the body velocity estimate xi = (vee(R0^T Rd), R0^T pd) (LieDFLNN's w~ and,
to first order, v~, read in ambient coordinates) gives the generalised force
Q = -d/d(xdot) (1/2 xi^T D xi) = (-1/2 R0 hat(a), -R0 b), (a, b) = D xi. As in LieDFLNN it enters
with weight h/2 at both ends of the step, F^-(x0, x1) = h/2 Q with R0 and F^+(x0, x1) = h/2 Q with
R1 in place of R0 (then, on SO(3)/SE(3) data, the residual's components along the group
directions equal LieDFLNN's residual for the same J_d, m, rho, D_ww -- a tested identity):
    r_k = d/dx_k [L_d(x_{k-1}, x_k) + L_d(x_k, x_{k+1})] + F^+(x_{k-1}, x_k) + F^-(x_k, x_{k+1}) in R^12.
Loss: w_DEL mean |r|^2 + w_reg mean penalty(log|det d^2 L_d / dx_k dx_{k+1}|) (the 12 x 12 mixed
Hessian by autodiff; it is -(1/h) times the constant kinetic matrix). Rollout: damped Newton on
x_{k+1} in R^12 from 2 x_k - x_{k-1}; the predicted R is not orthogonal and is returned as is.
Single-body groups only (SO(3) or SE(3)). With `runtime.fused` (the default) the training loss is
computed in closed form by `models.euclidean_dflnn.engines.fused` (the same numbers; `runtime.fused=false`: autograd).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import nn

from ...errors import ConfigError
from ...lie import Pose, ProductGroup, so3
from ...mechanics.mlp import MLP
from ...mechanics.parameterizations import Inertia, PositiveVector, SPSDMatrix
from ...solvers.newton import NewtonProblem
from ..base import (
    Batch,
    BuildContext,
    ImplicitModel,
    LossOptions,
    LossParts,
    TripletBatch,
    config_options,
    initial_scale,
)
from ..del_loss import del_regularity_loss
from .engines import fused as fused_dflnn

# rollout state: the pair (x_{k-1}, x_k), each (N, n)
State = tuple[torch.Tensor, torch.Tensor]


@dataclass
class EuclideanDFLNNOptions:
    """The Euclidean DFLNN's config options (conf/model/euclidean_dflnn.yaml): the schema `config/schema.py` checks the
    `model` section's keys and types against (`Model.Options`); `from_config` checks the values."""

    potential: Any = "mlp"  # mlp | none | auto
    damping: Any = "auto"  # auto | true | false
    mlp_width: int = 64
    mlp_depth: int = 3
    init_jitter: float = 0.1


class EuclideanDFLNN(ImplicitModel):
    """DEL model on the free coordinates x (..., n) of one body: the 9 entries of R, then p (n = 12
    for SE(3), 9 for SO(3)), with learned J_d, m, rho (SE(3)), D (and V(x))."""

    window = "triplet"

    def __init__(
        self,
        G: ProductGroup,
        h: float,
        potential: bool = False,
        damping: bool = True,
        mlp_width: int = 64,
        mlp_depth: int = 3,
        init_jitter: float = 0.1,
        epsilon: float = 10.0,
        seed: int = 0,
    ):
        super().__init__()
        if G.n_bodies != 1:
            raise ValueError("EuclideanDFLNN models one body")
        self.G, self.h = G, float(h)
        self.se3 = G.n_se3 == 1
        self.n = 12 if self.se3 else 9
        gen = torch.Generator().manual_seed(int(seed))
        self.mass: PositiveVector | None  # SE(3) only
        self.rho: nn.Parameter | None  # SE(3) only, (3,)
        # Mixed Hessian = -(1/h) K with K ~ s I_n when J_d = s I, m = s: n log(s/h) = epsilon.
        s = initial_scale(self.h, float(epsilon), self.n)
        self.inertia = Inertia(1, scale=2 * s, jitter=init_jitter, generator=gen)  # J = 2s I -> J_d = s I
        if self.se3:
            self.mass = PositiveVector(1, init=s)
            self.rho = nn.Parameter(init_jitter * torch.randn(3, generator=gen, dtype=torch.float64))
        else:
            self.mass, self.rho = None, None
        self.damping = SPSDMatrix(G.dim, init_diag=0.01 * s) if damping else None
        self.potential = MLP(self.n, 1, mlp_width, mlp_depth) if potential else None

    Options = EuclideanDFLNNOptions
    OPTIONS = tuple(f.name for f in fields(EuclideanDFLNNOptions))

    @classmethod
    def from_config(cls, ctx: BuildContext, **options) -> EuclideanDFLNN:
        """`potential` defaults to mlp even for a free body (see conf/model/euclidean_dflnn.yaml)."""
        opt = config_options(cls, options, cls.OPTIONS)
        if ctx.group.n_bodies != 1:
            raise ConfigError(
                f"euclidean_dflnn models a single rigid body (SO(3) or SE(3)); this dataset's group is {ctx.group.name}"
            )
        opt["potential"] = ctx.resolve_potential(opt.get("potential", "mlp")) == "mlp"
        opt["damping"] = ctx.resolve_damping(opt.get("damping", "auto"))
        return cls(ctx.group, ctx.h, epsilon=ctx.epsilon, seed=ctx.seed, **opt)

    def components(self) -> list[str]:
        """["J_d", "m"?, "rho_COM"?, "D"?, "V:MLP(x)"?]."""
        out = ["J_d"] + (["m", "rho_COM"] if self.se3 else [])
        if self.damping is not None:
            out.append("D")
        if self.potential is not None:
            out.append("V:MLP(x)")
        return out

    # ------------------------------------------------------------------ coordinates
    def to_x(self, g: Pose) -> torch.Tensor:
        """Pose (..., 1, 3, 3), (..., m, 3) -> x (..., n): 9 entries of R row by row, then p."""
        lead = g.R.shape[:-3]
        return torch.cat((g.R.reshape(*lead, 9), g.p.reshape(*lead, -1)), -1)

    def from_x(self, x: torch.Tensor) -> Pose:
        """Inverse of `to_x`: x (..., n) -> Pose R (..., 1, 3, 3), p (..., m, 3) (R not orthogonalised)."""
        lead = x.shape[:-1]
        return Pose(x[..., :9].reshape(*lead, 1, 3, 3), x[..., 9:].reshape(*lead, self.G.n_se3, 3))

    def _split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (..., n) -> (R (..., 3, 3), p (..., n - 9))."""
        return x[..., :9].reshape(*x.shape[:-1], 3, 3), x[..., 9:]

    # ------------------------------------------------------------------ discrete mechanics in x
    def lagrangian(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """L_d(x0, x1) = h [1/2 tr(Rd J_d Rd^T) + 1/2 m |pd + Rd rho|^2 - V(x0)]: x0, x1 (..., n) -> (...)."""
        R0, p0 = self._split(x0)
        R1, p1 = self._split(x1)
        Rd = (R1 - R0) / self.h
        Jd = self.inertia.Jd()[0]
        K = 0.5 * (Rd @ Jd * Rd).sum((-1, -2))  # 1/2 tr(Rd J_d Rd^T)
        if self.se3:
            assert self.mass is not None and self.rho is not None
            u = (p1 - p0) / self.h + (Rd @ self.rho[:, None])[..., 0]
            K = K + 0.5 * self.mass()[0] * (u * u).sum(-1)
        L = K
        if self.potential is not None:
            L = L - self.potential(x0)[..., 0]
        return self.h * L

    def forces(self, x0: torch.Tensor, x1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Generalised Rayleigh force of the step (x0, x1) applied at x0 and at x1, each (..., n).

        xi = (vee(R0^T Rd), R0^T pd) and (a, b) = D xi; the force at the endpoint with rotation
        Rj is Q_R = -1/2 Rj hat(a), Q_p = -Rj b (Rj = R0 is -d/d(xdot) of 1/2 xi^T D xi; using R1
        at the right endpoint makes the residual's tangential part equal LieDFLNN's on SO(3)/SE(3)).
        """
        if self.damping is None:
            z = torch.zeros_like(x0)
            return z, z
        R0, p0 = self._split(x0)
        R1, p1 = self._split(x1)
        w = so3.vee(R0.transpose(-1, -2) @ ((R1 - R0) / self.h))
        xi = w
        if self.se3:
            v = ((p1 - p0) / self.h)[..., None, :] @ R0  # (R0^T pd)^T
            xi = torch.cat((w, v[..., 0, :]), -1)
        c = xi @ self.damping().T
        A = so3.hat(c[..., :3])
        out = []
        for Rj in (R0, R1):
            Q = [(-0.5 * Rj @ A).reshape(*Rj.shape[:-2], 9)]
            if self.se3:
                Q.append(-(Rj @ c[..., 3:, None])[..., 0])
            out.append(torch.cat(Q, -1))
        return out[0], out[1]

    def residual(self, x_prev: torch.Tensor, x: torch.Tensor, x_next: torch.Tensor) -> torch.Tensor:
        """r_k = d/dx_k [L_d(x_prev, x_k) + L_d(x_k, x_next)] + F^+(x_prev, x_k) + F^-(x_k, x_next):
        x_prev, x, x_next (..., n) -> (..., n); differentiable w.r.t. x_prev, x_next and the parameters."""
        create = torch.is_grad_enabled()
        with torch.enable_grad():
            xk = x.detach().requires_grad_(True)
            L = self.lagrangian(x_prev, xk) + self.lagrangian(xk, x_next)
            (dL,) = torch.autograd.grad(L.sum(), xk, create_graph=True)
        r = dL + 0.5 * self.h * (self.forces(x_prev, x)[1] + self.forces(x, x_next)[0])
        return r if create else r.detach()

    def mixed_hessian(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """d^2 L_d / dx0 dx1, (..., n, n) by autodiff."""
        with torch.enable_grad():
            a, b = x0.detach().requires_grad_(True), x1.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.lagrangian(a, b).sum(), a, create_graph=True)
            rows = [torch.autograd.grad(g[..., i].sum(), b, create_graph=True)[0] for i in range(self.n)]
        return torch.stack(rows, -2)

    # ------------------------------------------------------------------ training
    def loss(self, batch: Batch, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
        """w_DEL mean |r_k|^2 + w_reg mean penalty(log|det d^2 L_d/dx0 dx1|) over triplets of poses
        R (N, 1, 3, 3), p (N, m, 3) (regularity pairs (P, ...)) -> (scalar (), {"del_loss", "reg_loss"} scalars ())."""
        assert isinstance(batch, TripletBatch), "EuclideanDFLNN trains on triplets (window = 'triplet')"
        if self.path == "fused":  # closed form (models/euclidean_dflnn/engines/fused.py), the same numbers
            n_reg = batch.reg[0].R.shape[0] if batch.reg is not None and opts.w_reg > 0 else 0
            x_prev, x, x_next = (self.to_x(g) for g in batch.poses())
            return del_regularity_loss(*fused_dflnn.euclidean_residual_and_logdet(self, x_prev, x, x_next, n_reg), opts)
        r = self.residual(*(self.to_x(g) for g in batch.poses()))
        logdet = None
        if batch.reg is not None and opts.w_reg > 0:
            H = self.mixed_hessian(self.to_x(batch.reg[0]), self.to_x(batch.reg[1]))
            logdet = torch.linalg.slogdet(H).logabsdet
        return del_regularity_loss(r, logdet, opts)

    # ------------------------------------------------------------------ implicit step (rollout)
    def implicit_start(self, g0: Pose, g1: Pose) -> State:
        """g0, g1 with R (N, 1, 3, 3), p (N, m, 3) -> (x0, x1), each (N, n)."""
        return self.to_x(g0), self.to_x(g1)

    def implicit_problem(self, state: State) -> NewtonProblem:
        """r_k(x_{k-1}, x_k, y) = 0 for y = x_{k+1} (N, n), from 2 x_k - x_{k-1}."""
        a, b = state
        return NewtonProblem.euclidean(lambda y: self.residual(a, b, y), 2 * b - a)

    def implicit_advance(self, state: State, x: torch.Tensor) -> tuple[State, Pose]:
        """Solution x = x_{k+1} (N, n) -> ((x_k, x_{k+1}), Pose R (N, 1, 3, 3), p (N, m, 3))."""
        x = x.detach()
        return (state[1], x), self.from_x(x)
