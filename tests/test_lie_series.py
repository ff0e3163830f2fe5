"""series.py coefficient functions against their closed forms in 80-digit mpmath arithmetic.

Error model (checked below): the Taylor branch is accurate to a few ulp; the closed forms
of (t - sin t)/t^3 and (1 - (t/2) cot(t/2))/t^2 cancel, losing ~c/t^2 ulp in the value
and ~D/t^4 ulp in the derivative just above the Taylor threshold. In float64 that is
<= 1e-13 (value) and <= 1.5e-9 (derivative) relative, in float32 <= 2e-6 and ~1e-2: the
coefficients multiply hat(w)^2 = O(t^2), so the effect on V, V^{-1} and their Jacobians
stays at the ulp level of the matrices (see test_lie_se3). The Taylor branch, cut after
(t^2)^4, is exact in value but its derivative carries a truncation of 5 c_5 (t^2)^4
(~7e-15 relative for sinc at the float64 threshold).
"""

from __future__ import annotations

import math

import mpmath
import pytest
import torch
from torch.autograd.functional import hessian

from liedfl_cli.lie import se3, series, so3
from liedfl_cli.lie.tolerances import tol

DPS = 80

CLOSED = {
    "sinc": lambda t: mpmath.sin(t) / t,
    "cosc": lambda t: (1 - mpmath.cos(t)) / t**2,
    "sinc3": lambda t: (t - mpmath.sin(t)) / t**3,
    "se3_vinv_coeff": lambda t: (1 - (t / 2) * mpmath.cot(t / 2)) / t**2,
}
# Cancellation constants of the error model: value rel err <= eps (8 + C / t^2),
# derivative rel err <= eps (8 + D / t^4).
C = {"sinc": 0, "cosc": 0, "sinc3": 6, "se3_vinv_coeff": 12}
D = {"sinc": 10, "cosc": 10, "sinc3": 100, "se3_vinv_coeff": 1000}
DTYPES = (torch.float64, torch.float32)
name_param = pytest.mark.parametrize("name", list(CLOSED))
dtype_param = pytest.mark.parametrize("dtype", DTYPES, ids=str)


def taylor_coeffs(name, K=20):
    """Exact coefficients c_k of f = sum_k c_k (t^2)^k."""
    f = mpmath.factorial
    if name == "sinc":
        return [(-1) ** k / f(2 * k + 1) for k in range(K)]
    if name == "cosc":
        return [(-1) ** k / f(2 * k + 2) for k in range(K)]
    if name == "sinc3":
        return [(-1) ** k / f(2 * k + 3) for k in range(K)]
    # 1 - x cot x = -sum_{j>=1} (-4)^j B_2j x^2j / (2j)!, x = t/2.
    return [(-1) ** k * mpmath.bernoulli(2 * k + 2) / f(2 * k + 2) for k in range(K)]


def ref_value(name, s):
    with mpmath.workdps(DPS):
        s = mpmath.mpf(s)
        return CLOSED[name](mpmath.sqrt(s)) if s > 0 else taylor_coeffs(name, 1)[0]


def ref_deriv(name, s):
    with mpmath.workdps(DPS):
        s = mpmath.mpf(s)
        if s < 1e-3:  # power series (converges for t < 2 pi) avoids differencing near 0
            return sum(k * c * s ** (k - 1) for k, c in enumerate(taylor_coeffs(name)) if k)
        return mpmath.diff(lambda u: CLOSED[name](mpmath.sqrt(u)), s)


def points(dtype, name):
    """t^2 values on both sides of the Taylor threshold, and up to pi^2 (V^{-1}: (2 pi - 0.5)^2)."""
    thr2 = torch.tensor(tol(dtype, "taylor") ** 2, dtype=dtype)
    below = torch.nextafter(thr2, torch.zeros_like(thr2))
    pts = [
        0.0,
        1e-30,
        1e-16,
        1e-8,
        1e-4,
        thr2.item() / 4,
        below.item(),
        thr2.item(),
        1.01 * thr2.item(),
        4 * thr2.item(),
        1.0,
        4.0,
        9.0,
        (math.pi - 1e-6) ** 2,
    ]
    if name == "se3_vinv_coeff":
        pts += [25.0, (2 * math.pi - 0.5) ** 2]
    return torch.tensor(pts, dtype=dtype)


