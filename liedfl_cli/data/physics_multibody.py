"""Ground truth for two coupled rigid bodies (continuous equations, numpy float64 + torch autodiff).

Bodies are SE(3) (free: rotation and position) or SO(3) (on a pivot fixed at the world origin),
SE(3) bodies first, as in `lie.ProductGroup`. Conventions as in `physics.py`: body-frame
velocities, R' = R hat(w), p' = R v, e3 up, gravity along -e3.

Lagrangian: sum_i T_i - V(g) with
    SE(3) body: T = 1/2 w.J w + 1/2 m |v + w x rho|^2      (J about the centre of mass)
    SO(3) body: T = 1/2 w.J w                              (J about the pivot)
    V = sum_i m_i g e3.(o_i + R_i rho_i) + V_int(g)        (o_i = p_i, or 0 for a pivot)
V_int is one of `mechanics.potentials.INTERACTIONS`. The conservative wrench of body i is
minus the left-trivialised gradient of V, obtained by torch autodiff of V over the matrices:
    tau_i = -2 vee_skew(R_i^T dV/dR_i),   f_i = -R_i^T dV/dp_i
(`potentials.left_gradient`; tested against finite differences of V(g exp(eta))). Rayleigh
damping -D xi acts on the flat tangent vector xi = (w_1, v_1, ..., w_k) of `ProductGroup`.
Equations of motion (forced Euler-Poincare, per body):
    SE(3): (Pi, P) = M (w, v);  Pi' = Pi x w + P x v + tau;  P' = P x w + f
    SO(3): J w' = (J w) x w + tau
State of one trajectory (flat): the 9 entries of each R_i (row by row), the 3 entries of each
SE(3) position, then xi (dim entries). All trajectories are integrated in ONE solve_ivp call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import ConfigError
from ..lie import Pose, ProductGroup
from ..mechanics.potentials import GravityPotential, InteractionPotential, SumPotential, left_gradient
from .physics import Simulation, _matrix, hat, integrate, project_rotations


@dataclass(frozen=True, eq=False)
class MultiBodySystem:
    """Rigid bodies of `kinds` (e.g. ("se3", "so3")) coupled by an interaction potential.

    J: (B, 3, 3) inertia per body, m: (B,), rho: (B, 3), g: gravity, D: (dim, dim) damping,
    interaction: None or a dict {kind, mu, r1, r2, moment1, moment2} between bodies 0 and 1.
    """

    kinds: tuple = ("se3", "so3")
    J: np.ndarray = field(default_factory=lambda: np.stack([np.eye(3), np.eye(3)]))
    m: np.ndarray = field(default_factory=lambda: np.ones(2))
    rho: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    g: float = 0.0
    D: np.ndarray | None = None
    interaction: dict | None = None
    wrench_extra: Callable | None = None  # (Pose numpy R, p, xi (T, dim)) -> (T, dim) extra covector
    # derived in __post_init__ (not constructor arguments)
    G: ProductGroup = field(init=False, repr=False)  # the group layout of `kinds`
    _M: list[np.ndarray] = field(init=False, repr=False)  # mass matrix per body (6x6 SE(3), 3x3 SO(3))
    _Minv: list[np.ndarray] = field(init=False, repr=False)  # their inverses
    V: torch.nn.Module | None = field(init=False, repr=False)  # gravity + interaction potential, or None

    def __post_init__(self):
        kinds = tuple(self.kinds)
        if any(k not in ("se3", "so3") for k in kinds) or list(kinds) != sorted(kinds):
            raise ConfigError(f"body kinds must be 'se3' then 'so3' entries, got {kinds}")
        G = ProductGroup(kinds.count("se3"), kinds.count("so3"))
        B = G.n_bodies
        J = np.asarray(self.J, dtype=np.float64)
        if J.shape[0] != B:
            raise ConfigError(f"physics.J needs one entry per body ({B})")
        J = np.stack([_matrix(J[i], 3, "J") for i in range(B)])
        m = np.asarray(self.m, dtype=np.float64).reshape(B)
        rho = np.asarray(self.rho, dtype=np.float64).reshape(B, 3)
        D = np.zeros((G.dim, G.dim)) if self.D is None else _matrix(self.D, G.dim, "D")
        if (m[: G.n_se3] <= 0).any():
            raise ConfigError(f"physics.m must be positive for SE(3) bodies, got {m.tolist()}")
        object.__setattr__(self, "kinds", kinds)
        object.__setattr__(self, "G", G)
        object.__setattr__(self, "J", J)
        object.__setattr__(self, "m", m)
        object.__setattr__(self, "rho", rho)
        object.__setattr__(self, "D", D)
        object.__setattr__(self, "g", float(self.g))
        # mass matrices (SE(3): 6x6 about the body origin; SO(3): J about the pivot)
        M = []
        for i in range(B):
            if i < G.n_se3:
                Hr = hat(rho[i])
                M.append(np.block([[J[i] + m[i] * Hr.T @ Hr, -m[i] * Hr.T], [-m[i] * Hr, m[i] * np.eye(3)]]))
            else:
                M.append(J[i])
        object.__setattr__(self, "_M", M)
        object.__setattr__(self, "_Minv", [np.linalg.inv(x) for x in M])
        terms: list[torch.nn.Module] = []
        if self.g != 0.0:
            terms.append(GravityPotential(G, m, rho, self.g))
        if self.interaction:
            inter = dict(self.interaction)
            kw = {k: inter[k] for k in ("r1", "r2", "moment1", "moment2") if k in inter}
            terms.append(InteractionPotential(G, inter["kind"], float(inter["mu"]), masses=m[:2], rhos=rho[:2], **kw))
        pot = None if not terms else (terms[0] if len(terms) == 1 else SumPotential(terms))
        object.__setattr__(self, "V", pot)

    # ------------------------------------------------------------------ state packing
    @property
    def state_size(self) -> int:
        return 9 * self.G.n_bodies + 3 * self.G.n_se3 + self.G.dim

    def pack(self, R, p, xi) -> np.ndarray:
        """R (T, B, 3, 3), p (T, m, 3), xi (T, dim) -> (T, S)."""
        T = R.shape[0]
        return np.concatenate(
            (
                np.asarray(R, np.float64).reshape(T, -1),
                np.asarray(p, np.float64).reshape(T, -1),
                np.asarray(xi, np.float64),
            ),
            -1,
        )

    def unpack(self, Y: np.ndarray) -> dict:
        B, m = self.G.n_bodies, self.G.n_se3
        lead = Y.shape[:-1]
        R = Y[..., : 9 * B].reshape(*lead, B, 3, 3)
        p = Y[..., 9 * B : 9 * B + 3 * m].reshape(*lead, m, 3)
        xi = Y[..., 9 * B + 3 * m :]
        return {"R": R, "p": p, "xi": xi}

    # ------------------------------------------------------------------ forces
    def potential(self, R, p) -> np.ndarray:
        """V(g), shape (...)."""
        if self.V is None:
            return np.zeros(np.shape(R)[:-3])
        with torch.no_grad():
            return self.V(Pose(torch.as_tensor(R), torch.as_tensor(p))).numpy()

    def conservative_covector(self, R, p) -> np.ndarray:
        """Conservative wrench -dV(g exp(eta))/d eta at 0, (..., dim) in the flat tangent layout."""
        if self.V is None:
            return np.zeros(np.shape(R)[:-3] + (self.G.dim,))
        g = Pose(torch.as_tensor(np.ascontiguousarray(R)), torch.as_tensor(np.ascontiguousarray(p)))
        return -left_gradient(self.V, self.G, g).numpy()

    def external_covector(self, R, p, xi) -> np.ndarray:
        """Non-conservative wrench -D xi (+ wrench_extra), (..., dim)."""
        assert self.D is not None  # __post_init__ replaces None by zeros
        out = -xi @ self.D.T
        if self.wrench_extra is not None:
            out = out + np.asarray(self.wrench_extra(R, p, xi), np.float64)
        return out

    # ------------------------------------------------------------------ equations of motion
    def accelerations(self, R, p, xi) -> np.ndarray:
        """xi' (T, dim) from the forced Euler-Poincare equations of every body."""
        F = self.conservative_covector(R, p) + self.external_covector(R, p, xi)
        out = np.empty_like(xi)
        for i, s in enumerate(self.G.body_slices()):
            x, Fi = xi[:, s], F[:, s]
            mom = x @ self._M[i].T
            if i < self.G.n_se3:
                w, v, Pi, P = x[:, :3], x[:, 3:], mom[:, :3], mom[:, 3:]
                rhs = np.concatenate((np.cross(Pi, w) + np.cross(P, v) + Fi[:, :3], np.cross(P, w) + Fi[:, 3:]), -1)
            else:
                rhs = np.cross(mom, x) + Fi
            out[:, s] = rhs @ self._Minv[i].T
        return out

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        S = self.state_size
        Y = y.reshape(-1, S)
        st = self.unpack(Y)
        R, p, xi = st["R"], st["p"], st["xi"]
        w_t, v_t = self.G.split(torch.from_numpy(np.ascontiguousarray(xi)))
        w, v = w_t.numpy(), v_t.numpy()
        B, m = self.G.n_bodies, self.G.n_se3
        out = np.empty_like(Y)
        out[:, : 9 * B] = (R @ hat(w)).reshape(Y.shape[0], -1)
        out[:, 9 * B : 9 * B + 3 * m] = (R[:, :m] @ v[..., None])[..., 0].reshape(Y.shape[0], -1)
        out[:, 9 * B + 3 * m :] = self.accelerations(R, p, xi)
        return out.reshape(-1)

    # ------------------------------------------------------------------ invariants
    def kinetic(self, xi) -> np.ndarray:
        """Sum over bodies of 1/2 xi_i . M_i xi_i, shape (...)."""
        out = np.zeros(np.shape(xi)[:-1])
        for i, s in enumerate(self.G.body_slices()):
            x = xi[..., s]
            out = out + 0.5 * np.einsum("...i,ij,...j->...", x, self._M[i], x)
        return out

    def energy(self, R, p, xi) -> np.ndarray:
        """Total mechanical energy T + V, shape (...)."""
        return self.kinetic(xi) + self.potential(R, p)

    def power(self, R, p, xi) -> np.ndarray:
        """dE/dt = xi . F_ext, shape (...)."""
        return (xi * self.external_covector(R, p, xi)).sum(-1)

    def world_momentum(self, R, p, xi):
        """(linear (..., 3), angular about the world origin (..., 3)) total momentum.

        SE(3) body: body momenta (Pi, P) about its origin -> world (R P, R Pi + p x R P);
        SO(3) body on the pivot at the origin: angular R J w, no linear momentum.
        """
        lin = np.zeros(np.shape(xi)[:-1] + (3,))
        ang = np.zeros_like(lin)
        for i, s in enumerate(self.G.body_slices()):
            mom = xi[..., s] @ self._M[i].T
            Ri = R[..., i, :, :]
            if i < self.G.n_se3:
                Pw = (Ri @ mom[..., 3:, None])[..., 0]
                lin = lin + Pw
                ang = ang + (Ri @ mom[..., :3, None])[..., 0] + np.cross(p[..., i, :], Pw)
            else:
                ang = ang + (Ri @ mom[..., None])[..., 0]
        return lin, ang


def simulate_multibody(
    system: MultiBodySystem, R0, p0, xi0, t, solver=None, progress: Callable[[float], None] | None = None
) -> Simulation:
    """Integrate from R0 (T, B, 3, 3), p0 (T, m, 3), xi0 (T, dim); sample at t.

    Returns a `Simulation` with R (T, N+1, B, 3, 3), p (T, N+1, m, 3) and, in `w`, the flat
    tangent velocity xi (T, N+1, dim) (`v` is None; split it with `system.G.split`).
    """
    Y, nfev = integrate(system.rhs, system.pack(R0, p0, xi0), t, solver, progress)
    st = system.unpack(Y)
    R, drift = project_rotations(st["R"])
    return Simulation(
        t=np.asarray(t, np.float64),
        R=R,
        w=np.ascontiguousarray(st["xi"]),
        p=np.ascontiguousarray(st["p"]),
        v=None,
        max_drift=drift,
        nfev=nfev,
    )


__all__ = ["MultiBodySystem", "simulate_multibody"]
