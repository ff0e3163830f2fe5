"""The loss and parameter gradient of one training batch of an SO(3)-only LieDFLNN without autograd
(`RotationalGradient`), for `train.fit`'s fused optimiser step.

`fused_training.rotational_loss` already has a hand-written gradient, and J_d and D have theirs
(`fused_maps._InertiaJdScalar` / `_InertiaJd`, `_SPSDScalar`); what autograd adds around them (the
graph, its engine, zeroing and accumulating `.grad`) is about a third of a default-run step. Here
the same functions' forward and backward run directly in order, under no_grad: the same kernels
on the same values, so loss and gradients are the autograd path's bit for bit
(tests/test_fused_step.py)."""

from __future__ import annotations

import math

import torch
from torch import nn

from ....mechanics.forces import RayleighForce
from ....mechanics.parameterizations import Inertia, SPSDMatrix
from .maps import (
    SCALAR_BODIES,
    SCALAR_DIM,
    _InertiaJd,
    _InertiaJdScalar,
    _map_contraction,
    _SPSDScalar,
    inertia_jd_grad_lists,
    inertia_jd_lists,
    spsd_grad_lists,
    spsd_lists,
)
from .training import IncrementBatch, IncrementSet, rotational_backward, rotational_forward


class _Ctx:
    """Stands in for autograd's ctx when a `torch.autograd.Function`'s forward and backward are
    called directly."""

    saved_tensors: tuple

    def save_for_backward(self, *tensors) -> None:
        self.saved_tensors = tensors


