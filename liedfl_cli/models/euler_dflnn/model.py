"""Euler-angle DFLNN (paper Exp 1): the discrete Lagrangian approach in ZYX Euler angles
q = (phi, theta, psi) treated as Euclidean coordinates.

    L_d(q0, q1) = h [ 1/2 qdot^T M(qm) qdot - V(qm) ],  qdot = (q1 - q0)/h,  qm = (q0 + q1)/2,
    M(q) = E(q)^T J E(q)   (rigid-body kinetic energy in Euler-angle rates, learned SPD J),
    Q(q0, q1) = -E(qm)^T D E(qm) qdot   (Rayleigh dissipation 1/2 w^T D w, w = E qdot, learned D),
    r_k = d/dq_k [L_d(q_{k-1}, q_k) + L_d(q_k, q_{k+1})] + h/2 [Q(q_{k-1}, q_k) + Q(q_k, q_{k+1})],

with E the Euler-rate matrix (`lie.euler.rate_matrix`, det E = cos theta: M is singular at gimbal
lock, which is the weakness the experiment exposes) and V an MLP on q (only when the scene has a
potential). Loss: w_DEL mean |r|^2 + w_reg mean penalty(log|det d^2 L_d/dq_k dq_{k+1}|), like
LieDFLNN (the same `regularity_penalty`, threshold train.epsilon).

Angles: each pose of a training triplet is converted with `euler.from_matrix` (principal
values); the triplet is then unwrapped around its middle pose, which keeps its principal value.
Rollouts do the same: before each step the pair (q_{k-1}, q_k) is shifted by the multiple of
2 pi that brings q_k to its principal value (L_d's kinetic and damping terms are 2 pi periodic;
only V sees the shift, and it then sees the same range as in training). q_{k+1} is found by
damped Newton on r_k (solver tolerance / iterations), warm-started at 2 q_k - q_{k-1}, and
converted back to SO(3) by `euler.to_matrix` for evaluation.

With `runtime.fused` (the default) the residual and the regularity term's mixed Hessian are computed
in closed form (`engines/fused.py`: `euler_residual` and `euler_mixed_hessian`, the same numbers to
rounding; `runtime.fused=false`: autograd of `lagrangian`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch

from ...lie import Pose, ProductGroup, euler
from ...mechanics.mlp import MLP
from ...mechanics.parameterizations import Inertia, SPSDMatrix
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
    require_single_so3,
    so3_pose,
)
from ..del_loss import del_regularity_loss
from .engines import fused as fused_dflnn


def _shift_to_principal(q_ref: torch.Tensor) -> torch.Tensor:
    """Multiple of 2 pi to subtract so that q_ref becomes principal (theta needs none): (..., 3) -> (..., 3)."""
    return q_ref - euler.wrap(q_ref)


# rollout state: the pair (q_{k-1}, q_k), each (N, 3)
State = tuple[torch.Tensor, torch.Tensor]


@dataclass
class EulerDFLNNOptions:
    """The Euler-angle DFLNN's config options (conf/model/euler_dflnn.yaml): the schema `config/schema.py` checks the
    `model` section's keys and types against (`Model.Options`); `from_config` checks the values."""

    potential: Any = "auto"  # auto | mlp | none
    damping: Any = "auto"  # auto | true | false
    mlp_width: int = 64
    mlp_depth: int = 3
    init_jitter: float = 0.1


