"""Ground-truth rigid-body dynamics on SO(3) and SE(3) (continuous equations, numpy float64).

Conventions (body frame, left trivialisation): R maps body to world coordinates, w is the body
angular velocity (R' = R hat(w)), v the body-frame linear velocity of the body origin (p' = R v),
e3 = (0, 0, 1) points up, gravity pulls along -e3.

SO(3) body, potential V(R) = m g e3^T R rho:
    J w' = (J w) x w + tau,      tau = -m g rho x (R^T e3) - D w (+ tau_extra(R, w)).

SE(3) body, kinetic energy 1/2 w^T J w + 1/2 m |v + w x rho|^2 and V(R, p) = m g e3^T (p + R rho):
    (Pi, P) = M (w, v),  M = [[J + m hat(rho)^T hat(rho), -m hat(rho)^T], [-m hat(rho), m I]]
    Pi' = Pi x w + P x v + tau,   P' = P x w + f      (forced Euler-Poincare equations)
    f = -m g R^T e3 - D_vw w - D_vv v,   tau = rho x (-m g R^T e3) - D_ww w - D_wv v.
Here J is the inertia about the centre of mass; M is constant, so (w', v') = M^{-1} (Pi', P').

All trajectories of a batch are integrated in ONE `scipy.integrate.solve_ivp` call on their stacked
state (the 9 entries of R row by row, then p, w, v).  Note that the solver's error norm is the RMS
over the whole stacked vector, so per-trajectory error control is (slightly) looser than rtol/atol
suggest for a single trajectory; at the default rtol = 1e-10 this is irrelevant.  After integration
every sampled R is projected onto SO(3) provided its drift ||R^T R - I||_F stays below 1e-6.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import ConfigError, SimulationError
from ..lie import so3

MAX_DRIFT = 1e-6
"""Largest ||R^T R - I||_F accepted from the integrator before projection onto SO(3)."""

E3 = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- small helpers
def hat(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) skew matrix with hat(w) x = w x x."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape + (3,), dtype=np.float64)
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _matrix(x, n: int, name: str) -> np.ndarray:
    """A length-n diagonal or an (n, n) matrix -> (n, n) float64."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape == (n,):
        return np.diag(a)
    if a.shape == (n, n):
        return a
    raise ConfigError(f"physics.{name} must be a length-{n} diagonal or an {n}x{n} matrix, got shape {a.shape}")


def orthogonality_drift(R: np.ndarray) -> np.ndarray:
    """||R^T R - I||_F, shape (...)."""
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    return np.sqrt((E * E).sum((-1, -2)))


@dataclass(frozen=True)
class SolverOptions:
    """Options handed to `scipy.integrate.solve_ivp`."""

    method: str = "RK45"
    rtol: float = 1e-10
    atol: float = 1e-12

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> SolverOptions:
        cfg = dict(cfg or {})
        unknown = set(cfg) - {"method", "rtol", "atol"}
        if unknown:
            raise ConfigError(f"solver: unknown key(s) {sorted(unknown)} (expected method, rtol, atol)")
        opts = cls(
            str(cfg.get("method", cls.method)), float(cfg.get("rtol", cls.rtol)), float(cfg.get("atol", cls.atol))
        )
        if opts.method not in ("RK45", "DOP853", "RK23", "Radau", "BDF", "LSODA"):
            raise ConfigError(f"solver.method must be a solve_ivp method such as RK45 or DOP853, got {opts.method!r}")
        if not (opts.rtol > 0 and opts.atol > 0):
            raise ConfigError(f"solver.rtol and solver.atol must be positive, got {opts.rtol}, {opts.atol}")
        return opts