class RotationalGradient:
    """(loss, {"del_loss", "reg_loss"}, gradients) of a batch for the model's trainable parameters
    `params` (in that order), as `LieDFLNN.loss` + `backward()` give them. Build with `make`."""

    def __init__(self, model, params: list[nn.Parameter], dampers: list[SPSDMatrix]):
        self.model, self.params, self.dampers = model, params, dampers
        inertia = model.inertia
        scalar = inertia.r.shape[0] <= SCALAR_BODIES and inertia.r.device.type == "cpu"
        self.jd_fn = _InertiaJdScalar if scalar else _InertiaJd
        ref = inertia.r
        self.C = _map_contraction(ref.dtype, float(model.h), ref.device)
        self.h = float(model.h)
        # where each computed gradient goes: params index of r, abc, and of each damper's (L, lambda)
        where = {id(p): i for i, p in enumerate(params)}
        self.slot_jd = (where.get(id(inertia.r)), where.get(id(inertia.abc)))
        self.slot_d = [(where.get(id(d.L_entries)), where.get(id(d.lam))) for d in dampers]

    @staticmethod
    def make(model, samples, opts, params: list[nn.Parameter]) -> RotationalGradient | None:
        """The fused gradient of `model` on `samples`, or None where it does not apply: the fused
        paths off or compiled, another loss, SE(3) bodies, a trainable potential or force other than
        a constant Rayleigh one with a small `SPSDMatrix`, or trainable parameters it does not cover."""
        # the caller (`LieDFLNN.value_and_grad`) has checked the model is a plain LieDFLNN
        if not isinstance(samples, IncrementSet) or not model._fused():
            return None
        if opts.loss != "del" or model.plan.wants_compile("train") or model.G.n_se3:
            return None
        if samples.dynamic_forces or samples.potential_trainable or not isinstance(model.inertia, Inertia):
            return None
        dampers = []
        for f in model.forces:
            if isinstance(f, RayleighForce):
                D = f.D
                if type(D) is not SPSDMatrix or D.dim > SCALAR_DIM or D.lam.device.type != "cpu":
                    return None
                dampers.append(D)
        covered = {id(model.inertia.r), id(model.inertia.abc)}
        covered |= {id(p) for D in dampers for p in (D.L_entries, D.lam)}
        if any(id(p) not in covered for p in params):
            return None
        return RotationalGradient(model, params, dampers)

    @torch.no_grad()
    def __call__(self, batch: IncrementBatch, opts) -> tuple[float, dict[str, float], list | None]:
        """(loss, {"del_loss", "reg_loss"} as floats, gradients per parameter); gradients None where
        the loss is not finite (the caller reports it; the backward of such a loss may raise)."""
        if self.jd_fn is _InertiaJdScalar:
            return self._scalar_call(batch, opts)
        inertia = self.model.inertia
        c_jd = _Ctx()
        Jd = self.jd_fn.forward(c_jd, inertia.r, inertia.abc)
        D = None
        c_d = []
        for damper in self.dampers:
            c = _Ctx()
            Df = _SPSDScalar.forward(c, damper.L_entries, damper.lam, damper.dim)
            c_d.append(c)
            D = Df if D is None else D + Df
        reg = batch.reg_W if batch.reg_W is not None and opts.w_reg > 0 else None
        loss, parts, backward = _rotational_loss(Jd, D, batch.fields, reg, self.C, self.h, opts)
        if not math.isfinite(loss):
            return loss, parts, None
        dJd, dD = backward()
        grads: list[torch.Tensor | None] = [None] * len(self.params)
        i_r, i_abc = self.slot_jd
        if i_r is not None or i_abc is not None:
            dr, dabc = self.jd_fn.backward(c_jd, dJd.view(Jd.shape))
            if i_r is not None:
                grads[i_r] = dr
            if i_abc is not None:
                grads[i_abc] = dabc
        for c, (i_l, i_lam) in zip(c_d, self.slot_d):
            if i_l is None and i_lam is None:
                continue
            d_entries, d_lam, _ = _SPSDScalar.backward(c, dD)
            if i_l is not None:
                grads[i_l] = d_entries
            if i_lam is not None:
                grads[i_lam] = d_lam
        return loss, parts, grads

    def _scalar_call(self, batch: IncrementBatch, opts) -> tuple[float, dict[str, float], list | None]:
        """`__call__` for few bodies: J_d and D built in Python floats (`fused_maps.inertia_jd_lists`,
        `spsd_lists`, the arithmetic of `_InertiaJdScalar` / `_SPSDScalar`) and made tensors in one
        call, and every gradient likewise (one tensor, viewed per parameter): the same values."""
        inertia = self.model.inertia
        B = inertia.r.shape[0]
        jd, jd_saved = inertia_jd_lists(inertia.r.tolist(), inertia.abc.tolist())
        flat = [x for body in jd for row in body for x in row]
        d_saved = []
        for damper in self.dampers:
            Dl, saved = spsd_lists(damper.L_entries.tolist(), damper.lam.tolist(), damper.dim)
            d_saved.append(saved)
            flat += [x for row in Dl for x in row]
        values = torch.tensor(flat, dtype=inertia.r.dtype, device=inertia.r.device)
        Jd = values[: 9 * B].view(B, 3, 3)
        D = None
        for k, damper in enumerate(self.dampers):
            n = damper.dim
            Df = values[9 * B + k * n * n : 9 * B + (k + 1) * n * n].view(n, n)
            D = Df if D is None else D + Df
        reg = batch.reg_W if batch.reg_W is not None and opts.w_reg > 0 else None
        loss, parts, backward = _rotational_loss(Jd, D, batch.fields, reg, self.C, self.h, opts)
        if not math.isfinite(loss):
            return loss, parts, None
        dJd, dD = backward()
        found: list[tuple[int | None, list, tuple[int, ...]]] = []  # (slot, values, shape)
        i_r, i_abc = self.slot_jd
        if i_r is not None or i_abc is not None:
            dr, dabc = inertia_jd_grad_lists(jd_saved, dJd.view(B, 3, 3).tolist())
            found += [(i_r, dr, (B, 3)), (i_abc, dabc, (B, 3))]
        if dD is not None and d_saved:
            g = dD.tolist()
            for saved, (i_l, i_lam) in zip(d_saved, self.slot_d):
                if i_l is not None or i_lam is not None:
                    d_entries, d_lam = spsd_grad_lists(saved, g)
                    found += [(i_l, d_entries, (len(d_entries),)), (i_lam, d_lam, (len(d_lam),))]
        pieces = [(slot, vals, shape) for slot, vals, shape in found if slot is not None]
        grads: list[torch.Tensor | None] = [None] * len(self.params)
        flat_g = [v for _, vals, _ in pieces for v in _flatten(vals)]
        buffer = torch.tensor(flat_g, dtype=inertia.r.dtype, device=inertia.r.device)
        start = 0
        for slot, _, shape in pieces:
            size = math.prod(shape)
            grads[slot] = buffer[start : start + size].view(shape)
            start += size
        return loss, parts, grads


def _flatten(values: list) -> list:
    return [x for row in values for x in row] if values and isinstance(values[0], list) else values


def _rotational_loss(Jd, D, f: dict, reg, C, h: float, opts):
    """`fused_training._RotationalLoss` without autograd: (loss, parts as floats, backward() ->
    (dJd, dD)); the loss is w_del del_loss + w_reg reg_loss in the same double arithmetic."""
    w_del, w_reg = float(opts.w_del), float(opts.w_reg)
    settings = (h, w_del, w_reg, float(opts.epsilon), str(opts.reg_form))
    del_t, reg_t, saved = rotational_forward(Jd.flatten(-2), D, f["A"], f.get("s"), f.get("static"), reg, C, settings)
    del_loss, reg_loss = float(del_t), float(reg_t)

    def backward():
        return rotational_backward(saved, w_del, w_reg)  # d loss / d del_loss = w_del exactly

    return w_del * del_loss + w_reg * reg_loss, {"del_loss": del_loss, "reg_loss": reg_loss}, backward
