"""Batched damped Newton and the rollout loop: convergence, flags, hard cases."""

import torch

from liedfl_cli.lie import SE3, SO3, Pose, so3
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.newton import damped_newton, jacobian
from liedfl_cli.solvers.options import SolverOptions

PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81}


def cubic(c):
    return lambda x: x**3 + x - c


def test_jacobian_matches_analytic():
    x = torch.randn(5, 3, dtype=torch.float64)
    J = jacobian(cubic(torch.zeros(5, 3, dtype=torch.float64)), x)
    torch.testing.assert_close(J, torch.diag_embed(3 * x**2 + 1))


def test_newton_solves_each_row_and_counts_iterations():
    c = torch.tensor([[0.0, 1.0], [10.0, -3.0], [1e-3, 2.0]], dtype=torch.float64)
    sol = damped_newton(cubic(c), torch.zeros_like(c), SolverOptions(tol=1e-12, max_iter=50))
    assert sol.converged.all()
    assert (cubic(c)(sol.xi).abs() < 1e-10).all()
    assert sol.iterations.shape == (3,) and (sol.iterations >= 1).all()
    assert sol.iterations[0] < sol.iterations[1]  # the far root needs more steps


def test_newton_reports_non_convergence():
    c = torch.tensor([[100.0], [0.5]], dtype=torch.float64)
    sol = damped_newton(cubic(c), torch.zeros_like(c), SolverOptions(tol=1e-14, max_iter=2))
    assert not sol.converged[0]
    assert sol.iterations[0] == 2


def test_newton_keeps_going_when_a_row_has_no_root():
    f = lambda x: torch.cat((x[:1] ** 2 + 1.0, x[1:] - 2.0))  # row 0: no real root
    sol = damped_newton(f, torch.ones(2, 1, dtype=torch.float64), SolverOptions(tol=1e-10, max_iter=10))
    assert not sol.converged[0] and sol.converged[1]
    assert torch.isfinite(sol.xi).all()
    torch.testing.assert_close(sol.xi[1], torch.tensor([2.0], dtype=torch.float64))


def _so3_start(n=3, seed=0):
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, 1, 3, generator=gen, dtype=torch.float64)), torch.zeros(n, 0, 3, dtype=torch.float64)
    )
    g1 = SO3.retract(g0, 0.1 * torch.randn(n, 3, generator=gen, dtype=torch.float64))
    return g0, g1


def test_rollout_solves_residual_and_stays_on_so3_over_long_horizon():
    model = physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.0, 0.0, 0.0]})
    g0, g1 = _so3_start()
    ro = model.rollout(g0, g1, 1000, SolverOptions(tol=1e-12, max_iter=20))
    assert ro.converged.all() and ro.n_failed == 0 and ro.first_failure() is None
    assert so3.orthogonality_error(ro.pose.R).max() < 1e-12
    assert (torch.linalg.det(ro.pose.R) - 1).abs().max() < 1e-12
    k = 500
    r = model.residual(
        ro.pose.index((slice(None), k - 1)), ro.pose.index((slice(None), k)), ro.pose.index((slice(None), k + 1))
    )
    assert r.abs().max() < 1e-10
    # free, undamped body: spatial angular momentum R J w is conserved by the variational scheme
    J = model.inertia.J()[0]
    R = ro.pose.R[:, :, 0]
    W = R[:, :-1].transpose(-1, -2) @ R[:, 1:]
    w = so3.log(W) / 0.1
    pi = (R[:, :-1] @ (J @ w[..., None]))[..., 0]
    assert (pi[:, -1] - pi[:, 0]).abs().max() / pi[:, 0].abs().max() < 5e-2  # midpoint-level approximation


def test_rollout_flags_non_converged_steps():
    model = physics_model(SO3, 0.1, {**PHYS, "D": [0.1, 0.1, 0.1]})
    g0, g1 = _so3_start()
    ro = model.rollout(g0, g1, 20, SolverOptions(tol=1e-30, max_iter=1))
    assert ro.n_failed == 3 * 19
    assert ro.first_failure() == 2  # the first predicted pose, g_2
    assert not ro.converged.any()


def test_se3_rollout_stays_on_group():
    model = physics_model(SE3, 0.05, {**PHYS, "D": [0.1, 0.1, 0.1, 0, 0, 0]})
    gen = torch.Generator().manual_seed(3)
    g0 = Pose(
        so3.exp(torch.randn(4, 1, 3, generator=gen, dtype=torch.float64)),
        torch.randn(4, 1, 3, generator=gen, dtype=torch.float64),
    )
    g1 = SE3.retract(g0, 0.05 * torch.randn(4, 6, generator=gen, dtype=torch.float64))
    ro = model.rollout(g0, g1, 200)
    assert ro.converged.all()
    assert so3.orthogonality_error(ro.pose.R).max() < 1e-12
