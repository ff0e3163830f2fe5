"""Fused hot paths of LieDFLNN, part 3 (see `models.liedflnn.engines.core`): the rollout's maps built once
(`RolloutMaps`, `RolloutState`) and the implicit Newton step on the increment (`FusedStep`: residual,
Jacobian, full iteration, the part `runtime.compile` compiles under the model's plan), and the rollout's
start/advance."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from ....lie import Pose, ProductGroup, so3
from ....lie.batched import HISTORY, compose, extrapolate_increments, retract_increment
from ....lie.tolerances import projects_poses
from ....mechanics import kinetic
from ....mechanics.forces import PDControl, RayleighForce, RayleighNonlinearForce, force_jacobian_xi
from ....mechanics.potentials import MLPPotential
from ....solvers import compile as compile_cache
from ....solvers.newton import NewtonProblem
from ... import mlp_derivatives
from .maps import Derived, _apply_map, _basis, _constants, derive, hessian_map, potential_covector, solve_small

AFFINE_FORCES = (RayleighNonlinearForce, PDControl)
"""Forces known to be affine in the velocity estimate: F(g, xi) = F(g, 0) + dF/dxi(g) xi."""


@dataclass
class RolloutMaps:
    """What a rollout builds once from the model's parameters (all detached).

    P: derived parameters. d1, d2, hess (B, 9, k): the rotational kinetic d1 / d2 residuals and
    mixed-Hessian blocks as linear maps of W.flatten(). rho_map (m, 9, 3): W.flatten() @ map =
    W rho. se3_block (m, 9, 36): the SE(3) bodies' 6x6 kinetic blocks. linear: for SO(3)-only
    groups whose forces are constant Rayleigh matrices, (lin_f, lin_J, lin_const) with
    W.flatten() @ lin_f = residual_var, @ lin_J = its Jacobian, and W_prev.flatten() @ lin_const
    = d2 + (h/2) F(g_prev, xi~_prev); None otherwise. kin_index / dxi_index: flat positions of
    the block-diagonal entries in a (dim, dim) matrix (several bodies)."""

    P: Derived
    d1: torch.Tensor
    d2: torch.Tensor
    hess: torch.Tensor
    rho_map: torch.Tensor | None
    se3_block: torch.Tensor | None
    linear: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None
    block_index: torch.Tensor | None
    potential_layers: list | None = None


@dataclass
class RolloutState:
    """State of a fused rollout: poses g_{k-1}, g_k, the increment W_{k-1} = g_{k-1}^{-1} g_k, the maps
    built once per rollout, and the increments before W_{k-1} (oldest first, at most `HISTORY` - 1): the
    warm start is all of them extrapolated (`lie.batched.extrapolate_increments`)."""

    g_prev: Pose
    g: Pose
    inc: Pose
    maps: RolloutMaps
    compile: bool = False
    before: tuple[Pose, ...] = ()

    def guess(self, G: ProductGroup) -> Pose:
        """The Newton start of the step from this state (see the class)."""
        return extrapolate_increments(G, (*self.before, self.inc))


def _d2_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 3): W.flatten() @ map = vee(J_d W - W^T J_d) / h (`kinetic.kinetic_d2`, rotation)."""
    E = _basis(Jd.dtype, Jd.device)[:, None]
    return (so3.vee(Jd @ E - E.transpose(-1, -2) @ Jd) / h).transpose(0, 1)


def _d1_map(Jd: torch.Tensor, h: float) -> torch.Tensor:
    """(B, 9, 3): W.flatten() @ map = vee(J_d W^T - W J_d) / h (`kinetic.kinetic_d1`, rotation)."""
    E = _basis(Jd.dtype, Jd.device)[:, None]
    return (so3.vee(Jd @ E.transpose(-1, -2) - E @ Jd) / h).transpose(0, 1)


def _block_index(G: ProductGroup, device: torch.device) -> torch.Tensor:
    """Flat positions in a (dim, dim) matrix of the block-diagonal entries, body by body
    (6x6 for SE(3) bodies, 3x3 for SO(3) bodies, row-major within a block), on `device`."""
    out = []
    for s in G.body_slices():
        rows = torch.arange(s.start, s.stop, device=device)
        out.append((rows[:, None] * G.dim + rows[None, :]).flatten())
    return torch.cat(out)


