"""Structured parameterisations that hold their guarantees for every parameter value.

Inertia: J = R_theta diag(e^a+e^b, e^a+e^c, e^b+e^c) R_theta^T (SPD and obeys the triangle
inequality of a physical body), J_d = tr(J)/2 I - J (the matrix-representation inertia of the
discrete rigid-body Lagrangian). Damping: D = L L^T + diag(lambda^2) with L lower triangular
(SPSD), started with every entry receiving gradient. Mass: m = exp(log_m) > 0.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..lie import so3


def jd_from_j(J: torch.Tensor) -> torch.Tensor:
    """J (..., 3, 3) -> J_d = tr(J)/2 I - J, the inverse map of J = tr(J_d) I - J_d."""
    tr = J.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    return 0.5 * tr * torch.eye(3, dtype=J.dtype, device=J.device) - J


class Inertia(nn.Module):
    """Per-body SPD inertia for `n` bodies; `J()` and `Jd()` have shape (n, 3, 3)."""

    def __init__(self, n: int, scale=1.0, jitter: float = 0.0, generator=None):
        """scale: initial J = scale I, a float or one value per body."""
        super().__init__()
        self.r = nn.Parameter(jitter * torch.randn(n, 3, generator=generator, dtype=torch.float64))
        log_half = torch.log(0.5 * torch.as_tensor(scale, dtype=torch.float64)).expand(n)[:, None]
        abc = log_half + jitter * torch.randn(n, 3, generator=generator, dtype=torch.float64)
        self.abc = nn.Parameter(abc)

    def J(self) -> torch.Tensor:
        e = torch.exp(self.abc)
        diag = torch.stack((e[:, 0] + e[:, 1], e[:, 0] + e[:, 2], e[:, 1] + e[:, 2]), -1)
        Rt = so3.exp(self.r)
        return Rt @ torch.diag_embed(diag) @ Rt.transpose(-1, -2)

    def Jd(self) -> torch.Tensor:
        return jd_from_j(self.J())

    @torch.no_grad()
    def set_J(self, J: torch.Tensor) -> None:
        """Set parameters so that J() == J (J (n, 3, 3) SPD with the triangle inequality)."""
        evals, evecs = torch.linalg.eigh(J.to(self.abc))
        evecs = evecs * torch.sign(torch.linalg.det(evecs))[..., None, None]
        ea = 0.5 * (evals[:, 0] + evals[:, 1] - evals[:, 2])
        eb = 0.5 * (evals[:, 0] - evals[:, 1] + evals[:, 2])
        ec = 0.5 * (-evals[:, 0] + evals[:, 1] + evals[:, 2])
        e = torch.stack((ea, eb, ec), -1)
        if (e <= 0).any():
            raise ValueError("inertia violates the triangle inequality; it is not a physical rigid body")
        self.abc.copy_(torch.log(e))
        self.r.copy_(so3.log(evecs))


class SPSDMatrix(nn.Module):
    """D = L L^T + diag(lambda^2), shape (dim, dim), SPSD for all parameters.

    Initialisation (D = init_diag I): L = sqrt(init_diag / 2) I (+ jitter below the diagonal) and
    lambda = sqrt(init_diag / 2) 1. Every parameter then receives gradient from the first step:
    d(L L^T)/dL_ij = E_ij L^T + L E_ji = c (E_ij + E_ji) at L = c I, c != 0, so off-diagonal
    damping can be learned. (With L = 0 the gradient of every L entry vanishes, L L^T is stuck at
    0 and only diagonal damping is ever fitted; with lambda = 0 likewise for lambda.)
    """

    _rows: torch.Tensor
    _cols: torch.Tensor

    def __init__(self, dim: int, init_diag: float = 0.1, jitter: float = 0.0, generator=None):
        super().__init__()
        self.dim = dim
        rows, cols = torch.tril_indices(dim, dim)
        self.register_buffer("_rows", rows, persistent=False)
        self.register_buffer("_cols", cols, persistent=False)
        c = math.sqrt(0.5 * init_diag)
        entries = c * (rows == cols).to(torch.float64)
        if jitter:
            off = (rows != cols).to(torch.float64)
            entries = entries + jitter * c * off * torch.randn(len(rows), generator=generator, dtype=torch.float64)
        self.L_entries = nn.Parameter(entries)
        self.lam = nn.Parameter(torch.full((dim,), c, dtype=torch.float64))

    @property
    def L(self) -> torch.Tensor:
        """Lower-triangular factor (dim, dim)."""
        L = self.L_entries.new_zeros(self.dim, self.dim)
        return L.index_put((self._rows, self._cols), self.L_entries)

    def forward(self) -> torch.Tensor:
        L = self.L
        M = L @ L.T  # symmetrised: matmul kernels need not round L L^T symmetrically
        return 0.5 * (M + M.T) + torch.diag(self.lam**2)

    @torch.no_grad()
    def set_matrix(self, D: torch.Tensor) -> None:
        """Set parameters so that forward() == D (D SPSD): diagonal D in lambda (L = 0), else its
        Cholesky factor in L (lambda = 0). Used for frozen, known damping."""
        D = D.to(self.L_entries)
        if torch.count_nonzero(D - torch.diag(torch.diagonal(D))) == 0:
            self.L_entries.zero_()
            self.lam.copy_(torch.sqrt(torch.clamp(torch.diagonal(D), min=0.0)))
        else:
            L = torch.linalg.cholesky(D + 1e-12 * torch.eye(self.dim, dtype=D.dtype, device=D.device))
            self.L_entries.copy_(L[self._rows, self._cols])
            self.lam.zero_()


class PositiveVector(nn.Module):
    """x = exp(log_x) > 0, shape (n,)."""

    def __init__(self, n: int, init: float = 1.0):
        super().__init__()
        self.log_x = nn.Parameter(torch.full((n,), math.log(init), dtype=torch.float64))

    def forward(self) -> torch.Tensor:
        return torch.exp(self.log_x)

    @torch.no_grad()
    def set_value(self, x: torch.Tensor) -> None:
        self.log_x.copy_(torch.log(x.to(self.log_x)))
