"""SO(3): exp/log values against matrix_exp, derivatives, quaternions, projection."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck
from torch.autograd.functional import hessian, jacobian

from liedfl_cli.lie import so3

F64 = torch.float64
EPS = torch.finfo(F64).eps
THETAS = (0.0, 1e-12, 1e-8, 1e-4, 1e-2, 1.0, math.pi - 1e-6)
theta_param = pytest.mark.parametrize("theta", THETAS, ids=lambda t: f"{t:.3g}")


def axes(n=4, seed=0):
    a = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return a / torch.linalg.vector_norm(a, dim=-1, keepdim=True)


def mexp(w):
    return torch.linalg.matrix_exp(so3.hat(w))


def rot_pi(a):
    """Rotation by exactly pi about unit a: 2 a a^T - I."""
    return 2 * a[..., :, None] * a[..., None, :] - torch.eye(3, dtype=a.dtype)


# ------------------------------------------------------------------------------ hat / vee
def test_hat_vee():
    w, x = torch.randn(2, 7, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    W = so3.hat(w)
    assert torch.equal(W, -W.transpose(-1, -2))
    # a matrix product against a cross product: a few roundings of terms of size |w| |x| (BLAS may use FMA)
    atol = 4 * EPS * float(w.abs().max() * x.abs().max())
    torch.testing.assert_close(so3.act(W, x), torch.linalg.cross(w, x), rtol=0, atol=atol)
    assert torch.equal(so3.vee(W), w)
    A = torch.randn(7, 3, 3, dtype=F64)
    assert torch.equal(so3.vee(A), so3.vee(0.5 * (A - A.transpose(-1, -2))))


# ---------------------------------------------------------------------------------- values
@theta_param
def test_exp_matches_matrix_exp(theta):
    w = theta * axes()
    # torch.linalg.matrix_exp itself is off by ~7e-14 at theta = 1e-2 (float64).
    atol = 1e-12 if theta == 1e-2 else 4e-15
    torch.testing.assert_close(so3.exp(w), mexp(w), rtol=0, atol=atol)


@pytest.mark.parametrize("delta", (-1e-9, 0.0, 1e-9))
def test_exp_continuous_across_taylor_threshold(delta):
    w = (0.1 + delta) * axes()  # float64 threshold: |w| = 0.1
    torch.testing.assert_close(so3.exp(w), mexp(w), rtol=0, atol=1e-15)
    w32 = ((0.3 + delta * 100) * axes()).float()  # float32 threshold: |w| = 0.3
    torch.testing.assert_close(so3.exp(w32), mexp(w32.double()).float(), rtol=0, atol=3e-7)


@theta_param
def test_log_recovers_w(theta):
    """Relative error ~1e-15 at every angle, including pi - 1e-6.

    The quaternion route (Shepperd's largest pivot, then 2 atan2(|q_v|, q_w)) needs no
    acos of the trace: near pi, q_w = cos(theta/2) comes from the antisymmetric part
    divided by an O(1) pivot, so the angle keeps O(eps) *absolute* accuracy. The trace
    formula would lose ~eps / sin(theta) ~ 1e-10 there (checked below for contrast).
    """
    w = theta * axes()
    for R in (so3.exp(w), mexp(w)):
        err = torch.linalg.vector_norm(so3.log(R) - w, dim=-1)
        ref_err = 1e-13 if theta == 1e-2 else 0.0  # matrix_exp's own error there
        assert (err <= 2e-15 * theta + ref_err).all(), err
    if theta == THETAS[-1]:
        tr = so3.exp(w).diagonal(dim1=-2, dim2=-1).sum(-1)
        naive = torch.acos(((tr - 1) / 2).clamp(-1, 1))
        assert (naive - theta).abs().max() > 1e-12  # what the quaternion route avoids


@pytest.mark.parametrize("dtype", (torch.float64, torch.float32), ids=str)
def test_log_accurate_across_series_threshold(dtype):
    """log switches to a series in |q_v| = sin(theta/2) below the Taylor threshold
    (theta ~ 0.2 in float64, ~ 0.61 in float32); it must be accurate on both sides."""
    thr = 2 * math.asin(0.1 if dtype == torch.float64 else 0.3)
    a = axes(8, seed=10)
    th = thr * torch.linspace(0.5, 1.5, 41, dtype=F64)[:, None, None]
    w = th * a
    err = torch.linalg.vector_norm(so3.log(so3.exp(w).to(dtype)).double() - w, dim=-1) / th[..., 0]
    assert err.max() < (2e-15 if dtype == torch.float64 else 4.5e-7)  # the x^8 series gave 1e-11 / 8e-7


def test_log_wraps_beyond_pi():
    a = axes()
    w = (math.pi + 0.5) * a
    torch.testing.assert_close(so3.log(so3.exp(w)), (math.pi + 0.5 - 2 * math.pi) * a, rtol=0, atol=1e-14)


def test_geodesic_distance_and_adjoint():
    gen = torch.Generator().manual_seed(2)
    R = so3.random((6,), generator=gen)
    w = 0.7 * torch.randn(6, 3, generator=gen, dtype=F64)
    d = so3.geodesic_distance(R, so3.retract(R, w))
    torch.testing.assert_close(d, torch.linalg.vector_norm(w, dim=-1), rtol=0, atol=1e-14)
    Ad = so3.adjoint(R)
    torch.testing.assert_close(so3.hat(so3.act(Ad, w)), R @ so3.hat(w) @ R.transpose(-1, -2), rtol=0, atol=1e-14)
    torch.testing.assert_close(so3.exp(so3.act(Ad, w)), R @ so3.exp(w) @ R.transpose(-1, -2), rtol=0, atol=1e-14)


# ----------------------------------------------------------------------------- derivatives
@theta_param
def test_exp_gradcheck(theta):
    for a in axes(2):
        w = (theta * a).requires_grad_()
        assert gradcheck(so3.exp, (w,))
        assert gradgradcheck(so3.exp, (w,))


@theta_param
def test_log_gradcheck(theta):
    for a in axes(2):
        w = theta * a
        # d log(exp(w)) / dw = I at every angle, including w = 0 exactly.
        torch.testing.assert_close(
            jacobian(lambda u: so3.log(so3.exp(u)), w), torch.eye(3, dtype=F64), rtol=0, atol=1e-12
        )
        # With respect to the 9 matrix entries (log is smooth in them off the manifold too).
        # Near pi, q_w = cos(theta/2) ~ 5e-7 flips sign (the log jumps to the antipode)
        # under an entry perturbation of ~1e-6, so the finite-difference step must be smaller.
        eps = 1e-9 if theta > 3 else 1e-6
        R = so3.exp(w).requires_grad_()
        assert gradcheck(so3.log, (R,), eps=eps, atol=1e-6)
        assert gradgradcheck(so3.log, (R,), eps=eps, atol=1e-5)


def test_log_gradient_finite_at_pi():
    """At theta = pi (q_w = 0) the discarded series branch once produced NaN gradients."""
    for R in (torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)), rot_pi(axes(1)[0])):
        R = R.clone().requires_grad_()
        (g,) = torch.autograd.grad(so3.log(R).sum(), R)
        assert torch.isfinite(g).all()


@pytest.mark.parametrize("theta", (0.0, 1e-12, 1e-8, 1e-4), ids=str)
def test_exp_derivatives_match_matrix_exp_at_tiny_angles(theta):
    """First and second derivatives of a scalar contraction of exp equal those of matrix_exp.

    At w = 0 exactly the closed form sin(t)/t would give NaN second derivatives; the Taylor
    branch (a polynomial in t^2 = w.w) keeps them finite and correct.
    """
    C = torch.randn(3, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    w = theta * axes(1)[0]
    f = lambda u: (C * so3.exp(u)).sum()
    f_ref = lambda u: (C * mexp(u)).sum()
    J, J_ref = jacobian(f, w), jacobian(f_ref, w)
    H, H_ref = hessian(f, w), hessian(f_ref, w)
    assert torch.isfinite(H).all()
    torch.testing.assert_close(J, J_ref, rtol=0, atol=1e-14)
    torch.testing.assert_close(H, H_ref, rtol=0, atol=1e-14)
    if theta == 0.0:  # exp(hat(w)) = I + W + W^2 / 2 + ...: gradient vee-like, Hessian from W^2/2
        # autodiff sums the entries of C in its own order: a few roundings of terms of size max|C|
        c = float(C.abs().max())
        torch.testing.assert_close(J, so3.vee(C - C.transpose(0, 1)), rtol=0, atol=4 * EPS * c)
        H_exact = 0.5 * (C + C.T) - torch.trace(C) * torch.eye(3, dtype=F64)
        torch.testing.assert_close(H, H_exact, rtol=0, atol=8 * EPS * c)


# ----------------------------------------------------------------------------- quaternions
def test_quaternion_roundtrip_random():
    gen = torch.Generator().manual_seed(4)
    R = so3.random((50,), generator=gen)
    q = so3.to_quaternion(R)
    torch.testing.assert_close(torch.linalg.vector_norm(q, dim=-1), torch.ones(50, dtype=F64))
    assert (q[..., 0] >= 0).all()
    torch.testing.assert_close(so3.from_quaternion(q), R, rtol=0, atol=1e-14)
    q0 = torch.randn(50, 4, generator=gen, dtype=F64)
    expected = q0 / torch.linalg.vector_norm(q0, dim=-1, keepdim=True) * torch.sign(q0[..., :1])
    torch.testing.assert_close(so3.to_quaternion(so3.from_quaternion(q0)), expected, rtol=0, atol=1e-14)


def test_quaternion_product_is_rotation_product():
    gen = torch.Generator().manual_seed(5)
    p, q = torch.randn(2, 10, 4, generator=gen, dtype=F64)
    pw, pv, qw, qv = p[:, :1], p[:, 1:], q[:, :1], q[:, 1:]
    pq = torch.cat((pw * qw - (pv * qv).sum(-1, keepdim=True), pw * qv + qw * pv + torch.linalg.cross(pv, qv)), -1)
    torch.testing.assert_close(
        so3.from_quaternion(pq), so3.from_quaternion(p) @ so3.from_quaternion(q), rtol=0, atol=1e-14
    )


def test_quaternion_and_log_at_exactly_pi():
    a = axes(6, seed=6)
    Rs = torch.cat((rot_pi(a), torch.diag_embed(torch.tensor([[1.0, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=F64))))
    a = torch.cat((a, torch.eye(3, dtype=F64)))
    q = so3.to_quaternion(Rs)
    assert torch.equal(q[:, 0], torch.zeros(9, dtype=F64))  # R symmetric: skew part exactly 0
    sign = torch.sign((q[:, 1:] * a).sum(-1, keepdim=True))  # axis is only defined up to sign
    torch.testing.assert_close(sign * q[:, 1:], a, rtol=0, atol=1e-14)
    torch.testing.assert_close(so3.from_quaternion(q), Rs, rtol=0, atol=1e-14)
    w = so3.log(Rs)
    torch.testing.assert_close(
        torch.linalg.vector_norm(w, dim=-1), torch.full((9,), math.pi, dtype=F64), rtol=0, atol=2e-15
    )
    torch.testing.assert_close(so3.exp(w), Rs, rtol=0, atol=1e-14)


@pytest.mark.parametrize("delta", (1e-6, 1e-9, 1e-12))
def test_quaternion_near_pi(delta):
    a = axes(6, seed=7)
    th = math.pi - delta
    R = so3.exp(th * a)
    q = so3.to_quaternion(R)
    # q_w = cos(th / 2) > 0 fixes the sign: the axis comes back as +a.
    expected = torch.cat((torch.full((6, 1), math.cos(th / 2), dtype=F64), math.sin(th / 2) * a), -1)
    torch.testing.assert_close(q, expected, rtol=0, atol=2e-15)
    torch.testing.assert_close(so3.from_quaternion(q), R, rtol=0, atol=1e-14)


# ------------------------------------------------------------------------------ projection
def test_project():
    gen = torch.Generator().manual_seed(8)
    R = so3.random((20,), generator=gen)
    torch.testing.assert_close(so3.project(R), R, rtol=0, atol=1e-14)
    M = R + 1e-3 * torch.randn(20, 3, 3, generator=gen, dtype=F64)
    P = so3.project(M)
    assert (so3.orthogonality_error(P) < 1e-14).all()
    torch.testing.assert_close(torch.linalg.det(P), torch.ones(20, dtype=F64))
    assert (so3.geodesic_distance(R, P) < 5e-3).all()
    assert (so3.geodesic_distance(R, P) > 0).all()
    # Polar decomposition: R S with S symmetric positive definite projects to R exactly.
    B = torch.randn(20, 3, 3, generator=gen, dtype=F64)
    S = B @ B.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=F64)
    torch.testing.assert_close(so3.project(R @ S), R, rtol=0, atol=1e-12)
    # An improper orthogonal matrix is sent to a proper rotation.
    assert (torch.linalg.det(so3.project(-R)) > 0.999).all()


def test_random_and_identity():
    R = so3.random((2, 3), generator=torch.Generator().manual_seed(9), dtype=torch.float32)
    assert R.shape == (2, 3, 3, 3) and R.dtype == torch.float32
    assert (so3.orthogonality_error(R) < 1e-5).all()
    Id = so3.identity((4,), dtype=torch.float32)
    assert Id.shape == (4, 3, 3) and torch.equal(Id, torch.eye(3).expand(4, 3, 3))
    assert torch.equal(so3.log(Id), torch.zeros(4, 3))