class EulerDFLNN(ImplicitModel):
    """DEL model in ZYX Euler angles q (..., 3) with M(q) = E^T J E, learned J, D (and V(q))."""

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
        self.G, self.h = G, float(h)
        gen = torch.Generator().manual_seed(int(seed))
        # Mixed Hessian ~ -(1/h) E^T J E: J = s I with 3 log(s/h) = epsilon starts at the threshold.
        scale = initial_scale(self.h, float(epsilon), 3)
        self.inertia = Inertia(1, scale=scale, jitter=init_jitter, generator=gen)
        self.damping = SPSDMatrix(3, init_diag=0.01 * scale) if damping else None
        self.potential = MLP(3, 1, mlp_width, mlp_depth) if potential else None

    Options = EulerDFLNNOptions
    OPTIONS = tuple(f.name for f in fields(EulerDFLNNOptions))

    @classmethod
    def from_config(cls, ctx: BuildContext, **options) -> EulerDFLNN:
        """Options of conf/model/euler_dflnn.yaml; `potential`/`damping: auto` follow the scene."""
        opt = config_options(cls, options, cls.OPTIONS)
        require_single_so3(ctx.group, "euler_dflnn")
        opt["potential"] = ctx.resolve_potential(opt.get("potential", "auto")) == "mlp"
        opt["damping"] = ctx.resolve_damping(opt.get("damping", "auto"))
        return cls(ctx.group, ctx.h, epsilon=ctx.epsilon, seed=ctx.seed, **opt)

    def components(self) -> list[str]:
        """["J (in M(q) = E^T J E)", "D"?, "V:MLP(q)"?]."""
        out = ["J (in M(q) = E^T J E)"]
        if self.damping is not None:
            out.append("D")
        if self.potential is not None:
            out.append("V:MLP(q)")
        return out

    # ------------------------------------------------------------------ discrete mechanics in q
    def lagrangian(self, q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor:
        """L_d(q0, q1) = h [1/2 w^T J w - V(qm)], w = E(qm) (q1 - q0)/h, qm = (q0 + q1)/2.

        q0, q1 (..., 3) -> (...).
        """
        qd = (q1 - q0) / self.h
        qm = 0.5 * (q0 + q1)
        w = (euler.rate_matrix(qm) @ qd[..., None])[..., 0]
        J = self.inertia.J()[0]
        L = 0.5 * (w * (w @ J.T)).sum(-1)
        if self.potential is not None:
            L = L - self.potential(qm)[..., 0]
        return self.h * L

    def force(self, q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor:
        """Generalised Rayleigh force Q = -E^T D E qdot at the midpoint: q0, q1 (..., 3) -> (..., 3)."""
        if self.damping is None:
            return torch.zeros_like(q0)
        E = euler.rate_matrix(0.5 * (q0 + q1))
        w = E @ ((q1 - q0) / self.h)[..., None]
        return -(E.transpose(-1, -2) @ (self.damping() @ w))[..., 0]

    def residual(self, q_prev: torch.Tensor, q: torch.Tensor, q_next: torch.Tensor) -> torch.Tensor:
        """Forced DEL residual r_k = D_2 L_d(q_prev, q) + D_1 L_d(q, q_next) + h/2 (Q(q_prev, q) + Q(q, q_next)):
        q_prev, q, q_next (..., 3) -> (..., 3); differentiable w.r.t. q_prev, q_next and the parameters."""
        if self.path == "fused" and q.dim() == 2:
            return fused_dflnn.euler_residual(self, q_prev, q, q_next)
        create = torch.is_grad_enabled()
        with torch.enable_grad():
            qk = q.detach().requires_grad_(True)
            L = self.lagrangian(q_prev, qk) + self.lagrangian(qk, q_next)
            (dL,) = torch.autograd.grad(L.sum(), qk, create_graph=True)
        r = dL + 0.5 * self.h * (self.force(q_prev, q) + self.force(q, q_next))
        return r if create else r.detach()

    def mixed_hessian(self, q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor:
        """d^2 L_d / dq0 dq1 by autodiff: q0, q1 (..., 3) -> (..., 3, 3)."""
        with torch.enable_grad():
            a, b = q0.detach().requires_grad_(True), q1.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.lagrangian(a, b).sum(), a, create_graph=True)
            rows = [torch.autograd.grad(g[..., i].sum(), b, create_graph=True)[0] for i in range(3)]
        return torch.stack(rows, -2)

    # ------------------------------------------------------------------ data conversion
    @staticmethod
    def angles(*poses: Pose) -> list[torch.Tensor]:
        """Consecutive poses -> ZYX angles unwrapped along the sequence around the middle pose.

        Each pose R (..., 1, 3, 3) -> one angle tensor q (..., 3) per pose; the middle one is principal.
        """
        q = torch.stack([euler.from_matrix(g.R[..., 0, :, :]) for g in poses], -2)
        q = euler.unwrap(q, dim=-2)
        mid = q[..., len(poses) // 2, :]
        q = q - _shift_to_principal(mid)[..., None, :]
        return list(q.unbind(-2))

    # ------------------------------------------------------------------ training
    def loss(self, batch: Batch, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
        """w_DEL mean |r_k|^2 + w_reg mean penalty(log|det d^2 L_d/dq0 dq1|) over triplets R (N, 1, 3, 3)
        (regularity pairs R (P, 1, 3, 3)) -> (scalar (), {"del_loss", "reg_loss"} scalars ())."""
        assert isinstance(batch, TripletBatch), "EulerDFLNN trains on triplets (window = 'triplet')"
        q_prev, q, q_next = self.angles(*batch.poses())
        r = self.residual(q_prev, q, q_next)
        logdet = None
        if batch.reg is not None and opts.w_reg > 0:
            a, b = self.angles(*batch.reg)
            H = fused_dflnn.euler_mixed_hessian(self, a, b) if self.path == "fused" else None
            logdet = torch.linalg.slogdet(self.mixed_hessian(a, b) if H is None else H).logabsdet
        return del_regularity_loss(r, logdet, opts)

    # ------------------------------------------------------------------ implicit step (rollout)
    def implicit_start(self, g0: Pose, g1: Pose) -> State:
        """g0, g1 with R (N, 1, 3, 3) -> (q0, q1), each (N, 3), unwrapped around q1."""
        q0, q1 = self.angles(g0, g1)
        return q0, q1

    @staticmethod
    def _principal_pair(state: State) -> State:
        """(q_{k-1}, q_k) shifted by the multiple of 2 pi that makes q_k principal."""
        q_prev, q = state
        shift = _shift_to_principal(q)
        return q_prev - shift, q - shift

    def implicit_problem(self, state: State) -> NewtonProblem:
        """r_k(q_{k-1}, q_k, x) = 0 for x = q_{k+1} (N, 3), from 2 q_k - q_{k-1} (pair made principal)."""
        a, b = self._principal_pair(state)
        return NewtonProblem.euclidean(lambda x: self.residual(a, b, x), 2 * b - a)

    def implicit_advance(self, state: State, x: torch.Tensor) -> tuple[State, Pose]:
        """Solution x = q_{k+1} (N, 3) -> ((q_k, q_{k+1}), Pose R (N, 1, 3, 3), p (N, 0, 3))."""
        _, b = self._principal_pair(state)
        q_next = x.detach()
        return (b, q_next), so3_pose(euler.to_matrix(q_next))
