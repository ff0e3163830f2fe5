"""Potentials V(g) on a product group; the discrete Lagrangian carries -h V(g_k).

Every potential maps a Pose with leading dims (...) to a tensor of shape (...).
"""

from __future__ import annotations

import torch
from torch import nn

from ..lie import Pose, ProductGroup, so3
from .mlp import MLP


class MLPPotential(nn.Module):
    """V_theta(g) = MLP(flatten(g)): rotation entries of every body and SE(3) positions."""

    def __init__(self, G: ProductGroup, width: int = 64, depth: int = 3):
        super().__init__()
        self.G = G
        self.net = MLP(9 * G.n_bodies + 3 * G.n_se3, 1, width, depth)

    def forward(self, g: Pose) -> torch.Tensor:
        return self.net(self.G.flatten(g))[..., 0]

    def describe(self) -> str:
        return f"MLP {self.net[0].out_features}x{(len(self.net) - 1) // 2}"


class GravityPotential(nn.Module):
    """V(g) = sum_i m_i g e3 . (p_i + R_i rho_i) (p_i = 0 for SO(3) bodies: a pivot at the origin).

    masses (B,), rhos (B, 3) are fixed buffers: this is the known potential of the scenes.
    """

    masses: torch.Tensor
    rhos: torch.Tensor

    def __init__(self, G: ProductGroup, masses, rhos, gravity: float):
        super().__init__()
        self.G = G
        self.register_buffer("masses", torch.as_tensor(masses, dtype=torch.float64).reshape(G.n_bodies))
        self.register_buffer("rhos", torch.as_tensor(rhos, dtype=torch.float64).reshape(G.n_bodies, 3))
        self.gravity = float(gravity)

    def forward(self, g: Pose) -> torch.Tensor:
        com_height = (g.R[..., 2, :] * self.rhos).sum(-1)  # e3 . R rho per body
        m = self.G.n_se3
        if m:
            com_height = torch.cat((com_height[..., :m] + g.p[..., 2], com_height[..., m:]), -1)
        return self.gravity * (self.masses * com_height).sum(-1)

    def left_gradient(self, g: Pose) -> torch.Tensor:
        """Closed form of dV(g exp(eta))/d eta at 0, (..., dim): per body the rotational part
        m g rho x (R^T e3) and, for SE(3) bodies, the translational part m g R^T e3 (tested against the
        generic `left_gradient`)."""
        up = g.R[..., 2, :]  # (..., B, 3): R^T e3 per body
        w = self.gravity * torch.cross((self.masses[:, None] * self.rhos).expand_as(up), up, dim=-1)
        m = self.G.n_se3
        v = self.gravity * self.masses[:m, None] * up[..., :m, :]
        return self.G.join(w, v)

    def describe(self) -> str:
        return "gravity"


STANDARD_GRAVITY = 9.81
"""Field strength used by `UniformGravityPotential` when the data declare gravity without a magnitude."""