def rollout_maps(model) -> RolloutMaps:
    G, h = model.G, model.h
    P = derive(model)
    P = Derived(P.Jd.detach(), P.mass.detach(), P.rho.detach(), None if P.D is None else P.D.detach())
    m = G.n_se3
    d1, d2, hess = _d1_map(P.Jd, h), _d2_map(P.Jd, h), hessian_map(P.Jd, h)
    rho_map = se3_block = None
    if m:
        E = _basis(P.Jd.dtype, P.Jd.device)
        rho_map = (E[None] @ P.rho[:, None, :, None])[..., 0]  # (m, 9, 3)
        se3_block = torch.stack(
            [
                kinetic.mixed_hessian_blocks(
                    ProductGroup(1, 0),
                    Pose(E[:, None], E.new_zeros(9, 1, 3)),
                    P.Jd[i : i + 1],
                    P.mass[i : i + 1],
                    P.rho[i : i + 1],
                    h,
                )[0].flatten(-2)
                for i in range(m)
            ]
        )
    linear = None
    if not m and all(isinstance(f, RayleighForce) for f in model.forces):
        linear = _linear_maps(model, P)
    block_index = _block_index(G, P.Jd.device) if G.n_bodies > 1 else None
    lys = None  # an MLP potential of a rotation-only group: its layers, parsed once per rollout
    if not m and isinstance(model.potential, MLPPotential):
        lys = mlp_derivatives.layers(model.potential.net)
    return RolloutMaps(P, d1, d2, hess, rho_map, se3_block, linear, block_index, lys)


def _linear_maps(model, P: Derived) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(lin_f (9B, dim), lin_J (9B, dim * dim), lin_const (9B, dim)) of an SO(3)-only model with
    constant forces, built by evaluating the reference formulas on the basis increments."""
    G, h = model.G, model.h
    B, dim = G.n_bodies, G.dim
    E = _basis(P.Jd.dtype, P.Jd.device)
    fs, Js, cs = [], [], []
    for b in range(B):
        W = E.new_zeros(9, B, 3, 3)
        W[:, b] = E
        inc = Pose(W, W.new_zeros(9, 0, 3))
        r = kinetic.kinetic_d1(G, inc, P.Jd, P.mass, P.rho, h)
        c = kinetic.kinetic_d2(G, inc, P.Jd, P.mass, P.rho, h)
        J = W.new_zeros(9, dim, dim)
        for sl, blk in zip(G.body_slices(), kinetic.mixed_hessian_blocks(G, inc, P.Jd, P.mass, P.rho, h)):
            J[:, sl, sl] = blk
        if P.D is not None:
            F = -(kinetic.velocity_estimate(G, inc, h) @ P.D.T)
            r = r + 0.5 * h * F
            c = c + 0.5 * h * F
            J = J + 0.5 * h * (-P.D @ kinetic.velocity_estimate_jacobian(G, inc, h))
        fs.append(r)
        Js.append(J.flatten(-2))
        cs.append(c)
    return torch.cat(fs).contiguous(), torch.cat(Js).contiguous(), torch.cat(cs).contiguous()


def rollout_start(model, g0: Pose, g1: Pose, compile_it: bool = False) -> RolloutState:
    """State before the first step; `compile_it`: run the compiled Newton step (the model's plan
    decides, `LieDFLNN.rollout_rows`)."""
    return RolloutState(g0, g1, model.G.increment(g0, g1), rollout_maps(model), compile_it)


def _kinetic_se3_terms(W: torch.Tensor, z: torch.Tensor, maps: RolloutMaps, h: float):
    """SE(3) bodies' kinetic pieces at increments W (T, m, 3, 3), z (T, m, 3): (X, W rho)."""
    assert maps.rho_map is not None
    Wrho = _apply_map(W.flatten(-2), maps.rho_map)
    return z + Wrho - maps.P.rho, Wrho


