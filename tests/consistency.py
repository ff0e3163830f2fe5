"""Consistency checks of the discrete scheme with the true parameters (catch sign/convention errors).

residual_order: max |residual| of the true-parameter scheme on exact trajectories sampled at h,
    h/2, h/4 shrinks like h^3 (the DEL residual is h x a local error of order h^2).
rollout_order: error at a fixed final time of the true-parameter rollout vs the exact solution
    shrinks like h^2 (the scheme is a second-order variational integrator).
"""

from __future__ import annotations

import numpy as np
import torch

from liedfl_cli.data.physics import RigidBodySE3, RigidBodySO3, simulate_se3, simulate_so3
from liedfl_cli.lie import SE3, SO3, Pose, so3
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.options import SolverOptions

PHYSICS = {
    "so3": {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1, 0.1, 0.1]},
    "se3": {
        "J": [1.521, 1.362, 1.211],
        "m": 0.5,
        "rho": [0.0, 0.5, 1.0],
        "g": 9.81,
        "D": [0.1, 0.1, 0.1, 0.05, 0.05, 0.05],
    },
    # SE(3) with rotational damping only: the translational velocity estimate (I - h/2 hat(w)) z / h is not
    # time-symmetric, so translational damping caps a composition at order 3 (docs/substeps.md)
    "se3_rotational_damping": {
        "J": [1.521, 1.362, 1.211],
        "m": 0.5,
        "rho": [0.0, 0.5, 1.0],
        "g": 9.81,
        "D": [0.1, 0.1, 0.1, 0.0, 0.0, 0.0],
    },
}


def exact(kind: str, h: float, final_time: float, n_traj: int = 4, seed: int = 0) -> Pose:
    """Tight-tolerance (DOP853, rtol 1e-13) samples at spacing h: Pose (T, N+1, ...)."""
    rng = np.random.default_rng(seed)
    ph = PHYSICS[kind]
    t = np.arange(round(final_time / h) + 1) * h
    w0 = rng.normal(size=(n_traj, 3))
    R0 = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n_traj)])
    R0 = R0 * np.sign(np.linalg.det(R0))[:, None, None]
    solver = {"method": "DOP853", "rtol": 1e-13, "atol": 1e-13}
    if kind == "so3":
        body = RigidBodySO3(J=np.diag(ph["J"]), m=ph["m"], rho=np.array(ph["rho"]), g=ph["g"], D=np.diag(ph["D"]))
        sim = simulate_so3(body, R0, w0, t, solver)
        return Pose(torch.from_numpy(sim.R)[:, :, None], torch.zeros(n_traj, len(t), 0, 3, dtype=torch.float64))
    body = RigidBodySE3(J=np.diag(ph["J"]), m=ph["m"], rho=np.array(ph["rho"]), g=ph["g"], D=np.diag(ph["D"]))
    sim = simulate_se3(body, R0, rng.normal(size=(n_traj, 3)), w0, rng.normal(size=(n_traj, 3)), t, solver)
    return Pose(torch.from_numpy(sim.R)[:, :, None], torch.from_numpy(sim.p)[:, :, None])


def _model(kind: str, h: float, substeps: int = 1, order: int = 2):
    from liedfl_cli.models.liedflnn.substeps import with_substeps

    return with_substeps(physics_model(SO3 if kind == "so3" else SE3, h, PHYSICS[kind]), substeps, order)


def residual_order(kind: str, hs=(0.08, 0.04, 0.02, 0.01), final_time: float = 0.8) -> dict:
    """Max residual per h and the fitted order (slope of log residual vs log h)."""
    res = []
    for h in hs:
        traj = exact(kind, h, final_time)
        model = _model(kind, h)
        r = model.residual(
            traj.index((slice(None), slice(0, -2))),
            traj.index((slice(None), slice(1, -1))),
            traj.index((slice(None), slice(2, None))),
        )
        res.append(float(r.abs().max()))
    slope = np.polyfit(np.log(hs), np.log(res), 1)[0]
    return {"h": list(hs), "max_residual": res, "order": float(slope)}


def rollout_order(
    kind: str, hs=(0.04, 0.02, 0.01, 0.005), final_time: float = 2.0, substeps: int = 1, order: int = 2
) -> dict:
    """Rotation (and position) error at t = final_time per h, started from exact (g0, g1), of the scheme
    with `substeps` sub-steps of order `order` (models/liedflnn/substeps.py; 1, 2: the paper's)."""
    errs, drift = [], 0.0
    for h in hs:
        traj = exact(kind, h, final_time)
        model = _model(kind, h, substeps, order)
        steps = traj.R.shape[1] - 1
        opts = SolverOptions(tol=1e-13, max_iter=20)
        ro = model.rollout(traj.index((slice(None), 0)), traj.index((slice(None), 1)), steps, opts)
        e = torch.linalg.matrix_norm(ro.pose.R[:, -1] - traj.R[:, -1]).max()
        if traj.p.shape[-2]:
            e = torch.maximum(e, torch.linalg.vector_norm(ro.pose.p[:, -1] - traj.p[:, -1], dim=-1).max())
        errs.append(float(e))
        drift = max(drift, float(so3.orthogonality_error(ro.pose.R).max()))
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    return {"h": list(hs), "final_error": errs, "order": float(slope), "max_orth_drift": drift}
