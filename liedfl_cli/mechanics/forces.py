"""External forces F(g, xi~) -> (..., dim) covectors in the flat tangent layout.

They enter the DEL residual as F^-_k = F^+_k = (h/2) F(g_k, xi~_k) with xi~_k the paper's
velocity estimate from the increment g_k^{-1} g_{k+1} (`kinetic.velocity_estimate`).
"""

from __future__ import annotations

import torch
from torch import nn

from ..lie import Pose, ProductGroup, so3
from .damping import PerBodyDampingNet, PerBodySPSD, apply_blocks, block_diagonal
from .mlp import MLP, value_and_input_jacobian
from .parameterizations import SPSDMatrix

COUPLINGS = ("coupled", "per_body")
"""How damping acts on a multibody system: one dim x dim matrix over all bodies (`coupled`) or one
block per body (`per_body`, `mechanics.damping`). Identical for a single body."""


def _coupling(value: str) -> str:
    if value not in COUPLINGS:
        raise ValueError(f"damping coupling must be one of {COUPLINGS}, got {value!r}")
    return value


class RayleighForce(nn.Module):
    """F = -D xi~ with a constant SPSD D (dim x dim); D starts at init_diag * scale * I.

    coupling: "coupled" (default) one SPSD matrix over the whole tangent space; "per_body" one SPSD
    block per body (block diagonal, `damping.PerBodySPSD`). `D()` is the (dim, dim) matrix either way.
    """

    name = "rayleigh"

    def __init__(self, G: ProductGroup, scale: float = 1.0, init_diag: float = 0.01, coupling: str = "coupled"):
        super().__init__()
        self.coupling = _coupling(coupling)
        self.D: PerBodySPSD | SPSDMatrix
        if self.coupling == "per_body" and G.n_bodies > 1:
            self.D = PerBodySPSD(G, init_diag=init_diag * scale)
        else:
            self.D = SPSDMatrix(G.dim, init_diag=init_diag * scale)

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        # per body too: one (dim, dim) product beats applying the blocks one size at a time
        # (Exp 4, forward + backward: 0.61-0.95x at batches 8-1000; scripts/bench_damping.py)
        return -(xi @ self.D().T)

    def jacobian_xi(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        """dF/d xi~ = -D, broadcast to (..., dim, dim)."""
        return (-self.D()).expand(*xi.shape[:-1], xi.shape[-1], xi.shape[-1])

    def describe(self) -> str:
        n = self.D.dim
        if isinstance(self.D, PerBodySPSD):
            return f"rayleigh (D {n}x{n} SPSD, per-body blocks)"
        return f"rayleigh (D {n}x{n} SPSD)"


def _mlp_desc(net: MLP) -> str:
    return f"MLP {net[0].out_features}x{(len(net) - 1) // 2}"


class RayleighNonlinearForce(nn.Module):
    """F = -D(g) xi~ with D(g) SPSD for every g and every parameter value, starting near
    init_diag * scale * I like `RayleighForce`.

    coupling: "per_body" (default) D(g) = blockdiag(D_b(g_b)), D_b = L_b L_b^T with a shared trunk
    and one head per body (`damping.PerBodyDampingNet`: each body's damping as that of a single
    rigid body, the paper's multibody treatment); "coupled" one D(g) = L(g) L(g)^T over the whole
    tangent space, L = c (I + N(flatten(g))) lower triangular with N a GELU MLP of every body's
    configuration (dim (dim+1)/2 outputs: 2628 for Exp 4). For one body both are one MLP of its
    configuration.
    """

    name = "rayleigh_nonlinear"

    def __init__(
        self,
        G: ProductGroup,
        scale: float = 1.0,
        init_diag: float = 0.01,
        width: int = 64,
        depth: int = 3,
        coupling: str = "per_body",
    ):
        super().__init__()
        self.G, n = G, G.dim
        self.coupling = _coupling(coupling)
        c = float(init_diag * scale) ** 0.5
        self.per_body: PerBodyDampingNet | None
        if self.coupling == "per_body":
            self.per_body = PerBodyDampingNet(G, c, width, depth)
            return
        self.per_body = None
        rows, cols = torch.tril_indices(n, n)
        self.register_buffer("_rows", rows, persistent=False)
        self.register_buffer("_cols", cols, persistent=False)
        self.register_buffer("_eye_entries", (rows == cols).to(torch.float64), persistent=False)
        self.register_buffer("c", torch.tensor(c, dtype=torch.float64))
        self.net = MLP(9 * G.n_bodies + 3 * G.n_se3, len(rows), width, depth)

    def L(self, g: Pose) -> torch.Tensor:
        """(..., dim, dim) lower-triangular factor (block diagonal for per-body coupling)."""
        if self.per_body is not None:
            return block_diagonal(self.G, *self.per_body.factors(g))
        entries = self.c * (self._eye_entries + self.net(self.G.flatten(g)))
        n = self.G.dim
        L = entries.new_zeros(*entries.shape[:-1], n, n)
        L[..., self._rows, self._cols] = entries
        return L

    def D(self, g: Pose) -> torch.Tensor:
        """(..., dim, dim) SPSD damping matrix at g, exactly symmetric.

        A batched matmul need not round L L^T symmetrically (seen on AVX-512 kernels), so the
        product is averaged with its transpose: (a + b) / 2 is the same float either way round.
        """
        if self.per_body is not None:
            return block_diagonal(self.G, *self.per_body.blocks(g))
        L = self.L(g)
        M = L @ L.transpose(-1, -2)
        return 0.5 * (M + M.transpose(-1, -2))

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        if self.per_body is not None:  # block by block, without the dim x dim matrix
            return -apply_blocks(self.G, *self.per_body.blocks(g), xi)
        return -(self.D(g) @ xi[..., None])[..., 0]

    def jacobian_xi(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        """dF/d xi~ = -D(g)."""
        return -self.D(g)

    def describe(self) -> str:
        if self.per_body is not None:
            return f"rayleigh_nonlinear (D(g) = blockdiag L_b(g_b) L_b(g_b)^T, {self.per_body.describe()})"
        return f"rayleigh_nonlinear (D(g) = L L^T, L {_mlp_desc(self.net)})"


class NNForce(nn.Module):
    """Unconstrained force F(g, xi~) = scale * MLP(flatten(g), xi~) in g* (no dissipative guarantee)."""

    name = "nn"
    scale: torch.Tensor

    def __init__(self, G: ProductGroup, scale: float = 1.0, width: int = 64, depth: int = 3):
        super().__init__()
        self.G = G
        self.register_buffer("scale", torch.tensor(float(scale), dtype=torch.float64))
        self.net = MLP(9 * G.n_bodies + 3 * G.n_se3 + G.dim, G.dim, width, depth)

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        x = torch.cat((self.G.flatten(g), xi), -1)
        return self.scale * self.net(x)

    def jacobian_xi(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        """dF/d xi~ (..., dim, dim) by forward mode through the MLP (`mlp.value_and_input_jacobian`;
        one pass instead of dim reverse passes)."""
        x = torch.cat((self.G.flatten(g), xi), -1)
        out = value_and_input_jacobian(self.net, x, slice(x.shape[-1] - xi.shape[-1], None))
        assert out is not None  # an MLP of `mechanics.mlp.MLP`'s form
        return self.scale * out[1]

    def describe(self) -> str:
        return f"nn (F(g, xi~) {_mlp_desc(self.net)})"


class ControlForce(nn.Module):
    """Learned control torque tau = C u(R, w~) on the rotational components of every body.

    C (3B x n_inputs) has unit-norm columns (normalised from a free parameter: the factorisation
    C u is only identifiable up to u -> S^-1 u, C -> C S, the normalisation removes the scale),
    u is a GELU MLP of the flattened rotations and rotational velocity estimates of all bodies.
    Translational components of SE(3) bodies get no control force.
    """

    name = "control"

    def __init__(self, G: ProductGroup, scale: float = 1.0, n_inputs: int = 3, width: int = 64, depth: int = 3):
        super().__init__()
        self.G = G
        k = 3 * G.n_bodies
        if int(n_inputs) < 1:
            raise ValueError(f"force.control.n_inputs must be >= 1, got {n_inputs}")
        init = torch.eye(k, int(n_inputs), dtype=torch.float64)
        if int(n_inputs) > k:  # more inputs than torque components: spread the extra columns
            init = init + torch.ones(k, int(n_inputs), dtype=torch.float64) / k
        self.C_raw = nn.Parameter(init)
        self.register_buffer("scale", torch.tensor(float(scale), dtype=torch.float64))
        self.u = MLP(9 * G.n_bodies + k, int(n_inputs), width, depth)

    def C(self) -> torch.Tensor:
        """(3B, n_inputs) input matrix with unit-norm columns."""
        return self.C_raw / torch.linalg.vector_norm(self.C_raw, dim=0, keepdim=True).clamp_min(1e-12)

    def torque(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        """(..., B, 3) control torque per body at (g, xi~)."""
        w, _ = self.G.split(xi)
        lead = w.shape[:-2]
        x = torch.cat((g.R.reshape(*lead, -1), w.reshape(*lead, -1)), -1)
        tau = self.scale * (self.u(x) @ self.C().T)
        return tau.reshape(*lead, self.G.n_bodies, 3)

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        tau = self.torque(g, xi)
        return self.G.join(tau, tau.new_zeros(*tau.shape[:-2], self.G.n_se3, 3))

    def describe(self) -> str:
        return f"control (tau = C u, C {self.C_raw.shape[0]}x{self.C_raw.shape[1]} unit columns, u {_mlp_desc(self.u)})"


class PDControl(nn.Module):
    """Known PD attitude control (the true force of the pd_control scene; not learnable, not in FORCES).

    tau = -K_R e_R - K_w w~ (+ m g rho x (R^T e3) when `feedforward`, cancelling the gravity torque),
    e_R = vee(R_f^T R - R^T R_f) / 2, on every body's rotation (SO(3) bodies on a pivot).
    """

    name = "pd_control"

    R_f: torch.Tensor
    mg_rho: torch.Tensor

    def __init__(
        self,
        G: ProductGroup,
        K_R: float,
        K_w: float,
        R_f,
        feedforward: bool = False,
        m: float = 0.0,
        rho=(0.0, 0.0, 0.0),
        g: float = 0.0,
        scale: float = 1.0,
    ):
        super().__init__()
        self.G, self.K_R, self.K_w, self.feedforward = G, float(K_R), float(K_w), bool(feedforward)
        self.register_buffer("R_f", torch.as_tensor(R_f, dtype=torch.float64).reshape(3, 3))
        self.register_buffer("mg_rho", float(m) * float(g) * torch.as_tensor(rho, dtype=torch.float64).reshape(3))

    def torque(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        w, _ = self.G.split(xi)
        R = g.R
        Rf = self.R_f.expand_as(R)
        # so3.vee(A) is the vee of the skew part (A - A^T)/2, so this is vee(R_f^T R - R^T R_f)/2
        e_R = so3.vee(Rf.transpose(-1, -2) @ R)
        tau = -self.K_R * e_R - self.K_w * w
        if self.feedforward:
            tau = tau + torch.cross(self.mg_rho.expand_as(w), R[..., 2, :], dim=-1)
        return tau

    def forward(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        tau = self.torque(g, xi)
        return self.G.join(tau, tau.new_zeros(*tau.shape[:-2], self.G.n_se3, 3))

    def jacobian_xi(self, g: Pose, xi: torch.Tensor) -> torch.Tensor:
        eye = -self.K_w * torch.eye(self.G.dim, dtype=xi.dtype, device=xi.device)
        for s in self.G.body_slices()[: self.G.n_se3]:  # translational parts carry no torque
            eye[s.start + 3 : s.stop, s.start + 3 : s.stop] = 0.0
        return eye.expand(*xi.shape[:-1], self.G.dim, self.G.dim)

    def describe(self) -> str:
        return "pd_control (true PD torque" + (" + gravity feed-forward" if self.feedforward else "") + ")"


FORCES = {
    "rayleigh": RayleighForce,
    "rayleigh_nonlinear": RayleighNonlinearForce,
    "nn": NNForce,
    "control": ControlForce,
}
"""Learnable forces by config option name (conf/force/<name>.yaml)."""


def force_jacobian_xi(force: nn.Module, g: Pose, xi: torch.Tensor) -> torch.Tensor:
    """dF(g, xi~)/d xi~ (..., dim, dim): the force's closed form if it has one, else autodiff
    (one reverse pass per tangent direction; rows of the batch are independent)."""
    closed_form = getattr(force, "jacobian_xi", None)
    if closed_form is not None:
        return closed_form(g, xi)
    with torch.enable_grad():
        x = xi.detach().requires_grad_(True)
        F = force(g, x)
        rows = [
            torch.autograd.grad(F[..., i].sum(), x, retain_graph=True, create_graph=False)[0]
            for i in range(F.shape[-1])
        ]
    return torch.stack(rows, -2)


def build_forces(G: ProductGroup, forces, scale: float) -> list[nn.Module]:
    """Instantiate forces from names or from a mapping name -> kwargs (extra keys like
    `_target_` are ignored: the registry key decides the class)."""
    items = forces.items() if hasattr(forces, "items") else [(f, {}) for f in forces]
    out = []
    for name, kwargs in items:
        if name not in FORCES:
            raise ValueError(f"unknown force {name!r}; choose from {sorted(FORCES)}")
        kw = {k: v for k, v in dict(kwargs or {}).items() if not k.startswith("_")}
        out.append(FORCES[name](G, scale=scale, **kw))
    return out
