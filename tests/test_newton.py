"""Batched damped Newton and the rollout loop: convergence, flags, hard cases."""

import torch

from liedfl_cli.lie import SE3, SO3, Pose, so3
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers import newton
from liedfl_cli.solvers.newton import NewtonProblem, jacobian, solve
from liedfl_cli.solvers.options import SolverOptions

PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81}


def _solve_euclidean(f, x0, opts):
    return solve(NewtonProblem.euclidean(f, x0), opts)


def cubic(c):
    return lambda x: x**3 + x - c


def test_jacobian_matches_analytic():
    x = torch.randn(5, 3, dtype=torch.float64)
    J = jacobian(cubic(torch.zeros(5, 3, dtype=torch.float64)), x)
    torch.testing.assert_close(J, torch.diag_embed(3 * x**2 + 1))


def test_newton_solves_each_row_and_counts_iterations():
    c = torch.tensor([[0.0, 1.0], [10.0, -3.0], [1e-3, 2.0]], dtype=torch.float64)
    sol = _solve_euclidean(cubic(c), torch.zeros_like(c), SolverOptions(tol=1e-12, max_iter=50))
    assert sol.converged.all()
    assert (cubic(c)(sol.xi).abs() < 1e-10).all()
    assert sol.iterations.shape == (3,) and (sol.iterations >= 1).all()
    assert sol.iterations[0] < sol.iterations[1]  # the far root needs more steps


def test_newton_reports_non_convergence():
    c = torch.tensor([[100.0], [0.5]], dtype=torch.float64)
    sol = _solve_euclidean(cubic(c), torch.zeros_like(c), SolverOptions(tol=1e-14, max_iter=2))
    assert not sol.converged[0]
    assert sol.iterations[0] == 2


def test_newton_keeps_going_when_a_row_has_no_root():
    f = lambda x: torch.cat((x[:1] ** 2 + 1.0, x[1:] - 2.0))  # row 0: no real root
    sol = _solve_euclidean(f, torch.ones(2, 1, dtype=torch.float64), SolverOptions(tol=1e-10, max_iter=10))
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


# ----------------------------------------------------------------------------- the rounding floor
FREE = {**PHYS, "g": 0.0, "D": [0.05] * 3}  # the free_rigid_body scene's physics (Exp 2)


def _rollouts(model, g0, g1, steps, opts):
    """(fused, reference) rollouts of the same model."""
    ref = model.with_path("reference").rollout(g0, g1, steps, opts)
    return model.rollout(g0, g1, steps, opts), ref


def _se3_start(n=2, seed=1):
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, 1, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, 1, 3, generator=gen, dtype=torch.float64),
    )
    return g0, SE3.retract(g0, 0.1 * torch.randn(n, 6, generator=gen, dtype=torch.float64))


def test_a_tolerance_below_rounding_converges_at_the_rounding_floor():
    """A Newton step cannot get below the rounding of its unknown: with tol = 0 (or any tol under
    16 eps) a free-body rollout converged on about 1/3 (fused) or none (reference) of its steps
    before the floor; now every step converges, on both paths, SO(3) and SE(3)."""
    cases = [
        (physics_model(SO3, 0.1, FREE), _so3_start(2)),
        (physics_model(SE3, 0.1, {**FREE, "D": [0.05] * 6}), _se3_start()),
    ]
    for model, (g0, g1) in cases:
        for tol in (0.0, 1e-17):
            # 20 steps: without the floor, 13-28 of 15 steps x 2 trajectories already fail (either path)
            for ro in _rollouts(model, g0, g1, 20, SolverOptions(tol=tol)):
                assert ro.n_failed == 0, (model.G.name, tol, ro.n_failed)
                assert float(ro.iterations.double().mean()) < 5  # 3.5-3.7 here: a step or two past 1e-12


def test_the_floor_leaves_flags_and_iteration_counts_as_they_were(monkeypatch):
    """Wherever tol is above the rounding floor (the default 1e-5, and 1e-12) the convergence flags,
    iteration counts and poses are those of the plain `step <= tol` test, bit for bit."""
    model = physics_model(SO3, 0.1, FREE)
    so3_start = _so3_start(3)
    se3 = physics_model(SE3, 0.1, {**FREE, "g": 9.81, "D": [0.05] * 6})
    for tol in (SolverOptions().tol, 1e-12):
        for m, (g0, g1) in ((model, so3_start), (se3, _se3_start(3))):
            opts = SolverOptions(tol=tol)
            now = _rollouts(m, g0, g1, 20, opts)
            with monkeypatch.context() as mp:
                mp.setattr(newton, "ROUNDING_ULPS", 0.0)
                plain = _rollouts(m, g0, g1, 20, opts)
            for a, b in zip(now, plain):
                assert torch.equal(a.converged, b.converged) and torch.equal(a.iterations, b.iterations)
                assert torch.equal(a.pose.R, b.pose.R) and torch.equal(a.pose.p, b.pose.p)


