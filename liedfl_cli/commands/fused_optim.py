"""SOAP (pytorch_optimizer's) with its per-step update batched over the parameters (`FusedSOAP`).

The default run trains four tiny tensors (J_d's r and abc, (1, 3) each; the damping's 6 + 3
entries): the library's per-tensor Python (about 30 small kernels and a dozen tensordots per tensor
per step) costs more than the loss. `FusedSOAP` keeps the library's state layout (`state[p]` holds
exp_avg, exp_avg_sq, GG, Q as the library writes them, so checkpoints are interchangeable with plain
SOAP) but stores those tensors as views of a few stacked buffers: one for the 1-D parameters
(identity projection: plain Adam with SOAP's bias correction) and one per shape of the 2-D
parameters (both dimensions preconditioned: X -> Q0^T X Q1 as batched products), so a step is about
25 kernels whatever the number of tensors. The eigenbasis refresh (QR every
`precondition_frequency` steps) and the first step (eigh) are the library's own code.

Same arithmetic as the library to rounding (the products are batched; tests/test_fused_step.py
compares the loss histories to 1e-12 relative). Anything else (3-D+ tensors, a dimension above
`max_precondition_dim`, merge_dims, precondition_1d, normalize_gradient, maximize, several
parameter groups, a parameter without a gradient) takes the library's step unchanged.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from pytorch_optimizer import SOAP


class _Stacks:
    """The stacked state of one step's parameters: `vec` (the 1-D parameters, concatenated) and
    `mats` ({shape: (params, exp_avg, exp_avg_sq, GG0, GG1, Q0, Q1)}, each (k, ...) stacked)."""

    def __init__(self, opt: SOAP, params: list[torch.Tensor]):
        vec = [p for p in params if p.dim() == 1]
        self.vec = vec
        self.vec_sizes = [p.numel() for p in vec]
        self.ea = self.eas = None
        if vec:
            self.ea = torch.cat([opt.state[p]["exp_avg"].reshape(-1) for p in vec])
            self.eas = torch.cat([opt.state[p]["exp_avg_sq"].reshape(-1) for p in vec])
            for p, ea, eas in zip(vec, self.ea.split(self.vec_sizes), self.eas.split(self.vec_sizes)):
                opt.state[p]["exp_avg"], opt.state[p]["exp_avg_sq"] = ea, eas
        shapes: dict[tuple, list[torch.Tensor]] = {}
        for p in params:
            if p.dim() == 2:
                shapes.setdefault(tuple(p.shape), []).append(p)
        self.mats: list[tuple[list[torch.Tensor], list[torch.Tensor]]] = []
        for ps in shapes.values():
            st = [opt.state[p] for p in ps]
            bufs = [
                torch.stack([s["exp_avg"] for s in st]),
                torch.stack([s["exp_avg_sq"] for s in st]),
                torch.stack([s["GG"][0] for s in st]),
                torch.stack([s["GG"][1] for s in st]),
                torch.stack([s["Q"][0] for s in st]),
                torch.stack([s["Q"][1] for s in st]),
            ]
            for i, s in enumerate(st):
                s["exp_avg"], s["exp_avg_sq"] = bufs[0][i], bufs[1][i]
                s["GG"], s["Q"] = [bufs[2][i], bufs[3][i]], [bufs[4][i], bufs[5][i]]
            self.mats.append((ps, bufs))


def _batchable(p: torch.Tensor, state: dict, max_dim: int) -> bool:
    """Whether the stacked step reproduces the library's for `p`: 1-D without a preconditioner,
    or 2-D with both dimensions preconditioned."""
    if p.dim() == 1:
        return len(state.get("GG", [0])[0]) == 0
    return p.dim() == 2 and max(p.shape) <= max_dim


class FusedSOAP(SOAP):
    """`pytorch_optimizer.SOAP` with the batched step of the module docstring (same arguments)."""

    def __init__(self, params, **kwargs: Any):
        super().__init__(params, **kwargs)
        self._stacks: _Stacks | None = None

    def load_state_dict(self, state_dict: dict) -> None:
        super().load_state_dict(state_dict)
        self._stacks = None  # the loaded tensors are not views of the stacks: rebuilt on the next step

    def _fast_group(self) -> dict | None:
        """The parameter group when the batched step applies now, else None (library step)."""
        if len(self.param_groups) != 1:
            return None
        group = self.param_groups[0]
        if group.get("step", 0) < 1 or group["merge_dims"] or group["precondition_1d"]:
            return None
        if group["normalize_gradient"] or self.maximize or not group["correct_bias"]:
            return None
        for p in group["params"]:
            if p.grad is None or p.grad.is_sparse or not self.state.get(p):
                return None
        if self._stacks is None:
            state, top = self.state, group["max_precondition_dim"]
            if not all(_batchable(p, state[p], top) for p in group["params"]):
                return None
            self._stacks = _Stacks(self, group["params"])
        return group

    @torch.no_grad()
    def step(self, closure=None):  # type: ignore[override]
        group = self._fast_group()
        if group is None:
            self._stacks = None  # the library's step may replace state tensors
            return super().step(closure)
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        stacks = self._stacks
        assert stacks is not None
        group["step"] += 1
        beta1, beta2 = group["betas"]
        step = group["step"] - 1
        step_size = group["lr"] * math.sqrt(self.debias(beta2, step)) / self.debias(beta1, step)
        eps, wd = group["eps"], group["weight_decay"]
        if stacks.vec:
            g = torch.cat([p.grad.reshape(-1) for p in stacks.vec]) if len(stacks.vec) > 1 else stacks.vec[0].grad
            assert stacks.ea is not None and stacks.eas is not None
            stacks.ea.lerp_(g, weight=1.0 - beta1)
            stacks.eas.lerp_(g.square(), weight=1.0 - beta2)
            upd = stacks.ea / stacks.eas.sqrt().add_(eps)
            torch._foreach_add_(stacks.vec, upd.split(stacks.vec_sizes), alpha=-step_size)
        refresh = step % group["precondition_frequency"] == 0
        for ps, (ea, eas, gg0, gg1, q0, q1) in stacks.mats:
            G = torch.stack([p.grad for p in ps])
            # the library's project: tensordot over dim 0 with Q0, then with Q1 (Q0^T X Q1)
            gp = (G.mT @ q0).mT @ q1
            ea.lerp_(G, weight=1.0 - beta1)
            eas.lerp_(gp.square(), weight=1.0 - beta2)
            de_nom = eas.sqrt().add_(eps)
            eap = (ea.mT @ q0).mT @ q1
            norm_grad = ((eap / de_nom).mT @ q0.mT).mT @ q1.mT  # backward projection Q0 X Q1^T
            torch._foreach_add_(ps, norm_grad.unbind(0), alpha=-step_size)
            shampoo = self.state[ps[0]]["shampoo_beta"]
            gg0.lerp_(G @ G.mT, weight=1.0 - shampoo)
            gg1.lerp_(G.mT @ G, weight=1.0 - shampoo)
        if wd != 0.0:
            torch._foreach_mul_(list(group["params"]), 1.0 - wd * group["lr"])
        if refresh and stacks.mats:
            self._refresh(group)
        return loss

    def _refresh(self, group: dict) -> None:
        """The library's eigenbasis refresh (`get_orthogonal_matrix_qr`, which also reorders
        exp_avg_sq) per 2-D parameter, written back into the stacks."""
        assert self._stacks is not None
        for ps, (_, eas, _, _, q0, q1) in self._stacks.mats:
            for i, p in enumerate(ps):
                state = self.state[p]
                Q = self.get_orthogonal_matrix_qr(state, group["max_precondition_dim"], False)
                q0[i].copy_(Q[0])
                q1[i].copy_(Q[1])
                eas[i].copy_(state["exp_avg_sq"])
                state["exp_avg_sq"], state["Q"] = eas[i], [q0[i], q1[i]]
