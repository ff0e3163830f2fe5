"""The loss shared by every model trained on the DEL residual (LieDFLNN per body and articulated,
Euler-angle and Euclidean DFLNN): w_DEL mean ||r||^2 + w_reg mean penalty(log|det H|)."""

from __future__ import annotations

import math

import torch

from .base import LossOptions


def regularity_penalty(logdet: torch.Tensor, epsilon: float, form: str = "relu") -> torch.Tensor:
    """Penalty keeping |det H| above e^epsilon, evaluated in log space (no overflow).

    relu:     ReLU(epsilon - log|det H|)
    gaussian: exp(-(|det H| e^-epsilon - 1)^2 / 2) / sqrt(2 pi), the paper's Gaussian form
              with its constant prefactor e^-epsilon dropped.
    """
    if form == "relu":
        return torch.relu(epsilon - logdet)
    if form == "gaussian":
        u = torch.exp(torch.clamp(logdet - epsilon, max=50.0))
        return torch.exp(-0.5 * (u - 1.0) ** 2) / math.sqrt(2 * math.pi)
    raise ValueError(f"train.reg_form must be 'relu' or 'gaussian', got {form!r}")


def del_regularity_loss(r: torch.Tensor, logdet: torch.Tensor | None, opts: LossOptions):
    """w_DEL mean ||r||^2 + w_reg mean penalty(logdet) -> (loss, {"del_loss", "reg_loss"}).

    Shared by every model trained on the DEL residual (LieDFLNN, Euler- and Euclidean DFLNN)."""
    del_loss = (r * r).mean()
    reg_loss = torch.zeros((), dtype=r.dtype, device=r.device)
    if logdet is not None:
        reg_loss = regularity_penalty(logdet, opts.epsilon, opts.reg_form).mean()
    return opts.w_del * del_loss + opts.w_reg * reg_loss, {"del_loss": del_loss, "reg_loss": reg_loss}