def test_step_tolerance_is_relative_to_the_unknown():
    eps = torch.finfo(torch.float64).eps
    floor = newton.ROUNDING_ULPS * eps
    rot = Pose(torch.eye(3, dtype=torch.float64).expand(4, 1, 3, 3), torch.zeros(4, 0, 3, dtype=torch.float64))
    assert newton.step_tolerance(rot, 1e-5) == 1e-5 and newton.step_tolerance(rot, 0.0) == floor
    x = torch.tensor([[0.5, -2.0], [1e6, 3.0]], dtype=torch.float64)
    torch.testing.assert_close(newton.step_tolerance(x, 0.0), torch.tensor([floor, 1e6 * floor], dtype=torch.float64))
    torch.testing.assert_close(
        newton.step_tolerance(x, 1e-5), torch.tensor([1e-5, 1e-5], dtype=torch.float64), rtol=0, atol=0
    )
    se3 = Pose(rot.R, torch.tensor([[[1e3, 0.0, 0.0]]] * 4, dtype=torch.float64))
    torch.testing.assert_close(newton.step_tolerance(se3, 1e-14), torch.full((4,), 1e3 * floor, dtype=torch.float64))


# ----------------------------------------------------------------------------- chord steps
def _counted(f):
    """NewtonProblem.euclidean(f, .) whose Jacobian calls (calls[0]) and restrictions (calls[1]) are
    counted."""
    calls = [0, 0]

    def problem(x0, rows=None):
        fr = f if rows is None else (lambda x: f(x, rows))
        p = NewtonProblem.euclidean(fr, x0)
        jac = p.jac

        def counting(x):
            calls[0] += 1
            return jac(x)

        p.jac = counting

        def restrict(r):
            calls[1] += 1
            return problem(p.x0[r], r if rows is None else rows[r])

        p.restrict = restrict
        return p

    return problem, calls


def test_chord_finds_newtons_root_with_one_jacobian_per_solve():
    c = torch.tensor([[0.5, 1.0], [2.0, -3.0], [1e-3, 0.8]], dtype=torch.float64)
    f = cubic(c)
    newton_sol = _solve_euclidean(f, torch.zeros_like(c), SolverOptions(tol=1e-13, max_iter=50))
    calls = [0]
    p = NewtonProblem.euclidean(f, torch.zeros_like(c))
    jac = p.jac
    p.jac = lambda x: calls.__setitem__(0, calls[0] + 1) or jac(x)
    opts = SolverOptions(tol=1e-13, max_iter=200, method="chord")
    sol = solve(p, opts)
    assert sol.converged.all() and calls[0] == 1
    torch.testing.assert_close(sol.xi, newton_sol.xi, rtol=0, atol=1e-12)
    assert (sol.iterations >= newton_sol.iterations).all() and (sol.iterations > newton_sol.iterations).any()
    # the reference loop takes the same chord steps: same iterates, flags and counts
    ref = solve(NewtonProblem.euclidean(f, torch.zeros_like(c)), opts, reference=True)
    torch.testing.assert_close(ref.xi, sol.xi, rtol=0, atol=1e-14)
    assert torch.equal(ref.iterations, sol.iterations) and torch.equal(ref.converged, sol.converged)


def test_chord_rows_iterated_apart_keep_their_own_jacobian():
    """At 64+ rows the slow rows continue in a restricted problem with their rows of the chord
    Jacobian (not a new one at their current iterate): the result equals the reference loop's."""
    T = 80
    c = torch.full((T, 1), 0.3, dtype=torch.float64)
    c[60:] = torch.linspace(1.0, 2.0, 20, dtype=torch.float64)[:, None]  # far roots: many chord steps

    def f(x, rows=None):
        cc = c if rows is None else c[rows]
        return x + 0.05 * x**3 - cc

    problem, calls = _counted(f)
    opts = SolverOptions(tol=1e-12, max_iter=200, method="chord")
    sol = solve(problem(torch.zeros(T, 1, dtype=torch.float64)), opts)
    assert sol.converged.all() and calls[0] == 1  # restricted rows reused their factor
    assert int(sol.iterations[60:].min()) > int(sol.iterations[:60].max())
    assert calls[1] >= 1  # the slow rows were iterated in a restricted problem
    ref = solve(NewtonProblem.euclidean(f, torch.zeros(T, 1, dtype=torch.float64)), opts, reference=True)
    torch.testing.assert_close(sol.xi, ref.xi, rtol=0, atol=1e-13)
    assert torch.equal(sol.iterations, ref.iterations)


def test_a_singular_chord_jacobian_is_flagged_not_propagated():
    """x^2 - c from x = 0: the chord Jacobian is singular, the least-squares step is zero, the row never
    converges and stays finite; the other row converges."""
    c = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    x0 = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    f = lambda x: x**2 - c
    opts = SolverOptions(tol=1e-10, max_iter=60, method="chord")
    sol = _solve_euclidean(f, x0, opts)
    assert not sol.converged[0] and sol.converged[1]
    assert torch.isfinite(sol.xi).all()
    torch.testing.assert_close(sol.xi[1], torch.tensor([2.0**0.5], dtype=torch.float64), rtol=0, atol=1e-9)
    ref = solve(NewtonProblem.euclidean(f, x0), opts, reference=True)
    assert torch.equal(ref.converged, sol.converged)
