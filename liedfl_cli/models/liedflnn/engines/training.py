"""Fused hot paths of LieDFLNN, part 2 (see `models.liedflnn.engines.core`): the training triplets stored as
precomputed increments (`IncrementSet`, `IncrementBatch`), the forced DEL residual of a batch, the
regularity log-determinants, and the SO(3)-only loss with a hand-written gradient
(`rotational_loss`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ....lie import Pose
from ....mechanics import kinetic
from ....mechanics.forces import RayleighForce, RayleighNonlinearForce, force_jacobian_xi
from ...base import TripletSet, oriented_logdet
from .maps import Derived, _apply_map, _map_contraction, _trainable, derive, potential_covector, training_maps


@dataclass
class IncrementBatch:
    """A batch of `IncrementSet`: the stored fields of the triplets `idx` and of the regularity
    pairs (`reg_W`, `reg_logdetW`), or None where the loss does not need them."""

    fields: dict[str, Any]
    reg_W: torch.Tensor | None
    reg_logdetW: torch.Tensor | None
    forces: list[nn.Module]  # trainable forces other than Rayleigh, evaluated per batch
    potential: bool  # the potential has trainable parameters: evaluated per batch


class IncrementSet(TripletSet):
    """Training triplets of a LieDFLNN stored as precomputed increments (see `engines/core.py`'s docstring).

    Fields (N triplets, B bodies, m SE(3) bodies, dim the tangent dimension):
      A (N, B, 9)             W_1 + W_2^T flattened (rotational kinetic residual)
      W1, u1, z2 (N, m, ...)  SE(3) bodies only: W_1, W_1^T z_1, z_2
      W2 (N, B, 9)            W_2 flattened (SE(3) residual terms and regularity pairs)
      s (N, dim)              xi~_1 + xi~_2 (constant Rayleigh damping)
      xi (2, N, dim)          velocity estimates of both time levels (configuration-dependent forces)
      levels (L, N, ...)      poses of both levels (L = 2) for those forces, or of the current
                              one (L = 1) where only the potential network reads them
      static (N, dim)         the residual terms without trainable parameters (known parts)
    """

    def __init__(self, model, data: Pose, steps: int):
        super().__init__(data, steps)
        G, h = model.G, model.h
        m = G.n_se3
        inc1 = G.increment(self.prev, self.cur)
        inc2 = G.increment(self.cur, self.nxt)
        xi1 = kinetic.velocity_estimate(G, inc1, h)
        xi2 = kinetic.velocity_estimate(G, inc2, h)
        f: dict[str, Any] = {"A": (inc1.R + inc2.R.transpose(-1, -2)).flatten(-2)}
        W2 = inc2.R.flatten(-2)
        if m:
            f["W1"] = inc1.R[:, :m]
            f["u1"] = (inc1.R[:, :m].transpose(-1, -2) @ inc1.p[..., None])[..., 0]
            f["z2"] = inc2.p
            f["W2"] = W2[:, :m]
        self.reg_W = W2
        self.reg_logdetW = torch.linalg.slogdet(inc2.R[:, :m]).logabsdet if m else None
        rayleigh = [x for x in model.forces if isinstance(x, RayleighForce)]
        others = [x for x in model.forces if not isinstance(x, RayleighForce)]
        if rayleigh:
            f["s"] = xi1 + xi2
        self.dynamic_forces = [x for x in others if _trainable(x)]
        self.potential_trainable = _trainable(model.potential)
        if self.dynamic_forces:  # both time levels, stacked: (2, N, ...)
            f["xi"] = torch.stack((xi1, xi2))
            f["levels"] = Pose(torch.stack((self.prev.R, self.cur.R)), torch.stack((self.prev.p, self.cur.p)))
        elif self.potential_trainable:  # the current level only: (1, N, ...)
            f["levels"] = Pose(self.cur.R[None], self.cur.p[None])
        static = torch.zeros_like(xi1)
        with torch.no_grad():
            for x in others:
                if not _trainable(x):
                    static = static + 0.5 * h * (x(self.prev, xi1) + x(self.cur, xi2))
            if model.potential is not None and not self.potential_trainable:
                static = static + potential_covector(model, self.cur)
        if any(not _trainable(x) for x in others) or (model.potential is not None and not self.potential_trainable):
            f["static"] = static
        self.static_jac: torch.Tensor | None = None  # dF/dxi~ of the frozen forces at (g_k, xi~_k), N x dim x dim
        frozen = [x for x in others if not _trainable(x)]
        if frozen:
            with torch.no_grad():
                self.static_jac = sum(force_jacobian_xi(x, self.cur, xi2) for x in frozen)  # type: ignore[assignment]
        self.fields = f
        del self.prev, self.cur, self.nxt  # everything needed is in `fields`

    def enable_jacobian(self) -> None:
        """Also give every batch what the step Jacobian at (g_k, W_k) needs (`models.liedflnn.losses`, loss
        newton): W2r, W_k of every body flattened (N, B, 9), and static_jac for frozen forces."""
        self.fields["W2r"] = self.reg_W
        if self.static_jac is not None:
            self.fields["static_jac"] = self.static_jac

    def batch(self, idx: torch.Tensor, generator: torch.Generator, reg_points: int) -> IncrementBatch:  # type: ignore[override]
        """Triplets `idx` plus `reg_points` random pairs from `generator` (the draws of `TripletSet`)."""
        reg_W = reg_ld = None
        idx = idx.to(self.reg_W.device)  # indices drawn on the training loop's CPU generator
        if reg_points > 0:
            reg_idx = torch.randint(0, self.n, (int(reg_points),), generator=generator).to(idx.device)
            reg_W = self.reg_W.index_select(0, reg_idx)
            reg_ld = self.reg_logdetW.index_select(0, reg_idx) if self.reg_logdetW is not None else None
        fields: dict[str, Any] = {}  # tensors, and the Pose of "levels"
        for k, v in self.fields.items():
            if k == "levels":
                fields[k] = Pose(v.R.index_select(1, idx), v.p.index_select(1, idx))
            else:
                fields[k] = v.index_select(1 if k == "xi" else 0, idx)
        return IncrementBatch(fields, reg_W, reg_ld, self.dynamic_forces, self.potential_trainable)


def training_residual(model, batch: IncrementBatch, P: Derived, kin_map: torch.Tensor) -> torch.Tensor:
    """The forced DEL residual of the batch's triplets (`LieDFLNN.residual`), shape (N, dim);
    kin_map = `kinetic_residual_map(P.Jd, h)`."""
    G, h = model.G, model.h
    m = G.n_se3
    f = batch.fields
    w = _apply_map(f["A"], kin_map)  # (N, B, 3)
    if m:
        rho = P.rho
        W1 = f["W1"]
        W2 = f["W2"].unflatten(-1, (3, 3))
        W2rho = (W2 @ rho[..., None])[..., 0]
        X2 = f["z2"] + W2rho - rho
        a2 = f["z2"] + W2rho
        WtX1 = f["u1"] + rho - (W1.transpose(-1, -2) @ rho[..., None])[..., 0]
        scale = (P.mass / h)[..., None]
        extra = scale * (torch.linalg.cross(X2, a2) + torch.linalg.cross(rho.expand_as(WtX1), WtX1))
        w = torch.cat((w[..., :m, :] + extra, w[..., m:, :]), -2)
        v = scale * (WtX1 - X2)
    else:
        v = w[..., :0, :]
    r = G.join(w, v)
    if P.D is not None:
        r = r - (0.5 * h) * (f["s"] @ P.D.T)
    if batch.forces:
        r = r + batch_forces(model, batch.forces, f)
    if "static" in f:
        r = r + f["static"]
    if batch.potential:
        levels = f["levels"]
        r = r + potential_covector(model, Pose(levels.R[-1], levels.p[-1]), create_graph=True)
    return r


def batch_forces(model, forces: list[nn.Module], f: dict) -> torch.Tensor:
    """(h/2)(F(g_prev, xi~_1) + F(g, xi~_2)) summed over `forces`, each evaluated once on both
    time levels stacked."""
    levels = f["levels"]
    both = Pose(levels.R.flatten(0, 1), levels.p.flatten(0, 1))
    xi = f["xi"].flatten(0, 1)
    n = f["xi"].shape[1]
    out = None
    for x in forces:
        F = force_value(x, both, xi)
        out = F if out is None else out + F
    assert out is not None
    return 0.5 * model.h * (out[:n] + out[n:])


def force_value(force: nn.Module, g: Pose, xi: torch.Tensor) -> torch.Tensor:
    """F(g, xi~); the coupled configuration-dependent Rayleigh force D(g) xi~ = L (L^T xi~) as two
    matrix-vector products instead of forming the dim x dim matrix L L^T per sample (the per-body
    one applies its blocks itself)."""
    if type(force) is RayleighNonlinearForce and getattr(force, "per_body", None) is None:
        L = force.L(g)
        return -(L @ (L.transpose(-1, -2) @ xi[..., None]))[..., 0]
    return force(g, xi)


def regularity_slogdet(
    model, batch: IncrementBatch, P: Derived, hess_map: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(log|det H_b|, sign det(-H_b)) of each body's mixed-Hessian block at the regularity pairs,
    both (P, B) (`LieDFLNN.regularity_slogdet`).

    SE(3) blocks [[H + s P W P, -s P W], [s W P, -s W]] (s = m/h) have the Schur complement H, so
    log|det| = log|det H| + 3 log s + log|det W| and det(-block) = -s^3 det W det H: with W a
    rotation, sign det(-H_b) = -sign det H for SE(3) and SO(3) bodies alike."""
    assert batch.reg_W is not None
    Hflat = _apply_map(batch.reg_W, hess_map)
    sl = torch.linalg.slogdet(Hflat.unflatten(-1, (3, 3)))
    logdet = sl.logabsdet
    m = model.G.n_se3
    if m:
        assert batch.reg_logdetW is not None
        se = logdet[..., :m] + 3.0 * torch.log(P.mass / model.h) + batch.reg_logdetW
        logdet = torch.cat((se, logdet[..., m:]), -1)
    return logdet, -sl.sign


def residual_and_logdet(model, batch: IncrementBatch, opts) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(residual (N, dim), regularity log|det| (P, B) or None) of a batch, with the derived
    parameters built once (`LieDFLNN.loss` turns them into the loss); blocks of the wrong
    orientation carry `base.oriented_logdet`'s value."""
    P = derive(model)
    kin_map, hess_map = training_maps(P.Jd, model.h)
    use_reg = batch.reg_W is not None and opts.w_reg > 0
    logdet = oriented_logdet(*regularity_slogdet(model, batch, P, hess_map), opts.epsilon) if use_reg else None
    return training_residual(model, batch, P, kin_map), logdet


def rotational_only(model, batch: IncrementBatch) -> bool:
    """Whether `rotational_loss` applies: SO(3) bodies only, and nothing trainable besides J_d and
    the constant Rayleigh D (frozen parts are in the batch's `static` field)."""
    return not model.G.n_se3 and not batch.forces and not batch.potential


def rotational_loss(model, batch: IncrementBatch, opts) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of an SO(3)-only model whose trainable parts are J_d and D, with its gradient
    with respect to (J_d, D) written by hand (`_RotationalLoss`): the batch-sized part of the
    graph is a handful of kernels each way; autograd only sees J_d's and D's parameterisations."""
    P = derive(model)
    reg = batch.reg_W if batch.reg_W is not None and opts.w_reg > 0 else None
    static = batch.fields.get("static")
    s = batch.fields.get("s")
    C = _map_contraction(P.Jd.dtype, float(model.h), P.Jd.device)
    settings = (float(model.h), float(opts.w_del), float(opts.w_reg), float(opts.epsilon), str(opts.reg_form))
    A = batch.fields["A"]
    loss, del_loss, reg_loss = _RotationalLoss.apply(P.Jd.flatten(-2), P.D, A, s, static, reg, C, settings)
    return loss, {"del_loss": del_loss, "reg_loss": reg_loss}


def _penalty_and_slope(logdet: torch.Tensor, epsilon: float, form: str) -> tuple[torch.Tensor, torch.Tensor]:
    """`del_loss.regularity_penalty` and its derivative with respect to logdet."""
    if form == "relu":
        gap = epsilon - logdet
        return torch.relu(gap), -(gap > 0).to(logdet.dtype)
    if form == "gaussian":
        x = logdet - epsilon
        u = torch.exp(torch.clamp(x, max=50.0))
        pen = torch.exp(-0.5 * (u - 1.0) ** 2) / math.sqrt(2 * math.pi)
        return pen, -pen * (u - 1.0) * u * (x <= 50.0).to(logdet.dtype)
    raise ValueError(f"train.reg_form must be 'relu' or 'gaussian', got {form!r}")


def _oriented_penalty_and_slope(sl, epsilon: float, form: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The penalty of `base.oriented_logdet` of SO(3) blocks (sign det(-H) = -sign det H) from
    their `slogdet` and its derivative with respect to log|det H| (unchanged where det(-H) > 0)."""
    if form == "relu":
        return _oriented_relu(sl, epsilon)
    right = sl.sign < 0
    pen, slope = _penalty_and_slope(oriented_logdet(sl.logabsdet, -sl.sign, epsilon), epsilon, form)
    return pen, torch.where(right, slope, -torch.sign(sl.logabsdet - epsilon) * slope)


def _oriented_relu(sl, epsilon: float) -> tuple[torch.Tensor, torch.Tensor]:
    """`_oriented_penalty_and_slope` of the relu form for the few (P, B) regularity blocks in
    Python floats: the same IEEE operations as the tensor formulas (subtractions, comparisons, abs,
    signs of zero included), so the same bits, in 4 kernel calls instead of about 15."""
    pens, slopes = [], []
    for signs, lads in zip(sl.sign.tolist(), sl.logabsdet.tolist()):
        pen_row, slope_row = [], []
        for sign, lad in zip(signs, lads):
            right = sign < 0  # det(-H) > 0: the normal orientation
            x = lad if -sign > 0 else epsilon - 1.0 - abs(lad - epsilon)  # base.oriented_logdet
            gap = epsilon - x
            slope = -float(gap > 0)
            if not right:
                t = lad - epsilon
                slope = -float((t > 0) - (t < 0)) * slope  # -sign(t) * slope
            pen_row.append(max(gap, 0.0))  # relu; NaN stays NaN
            slope_row.append(slope)
        pens.append(pen_row)
        slopes.append(slope_row)
    opts = {"dtype": sl.logabsdet.dtype, "device": sl.logabsdet.device}
    return torch.tensor(pens, **opts), torch.tensor(slopes, **opts)


def rotational_forward(Jd_flat, D, A, s, static, reg_W, C, settings) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """(del_loss, reg_loss, saved) of `_RotationalLoss` (see there); `saved` is what
    `rotational_backward` needs."""
    h, w_del, w_reg, epsilon, form = settings
    B = Jd_flat.shape[0]
    maps = Jd_flat @ C
    kin = maps[:, :27].unflatten(-1, (9, 3))
    r = _apply_map(A, kin).flatten(-2)
    if D is not None:
        r = r - (0.5 * h) * (s @ D.T)
    if static is not None:
        r = r + static
    del_loss = (r * r).mean()
    H = slope = None
    if reg_W is not None:
        H = _apply_map(reg_W, maps[:, 27:].unflatten(-1, (9, 9))).unflatten(-1, (3, 3))
        pen, slope = _oriented_penalty_and_slope(torch.linalg.slogdet(H), epsilon, form)
        reg_loss = pen.mean()
    else:
        reg_loss = torch.zeros((), dtype=r.dtype, device=r.device)
    return del_loss, reg_loss, (r, A, s, reg_W, H, slope, C, (h, B, D is not None))


def rotational_backward(saved: tuple, g_del, g_reg) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(dJd_flat (B, 9), dD (dim, dim) or None) of `_RotationalLoss` for the gradients g_del and
    g_reg of del_loss and reg_loss (tensors or floats: the same values)."""
    r, A, s, reg_W, H, slope, C, (h, B, has_D) = saved
    dr = (2.0 * g_del / r.numel()) * r
    C_kin_T, C_hess_T = _transposed_parts(C)
    dkin = A.permute(1, 2, 0) @ dr.unflatten(-1, (B, 3)).transpose(0, 1)  # (B, 9, N) @ (B, N, 3)
    dJd = dkin.flatten(-2) @ C_kin_T
    dD = -(0.5 * h) * (dr.T @ s) if has_D else None
    if reg_W is not None:
        dlogdet = (g_reg / slope.numel()) * slope  # (P, B)
        dH = dlogdet[..., None, None] * torch.linalg.inv(H).transpose(-1, -2)
        dhess = reg_W.permute(1, 2, 0) @ dH.flatten(-2).transpose(0, 1)  # (B, 9, P) @ (B, P, 9)
        dJd = dJd + dhess.flatten(-2) @ C_hess_T
    return dJd, dD


_TRANSPOSED: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}


def _transposed_parts(C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(C[:, :27].T, C[:, 27:].T): the same views each step, made once per contraction (the
    contractions are cached for good, `fused_maps._map_contraction`; C itself is kept alongside so
    that its id is never reused)."""
    hit = _TRANSPOSED.get(id(C))
    if hit is None or hit[0] is not C:
        hit = _TRANSPOSED[id(C)] = (C, C[:, :27].T, C[:, 27:].T)
    return hit[1], hit[2]


class _RotationalLoss(torch.autograd.Function):
    """(loss, del_loss, reg_loss) of `rotational_loss` from J_d.flatten() (B, 9) and D (dim, dim):

        r = A @ kinetic_residual_map(J_d) - (h/2) s D^T + static,    del_loss = mean r^2
        H = W_2 @ hessian_map(J_d),                                   reg_loss = mean penalty(log|det H|)

    Both maps are J_d.flatten() @ C (`_map_contraction`), so the gradient is
    dJ_d = (A^T dr) C_r^T + (W_2^T dH) C_H^T with dH = dlogdet H^-T, and dD = -(h/2) dr^T s.
    (`rotational_forward` / `rotational_backward`; `models.liedflnn.engines.gradient` calls them without autograd.)"""

    @staticmethod
    def forward(ctx, Jd_flat, D, A, s, static, reg_W, C, settings):
        _, w_del, w_reg, _, _ = settings
        del_loss, reg_loss, saved = rotational_forward(Jd_flat, D, A, s, static, reg_W, C, settings)
        ctx.save_for_backward(*saved[:7])
        ctx.settings = (saved[7], w_del, w_reg)
        return w_del * del_loss + w_reg * reg_loss, del_loss, reg_loss

    @staticmethod
    def backward(ctx, g_loss, g_del, g_reg):
        fixed, w_del, w_reg = ctx.settings
        g_del = g_loss * w_del + (g_del if g_del is not None else 0.0)
        g_reg = g_loss * w_reg + (g_reg if g_reg is not None else 0.0)
        dJd, dD = rotational_backward((*ctx.saved_tensors, fixed), g_del, g_reg)
        return dJd, dD, None, None, None, None, None, None


def increments_loss(model, batch: IncrementBatch, opts) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """`LieDFLNN.loss` of an `IncrementBatch`: the fused residual and regularity (what `runtime.compile`
    compiles for training); SO(3)-only models whose trainable parts are J_d and D take the hand-written
    gradient of `rotational_loss`. Equal to the model's own `triplet_loss` to rounding (tests/test_fused.py)."""
    from ...del_loss import del_regularity_loss

    if rotational_only(model, batch) and not torch.compiler.is_compiling():
        return rotational_loss(model, batch, opts)
    return del_regularity_loss(*residual_and_logdet(model, batch, opts), opts)