def kinetic_d1(G: ProductGroup, x: Pose, maps: RolloutMaps, h: float) -> torch.Tensor:
    """`kinetic.kinetic_d1` with the rotational part from its linear map."""
    w = _apply_map(x.R.flatten(-2), maps.d1)
    m = G.n_se3
    if not m:
        return G.join(w, w[..., :0, :])
    X, Wrho = _kinetic_se3_terms(x.R[..., :m, :, :], x.p, maps, h)
    scale = (maps.P.mass / h)[..., None]
    w = torch.cat((w[..., :m, :] + scale * torch.linalg.cross(X, x.p + Wrho), w[..., m:, :]), -2)
    return G.join(w, -scale * X)


def kinetic_d2(G: ProductGroup, x: Pose, maps: RolloutMaps, h: float) -> torch.Tensor:
    """`kinetic.kinetic_d2` with the rotational part from its linear map."""
    w = _apply_map(x.R.flatten(-2), maps.d2)
    m = G.n_se3
    if not m:
        return G.join(w, w[..., :0, :])
    Wm = x.R[..., :m, :, :]
    X, _ = _kinetic_se3_terms(Wm, x.p, maps, h)
    WtX = (Wm.transpose(-1, -2) @ X[..., None])[..., 0]
    scale = (maps.P.mass / h)[..., None]
    rho = maps.P.rho.expand_as(WtX)
    w = torch.cat((w[..., :m, :] + scale * torch.linalg.cross(rho, WtX), w[..., m:, :]), -2)
    return G.join(w, scale * WtX)


def kinetic_blocks(G: ProductGroup, x: Pose, maps: RolloutMaps) -> torch.Tensor:
    """Block-diagonal entries of the kinetic mixed Hessian, body by body: (T, 36 m + 9 n)."""
    m = G.n_se3
    Wf = x.R.flatten(-2)
    parts = []
    if m:
        assert maps.se3_block is not None
        parts.append(_apply_map(Wf[..., :m, :], maps.se3_block).flatten(-2))
    if G.n_so3:
        parts.append(_apply_map(Wf[..., m:, :], maps.hess[m:]).flatten(-2))
    return parts[0] if len(parts) == 1 else torch.cat(parts, -1)


def velocity_jacobian_blocks(G: ProductGroup, x: Pose, h: float) -> torch.Tensor:
    """Block-diagonal entries of `kinetic.velocity_estimate_jacobian`, body by body: (T, 36 m + 9 n)."""
    W, z = x.R, x.p
    eye = _constants(W.dtype, W.device)["eye"]
    trW = W.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    dw = (trW * eye - W.transpose(-1, -2)) / (2 * h)  # (T, B, 3, 3)
    m = G.n_se3
    if not m:
        return dw.flatten(-3)
    Wm, dwm = W[..., :m, :, :], dw[..., :m, :, :]
    w_t = so3.vee(Wm) / h
    dvv = (eye - 0.5 * h * so3.hat(w_t)) @ Wm / h
    dvw = 0.5 * so3.hat(z) @ dwm
    top = torch.cat((dwm, torch.zeros_like(dwm)), -1)
    se = torch.cat((top, torch.cat((dvw, dvv), -1)), -2).flatten(-3)
    return se if not G.n_so3 else torch.cat((se, dw[..., m:, :, :].flatten(-3)), -1)


def _block_diagonal(vals: torch.Tensor, index: torch.Tensor | None, dim: int) -> torch.Tensor:
    """(T, nnz) block-diagonal entries -> (T, dim, dim) (one body: the block itself)."""
    if index is None:
        return vals.unflatten(-1, (dim, dim))
    out = vals.new_zeros(*vals.shape[:-1], dim * dim)
    out.index_copy_(-1, index, vals)
    return out.unflatten(-1, (dim, dim))


