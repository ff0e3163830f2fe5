"""Single rigid-body scenes of the paper's experiments 1-3 (SO(3) and SE(3)), simulated from the
continuous equations (`physics.py`).

Config fields (conf/dataset/*.yaml, checked by `scene_common.check_config`): name, h, n_trajectories,
steps (generated length N), train_steps, rollout_steps, test_fraction, n_test (null or int), seed,
physics {J (diag), m, rho, g, D (diag, length 3 or 6)}, initial {scene specific}, solver {method, rtol,
atol}. Each generator takes such a config (a `DatasetConfig` or plain dict) and returns a `Dataset`; the
registry `scenes.SCENES` maps scene names to them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .hdf5 import Dataset
from .physics import RigidBodySE3, RigidBodySO3, Simulation, simulate_se3, simulate_so3
from .scene_common import (
    check_config,
    dataset_params,
    haar_rotations,
    make_split,
    rigid_physics,
    rngs,
    sample_times,
    section,
    simulation_info,
    to_dict,
    uniform_ball,
)


def _assemble(c: dict, sim: Simulation, body, kinds: list[str], split_seed, scene_params: dict) -> Dataset:
    T = sim.R.shape[0]
    R = sim.R[:, :, None]
    if sim.p is not None:
        assert sim.v is not None  # an SE(3) simulation has both positions and linear velocities
        p, v = sim.p[:, :, None], sim.v[:, :, None]
        tau_ext, f_ext = body.external_wrench(sim.R, sim.p, sim.w, sim.v)
        energy = body.energy(sim.R, sim.p, sim.w, sim.v)
        f_ext = f_ext[:, :, None]
    else:
        p = np.zeros(sim.R.shape[:2] + (0, 3))
        v, f_ext = p.copy(), p.copy()
        tau_ext = body.external_torque(sim.R, sim.w)
        energy = body.energy(sim.R, sim.w)
    return Dataset(
        R=R,
        p=p,
        h=float(c["h"]),
        scene=c["name"],
        body_names=["body"],
        body_kinds=kinds,
        params=dataset_params(c, physics=scene_params, simulation=simulation_info(sim)),
        seed=int(c["seed"]),
        split=make_split(T, float(c["test_fraction"]), c["n_test"], split_seed),
        extras={"omega": sim.w[:, :, None], "v": v, "tau_ext": tau_ext[:, :, None], "f_ext": f_ext, "energy": energy},
        t=sim.t,
    )


def heavy_so3(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 1: heavy rigid body on SO(3) with damping; R0 = I, w0 = omega_scale * U(ball(omega_radius))."""
    c = check_config(to_dict(cfg))
    ph = rigid_physics(c, 3)
    ini = section(c, "initial", ("omega_scale", "omega_radius"), ("omega_scale", "omega_radius"))
    rng, split_seed = rngs(c["seed"])
    T = int(c["n_trajectories"])
    w0 = float(ini["omega_scale"]) * uniform_ball(rng, T, float(ini["omega_radius"]))
    R0 = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    body = RigidBodySO3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_so3(body, R0, w0, sample_times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["so3"], split_seed, ph)


def free_rigid_body(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 2: rigid body on SO(3) (g = 0 by default) with damping; Haar R0, w0 ~ N(0, omega_std^2 I)."""
    c = check_config(to_dict(cfg))
    ph = rigid_physics(c, 3)
    ini = section(c, "initial", ("omega_std",), ("omega_std",))
    rng, split_seed = rngs(c["seed"])
    T = int(c["n_trajectories"])
    R0 = haar_rotations(rng, T)
    w0 = float(ini["omega_std"]) * rng.standard_normal((T, 3))
    body = RigidBodySO3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_so3(body, R0, w0, sample_times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["so3"], split_seed, ph)


def heavy_se3(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 3: rigid body on SE(3) in gravity with damping on (w, v); Haar R0, Gaussian p0, w0, v0."""
    c = check_config(to_dict(cfg))
    ph = rigid_physics(c, 6)
    ini = section(c, "initial", ("p_std", "omega_std", "v_std"), ("p_std", "omega_std", "v_std"))
    rng, split_seed = rngs(c["seed"])
    T = int(c["n_trajectories"])
    R0 = haar_rotations(rng, T)
    p0 = float(ini["p_std"]) * rng.standard_normal((T, 3))
    w0 = float(ini["omega_std"]) * rng.standard_normal((T, 3))
    v0 = float(ini["v_std"]) * rng.standard_normal((T, 3))
    body = RigidBodySE3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"])
    sim = simulate_se3(body, R0, p0, w0, v0, sample_times(c), c["solver"], progress)
    return _assemble(c, sim, body, ["se3"], split_seed, ph)


__all__ = ["heavy_so3", "free_rigid_body", "heavy_se3"]
