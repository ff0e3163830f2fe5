"""Multibody and controlled scenes (two bodies on SE(3) x SO(3), PD-controlled heavy body).

Listed in the registry `scenes.SCENES`. Besides the common dataset fields
(scene_common.REQUIRED_KEYS) these scenes read one extra block:

two_body   (conf/dataset/two_body.yaml)  SE(3) x SO(3): body 1 a free rigid body in gravity,
    body 2 a heavy body on a pivot at the world origin, coupled by an interaction potential.
    physics: J (2 lists of 3 diagonal entries; body 1 about its centre of mass, body 2 about the
             pivot), m (2), rho (2 x 3, body frames), g, D (9 = dim, diagonal on (w1, v1, w2))
    interaction: {kind, mu, r1, r2, moment1, moment2} (mechanics.potentials.InteractionPotential;
             r1/r2 are attachment points, moment1/moment2 the dipole moments, all body frame)
    initial: R_i0 = exp(rot_std N(0, I)); body 1 starts at the spring's rest point shifted by
             `offset` (world) plus p_std N(0, I), i.e. p1 = R2 r2 - R1 r1 + offset + noise;
             w_i ~ N(0, omega_std^2 I), v1 ~ N(0, v_std^2 I).
pd_control (conf/dataset/pd_control.yaml)  Exp 5: the heavy body of Exp 1 driven by a PD attitude
    controller tau_PD = -K_R e_R - K_w w (+ the gravity feed-forward of the paper's appendix when
    control.feedforward; Exp 5 itself uses tau = tau_cons + tau_PD, i.e. no feed-forward, the default),
    K_R = k_r Jbar I, K_w = k_w Jbar I, Jbar = mean of the 9 entries of J.
    control: {R_f (target, rotation vector), k_r, k_w, feedforward}
    initial: {R0 (rotation vector), omega0, perturb}: trajectory i >= 1 starts from
             (R0 exp(perturb N), omega0 + perturb N); with perturb = 0 every trajectory is a copy of
             the first, which is how Exp 5's "train on one trajectory, roll the same one out" is
             expressed with disjoint train/test splits.
    extras: tau_control (T, N+1, 1, 3) the true PD torque (evaluation only); tau_ext = PD + damping.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..errors import ConfigError
from ..lie import so3
from .hdf5 import Dataset
from .physics import RigidBodySO3, simulate_so3
from .physics_multibody import MultiBodySystem, simulate_multibody
from .scene_common import (
    check_config,
    dataset_params,
    make_split,
    rigid_physics,
    rngs,
    sample_times,
    section,
    simulation_info,
    to_dict,
    vector,
)

INTERACTION_KEYS = ("kind", "mu", "r1", "r2", "moment1", "moment2")
CONTROL_KEYS = ("R_f", "k_r", "k_w", "feedforward")


# --------------------------------------------------------------------------- two bodies
def two_body_physics(c: dict) -> dict:
    """Validated physics + interaction of a two_body config -> the dict stored in params["physics"]."""
    from ..mechanics.potentials import INTERACTIONS

    ph = section(c, "physics", ("J", "m", "rho", "g", "D"))
    J = np.asarray(ph["J"], dtype=np.float64)
    if J.shape != (2, 3) or (J <= 0).any():
        raise ConfigError(
            f"dataset.physics.J must be 2 lists of 3 positive diagonal entries (body 1, body 2), got {ph['J']!r}"
        )
    for i in range(2):
        a, b, cc = sorted(J[i])
        if a + b < cc:
            raise ConfigError(f"dataset.physics.J of body {i + 1} violates the triangle inequality: {J[i].tolist()}")
    m = np.asarray(ph["m"], dtype=np.float64)
    if m.shape != (2,) or (m <= 0).any():
        raise ConfigError(f"dataset.physics.m must be 2 positive masses, got {ph['m']!r}")
    rho = np.asarray(ph["rho"], dtype=np.float64)
    if rho.shape != (2, 3):
        raise ConfigError(f"dataset.physics.rho must be 2 lists of 3 numbers, got {ph['rho']!r}")
    D = np.asarray(ph["D"], dtype=np.float64)
    if D.shape != (9,) or (D < 0).any():
        raise ConfigError(f"dataset.physics.D must be 9 non-negative numbers (diagonal on w1, v1, w2), got {ph['D']!r}")
    it = section(c, "interaction", INTERACTION_KEYS)
    if it["kind"] not in INTERACTIONS:
        raise ConfigError(f"dataset.interaction.kind must be one of {list(INTERACTIONS)}, got {it['kind']!r}")
    inter = {"kind": str(it["kind"]), "mu": float(it["mu"])}
    for k in ("r1", "r2", "moment1", "moment2"):
        inter[k] = vector(it[k], 3, f"interaction.{k}")
    return {
        "J": J.tolist(),
        "m": m.tolist(),
        "rho": rho.tolist(),
        "g": float(ph["g"]),
        "D": D.tolist(),
        "interaction": inter,
        "bodies": ["se3", "so3"],
    }


def two_body_system(physics: dict) -> MultiBodySystem:
    return MultiBodySystem(
        ("se3", "so3"), physics["J"], physics["m"], physics["rho"], physics["g"], physics["D"], physics["interaction"]
    )


def two_body(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """SE(3) x SO(3): free body 1 and pivoted body 2 in gravity, coupled by an interaction potential."""
    c = check_config(to_dict(cfg))
    physics = two_body_physics(c)
    ini = section(
        c, "initial", ("rot_std", "offset", "p_std", "omega_std", "v_std"), ("rot_std", "p_std", "omega_std", "v_std")
    )
    offset = np.asarray(vector(ini["offset"], 3, "initial.offset"))
    system = two_body_system(physics)
    rng, split_seed = rngs(c["seed"])
    T = int(c["n_trajectories"])
    R0 = so3.exp(torch.from_numpy(float(ini["rot_std"]) * rng.standard_normal((T, 2, 3)))).numpy()
    r1, r2 = np.asarray(physics["interaction"]["r1"]), np.asarray(physics["interaction"]["r2"])
    X2 = R0[:, 1] @ r2
    p0 = (X2 - R0[:, 0] @ r1 + offset + float(ini["p_std"]) * rng.standard_normal((T, 3)))[:, None]
    w0 = float(ini["omega_std"]) * rng.standard_normal((T, 2, 3))
    v0 = float(ini["v_std"]) * rng.standard_normal((T, 1, 3))
    xi0 = system.G.join(torch.from_numpy(w0), torch.from_numpy(v0)).numpy()
    sim = simulate_multibody(system, R0, p0, xi0, sample_times(c), c["solver"], progress)
    assert sim.p is not None  # simulate_multibody always returns positions
    xi = sim.w
    w, v = (a.numpy() for a in system.G.split(torch.from_numpy(xi)))
    F_ext = system.external_covector(sim.R, sim.p, xi)
    tau_ext, f_ext = (a.numpy() for a in system.G.split(torch.from_numpy(F_ext)))
    return Dataset(
        R=sim.R,
        p=sim.p,
        h=float(c["h"]),
        scene=c["name"],
        body_names=["body1", "body2"],
        body_kinds=["se3", "so3"],
        params=dataset_params(c, physics=physics, simulation=simulation_info(sim)),
        seed=int(c["seed"]),
        split=make_split(T, float(c["test_fraction"]), c["n_test"], split_seed),
        extras={"omega": w, "v": v, "tau_ext": tau_ext, "f_ext": f_ext, "energy": system.energy(sim.R, sim.p, xi)},
        t=sim.t,
    )


# --------------------------------------------------------------------------- PD control (Exp 5)
def pd_gains(J_diag, k_r: float, k_w: float) -> tuple[float, float, float]:
    """(K_R, K_w, Jbar) with Jbar the mean of the 9 entries of J = diag(J_diag)."""
    J_bar = float(np.diag(np.asarray(J_diag, dtype=np.float64)).mean())
    return float(k_r) * J_bar, float(k_w) * J_bar, J_bar


def pd_torque(R: np.ndarray, w: np.ndarray, control: dict, m: float, rho, g: float) -> np.ndarray:
    """True PD torque -K_R e_R - K_w w (+ feed-forward m g rho x R^T e3), (..., 3)."""
    R_f = so3.exp(torch.as_tensor(control["R_f"], dtype=torch.float64)).numpy()
    E = np.swapaxes(R_f, -1, -2) @ R - np.swapaxes(R, -1, -2) @ R_f
    e_R = 0.5 * np.stack((E[..., 2, 1], E[..., 0, 2], E[..., 1, 0]), -1)
    tau = -control["K_R"] * e_R - control["K_w"] * w
    if control["feedforward"]:
        tau = tau + m * g * np.cross(np.asarray(rho, np.float64), R[..., 2, :])
    return tau


def pd_control(cfg, progress: Callable[[float], None] | None = None) -> Dataset:
    """Exp 5: heavy rigid body on SO(3) under PD attitude control toward R_f."""
    c = check_config(to_dict(cfg))
    ph = rigid_physics(c, 3)
    ct = section(c, "control", CONTROL_KEYS)
    if not isinstance(ct["feedforward"], bool):
        raise ConfigError(f"dataset.control.feedforward must be true or false, got {ct['feedforward']!r}")
    K_R, K_w, J_bar = pd_gains(ph["J"], float(ct["k_r"]), float(ct["k_w"]))
    control = {
        "R_f": vector(ct["R_f"], 3, "control.R_f"),
        "k_r": float(ct["k_r"]),
        "k_w": float(ct["k_w"]),
        "J_bar": J_bar,
        "K_R": K_R,
        "K_w": K_w,
        "feedforward": bool(ct["feedforward"]),
    }
    physics = dict(ph, control=control, bodies=["so3"])
    ini = section(c, "initial", ("R0", "omega0", "perturb"), ("perturb",))
    rng, split_seed = rngs(c["seed"])
    T = int(c["n_trajectories"])
    eps = float(ini["perturb"])
    dR = eps * rng.standard_normal((T, 3))
    dw = eps * rng.standard_normal((T, 3))
    dR[0], dw[0] = 0.0, 0.0  # trajectory 0 is the configured initial condition
    R0 = (
        so3.exp(torch.as_tensor(vector(ini["R0"], 3, "initial.R0"), dtype=torch.float64))
        @ so3.exp(torch.from_numpy(dR))
    ).numpy()
    w0 = np.asarray(vector(ini["omega0"], 3, "initial.omega0")) + dw

    def tau_pd(R, w):
        return pd_torque(R, w, control, ph["m"], ph["rho"], ph["g"])

    body = RigidBodySO3(J=ph["J"], m=ph["m"], rho=ph["rho"], g=ph["g"], D=ph["D"], tau_extra=tau_pd)
    sim = simulate_so3(body, R0, w0, sample_times(c), c["solver"], progress)
    p = np.zeros(sim.R.shape[:2] + (0, 3))
    return Dataset(
        R=sim.R[:, :, None],
        p=p,
        h=float(c["h"]),
        scene=c["name"],
        body_names=["body"],
        body_kinds=["so3"],
        params=dataset_params(c, physics=physics, simulation=simulation_info(sim)),
        seed=int(c["seed"]),
        split=make_split(T, float(c["test_fraction"]), c["n_test"], split_seed),
        extras={
            "omega": sim.w[:, :, None],
            "v": p.copy(),
            "tau_ext": body.external_torque(sim.R, sim.w)[:, :, None],
            "tau_control": tau_pd(sim.R, sim.w)[:, :, None],
            "f_ext": p.copy(),
            "energy": body.energy(sim.R, sim.w),
        },
        t=sim.t,
    )


__all__ = ["two_body", "pd_control", "two_body_physics", "two_body_system", "pd_gains", "pd_torque"]