class UniformGravityPotential(nn.Module):
    """Learnable potential of a uniform field: V(g) = sum_i m_i gamma.(p_i + R_i rho_i) over the SE(3)
    bodies + sum_j gamma.(R_j c_j) over the SO(3) bodies (heavy bodies on a pivot at the origin),
    gamma = g u with the field strength g (fixed) and the unit "up" direction u (e3 unless learned;
    gravity acts along -u).

    SE(3) bodies: m_i and rho_i are the kinetic term's mass and centre of mass (the same modules,
    passed in and shared), so the potential adds no parameters for them and the mass cannot hide in
    the potential. SO(3) bodies: only the first moment c_j = m_j rho_j enters (the pivot form
    m g e3.R rho), so c_j is the parameter (3 per body, starting at 0). `learn_direction`: u = a/|a|
    with a learned (starts at e3, or at `up`; 3 parameters). `up`: the fixed (or starting) up direction,
    e.g. the data's declared params["gravity_up"] (default e3).

    As every part of L_d, V is only identified up to the common scale of (J_d, m, c, D): compare
    m / tr J_d and c / tr J_d with the truth; rho and u are identified as they are.
    """

    gravity: torch.Tensor
    direction_raw: torch.Tensor
    mass: nn.Module  # SE(3) bodies only (with rho)
    rho: torch.Tensor

    def __init__(
        self,
        G: ProductGroup,
        gravity: float = STANDARD_GRAVITY,
        mass: nn.Module | None = None,
        rho: torch.Tensor | None = None,
        learn_direction: bool = False,
        up=None,
    ):
        super().__init__()
        self.G = G
        if G.n_se3 and (mass is None or rho is None):
            raise ValueError("uniform_gravity on SE(3) bodies needs the kinetic term's mass and rho_COM")
        self.register_buffer("gravity", torch.tensor(float(gravity), dtype=torch.float64))
        if G.n_se3:
            assert mass is not None and rho is not None  # checked above
            self.mass = mass  # shared modules: registered here too, counted once by parameters()
            self.rho = rho
        self.moment = nn.Parameter(torch.zeros(G.n_so3, 3, dtype=torch.float64)) if G.n_so3 else None
        start = torch.tensor([0.0, 0.0, 1.0] if up is None else [float(x) for x in up], dtype=torch.float64)
        if start.shape != (3,) or not bool(torch.isfinite(start).all()) or float(start.norm()) == 0.0:
            raise ValueError(f"uniform_gravity: up direction {up!r} must be a non-zero 3-vector")
        if learn_direction:
            self.direction_raw = nn.Parameter(start)
        else:
            self.register_buffer("direction_raw", start)
        self.learn_direction = bool(learn_direction)

    def direction(self) -> torch.Tensor:
        """Unit up direction u (3,)."""
        return self.direction_raw / torch.linalg.vector_norm(self.direction_raw)

    def field(self) -> torch.Tensor:
        """gamma = g u (3,)."""
        return self.gravity * self.direction()

    def first_moments(self) -> torch.Tensor:
        """(B, 3): m_i rho_i of the SE(3) bodies, then c_j of the SO(3) bodies."""
        parts = []
        if self.G.n_se3:
            parts.append(self.mass()[:, None] * self.rho)
        if self.moment is not None:
            parts.append(self.moment)
        return torch.cat(parts, 0)

    def forward(self, g: Pose) -> torch.Tensor:
        gamma = self.field()
        up = (g.R * gamma[:, None]).sum(-2)  # (..., B, 3): R^T gamma per body
        V = (up * self.first_moments()).sum((-1, -2))  # sum_b gamma . R_b (m rho)_b
        if self.G.n_se3:
            V = V + (self.mass() * (g.p @ gamma)).sum(-1)
        return V

    def left_gradient(self, g: Pose) -> torch.Tensor:
        """Closed form of dV(g exp(eta))/d eta at 0, (..., dim): per body the rotational part
        (m rho) x (R^T gamma) and, for SE(3) bodies, the translational part m R^T gamma."""
        gamma = self.field()
        up = (g.R * gamma[:, None]).sum(-2)  # (..., B, 3)
        w = torch.cross(self.first_moments().expand_as(up), up, dim=-1)
        m = self.G.n_se3
        v = self.mass()[:, None] * up[..., :m, :] if m else up[..., :0, :]
        return self.G.join(w, v)

    def describe(self) -> str:
        parts = [f"uniform_gravity (g = {float(self.gravity):g}"]
        if self.G.n_se3:
            parts.append("m, rho_COM shared with the kinetic term")
        if self.G.n_so3:
            parts.append(f"m rho of {self.G.n_so3} pivot bod{'y' if self.G.n_so3 == 1 else 'ies'}")
        u = [round(float(x), 4) for x in self.direction()]
        along = "along -e3" if u == [0.0, 0.0, 1.0] else f"along -{u}"
        parts.append("direction learned" if self.learn_direction else along)
        return "; ".join(parts) + ")"


# ----------------------------------------------------------------------------- interactions
INTERACTIONS = ("spring", "relative_rotation", "relative_rotation_trace", "newton", "dipole")
"""Interaction potentials between two bodies (the paper's appendix list), `InteractionPotential.kind`."""


def _vec3(x, name: str) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=torch.float64)
    if t.shape != (3,):
        raise ValueError(f"interaction.{name} must be 3 numbers, got {x!r}")
    return t


