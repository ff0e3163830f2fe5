"""Training losses that measure prediction (`train.loss`): del | newton | rollout.

del      w_DEL mean ||r||^2 + w_reg mean penalty(log|det H_b|), the paper's loss (`del_loss.del_regularity_loss`).
newton   w_DEL mean ||H^-1 r||^2 + the same regularity term. H = d r(g_k, g_k W exp(delta)) / d delta at 0
         (`jacobian_var`: kinetic mixed Hessian + force terms) at the data's W_k, so -H^-1 r is the Newton
         step from the observed g_{k+1} towards the model's prediction: to first order the one-step
         prediction error in the tangent space (rad / step for rotations; docs/math.md). H^-1 r does not
         change when L_d and F are scaled by a common factor (r and H scale alike), so the loss cannot be
         lowered by shrinking L_d; the regularity term keeps its absolute weight and only fixes the scale.
rollout  first `del` for train.epochs, then a fine-tuning stage (`liedfl_cli.commands.finetune`) on the k-step
         rollout error of windows of k+2 true poses started from their first two, the gradient taken
         through the converged Newton solves by the implicit function theorem (`rollout_window_loss`).

Singular or huge H^-1 r: rows whose solve fails (LU pivot zero, non-finite result) are left out of the
mean (counted in the part `singular`, a fraction) and steps longer than NEWTON_CLIP are scaled down to it
(counted in `clipped`): a prediction 1 rad off after one step is a failed prediction whatever its size.

The reference path works for any `ImplicitModel` that exposes `residual(g_prev, g, g_next)` and
`jacobian_var(g, inc)` on a `ProductGroup` `G` (LieDFLNN and its subclasses); the fused path serves
LieDFLNN's `fused.IncrementBatch` and uses per-body blocks of H when the forces act body by body.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch.func import jacrev

from ...errors import ConfigError
from ...lie import Pose, ProductGroup
from ...mechanics import kinetic
from ...mechanics.damping import PerBodySPSD
from ...mechanics.forces import RayleighForce, RayleighNonlinearForce
from ...solvers.newton import solve
from ...solvers.options import SolverOptions
from ..base import ImplicitModel, LossOptions, LossParts, TrajectoryBatch, TripletBatch, oriented_logdet
from .engines import core as fused

LOSSES = ("del", "newton", "rollout")


NEWTON_CLIP = 1.0
"""Largest Newton step |H^-1 r| (tangent norm) the newton loss and the rollout loss's IFT step take."""


# ---------------------------------------------------------------------------- support
def supports_prediction_losses(model: Any) -> bool:
    """Whether `model` offers what newton / rollout need: an ImplicitModel on a ProductGroup with
    `residual(g_prev, g, g_next)` and `jacobian_var(g, inc)`."""
    return (
        isinstance(model, ImplicitModel)
        and isinstance(getattr(model, "G", None), ProductGroup)
        and callable(getattr(model, "residual", None))
        and callable(getattr(model, "jacobian_var", None))
    )


def check_loss(model: Any, loss: str) -> None:
    """One-line ConfigError for an unknown loss or one the model cannot train with."""
    if loss not in LOSSES:
        raise ConfigError(f"train.loss={loss!r}: choose one of {', '.join(LOSSES)}")
    if loss != "del" and not supports_prediction_losses(model):
        name = getattr(model, "name", "") or type(model).__name__
        raise ConfigError(f"train.loss={loss} is not available for {name}")


def training_stage(model: Any, data: Pose, steps: int, opts: LossOptions) -> tuple[LossOptions, Any]:
    """(the options, the samples) of `train.fit`'s stage: `rollout` trains with `del` first (its
    fine-tuning stage is `liedfl_cli.commands.finetune`); `newton` asks a fused set for the Jacobian's fields."""
    check_loss(model, opts.loss)
    if opts.loss == "rollout":
        opts = dataclasses.replace(opts, loss="del")
    samples = model.training_set(data, steps)
    if opts.loss == "newton" and callable(getattr(samples, "enable_jacobian", None)):
        samples.enable_jacobian()  # fused.IncrementSet, articulated.ArticulatedTriplets
    return opts, samples