def value_and_grad(name, s):
    s = s.clone().requires_grad_()
    v = getattr(series, name)(s)
    (g,) = torch.autograd.grad(v.sum(), s)
    return v.detach(), g


@name_param
@dtype_param
def test_values_and_derivatives_vs_mpmath(name, dtype):
    eps = torch.finfo(dtype).eps
    s = points(dtype, name)
    v, g = value_and_grad(name, s)
    thr2 = tol(dtype, "taylor") ** 2
    c5 = abs(float(taylor_coeffs(name, 6)[5]))  # first coefficient the Taylor branch drops
    for si, vi, gi in zip(s.tolist(), v.tolist(), g.tolist()):
        r, dr = ref_value(name, si), ref_deriv(name, si)
        if si >= thr2:  # closed form: cancellation
            c, d, trunc0, trunc1 = C[name] / si, D[name] / si**2, 0.0, 0.0
        else:  # Taylor branch: truncation after (t^2)^4, larger in the derivative (5 c5 s^4)
            c, d, trunc0, trunc1 = 0.0, 0.0, c5 * si**5, 5 * c5 * si**4
        # Absolute floor eps: sin(t)/t near t = pi is ill-conditioned in t itself.
        assert abs(vi - r) <= eps * (8 + c) * abs(r) + eps + 2 * trunc0, (si, vi, float(r))
        assert abs(gi - dr) <= eps * (8 + d) * abs(dr) + eps + 2 * trunc1, (si, gi, float(dr))


@name_param
@dtype_param
def test_taylor_derivatives_at_zero(name, dtype):
    """f^(k)(0) = k! c_k for k <= 4: the branch is a polynomial in t^2 with exact coefficients,
    so all derivatives through w.w are finite at w = 0."""
    with mpmath.workdps(DPS):
        c = taylor_coeffs(name)
    s = torch.zeros((), dtype=dtype, requires_grad=True)
    d = getattr(series, name)(s)
    for k in range(5):
        expected = float(mpmath.factorial(k) * c[k])
        assert torch.isfinite(d)
        assert abs(d.item() - expected) <= 4 * torch.finfo(dtype).eps * abs(expected), (k, d.item(), expected)
        if k < 4:
            (d,) = torch.autograd.grad(d, s, create_graph=True)


@name_param
@dtype_param
def test_continuity_across_threshold(name, dtype):
    eps = torch.finfo(dtype).eps
    thr2 = torch.tensor(tol(dtype, "taylor") ** 2, dtype=dtype)
    s = torch.stack((torch.nextafter(thr2, torch.zeros_like(thr2)), thr2))
    (v_lo, v_hi), (g_lo, g_hi) = value_and_grad(name, s)
    t2 = thr2.item()
    assert abs(v_hi - v_lo) <= 2 * eps * (8 + C[name] / t2) * abs(v_lo)
    assert abs(g_hi - g_lo) <= 2 * eps * (8 + D[name] / t2**2) * abs(g_lo)


@pytest.mark.parametrize("t", (0.1001, 0.29, 0.3001, 0.31, 0.5, 1.0, 2.0))
def test_float32_hessians_of_composites(t):
    """Second derivatives of the closed forms are poor just above the float32 threshold
    (d^2/ds^2 of se3_vinv_coeff is off by a factor ~5 at t = 0.3), but they enter V, V^{-1}
    and exp weighted by O(t^4), so the Hessians of the composites stay within ~1e-5 relative."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(3, generator=gen, dtype=torch.float64)
    w = t * a / torch.linalg.vector_norm(a)
    Cm = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    for f in (so3.exp, se3.V_matrix, se3.V_inverse):
        h64 = hessian(lambda u, f=f: (Cm * f(u)).sum(), w)
        h32 = hessian(lambda u, f=f: (Cm.float() * f(u)).sum(), w.float()).double()
        assert (h32 - h64).abs().max() <= 3e-5 * h64.abs().max(), f.__name__


def test_tolerance_table():
    assert tol(torch.float64, "taylor") == 0.1
    assert tol(torch.float16, "taylor") == tol(torch.float32, "taylor")  # fallback row
    # Truncating after t^8 costs < eps at the threshold (the next sinc term is t^10 / 11!).
    for dtype in DTYPES:
        t = tol(dtype, "taylor")
        assert t**10 / math.factorial(11) < torch.finfo(dtype).eps