# --------------------------------------------------------------------------- SO(3)
@dataclass(frozen=True, eq=False)
class RigidBodySO3:
    """Heavy (or free, g = 0) rigid body on SO(3) with Rayleigh damping.

    J: (3, 3) inertia (about the pivot), m: mass, rho: (3,) centre of mass in the body frame,
    g: gravitational acceleration, D: (3, 3) symmetric positive semidefinite damping,
    tau_extra: optional callable (R (T, 3, 3), w (T, 3)) -> (T, 3) extra body-frame torque.
    """

    J: np.ndarray
    m: float = 0.0
    rho: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: float = 0.0
    D: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    tau_extra: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    _Jinv: np.ndarray = field(init=False, repr=False)  # J^{-1}, set by __post_init__

    state_size = 12

    def __post_init__(self):
        object.__setattr__(self, "J", _matrix(self.J, 3, "J"))
        object.__setattr__(self, "D", _matrix(self.D, 3, "D"))
        object.__setattr__(self, "rho", np.asarray(self.rho, dtype=np.float64).reshape(3))
        object.__setattr__(self, "m", float(self.m))
        object.__setattr__(self, "g", float(self.g))
        object.__setattr__(self, "_Jinv", np.linalg.inv(self.J))

    # -- forces
    def gravity_torque(self, R: np.ndarray) -> np.ndarray:
        """tau_grav = -m g rho x (R^T e3), (..., 3)."""
        return -self.m * self.g * np.cross(self.rho, R[..., 2, :])

    def external_torque(self, R: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Non-conservative torque -D w (+ tau_extra), (..., 3)."""
        tau = -w @ self.D.T
        if self.tau_extra is not None:
            tau = tau + np.asarray(self.tau_extra(R, w), dtype=np.float64)
        return tau

    def torque(self, R: np.ndarray, w: np.ndarray) -> np.ndarray:
        return self.gravity_torque(R) + self.external_torque(R, w)

    # -- equations of motion
    def angular_acceleration(self, R: np.ndarray, w: np.ndarray) -> np.ndarray:
        """w' = J^{-1} ((J w) x w + tau), (..., 3)."""
        return (np.cross(w @ self.J.T, w) + self.torque(R, w)) @ self._Jinv.T

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """Right-hand side on the flat stacked state (T * 12,)."""
        Y = y.reshape(-1, 12)
        R, w = Y[:, :9].reshape(-1, 3, 3), Y[:, 9:]
        out = np.empty_like(Y)
        out[:, :9] = (R @ hat(w)).reshape(-1, 9)
        out[:, 9:] = self.angular_acceleration(R, w)
        return out.reshape(-1)

    # -- energy
    def potential(self, R: np.ndarray) -> np.ndarray:
        """V(R) = m g e3^T R rho, shape (...)."""
        return self.m * self.g * (R[..., 2, :] @ self.rho)

    def kinetic(self, w: np.ndarray) -> np.ndarray:
        return 0.5 * np.einsum("...i,ij,...j->...", w, self.J, w)

    def energy(self, R: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Total energy 1/2 w^T J w + m g e3^T R rho, shape (...)."""
        return self.kinetic(w) + self.potential(R)

    def power(self, R: np.ndarray, w: np.ndarray) -> np.ndarray:
        """dE/dt = w . tau_ext (= -w^T D w without tau_extra), shape (...)."""
        return (w * self.external_torque(R, w)).sum(-1)

    # -- state packing
    @staticmethod
    def pack(R: np.ndarray, w: np.ndarray) -> np.ndarray:
        R, w = np.asarray(R, np.float64), np.asarray(w, np.float64)
        return np.concatenate((R.reshape(*R.shape[:-2], 9), w), -1)

    @staticmethod
    def unpack(Y: np.ndarray) -> dict:
        return {"R": Y[..., :9].reshape(*Y.shape[:-1], 3, 3), "w": Y[..., 9:12]}


# --------------------------------------------------------------------------- SE(3)
@dataclass(frozen=True, eq=False)
class RigidBodySE3:
    """Rigid body on SE(3) in a gravitational field with Rayleigh damping.

    J: (3, 3) inertia about the centre of mass, m: mass, rho: (3,) centre of mass in the body frame,
    g: gravitational acceleration, D: (6, 6) symmetric PSD damping acting on (w, v),
    wrench_extra: optional callable (R, p, w, v) -> (tau (T, 3), f (T, 3)) extra body-frame wrench.
    """

    J: np.ndarray
    m: float = 1.0
    rho: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: float = 0.0
    D: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    wrench_extra: Callable | None = None
    _Minv: np.ndarray = field(init=False, repr=False)  # inverse 6x6 mass matrix, set by __post_init__

    state_size = 18

    def __post_init__(self):
        object.__setattr__(self, "J", _matrix(self.J, 3, "J"))
        object.__setattr__(self, "D", _matrix(self.D, 6, "D"))
        object.__setattr__(self, "rho", np.asarray(self.rho, dtype=np.float64).reshape(3))
        object.__setattr__(self, "m", float(self.m))
        object.__setattr__(self, "g", float(self.g))
        if self.m <= 0:
            raise ConfigError(f"physics.m must be positive for an SE(3) body, got {self.m}")
        object.__setattr__(self, "_Minv", np.linalg.inv(self.mass_matrix()))

    def mass_matrix(self) -> np.ndarray:
        """Generalised 6x6 mass matrix M with (Pi, P) = M (w, v)."""
        Hr, m = hat(self.rho), self.m
        return np.block([[self.J + m * Hr.T @ Hr, -m * Hr.T], [-m * Hr, m * np.eye(3)]])

    def momenta(self, w: np.ndarray, v: np.ndarray):
        """Body momenta Pi = J w + rho x P, P = m (v + w x rho)."""
        P = self.m * (v + np.cross(w, self.rho))
        return w @ self.J.T + np.cross(self.rho, P), P

    # -- forces
    def gravity_wrench(self, R: np.ndarray):
        """(tau_g, f_g) with f_g = -m g R^T e3 and tau_g = rho x f_g (body frame)."""
        f = -self.m * self.g * R[..., 2, :]
        return np.cross(self.rho, f), f

    def external_wrench(self, R, p, w, v):
        """Non-conservative wrench -D (w, v) (+ wrench_extra)."""
        xi = np.concatenate((w, v), -1)
        d = -xi @ self.D.T
        tau, f = d[..., :3], d[..., 3:]
        if self.wrench_extra is not None:
            te, fe = self.wrench_extra(R, p, w, v)
            tau, f = tau + np.asarray(te, np.float64), f + np.asarray(fe, np.float64)
        return tau, f

    # -- equations of motion
    def accelerations(self, R, p, w, v):
        """(w', v') from the forced Euler-Poincare equations, each (..., 3)."""
        Pi, P = self.momenta(w, v)
        tg, fg = self.gravity_wrench(R)
        te, fe = self.external_wrench(R, p, w, v)
        dPi = np.cross(Pi, w) + np.cross(P, v) + tg + te
        dP = np.cross(P, w) + fg + fe
        acc = np.concatenate((dPi, dP), -1) @ self._Minv.T
        return acc[..., :3], acc[..., 3:]

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """Right-hand side on the flat stacked state (T * 18,)."""
        Y = y.reshape(-1, 18)
        R, p, w, v = Y[:, :9].reshape(-1, 3, 3), Y[:, 9:12], Y[:, 12:15], Y[:, 15:18]
        out = np.empty_like(Y)
        out[:, :9] = (R @ hat(w)).reshape(-1, 9)
        out[:, 9:12] = (R @ v[..., None])[..., 0]
        out[:, 12:15], out[:, 15:18] = self.accelerations(R, p, w, v)
        return out.reshape(-1)

    # -- energy
    def potential(self, R, p) -> np.ndarray:
        """V = m g e3^T (p + R rho), shape (...)."""
        return self.m * self.g * (p[..., 2] + R[..., 2, :] @ self.rho)

    def kinetic(self, w, v) -> np.ndarray:
        u = v + np.cross(w, self.rho)
        return 0.5 * np.einsum("...i,ij,...j->...", w, self.J, w) + 0.5 * self.m * (u * u).sum(-1)

    def energy(self, R, p, w, v) -> np.ndarray:
        return self.kinetic(w, v) + self.potential(R, p)

    def power(self, R, p, w, v) -> np.ndarray:
        """dE/dt = (w, v) . (tau_ext, f_ext)."""
        tau, f = self.external_wrench(R, p, w, v)
        return (w * tau).sum(-1) + (v * f).sum(-1)

    def centre_of_mass(self, R, p) -> np.ndarray:
        """World-frame centre of mass c = p + R rho, (..., 3)."""
        return p + R @ self.rho

    # -- state packing
    @staticmethod
    def pack(R, p, w, v) -> np.ndarray:
        R = np.asarray(R, np.float64)
        return np.concatenate(
            (
                R.reshape(*R.shape[:-2], 9),
                np.asarray(p, np.float64),
                np.asarray(w, np.float64),
                np.asarray(v, np.float64),
            ),
            -1,
        )

    @staticmethod
    def unpack(Y: np.ndarray) -> dict:
        return {"R": Y[..., :9].reshape(*Y.shape[:-1], 3, 3), "p": Y[..., 9:12], "w": Y[..., 12:15], "v": Y[..., 15:18]}


# --------------------------------------------------------------------------- integration
@dataclass
class Simulation:
    """Sampled ground truth: t (N+1,), R (T, N+1, 3, 3), w (T, N+1, 3), p and v (T, N+1, 3) or None."""

    t: np.ndarray
    R: np.ndarray
    w: np.ndarray
    p: np.ndarray | None = None
    v: np.ndarray | None = None
    max_drift: float = 0.0
    nfev: int = 0


def solve_ivp(*args, **kwargs):
    """`scipy.integrate.solve_ivp`, imported at the first call: loading scipy.integrate costs ~0.5 s of
    every `liedfl` start, and only generating a dataset integrates."""
    from scipy.integrate import solve_ivp as scipy_solve_ivp

    return scipy_solve_ivp(*args, **kwargs)


def integrate(
    rhs,
    Y0: np.ndarray,
    t: np.ndarray,
    solver: SolverOptions | Mapping | None = None,
    progress: Callable[[float], None] | None = None,
) -> tuple[np.ndarray, int]:
    """Integrate the stacked state Y0 (T, S) with one solve_ivp call; returns (Y (T, N+1, S), nfev).

    `progress(t)` (optional) is called with the current solver time, at most ~200 times.
    """
    opts = solver if isinstance(solver, SolverOptions) else SolverOptions.from_config(solver)
    Y0 = np.asarray(Y0, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T, S = Y0.shape
    if t.ndim != 1 or t.size < 1:
        raise ValueError(f"sample times must be a non-empty 1-D array, got shape {t.shape}")
    if t.size == 1:
        return Y0[:, None, :].copy(), 0
    fun = rhs
    if progress is not None:
        span, last = float(t[-1] - t[0]), [t[0]]

        def fun(tt, y):
            if tt - last[0] >= span / 200 or tt >= t[-1]:
                last[0] = tt
                progress(float(tt))
            return rhs(tt, y)

    sol = solve_ivp(
        fun, (float(t[0]), float(t[-1])), Y0.reshape(-1), method=opts.method, t_eval=t, rtol=opts.rtol, atol=opts.atol
    )
    if sol.status != 0 or sol.y.shape[1] != t.size:
        raise SimulationError(f"solve_ivp ({opts.method}) failed: {sol.message}")
    if progress is not None:
        progress(float(t[-1]))
    Y = sol.y.reshape(T, S, t.size).transpose(0, 2, 1)
    if not np.isfinite(Y).all():
        i = tuple(int(k) for k in np.argwhere(~np.isfinite(Y))[0])
        raise SimulationError(
            f"solve_ivp ({opts.method}) produced a non-finite state at (trajectory, sample, entry) {i}"
        )
    return np.ascontiguousarray(Y), int(sol.nfev)


def project_rotations(R: np.ndarray, max_drift: float = MAX_DRIFT) -> tuple[np.ndarray, float]:
    """Project integrated rotations onto SO(3); raise SimulationError if any drifted by > max_drift."""
    drift = orthogonality_drift(R)
    worst = float(drift.max()) if drift.size else 0.0
    if worst > max_drift:
        i = tuple(int(k) for k in np.unravel_index(int(drift.argmax()), drift.shape))
        raise SimulationError(
            f"integrated rotation drifted off SO(3) by ||R^T R - I||_F = {worst:.3e} > {max_drift:.0e} at "
            f"(trajectory, sample) {i}; tighten solver.rtol/atol"
        )
    Rp = so3.project(torch.from_numpy(np.ascontiguousarray(R))).numpy()
    return Rp, worst


def simulate_so3(
    body: RigidBodySO3,
    R0: np.ndarray,
    w0: np.ndarray,
    t: np.ndarray,
    solver: SolverOptions | Mapping | None = None,
    progress: Callable[[float], None] | None = None,
) -> Simulation:
    """Integrate T trajectories from R0 (T, 3, 3), w0 (T, 3), sampled at times t (N+1,)."""
    Y, nfev = integrate(body.rhs, body.pack(R0, w0), t, solver, progress)
    s = body.unpack(Y)
    R, drift = project_rotations(s["R"])
    return Simulation(t=np.asarray(t, np.float64), R=R, w=np.ascontiguousarray(s["w"]), max_drift=drift, nfev=nfev)


def simulate_se3(
    body: RigidBodySE3,
    R0: np.ndarray,
    p0: np.ndarray,
    w0: np.ndarray,
    v0: np.ndarray,
    t: np.ndarray,
    solver: SolverOptions | Mapping | None = None,
    progress: Callable[[float], None] | None = None,
) -> Simulation:
    """Integrate T trajectories from (R0, p0, w0, v0) (each (T, ...)), sampled at times t (N+1,)."""
    Y, nfev = integrate(body.rhs, body.pack(R0, p0, w0, v0), t, solver, progress)
    s = body.unpack(Y)
    R, drift = project_rotations(s["R"])
    return Simulation(
        t=np.asarray(t, np.float64),
        R=R,
        w=np.ascontiguousarray(s["w"]),
        p=np.ascontiguousarray(s["p"]),
        v=np.ascontiguousarray(s["v"]),
        max_drift=drift,
        nfev=nfev,
    )


__all__ = [
    "MAX_DRIFT",
    "hat",
    "orthogonality_drift",
    "SolverOptions",
    "RigidBodySO3",
    "RigidBodySE3",
    "Simulation",
    "integrate",
    "project_rotations",
    "simulate_so3",
    "simulate_se3",
]