class FusedStep:
    """One implicit step of a LieDFLNN: the residual, its Jacobian and a full Newton iteration on
    the increment x = (W, z), with the part fixed by (g_{k-1}, g_k) computed once: the kinetic
    d2 term, the forces at (g_{k-1}, xi~_{k-1}), the potential's covector at g_k and, for forces
    affine in xi~ (Rayleigh, configuration-dependent Rayleigh, PD control), their value at
    xi~ = 0 and their Jacobian at g_k. Other forces (`generic`) are evaluated per iteration."""

    def __init__(self, model, state: RolloutState, compiled_iterate=None):
        G, h = model.G, model.h
        self.G, self.h, self.maps, self.g = G, h, state.maps, state.g
        maps, P = state.maps, state.maps.P
        g_prev, g, inc = state.g_prev, state.g, state.inc
        self.generic: list[nn.Module] = []
        self.B: torch.Tensor | None = None
        cov = None
        if model.potential is not None:
            cov = self._potential_covector(model, g)
        if maps.linear is not None:
            W = inc.R.flatten(-3)
            if cov is not None and W.dim() == 2:
                const, cov = torch.addmm(cov, W, maps.linear[2]), None
            else:
                const = W @ maps.linear[2]
        else:
            xi_prev = kinetic.velocity_estimate(G, inc, h)
            const = kinetic_d2(G, inc, maps, h)
            B_aff = None if P.D is None else -P.D
            half = None if P.D is None else -(xi_prev @ P.D.T)
            for f in model.forces:
                if isinstance(f, RayleighForce):
                    continue
                Fp = f(g_prev, xi_prev)
                half = Fp if half is None else half + Fp
                if isinstance(f, AFFINE_FORCES):
                    zero = torch.zeros_like(xi_prev)
                    Bf = force_jacobian_xi(f, g, zero).detach()
                    half = half + f(g, zero)
                    B_aff = Bf if B_aff is None else B_aff + Bf
                else:
                    self.generic.append(f)
            if half is not None:
                const = const + 0.5 * h * half
            self.B = B_aff
        if cov is not None:
            const = const + cov
        self.const = const
        self.compiled_iterate = compiled_iterate if not self.generic else None
        self.forces_at = mlp_derivatives.ForcesAt(G, self.generic, g) if self.generic else None

    @classmethod
    def from_parts(cls, model, maps: RolloutMaps, g: Pose, const: torch.Tensor) -> FusedStep:
        """The step of a model without per-iteration forces or an affine force Jacobian (constant
        Rayleigh damping at most: `maps.linear`) from its fixed part `const` (T, dim) at g_k."""
        step = cls.__new__(cls)
        step.G, step.h, step.maps, step.g, step.const = model.G, model.h, maps, g, const
        step.generic, step.B, step.compiled_iterate, step.forces_at = [], None, None, None
        return step

    def _potential_covector(self, model, g: Pose) -> torch.Tensor:
        """The potential's covector at g_k (detached: the step's fixed part needs no graph)."""
        lys = self.maps.potential_layers
        if lys is None or g.R.dim() != 4:
            return potential_covector(model, g).detach()
        with torch.no_grad():
            return mlp_derivatives.rotation_potential_covector(lys, model.G, g.R, model.h)

    def f(self, x: Pose) -> torch.Tensor:
        """The residual at the increment x, (T, dim)."""
        r = step_residual(self.G, self.h, x, self.const, self.B, self.maps)
        if self.forces_at is not None:
            xi = kinetic.velocity_estimate(self.G, x, self.h)
            r = r + 0.5 * self.h * self.forces_at.value(xi, key=x.R)
        return r

    def jac(self, x: Pose) -> torch.Tensor:
        """d f(x exp(delta)) / d delta at 0, (T, dim, dim)."""
        extra = None
        if self.forces_at is not None:
            extra = self.forces_at.jacobian(kinetic.velocity_estimate(self.G, x, self.h), key=x.R)
        return step_jacobian(self.G, self.h, x, self.B, self.maps, extra)

    def retract(self, x: Pose, delta: torch.Tensor) -> Pose:
        return retract_increment(self.G, x, delta)

    def restrict(self, rows: torch.Tensor) -> NewtonProblem:
        """The Newton problem of the rows `rows` (for the last iterations of a few rows)."""
        sub = copy.copy(self)
        sub.const = self.const.index_select(0, rows)
        sub.g = Pose(self.g.R.index_select(0, rows), self.g.p.index_select(0, rows))
        if self.B is not None and self.B.dim() == 3:
            sub.B = self.B.index_select(0, rows)
        if self.forces_at is not None:
            sub.forces_at = self.forces_at.restrict(rows)
        return sub.problem(None)

    def problem(self, x0) -> NewtonProblem:
        return NewtonProblem(self.f, self.jac, x0, self.retract, iterate=self.iterate, restrict=self.restrict)

    def iterate(self, x: Pose, r: torch.Tensor):
        """One full Newton step from x: (delta, singular, candidate x', residual at x')."""
        if self.compiled_iterate is not None:
            return self.compiled_iterate(self.G, self.h, x, r, self.const, self.B, self.maps)
        if not self.generic:
            return step_iterate(self.G, self.h, x, r, self.const, self.B, self.maps)
        sol, singular = solve_small(self.jac(x), r)
        delta = -sol
        cand = self.retract(x, delta)
        return delta, singular, cand, self.f(cand)


