"""Empirical convergence orders of the true-parameter scheme against tight-tolerance solutions:
residual O(h^3), rollout O(h^2) at fixed final time (catches sign and convention errors)."""

import pytest

from consistency import residual_order, rollout_order


@pytest.mark.parametrize("kind", ["so3", "se3"])
def test_residual_is_third_order(kind):
    out = residual_order(kind, hs=(0.08, 0.04, 0.02), final_time=0.6)
    assert 2.8 < out["order"] < 3.2, out
    ratios = [a / b for a, b in zip(out["max_residual"], out["max_residual"][1:])]
    assert all(6.5 < r < 9.5 for r in ratios), ratios  # halving h divides the residual by ~8


@pytest.mark.parametrize("kind", ["so3", "se3"])
def test_rollout_is_second_order_and_stays_on_group(kind):
    out = rollout_order(kind, hs=(0.04, 0.02, 0.01), final_time=0.6)
    assert 1.8 < out["order"] < 2.2, out
    assert out["max_orth_drift"] < 1e-13


@pytest.mark.parametrize("change", [{"g": -9.81}, {"D": [0.0, 0.0, 0.0]}, {"J": [1.362, 1.521, 1.211]}])
def test_wrong_physics_is_caught(change):
    """A flipped gravity sign, a missing damping force or swapped inertia axes leave a residual
    far above the O(h^3) level of the true scheme."""
    import consistency
    from liedfl_cli.lie import SO3
    from liedfl_cli.models.true_scheme import physics_model

    h = 0.02
    traj = consistency.exact("so3", h, 0.4)
    idx = lambda a, b: traj.index((slice(None), slice(a, b)))
    good = physics_model(SO3, h, consistency.PHYSICS["so3"])
    bad = physics_model(SO3, h, {**consistency.PHYSICS["so3"], **change})
    r_good = good.residual(idx(0, -2), idx(1, -1), idx(2, None)).abs().max()
    r_bad = bad.residual(idx(0, -2), idx(1, -1), idx(2, None)).abs().max()
    assert r_bad > 20 * r_good