class InteractionPotential(nn.Module):
    """V_int(g) between bodies `a` and `b` of a product group (known potential of a scene).

    Body origins: o_i = p_i for SE(3) bodies and o_i = 0 for SO(3) bodies (a pivot at the world
    origin). Points fixed in body i: attachment X_i = o_i + R_i r_i, centre of mass
    c_i = o_i + R_i rho_i, magnetic moment R_i n_i. With d = X_b - X_a:

      spring                   mu/2 |X_a - X_b|^2
      relative_rotation        mu/2 |log(R_a^T R_b)|^2
      relative_rotation_trace  mu (3 - tr(R_a^T R_b))
      newton                   -mu m_a m_b / |c_b - c_a|     (mu: gravitational constant)
      dipole                   mu / |d|^3 ((R_a n_a).(R_b n_b) - 3 (R_a n_a . d)(R_b n_b . d) / |d|^2)
                               (mu = mu_0 / (4 pi))

    All parameters are fixed buffers (no trainable parameters).
    """

    r: torch.Tensor
    n: torch.Tensor
    m: torch.Tensor
    rho: torch.Tensor

    def __init__(
        self,
        G: ProductGroup,
        kind: str,
        mu: float,
        r1=(0.0, 0.0, 0.0),
        r2=(0.0, 0.0, 0.0),
        moment1=(0.0, 0.0, 1.0),
        moment2=(0.0, 0.0, 1.0),
        masses=(1.0, 1.0),
        rhos=((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        bodies=(0, 1),
    ):
        super().__init__()
        if kind not in INTERACTIONS:
            raise ValueError(f"interaction.kind must be one of {INTERACTIONS}, got {kind!r}")
        a, b = (int(i) for i in bodies)
        if not (0 <= a < G.n_bodies and 0 <= b < G.n_bodies and a != b):
            raise ValueError(f"interaction bodies {bodies} do not name two bodies of {G.name}")
        self.G, self.kind, self.mu, self.a, self.b = G, kind, float(mu), a, b
        self.register_buffer("r", torch.stack((_vec3(r1, "r1"), _vec3(r2, "r2"))))
        self.register_buffer("n", torch.stack((_vec3(moment1, "moment1"), _vec3(moment2, "moment2"))))
        self.register_buffer("m", torch.as_tensor(masses, dtype=torch.float64).reshape(2))
        self.register_buffer("rho", torch.as_tensor(rhos, dtype=torch.float64).reshape(2, 3))

    def _origin(self, g: Pose, i: int) -> torch.Tensor:
        if i < self.G.n_se3:
            return g.p[..., i, :]
        return g.R.new_zeros(*g.R.shape[:-3], 3)

    def _point(self, g: Pose, i: int, local: torch.Tensor) -> torch.Tensor:
        return self._origin(g, i) + (g.R[..., i, :, :] @ local[:, None])[..., 0]

    def forward(self, g: Pose) -> torch.Tensor:
        a, b, mu = self.a, self.b, self.mu
        Ra, Rb = g.R[..., a, :, :], g.R[..., b, :, :]
        if self.kind == "spring":
            d = self._point(g, a, self.r[0]) - self._point(g, b, self.r[1])
            return 0.5 * mu * (d * d).sum(-1)
        if self.kind == "relative_rotation":
            w = so3.log(Ra.transpose(-1, -2) @ Rb)
            return 0.5 * mu * (w * w).sum(-1)
        if self.kind == "relative_rotation_trace":
            return mu * (3.0 - (Ra * Rb).sum((-1, -2)))  # tr(Ra^T Rb) = sum of entrywise products
        if self.kind == "newton":
            d = self._point(g, b, self.rho[1]) - self._point(g, a, self.rho[0])
            return -mu * self.m[0] * self.m[1] / torch.linalg.vector_norm(d, dim=-1)
        # dipole
        d = self._point(g, b, self.r[1]) - self._point(g, a, self.r[0])
        na, nb = (Ra @ self.n[0][:, None])[..., 0], (Rb @ self.n[1][:, None])[..., 0]
        r2 = (d * d).sum(-1)
        r3 = r2 * torch.sqrt(r2)
        return mu / r3 * ((na * nb).sum(-1) - 3.0 * (na * d).sum(-1) * (nb * d).sum(-1) / r2)

    def describe(self) -> str:
        return f"interaction:{self.kind}"


class SumPotential(nn.Module):
    """V = sum of potentials (e.g. gravity + interaction), shape (...)."""

    def __init__(self, terms):
        super().__init__()
        self.terms = nn.ModuleList(terms)

    def forward(self, g: Pose) -> torch.Tensor:
        out = self.terms[0](g)
        for t in self.terms[1:]:
            out = out + t(g)
        return out

    def describe(self) -> str:
        return "+".join(_describe(t) for t in self.terms)


def _describe(p: nn.Module) -> str:
    describe = getattr(p, "describe", None)
    if describe is not None:
        return describe()
    return type(p).__name__


def left_gradient(V: nn.Module, G: ProductGroup, g: Pose, create_graph: bool = False) -> torch.Tensor:
    """dV(g exp(eta))/d eta at 0 (the left-trivialised gradient), shape (..., dim), by autodiff
    of V over the matrices: for each body the rotational part is 2 vee(R^T dV/dR) (vee of the
    skew part, so3.vee), and for SE(3) bodies the translational part R^T dV/dp."""
    with torch.enable_grad():
        R = g.R.detach().requires_grad_(True) if not create_graph else g.R
        p = g.p.detach().requires_grad_(True) if not create_graph else g.p
        val = V(Pose(R, p)).sum()
        dR, dp = torch.autograd.grad(val, (R, p), create_graph=create_graph, allow_unused=True)
    dR = torch.zeros_like(g.R) if dR is None else dR
    dp = torch.zeros_like(g.p) if dp is None else dp
    w = 2.0 * so3.vee(g.R.transpose(-1, -2) @ dR)
    m = G.n_se3
    v = (g.R[..., :m, :, :].transpose(-1, -2) @ dp[..., None])[..., 0]
    return G.join(w, v)