def step_residual(G: ProductGroup, h: float, x: Pose, const, B, maps: RolloutMaps) -> torch.Tensor:
    """Residual at the increment x without per-iteration (generic) forces, (T, dim)."""
    if maps.linear is not None:
        W = x.R.flatten(-3)
        return torch.addmm(const, W, maps.linear[0]) if W.dim() == 2 else const + W @ maps.linear[0]
    r = const + kinetic_d1(G, x, maps, h)
    if B is not None:
        xi = kinetic.velocity_estimate(G, x, h)
        Bxi = xi @ B.transpose(-1, -2) if B.dim() == 2 else (B @ xi[..., None])[..., 0]
        r = r + 0.5 * h * Bxi
    return r


def step_jacobian(G: ProductGroup, h: float, x: Pose, B, maps: RolloutMaps, extra=None) -> torch.Tensor:
    """Jacobian of `step_residual` (+ `extra`, the generic forces' dF/dxi~), (T, dim, dim)."""
    dim = G.dim
    if maps.linear is not None:
        return (x.R.flatten(-3) @ maps.linear[1]).unflatten(-1, (dim, dim))
    J = _block_diagonal(kinetic_blocks(G, x, maps), maps.block_index, dim)
    dF = B if extra is None else (extra if B is None else B + extra)
    if dF is not None:
        dxi = _block_diagonal(velocity_jacobian_blocks(G, x, h), maps.block_index, dim)
        J = J + 0.5 * h * (dF @ dxi)
    return J


def step_iterate(G: ProductGroup, h: float, x: Pose, r: torch.Tensor, const, B, maps: RolloutMaps):
    """One full Newton step (no generic forces): (delta, singular, x', residual at x'). Pure
    tensor code: what `runtime.compile` compiles."""
    sol, singular = solve_small(step_jacobian(G, h, x, B, maps), r)
    delta = -sol
    cand = retract_increment(G, x, delta)
    return delta, singular, cand, step_residual(G, h, cand, const, B, maps)


def rollout_problem(model, state: RolloutState) -> NewtonProblem:
    compiled = compile_cache.compiled(step_iterate, "rollout_step") if state.compile else None
    return FusedStep(model, state, compiled).problem(state.guess(model.G))


def rollout_advance(model, state: RolloutState, x: Pose) -> tuple[RolloutState, Pose]:
    """Newton-Schulz-cleaned increment, next pose, next state (`LieDFLNN.implicit_advance`)."""
    W = x.R.detach()
    three = _constants(W.dtype, W.device)["three_eye"]
    # W (3I - W^T W) / 2, the halving last (exact, so bit for bit the textbook order; the algebraically
    # equal 1.5 W - 0.5 W W^T W rounds differently and, in float32, drifts differently)
    W = (W @ (three - W.transpose(-1, -2) @ W)).mul_(0.5)
    inc = Pose(W, x.p.detach())
    g_next = compose(model.G, state.g, inc)
    if projects_poses(W.dtype):  # below float64 the composed poses drift off SO(3) too
        g_next = Pose(so3.orthonormalize(g_next.R), g_next.p)
    before = (*state.before, state.inc)[1 - HISTORY :]
    return RolloutState(state.g, g_next, inc, state.maps, state.compile, before), g_next
