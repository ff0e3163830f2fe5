"""Scalar coefficient functions of exp/log on SO(3) and SE(3), safe at theta -> 0.

Each function takes theta^2 (not theta) so that its Taylor branch is a polynomial in
theta^2 and first and second derivatives through w.w stay finite at w = 0. The closed
form is evaluated on a `safe` argument in the Taylor region, so `torch.where` never
mixes a NaN/inf gradient into the result.
"""

from __future__ import annotations

import torch

from .tolerances import tol


def _split(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    small = theta2 < tol(theta2.dtype, "taylor") ** 2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    return small, safe2, torch.sqrt(safe2)


def _poly(t2: torch.Tensor, coeffs: tuple[float, ...]) -> torch.Tensor:
    out = torch.full_like(t2, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * t2 + c
    return out


def sinc(theta2: torch.Tensor) -> torch.Tensor:
    """sin(t)/t as a function of t^2, elementwise: theta2 (...) -> (...)."""
    small, _, t = _split(theta2)
    taylor = _poly(theta2, (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880))
    return torch.where(small, taylor, torch.sin(t) / t)


def cosc(theta2: torch.Tensor) -> torch.Tensor:
    """(1 - cos t)/t^2 as a function of t^2, elementwise: theta2 (...) -> (...)."""
    small, s2, t = _split(theta2)
    taylor = _poly(theta2, (0.5, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800))
    # 2 sin^2(t/2) avoids the cancellation in 1 - cos t.
    return torch.where(small, taylor, 2.0 * torch.sin(0.5 * t) ** 2 / s2)


def sinc3(theta2: torch.Tensor) -> torch.Tensor:
    """(t - sin t)/t^3 as a function of t^2, elementwise: theta2 (...) -> (...)."""
    small, s2, t = _split(theta2)
    taylor = _poly(theta2, (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800))
    return torch.where(small, taylor, (t - torch.sin(t)) / (s2 * t))


def se3_vinv_coeff(theta2: torch.Tensor) -> torch.Tensor:
    """(1 - (t/2) cot(t/2)) / t^2, the hat(w)^2 coefficient of V(w)^{-1}; finite up to t = pi.

    Elementwise in t^2: theta2 (...) -> (...).
    """
    small, s2, t = _split(theta2)
    taylor = _poly(theta2, (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160))
    half = 0.5 * t
    return torch.where(small, taylor, (1.0 - half * torch.cos(half) / torch.sin(half)) / s2)
