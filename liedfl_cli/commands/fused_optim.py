"""SOAP (pytorch_optimizer's) with its per-step update issued as list operations (`FusedSOAP`).

The default run trains four tiny tensors (J_d's r and abc, (1, 3) each; the damping's 6 + 3
entries): the library's per-tensor Python (about 30 small kernels, a dozen `torch.tensordot`
wrappers and their dimension bookkeeping per tensor per step) costs more than the loss. `FusedSOAP`
runs the same kernels on the same tensors, in the same order per tensor, but issues the elementwise
ones for all tensors at once (`torch._foreach_*`: one call, the per-tensor kernel inside) and the
projections as direct `tensordot` calls. The result is the library's bit for bit, which matters:
SOAP's first eigenbasis comes from a rank-one statistic, whose null space eigh fixes by rounding,
so a last-bit difference in one step changes a whole training run (the merged kernels of a
stacked buffer did, by 2 % of the final loss after 1000 epochs). State, checkpoints and the
eigenbasis refresh (`precondition_frequency`) are the library's own.

The list step covers 1-D tensors without a preconditioner and tensors of 2 or more dimensions with
every dimension preconditioned (Exp 4's per-body force heads are 3-D); a parameter without a gradient
is left alone, as the library's step leaves it (Exp 4's potential's last bias: a constant shift of V
does not enter the forced DEL equations). Anything else (a dimension above `max_precondition_dim`,
merge_dims, precondition_1d, normalize_gradient, maximize, several parameter groups, a gradient
whose state the library has yet to create, the first step) takes the library's step unchanged.
"""

from __future__ import annotations

import math

import torch
from pytorch_optimizer import SOAP

_tensordot = torch._C._VariableFunctions.tensordot  # type: ignore[attr-defined]  # torch.tensordot's kernel call


def _listable(p: torch.Tensor, state: dict, max_dim: int) -> bool:
    """Whether the list step reproduces the library's for `p`: 1-D without a preconditioner, or 2-D
    and more with every dimension preconditioned."""
    if not state or state.get("Q") is None:
        return False
    if p.dim() == 1:
        return len(state["GG"][0]) == 0
    return p.dim() >= 2 and max(p.shape) <= max_dim and len(state["GG"]) == p.dim()


class FusedSOAP(SOAP):
    """`pytorch_optimizer.SOAP` with the list step of the module docstring (same arguments)."""

    def _list_group(self) -> dict | None:
        """The parameter group when the list step applies now, else None (the library's step)."""
        if len(self.param_groups) != 1:
            return None
        group = self.param_groups[0]
        if group.get("step", 0) < 1 or group["merge_dims"] or group["precondition_1d"]:
            return None
        if group["normalize_gradient"] or self.maximize:
            return None
        top = group["max_precondition_dim"]
        for p in group["params"]:
            if p.grad is not None and (p.grad.is_sparse or not _listable(p, self.state.get(p, {}), top)):
                return None
        return group

    def step(self, closure=None):
        """One step. torch wraps every optimiser's `step` in a profiler scope and its hook calls
        (tens of microseconds here, a few per cent of a default-run step); `step.hooked` below keeps
        that wrapper off, and this method takes it only where it does something: while the torch
        profiler runs or a step hook is registered."""
        if self._optimizer_step_pre_hooks or self._optimizer_step_post_hooks or _global_hooks():
            return _HOOKED_STEP(self, closure)
        return self._step(closure)

    step.hooked = True  # type: ignore[attr-defined]  # read by torch.optim.Optimizer._patch_step_function

    @torch.no_grad()
    def _step(self, closure=None):
        group = self._list_group()
        if group is None:
            return super().step(closure)
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        group["step"] += 1
        beta1, beta2 = group["betas"]
        step = group["step"] - 1
        step_size = group["lr"]
        if group["correct_bias"]:
            step_size *= math.sqrt(self.debias(beta2, step)) / self.debias(beta1, step)
        params = [p for p in group["params"] if p.grad is not None]  # the library skips the others
        states = [self.state[p] for p in params]
        grads = [p.grad for p in params]
        mats = [i for i, p in enumerate(params) if p.dim() >= 2]
        exp_avg = [s["exp_avg"] for s in states]
        exp_avg_sq = [s["exp_avg_sq"] for s in states]
        projected = list(grads)  # 1-D: the identity projection (the library's permute of one dimension)
        for i in mats:
            projected[i] = self._project(grads[i], states[i]["Q"], 0)
        torch._foreach_lerp_(exp_avg, grads, 1.0 - beta1)
        torch._foreach_lerp_(exp_avg_sq, torch._foreach_pow(projected, 2), 1.0 - beta2)
        de_nom = torch._foreach_sqrt(exp_avg_sq)
        torch._foreach_add_(de_nom, group["eps"])
        ea_projected = list(exp_avg)
        for i in mats:
            ea_projected[i] = self._project(exp_avg[i], states[i]["Q"], 0)
        norm_grad = list(torch._foreach_div(ea_projected, de_nom))
        for i in mats:
            norm_grad[i] = self._project(norm_grad[i], states[i]["Q"], 1)
        torch._foreach_add_(params, norm_grad, alpha=-step_size)
        if group["weight_decay"] != 0.0:  # decoupled, as the library's apply_weight_decay
            torch._foreach_mul_(params, 1.0 - group["weight_decay"] * group["lr"])
        if mats:
            pairs = [(i, k) for i in mats for k in range(params[i].dim())]
            gg = [states[i]["GG"][k] for i, k in pairs]
            outer = [_tensordot(grads[i], grads[i], *[_others(params[i].dim(), k)] * 2) for i, k in pairs]
            shampoo = {states[i]["shampoo_beta"] for i in mats}
            if len(shampoo) == 1:
                torch._foreach_lerp_(gg, outer, 1.0 - shampoo.pop())
            else:
                for g, o, (i, _) in zip(gg, outer, pairs):
                    g.lerp_(o, weight=1.0 - states[i]["shampoo_beta"])
            for i in mats:
                if step > 0 and step % states[i]["precondition_frequency"] == 0:
                    states[i]["Q"] = self.get_orthogonal_matrix_qr(states[i], group["max_precondition_dim"], False)
        return loss

    @staticmethod
    def _project(x: torch.Tensor, Q: list, back: int) -> torch.Tensor:
        """The library's `project` of a tensor with every dimension preconditioned (2-D: Q0^T x Q1,
        or Q0 x Q1^T with back = 1): the same tensordots, one per dimension, each contracting the
        leading one and appending its image last."""
        for q in Q:
            x = _tensordot(x, q, [0], [back])
        return x


def _others(ndim: int, k: int) -> list[int]:
    """Every dimension but k: the library's contraction for the preconditioner statistic GG[k]."""
    return [d for d in range(ndim) if d != k]


def _global_hooks() -> bool:
    """Whether global optimiser step hooks are registered or the torch profiler runs."""
    from torch.optim import optimizer

    return bool(
        optimizer._global_optimizer_pre_hooks
        or optimizer._global_optimizer_post_hooks
        or torch.autograd.profiler._is_profiler_enabled
    )


_HOOKED_STEP = torch.optim.Optimizer.profile_hook_step(FusedSOAP._step)  # torch's wrapper, for the cases above
