"""SE(3): exp/log/V against matrix exponentials, derivatives, homogeneous-matrix consistency."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck
from torch.autograd.functional import jacobian

from liedfl_cli.lie import se3, so3

F64 = torch.float64
THETAS = (0.0, 1e-12, 1e-8, 1e-4, 1e-2, 1.0, math.pi - 1e-6)
theta_param = pytest.mark.parametrize("theta", THETAS, ids=lambda t: f"{t:.3g}")


def tangents(theta, n=4, seed=0):
    """n twists (w, v) with |w| = theta along random axes and v ~ N(0, 1)."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3, generator=gen, dtype=F64)
    a = a / torch.linalg.vector_norm(a, dim=-1, keepdim=True)
    return torch.cat((theta * a, torch.randn(n, 3, generator=gen, dtype=F64)), -1)


def random_pose(n, seed):
    gen = torch.Generator().manual_seed(seed)
    return so3.random((n,), generator=gen), torch.randn(n, 3, generator=gen, dtype=F64)


def test_hat_vee_and_matrix_roundtrip():
    xi = tangents(0.7)
    X = se3.hat(xi)
    assert X.shape == (4, 4, 4) and torch.equal(X[:, 3], torch.zeros(4, 4, dtype=F64))
    assert torch.equal(se3.vee(X), xi)
    R, p = random_pose(4, 1)
    T = se3.to_matrix(R, p)
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(4, 4))
    R2, p2 = se3.from_matrix(T)
    assert torch.equal(R2, R) and torch.equal(p2, p)


@theta_param
def test_exp_matches_matrix_exp(theta):
    xi = tangents(theta)
    T = torch.linalg.matrix_exp(se3.hat(xi))
    R, p = se3.exp(xi)
    torch.testing.assert_close(se3.to_matrix(R, p), T, rtol=0, atol=1e-14)


@theta_param
def test_V_matrix_is_block_of_matrix_exp(theta):
    """V(w) is the upper-right block of exp([[hat(w), I], [0, 0]])."""
    w = tangents(theta)[:, :3]
    A = torch.zeros(4, 6, 6, dtype=F64)
    A[:, :3, :3] = so3.hat(w)
    A[:, :3, 3:] = torch.eye(3, dtype=F64)
    torch.testing.assert_close(se3.V_matrix(w), torch.linalg.matrix_exp(A)[:, :3, 3:], rtol=0, atol=1e-14)


@pytest.mark.parametrize("theta", (*THETAS, 2 * math.pi - 0.5), ids=lambda t: f"{t:.3g}")
def test_V_inverse_inverts_V(theta):
    w = tangents(theta)[:, :3]
    eye = torch.eye(3, dtype=F64).expand(4, 3, 3)
    # cond(V) grows like 1 / (2 pi - theta) toward 2 pi.
    atol = 1e-14 if theta < 4 else 1e-13
    torch.testing.assert_close(se3.V_inverse(w) @ se3.V_matrix(w), eye, rtol=0, atol=atol)
    torch.testing.assert_close(se3.V_matrix(w) @ se3.V_inverse(w), eye, rtol=0, atol=atol)


@theta_param
def test_log_recovers_xi(theta):
    xi = tangents(theta)
    torch.testing.assert_close(se3.log(*se3.exp(xi)), xi, rtol=0, atol=4e-15)


def test_group_ops_match_homogeneous_matrices():
    (R1, p1), (R2, p2) = random_pose(5, 2), random_pose(5, 3)
    T1, T2 = se3.to_matrix(R1, p1), se3.to_matrix(R2, p2)
    torch.testing.assert_close(se3.to_matrix(*se3.compose(R1, p1, R2, p2)), T1 @ T2, rtol=0, atol=1e-14)
    torch.testing.assert_close(se3.to_matrix(*se3.inverse(R1, p1)), torch.linalg.inv(T1), rtol=0, atol=1e-14)
    x = torch.randn(5, 3, dtype=F64)
    xh = torch.cat((x, torch.ones(5, 1, dtype=F64)), -1)
    torch.testing.assert_close(se3.act(R1, p1, x), (T1 @ xh[..., None])[:, :3, 0], rtol=0, atol=1e-14)
    eta = tangents(0.4, n=5, seed=4)
    expected = T1 @ torch.linalg.matrix_exp(se3.hat(eta))
    torch.testing.assert_close(se3.to_matrix(*se3.retract(R1, p1, eta)), expected, rtol=0, atol=1e-14)
    # Adjoint: hat(Ad_g xi) = T hat(xi) T^{-1}.
    lhs = se3.hat((se3.adjoint(R1, p1) @ eta[..., None])[..., 0])
    torch.testing.assert_close(lhs, T1 @ se3.hat(eta) @ torch.linalg.inv(T1), rtol=0, atol=1e-14)
    Ri, pi_ = se3.identity((5,))
    assert torch.equal(se3.to_matrix(Ri, pi_), torch.eye(4, dtype=F64).expand(5, 4, 4))


# ----------------------------------------------------------------------------- derivatives
@theta_param
def test_exp_gradcheck(theta):
    xi = tangents(theta, n=2).requires_grad_()
    assert gradcheck(se3.exp, (xi,))
    assert gradgradcheck(se3.exp, (xi,))


@theta_param
def test_V_inverse_gradcheck(theta):
    w = tangents(theta, n=2)[:, :3].requires_grad_()
    assert gradcheck(se3.V_inverse, (w,))
    assert gradgradcheck(se3.V_inverse, (w,))


@theta_param
def test_log_gradcheck(theta):
    xi = tangents(theta, n=2)
    J = jacobian(lambda u: se3.log(*se3.exp(u)), xi[0])
    torch.testing.assert_close(J, torch.eye(6, dtype=F64), rtol=0, atol=1e-12)
    R, p = se3.exp(xi)
    eps = 1e-9 if theta > 3 else 1e-6  # see test_lie_so3.test_log_gradcheck
    inputs = (R.requires_grad_(), p.requires_grad_())
    assert gradcheck(se3.log, inputs, eps=eps, atol=1e-6)
    assert gradgradcheck(se3.log, inputs, eps=eps, atol=1e-5)