# ---------------------------------------------------------------------------- the guarded solve
def newton_step(J: torch.Tensor, r: torch.Tensor, clip: float = NEWTON_CLIP):
    """(H^-1 r (..., n), singular (...,) bool, clipped (...,) bool) for J (..., n, n), r (..., n).

    Singular rows (solve fails, or a non-finite result) give 0 and are flagged; they are solved again
    with J = I so that no NaN reaches the gradient. Results longer than `clip` are scaled to `clip`
    (x clip/|x|, a smooth map; rows within it are returned bit for bit)."""
    sol, info = torch.linalg.solve_ex(J, r.unsqueeze(-1))
    x = sol[..., 0]
    bad = (info > 0) | ~torch.isfinite(x).all(-1)
    if bool(bad.any()):
        eye = torch.eye(J.shape[-1], dtype=J.dtype, device=J.device)
        Js = torch.where(bad[..., None, None], eye, J)
        rs = torch.where(bad[..., None], torch.zeros_like(r), r)
        x = torch.linalg.solve(Js, rs.unsqueeze(-1))[..., 0]
    norm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    clipped = norm[..., 0] > clip
    x = x * (clip / norm.clamp(min=clip))
    return x, bad, clipped


def newton_regularity_loss(x, singular, clipped, logdet, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
    """w_DEL mean ||x||^2 (rows not singular) + w_reg mean penalty(logdet) -> (loss, parts)."""
    keep = (~singular).to(x.dtype)
    newton_loss = ((x * x).sum(-1) * keep).sum() / keep.sum().clamp(min=1.0)
    reg_loss = torch.zeros((), dtype=x.dtype, device=x.device)
    if logdet is not None:
        reg_loss = _penalty(logdet, opts)
    parts = {
        "newton_loss": newton_loss,
        "reg_loss": reg_loss,
        "singular": singular.to(x.dtype).mean(),
        "clipped": clipped.to(x.dtype).mean(),
    }
    return opts.w_del * newton_loss + opts.w_reg * reg_loss, parts


# ---------------------------------------------------------------------------- reference path
def autodiff_jacobian_var(model: Any, g: Pose, inc: Pose) -> torch.Tensor:
    """d residual_var(g, g inc exp(delta)) / d delta at 0 by torch.func (differentiable in the
    parameters): the Jacobian of models whose own `jacobian_var` is detached (LieDFLNN's generic mode)."""
    G = model.G

    def one(gR, gp, iR, ip):
        g1, i1 = Pose(gR[None], gp[None]), Pose(iR[None], ip[None])
        f = lambda d: model.residual_var(g1, G.compose(g1, G.retract(i1, d[None])))[0]
        return jacrev(f)(iR.new_zeros(G.dim))

    return torch.vmap(one)(g.R, g.p, inc.R, inc.p)


def step_jacobian(model: Any, g: Pose, inc: Pose) -> torch.Tensor:
    """The model's `jacobian_var(g, inc)`, or its torch.func version where that one is detached from
    the parameters (LieDFLNN's generic mode; forces without a closed-form dF/dxi~)."""
    no_closed_form = any(getattr(f, "jacobian_xi", None) is None for f in getattr(model, "forces", ()))
    if getattr(model, "residual_mode", "fast") == "generic" or no_closed_form:
        J = autodiff_jacobian_var(model, g, inc)
        # a model on reduced coordinates (an articulated tree's joints) maps the full Jacobian
        return model.reduce_jacobian(g, inc, J) if getattr(model, "reduced", False) else J
    return model.jacobian_var(g, inc)


def newton_residual(model: Any, g_prev: Pose, g: Pose, g_next: Pose):
    """(H^-1 r, singular, clipped) of triplets on the reference path (`newton_step`)."""
    r = model.residual(g_prev, g, g_next)
    J = step_jacobian(model, g, model.G.increment(g, g_next))
    return newton_step(J, r)


def _reference_logdet(model: Any, batch: TripletBatch, opts: LossOptions):
    if batch.reg is None or opts.w_reg <= 0 or not hasattr(model, "regularity_slogdet"):
        return None
    logabsdet, sign = model.regularity_slogdet(*batch.reg)
    return oriented_logdet(logabsdet, sign, opts.epsilon)


# ---------------------------------------------------------------------------- fused path
def forces_per_body(model: Any) -> bool:
    """Whether every force acts body by body (dF/dxi~ block diagonal), so that H is block diagonal."""
    if model.G.n_bodies == 1:
        return True
    for f in model.forces:
        if isinstance(f, RayleighForce) and isinstance(f.D, PerBodySPSD):
            continue
        if isinstance(f, RayleighNonlinearForce) and getattr(f, "per_body", None) is not None:
            continue
        return False
    return True


def _force_jacobian_graph(force, g: Pose, xi: torch.Tensor) -> torch.Tensor:
    """dF/dxi~ with its graph to the force's parameters (closed form where the force has one)."""
    closed = getattr(force, "jacobian_xi", None)
    if closed is not None:
        return closed(g, xi)
    x = xi.detach().requires_grad_(True)
    with torch.enable_grad():
        F = force(g, x)
        rows = [torch.autograd.grad(F[..., i].sum(), x, create_graph=True)[0] for i in range(F.shape[-1])]
    return torch.stack(rows, -2)


def _so3_diagonal_blocks(M: torch.Tensor, start: int, n: int) -> torch.Tensor:
    """The n diagonal 3x3 blocks of M[..., start:, start:] (..., dim, dim) -> (..., n, 3, 3)."""
    sub = M[..., start:, start:].unflatten(-1, (n, 3)).unflatten(-3, (n, 3))  # (..., n, 3, n, 3)
    return torch.diagonal(sub, dim1=-4, dim2=-2).permute(*range(sub.dim() - 4), -1, -3, -2)


def fused_newton_residual(model: Any, batch: fused.IncrementBatch, P: fused.Derived, r: torch.Tensor, hess_map):
    """(H^-1 r, singular, clipped) of an IncrementBatch (fields from `IncrementSet.enable_jacobian`):
    per-body blocks when the forces act body by body, one dim x dim solve per triplet otherwise."""
    G, h = model.G, model.h
    m, n, dim = G.n_se3, G.n_so3, G.dim
    f = batch.fields
    if "W2r" not in f:
        raise ValueError("train.loss=newton: the training set was built without the Jacobian's fields")
    W2f = f["W2r"]
    N = W2f.shape[0]
    W2 = W2f.unflatten(-1, (3, 3))
    inc = Pose(W2, f["z2"] if m else W2.new_zeros(N, 0, 3))
    dF: torch.Tensor | None = None if P.D is None else -P.D
    if batch.forces:
        levels = f["levels"]
        g = Pose(levels.R[-1], levels.p[-1])
        xi = f["xi"][-1]
        for force in batch.forces:
            Jx = _force_jacobian_graph(force, g, xi)
            dF = Jx if dF is None else dF + Jx
    if "static_jac" in f:
        dF = f["static_jac"] if dF is None else dF + f["static_jac"]
    se3 = (
        kinetic.mixed_hessian_blocks(ProductGroup(m, 0), Pose(W2[:, :m], inc.p), P.Jd[:m], P.mass, P.rho, h)
        if m
        else []
    )
    rot = fused._apply_map(W2f[:, m:], hess_map[m:]).unflatten(-1, (3, 3)) if n else None  # (N, n, 3, 3)
    if not forces_per_body(model):
        J = r.new_zeros(N, dim, dim)
        for i, s in enumerate(G.body_slices()):
            J[:, s, s] = se3[i] if i < m else rot[:, i - m]  # type: ignore[index]
        if dF is not None:
            J = J + 0.5 * h * (dF @ kinetic.velocity_estimate_jacobian(G, inc, h))
        return newton_step(J, r)
    # block diagonal: the SE(3) bodies one by one, the SO(3) bodies in one batched solve
    xs, bads, clips = [], [], []
    dxi = kinetic.velocity_estimate_jacobian(ProductGroup(m, 0), Pose(W2[:, :m], inc.p), h) if m else None
    for i in range(m):
        s = slice(6 * i, 6 * i + 6)
        Jb = se3[i]
        if dF is not None:
            Jb = Jb + 0.5 * h * (dF[..., s, s] @ dxi[:, s, s])  # type: ignore[index]
        x, bad, cl = newton_step(Jb, r[:, s])
        xs.append(x)
        bads.append(bad)
        clips.append(cl)
    if n:
        assert rot is not None
        Jr = rot
        if dF is not None:
            W = W2[:, m:]
            eye = torch.eye(3, dtype=W.dtype, device=W.device)
            trW = W.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
            dw = (trW * eye - W.transpose(-1, -2)) / (2 * h)  # (N, n, 3, 3): d w~ / d delta_w
            Jr = Jr + 0.5 * h * (_so3_diagonal_blocks(dF, 6 * m, n) @ dw)
        x, bad, cl = newton_step(Jr, r[:, 6 * m :].unflatten(-1, (n, 3)))
        xs.append(x.flatten(-2))
        bads.append(bad.any(-1))
        clips.append(cl.any(-1))
    x = torch.cat(xs, -1)
    return x, torch.stack(bads, -1).any(-1), torch.stack(clips, -1).any(-1)


# ---------------------------------------------------------------------------- the newton loss
def newton_loss(model: Any, batch: Any, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
    """`train.loss=newton` of a batch: w_DEL mean ||H^-1 r||^2 + w_reg mean penalty (see the module)."""
    if isinstance(batch, fused.IncrementBatch):
        P = fused.derive(model)
        kin_map, hess_map = fused.training_maps(P.Jd, model.h)
        r = fused.training_residual(model, batch, P, kin_map)
        logdet = None
        if batch.reg_W is not None and opts.w_reg > 0:
            logabsdet, sign = fused.regularity_slogdet(model, batch, P, hess_map)
            logdet = oriented_logdet(logabsdet, sign, opts.epsilon)
        x, singular, clipped = fused_newton_residual(model, batch, P, r, hess_map)
        return newton_regularity_loss(x, singular, clipped, logdet, opts)
    assert isinstance(batch, TripletBatch), "train.loss=newton trains on triplets"
    x, singular, clipped = newton_residual(model, *batch.poses())
    return newton_regularity_loss(x, singular, clipped, _reference_logdet(model, batch, opts), opts)


# ---------------------------------------------------------------------------- the rollout loss
def check_rollout_horizon(horizon: int, steps: int) -> None:
    """One-line ConfigError unless windows of `horizon` + 2 poses fit in the first `steps` steps
    (`steps` + 1 poses) of a trajectory (`train.loss=rollout`; checked before training starts)."""
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1 or int(steps) + 1 < horizon + 2:
        raise ConfigError(
            f"train.rollout_loss.horizon={horizon}: needs windows of horizon + 2 poses within the "
            f"{int(steps) + 1} training poses of a trajectory (dataset.train_steps={int(steps)})"
        )


class WindowSet:
    """Windows of k + 2 consecutive true poses within the first `steps` steps of each trajectory
    (T, N+1, ...): R (W, k+2, B, 3, 3), p (W, k+2, m, 3), every start 0 .. steps - k - 1."""

    def __init__(self, data: Pose, steps: int, horizon: int):
        steps = min(int(steps), data.R.shape[1] - 1)
        check_rollout_horizon(horizon, steps)
        L = int(horizon) + 2
        starts = range(0, steps + 2 - L)
        R = torch.cat([data.R[:, s : s + L] for s in starts])
        p = torch.cat([data.p[:, s : s + L] for s in starts])
        self.traj = Pose(R, p)
        self.n = R.shape[0]

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> TrajectoryBatch:
        return TrajectoryBatch(self.traj.index(idx.to(self.traj.R.device)))


def _at(traj: Pose, j: int) -> Pose:
    return Pose(traj.R[:, j], traj.p[:, j])


def rollout_window_loss(
    model: Any, batch: TrajectoryBatch, opts: LossOptions, solver: SolverOptions | None = None
) -> tuple[torch.Tensor, LossParts]:
    """Mean squared k-step rollout error of windows (N, k+2, ...) started from their first two poses:
    per step, sum over bodies of |log(R_true^T R_pred)|^2 (rad^2) + |p_pred - p_true|^2, averaged over
    the steps whose solves (and every earlier one of the window) converged; + w_reg mean penalty on the
    windows' true pairs.

    Each step is solved without grad (the model's own Newton problem, warm-started as in a rollout),
    then ONE Newton step is taken with grad from the converged x*: x = x* exp(-J(x*)^-1 f(x*)), J
    detached and f built with its graph to the parameters and to the predicted poses it starts from.
    Its value is x* (to the solver's tolerance) and its derivative -J^-1 df/dtheta, the implicit
    function theorem's, so gradients flow through the whole k-step chain exactly at convergence."""
    traj = batch.traj
    G = model.G
    k = traj.R.shape[1] - 2
    solver = solver or SolverOptions()
    reference = model.path != "fused"  # fixed when the model was built
    g_prev, g = _at(traj, 0), _at(traj, 1)
    alive = torch.ones(traj.R.shape[0], dtype=torch.bool, device=traj.R.device)
    sq_sum = traj.R.new_zeros(())
    rot_sum, pos_sum, count = 0.0, 0.0, traj.R.new_zeros(())
    failed = 0
    for j in range(k):
        with torch.no_grad():
            gp_d, g_d = Pose(g_prev.R.detach(), g_prev.p.detach()), Pose(g.R.detach(), g.p.detach())
            sol = solve(model.implicit_problem(model.implicit_start(gp_d, g_d)), solver, reference=reference)
        x_star = Pose(sol.x.R.detach(), sol.x.p.detach())
        with torch.enable_grad():
            f = model.residual(g_prev, g, G.compose(g, x_star))
        J = model.jacobian_var(g_d, x_star).detach()
        step, bad, _ = newton_step(J, f)
        ok = sol.converged & ~bad
        failed += int((alive & ~ok).sum())
        alive = alive & ok
        # the model's own Newton update (along the joints of a reduced articulated tree)
        retract = getattr(model, "step_retract", None)
        g_next = G.compose(g, retract(g, x_star, -step) if retract is not None else G.retract(x_star, -step))
        truth = _at(traj, j + 2)
        rot = _rot_sq(truth, g_next)
        pos = ((g_next.p - truth.p) ** 2).sum((-1, -2))
        w = alive.to(f.dtype)
        sq_sum = sq_sum + ((rot + pos) * w).sum()
        rot_sum = rot_sum + (rot.detach() * w).sum()
        pos_sum = pos_sum + (pos.detach() * w).sum()
        count = count + w.sum()
        g_prev, g = g, g_next
    denom = count.clamp(min=1.0)
    rollout = sq_sum / denom
    reg_loss = torch.zeros((), dtype=traj.R.dtype, device=traj.R.device)
    if opts.w_reg > 0 and hasattr(model, "regularity_slogdet"):
        a, b = traj.index((slice(None), slice(0, -1))), traj.index((slice(None), slice(1, None)))
        flat = lambda q: Pose(q.R.flatten(0, 1), q.p.flatten(0, 1))
        logabsdet, sign = model.regularity_slogdet(flat(a), flat(b))
        logdet = oriented_logdet(logabsdet, sign, opts.epsilon)
        reg_loss = _penalty(logdet, opts)
    parts = {
        "rollout_loss": rollout,
        "reg_loss": reg_loss,
        "rollout_rot_rms": torch.sqrt(rot_sum / denom),
        "rollout_pos_rms": torch.sqrt(pos_sum / denom),
        "not_converged": torch.tensor(float(failed), dtype=traj.R.dtype, device=traj.R.device),
    }
    return rollout + opts.w_reg * reg_loss, parts


def _penalty(logdet: torch.Tensor, opts: LossOptions) -> torch.Tensor:
    """mean `del_loss.regularity_penalty` (the same formulas, `fused._penalty_and_slope`)."""
    return fused._penalty_and_slope(logdet, opts.epsilon, opts.reg_form)[0].mean()


def _rot_sq(truth: Pose, pred: Pose) -> torch.Tensor:
    """Sum over bodies of the squared geodesic distance |log(R_true^T R_pred)|^2, shape (N,)."""
    from ...lie import so3

    w = so3.log(truth.R.transpose(-1, -2) @ pred.R)
    return (w * w).sum((-1, -2))
