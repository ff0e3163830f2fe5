"""The zero-parameter references (`solvers.one_step`): constant acceleration is exact on a rotation with
constant angular acceleration about a fixed axis (and quadratic positions), constant velocity (SE(3) and
Euclidean) on uniform motion; every evaluation has a row for each, and a model is said to beat guessing
(`beats_references`) only when it beats the best of them over the same samples."""

from __future__ import annotations

import numpy as np
import torch

from helpers import write_model_rollout
from liedfl_cli.commands.evaluate import run_eval_from_objects
from liedfl_cli.config.typed import EvalConfig, RunConfig
from liedfl_cli.data.hdf5 import Dataset
from liedfl_cli.lie import Pose, ProductGroup, so3
from liedfl_cli.solvers.one_step import (
    constant_acceleration_one_step,
    constant_acceleration_rollout,
    constant_velocity_one_step,
    constant_velocity_rollout,
    euclidean_velocity_one_step,
    euclidean_velocity_rollout,
)

CFG = RunConfig("eval", eval=EvalConfig(plots=False))
N = 30


def _accelerating(T: int = 3, n: int = N, n_se3: int = 1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R0 exp(theta_k a) about a fixed axis a with theta_k = w k + alpha k^2 / 2 (constant
    angular acceleration), positions p0 + v k + c k^2 / 2: R (T, n+1, B, 3, 3), p (T, n+1, n_se3, 3)."""
    rng = np.random.default_rng(seed)
    B = n_se3 + 1
    k = np.arange(n + 1, dtype=float)
    axis = rng.standard_normal((T, 1, B, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    w, alpha = rng.uniform(0.05, 0.1, (T, 1, B, 1)), rng.uniform(-0.004, 0.004, (T, 1, B, 1))
    theta = w * k[None, :, None, None] + 0.5 * alpha * k[None, :, None, None] ** 2
    R0 = so3.exp(torch.from_numpy(rng.standard_normal((T, 1, B, 3))))
    R = (R0 @ so3.exp(torch.from_numpy(theta * axis))).numpy()
    p0, v, c = (rng.standard_normal((T, 1, n_se3, 3)) for _ in range(3))
    kk = k[None, :, None, None]
    p = p0 + v * kk + 0.01 * c * kk**2
    return R, p


def _uniform(T: int = 3, n: int = N, n_se3: int = 1, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R0 exp(k w) (constant body angular velocity), positions p0 + k v."""
    rng = np.random.default_rng(seed)
    B = n_se3 + 1
    k = np.arange(n + 1, dtype=float)[None, :, None, None]
    w = rng.uniform(-0.1, 0.1, (T, 1, B, 3))
    R0 = so3.exp(torch.from_numpy(rng.standard_normal((T, 1, B, 3))))
    R = (R0 @ so3.exp(torch.from_numpy(k * w))).numpy()
    p = rng.standard_normal((T, 1, n_se3, 3)) + k * rng.standard_normal((T, 1, n_se3, 3))
    return R, p


def _pose(R, p) -> Pose:
    return Pose(torch.from_numpy(R), torch.from_numpy(p))


def _dataset(R, p) -> Dataset:
    n_se3 = p.shape[-2]
    return Dataset(
        R=R,
        p=p,
        h=0.1,
        scene="free_rigid_body",
        body_names=[f"b{i}" for i in range(R.shape[2])],
        body_kinds=["se3"] * n_se3 + ["so3"] * (R.shape[2] - n_se3),
        split={"train": [0], "test": list(range(1, R.shape[0]))},
    )


def _err(a: Pose, b: Pose) -> float:
    return max(float((a.R - b.R).abs().max()), float((a.p - b.p).abs().max()) if a.p.numel() else 0.0)


def test_constant_acceleration_is_exact_on_constant_angular_acceleration():
    R, p = _accelerating()
    truth = _pose(R, p)
    G = ProductGroup(n_se3=1, n_so3=1)
    one = constant_acceleration_one_step(G, truth)
    target = truth.index((slice(None), slice(2, None)))
    # g_2 has only two poses before it (constant velocity's guess); from g_3 on the guess is exact
    assert _err(one.index((slice(None), slice(1, None))), target.index((slice(None), slice(1, None)))) < 1e-10
    g = [truth.index((slice(None), k)) for k in range(3)]
    ro = constant_acceleration_rollout(g[0], g[1], g[2], N)
    assert ro.R.shape == truth.R.shape and _err(ro, truth) < 1e-9
    # constant velocity is not exact here: the references differ on this motion
    cv = constant_velocity_one_step(G, truth)
    assert _err(cv, target) > 1e-4
    cv_ro = constant_velocity_rollout(G, g[0], g[1], N)
    assert _err(cv_ro, truth) > 1e-2


def test_constant_velocity_is_exact_on_uniform_motion():
    R, p = _uniform()
    truth = _pose(R, p)
    G = ProductGroup(n_se3=1, n_so3=1)
    g0, g1 = truth.index((slice(None), 0)), truth.index((slice(None), 1))
    # Euclidean positions: exact for p0 + k v whatever the rotation does
    assert _err(euclidean_velocity_rollout(g0, g1, N), truth) < 1e-10
    target = truth.index((slice(None), slice(2, None)))
    assert _err(euclidean_velocity_one_step(G, truth), target) < 1e-10
    # constant acceleration (from g_3 on: g_2 gets the SE(3) constant-velocity guess) is exact here too
    later = (slice(None), slice(1, None))
    assert _err(constant_acceleration_one_step(G, truth).index(later), target.index(later)) < 1e-10
    # the SE(3) guess is exact for the rotations (same body-frame increment) but not for positions that
    # move in a straight line while the body spins: that is the case for the Euclidean reference
    se3 = constant_velocity_rollout(G, g0, g1, N)
    assert float((se3.R - truth.R).abs().max()) < 1e-10
    assert float((se3.p - truth.p).abs().max()) > 1e-2


def test_every_evaluation_has_both_references_and_ca_wins_on_accelerating_data(tmp_path):
    R, p = _accelerating(T=3)
    ds = _dataset(R, p)
    idx = ds.split["test"]
    # a "model" that is constant velocity itself, written as a rollout from the same first pair
    G = ProductGroup(n_se3=1, n_so3=1)
    truth = _pose(R[idx], p[idx])
    cv = constant_velocity_rollout(G, truth.index((slice(None), 0)), truth.index((slice(None), 1)), N)
    write_model_rollout(tmp_path / "rollout.h5", ds, idx, cv.R.numpy(), cv.p.numpy())
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    assert {"constant_velocity", "constant_acceleration", "constant_velocity_euclidean"} <= set(rows)
    ca = rows["constant_acceleration"]
    assert (
        ca["geodesic_error_mean"] < 1e-9
        and ca["one_step_rot_error_mean"] < 0.1 * rows["constant_velocity"]["one_step_rot_error_mean"]
    )
    model = rows["model"]
    assert abs(model["rollout_vs_cv"] - 1.0) < 1e-9  # the model is constant velocity
    assert model["best_reference"] == "constant_acceleration"
    assert model["rollout_vs_best"] > 10 and model["beats_references"] is False
    text = (tmp_path / "eval.md").read_text()
    assert "constant acceleration" in text and "beats_references" in text


def test_uniform_motion_makes_euclidean_velocity_the_best_position_guess(tmp_path):
    R, p = _uniform(T=3)
    ds = _dataset(R, p)
    idx = ds.split["test"]
    ent_R, ent_p = R[idx], p[idx].copy()
    ent_p[:, 2:] += 1e-3  # a model off by a constant 1e-3 in every predicted position
    write_model_rollout(tmp_path / "rollout.h5", ds, idx, ent_R.copy(), ent_p)
    rows = {r["model"]: r for r in run_eval_from_objects(CFG, ds, tmp_path)}
    assert rows["constant_velocity_euclidean"]["position_error_mean"] < 1e-10
    assert rows["constant_velocity"]["position_error_mean"] > 1e-2
    # exact references make any position error infinitely worse than guessing: no "better than guessing"
    assert rows["model"]["beats_references"] is False


def test_validation_pass_measures_against_constant_acceleration():
    from liedfl_cli.commands.validation import Validator, constant_acceleration_guesses, format_pass
    from liedfl_cli.solvers.options import SolverOptions

    R, p = _accelerating(T=4, n=12)
    truth = _pose(R, p)
    G = ProductGroup(n_se3=1, n_so3=1)
    v = Validator(G, truth, SolverOptions(), horizon=4, every=1)
    # exact except at k = 1 (constant velocity's guess there): far below constant velocity's error
    assert v._ca is not None and v._ca < 0.2 * v.cv_error
    ca = constant_acceleration_guesses(G, truth, 10_000)
    assert ca.R.shape[0] == 4 * 11
    exact = ca.R.reshape(4, 11, *ca.R.shape[2:])[:, 1:] - torch.from_numpy(R[:, 3:])
    assert float(exact.abs().max()) < 1e-10

    class Repeat:  # a "model" that is constant velocity: worse than the best reference
        training = False

        def eval(self):
            return self

        def train(self, mode=True):
            return self

        def rollout(self, g0, g1, steps, opts):
            from types import SimpleNamespace

            pose = constant_velocity_rollout(G, g0, g1, steps)
            return SimpleNamespace(pose=pose, converged=torch.ones(pose.R.shape[0], max(steps - 1, 0), dtype=bool))

    row = v.measure(Repeat())
    assert abs(row["val_one_step_vs_cv"] - 1.0) < 1e-9
    assert row["val_one_step_vs_ca"] > 5 and row["val_one_step_vs_best"] == row["val_one_step_vs_ca"]
    assert "x CA" in format_pass(row)


def test_mocap_one_step_table_has_every_reference_and_the_ratio_to_the_best():
    from types import SimpleNamespace

    from liedfl_cli.evaluation.mocap import ONE_STEP_REFERENCES, best_reference_ratios, one_step_errors

    R, p = _accelerating(T=2, n=20)
    G = ProductGroup(n_se3=1, n_so3=1)
    truth = _pose(R, p)
    cv = constant_velocity_one_step(G, truth)  # stored "model" predictions: constant velocity itself
    stored = SimpleNamespace(R=cv.R.numpy(), pose=cv, converged=np.ones(cv.R.shape[:2], bool))
    out = one_step_errors(None, R, p, None, stored=stored, group=G)
    assert out is not None and set(ONE_STEP_REFERENCES) <= set(out)
    for k in ("root_rot", "joint_rot", "root_pos"):
        assert np.all(out["const_acceleration"][k] < 0.2 * out["const_velocity"][k]), k
        np.testing.assert_allclose(out["model"][k], out["const_velocity"][k], rtol=1e-12)
    ratios = best_reference_ratios(out)
    assert ratios is not None and all(r > 5 for k in ratios for r in ratios[k])
