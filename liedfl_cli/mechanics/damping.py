"""Per-body damping on SE(3)^m x SO(3)^n: block-diagonal D with one SPSD block per body.

The paper learns every component of a multibody system "as if [the bodies] were single rigid
bodies", so each body gets its own damping block D_b (6x6 for an SE(3) body, 3x3 for an SO(3)
body) acting on its own velocity estimate xi~_b; the coupled alternative (one dim x dim matrix,
`coupling: coupled` in the force configs) couples every pair of bodies.

- `PerBodySPSD`: constant blocks D_b = L_b L_b^T + diag(lambda_b^2) (`parameterizations.SPSDMatrix`
  per body).
- `PerBodyDampingNet`: configuration-dependent blocks D_b(g_b) = L_b(g_b) L_b(g_b)^T with
  L_b(g_b) = c (I + tril(H_b phi(g_b))): ONE shared GELU trunk phi (width x depth) of the body's own
  configuration (its 9 rotation entries and, for SE(3) bodies, its 3 position entries; zeros for
  SO(3) bodies) and one linear head H_b per body. Why shared trunk + per-body heads rather than one
  MLP per body: (i) parameters grow as width^2 + B * width * k instead of B * width^2 (Exp 4, width
  32, depth 3: 7,577 instead of 61,081 for 23 separate MLPs and 95,588 for the coupled 72x72 form);
  (ii) the data of Exp 4 are two recordings of ~470 frames: a shared trunk is fitted to the
  orientations of all 23 bodies (~21,000 samples) instead of ~940 per body, while the heads keep
  every body's damping its own; (iii) one batched evaluation for all bodies.

Both are exactly symmetric positive semidefinite for every parameter value and every g.
Layout of the flat tangent vector (body by body, SE(3) bodies first) as in `lie.ProductGroup`.
"""

from __future__ import annotations

import math
from typing import cast

import torch
from torch import nn

from ..lie import Pose, ProductGroup
from .mlp import MLP
from .parameterizations import SPSDMatrix


def body_dims(G: ProductGroup) -> list[int]:
    """Tangent dimension of each body: 6 for SE(3), 3 for SO(3)."""
    return [6] * G.n_se3 + [3] * G.n_so3


def split_bodies(G: ProductGroup, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., dim) -> (SE(3) part (..., m, 6), SO(3) part (..., n, 3))."""
    m = G.n_se3
    lead = xi.shape[:-1]
    return xi[..., : 6 * m].reshape(*lead, m, 6), xi[..., 6 * m :].reshape(*lead, G.n_so3, 3)


def join_bodies(se: torch.Tensor, so: torch.Tensor) -> torch.Tensor:
    """Inverse of `split_bodies`."""
    return torch.cat((se.flatten(-2), so.flatten(-2)), -1)


def block_diagonal(G: ProductGroup, se: torch.Tensor, so: torch.Tensor) -> torch.Tensor:
    """Blocks (..., m, 6, 6) and (..., n, 3, 3) -> the (..., dim, dim) block-diagonal matrix (one
    scatter of all blocks' entries: one autograd node, whatever the number of bodies)."""
    lead = se.shape[:-3] if G.n_se3 else so.shape[:-3]
    ref = se if G.n_se3 else so
    entries = torch.cat((se.flatten(-3), so.flatten(-3)), -1)  # (..., 36 m + 9 n), body after body
    out = ref.new_zeros(*lead, G.dim * G.dim)
    out = out.index_copy(-1, _block_positions(G, ref.device), entries)
    return out.view(*lead, G.dim, G.dim)


def _block_positions(G: ProductGroup, device: torch.device) -> torch.Tensor:
    """Positions in the flattened (dim, dim) matrix of every block entry, body after body, row major."""
    key = (G.n_se3, G.n_so3, device)
    if key not in _POSITIONS:
        pos = [i * G.dim + j for s in G.body_slices() for i in range(s.start, s.stop) for j in range(s.start, s.stop)]
        _POSITIONS[key] = torch.tensor(pos, dtype=torch.long, device=device)
    return _POSITIONS[key]


_POSITIONS: dict[tuple, torch.Tensor] = {}


def apply_blocks(G: ProductGroup, se: torch.Tensor, so: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """(blockdiag(se, so) xi) without forming the dim x dim matrix, (..., dim)."""
    a, b = split_bodies(G, xi)
    return join_bodies((se @ a[..., None])[..., 0], (so @ b[..., None])[..., 0])


def _sym(M: torch.Tensor) -> torch.Tensor:
    """M + M^T over 2, exactly symmetric (a batched matmul need not round L L^T symmetrically)."""
    return 0.5 * (M + M.transpose(-1, -2))


class PerBodySPSD(nn.Module):
    """Constant block-diagonal SPSD damping: one `SPSDMatrix` per body (starts at init_diag I)."""

    def __init__(self, G: ProductGroup, init_diag: float = 0.1):
        super().__init__()
        self.G, self.dim = G, G.dim
        self.blocks = nn.ModuleList(SPSDMatrix(d, init_diag=init_diag) for d in body_dims(G))

    def forward(self) -> torch.Tensor:
        """(dim, dim) block-diagonal D."""
        return block_diagonal(self.G, *self.block_matrices())

    def block_matrices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(D_se (m, 6, 6), D_so (n, 3, 3)): each body's block `SPSDMatrix()`, all bodies of a size at
        once (the blocks' parameters stacked: a few kernels instead of a few per body)."""
        G = self.G
        every = [cast(SPSDMatrix, b) for b in self.blocks]  # nn.ModuleList yields nn.Module
        out = []
        for first, count, n in ((0, G.n_se3, 6), (G.n_se3, G.n_so3, 3)):
            blocks = every[first : first + count]
            if not blocks:
                out.append(every[0].lam.new_zeros(0, n, n))
                continue
            entries = torch.stack([b.L_entries for b in blocks])  # (k, n (n + 1) / 2)
            lam = torch.stack([b.lam for b in blocks])  # (k, n)
            rows, cols = blocks[0]._rows, blocks[0]._cols
            L = entries.new_zeros(count, n * n).index_copy(1, rows * n + cols, entries).view(count, n, n)
            out.append(_sym(L @ L.transpose(-1, -2)) + torch.diag_embed(lam * lam))
        return out[0], out[1]

    @torch.no_grad()
    def set_matrix(self, D: torch.Tensor) -> None:
        """Set from a (dim, dim) matrix; its off-block entries must vanish."""
        mask = block_diagonal(
            self.G,
            torch.ones(self.G.n_se3, 6, 6, dtype=D.dtype, device=D.device),
            torch.ones(self.G.n_so3, 3, 3, dtype=D.dtype, device=D.device),
        )
        if torch.count_nonzero(D * (1 - mask)):
            raise ValueError("damping couples different bodies; per-body damping cannot represent it")
        for blk, s in zip(self.blocks, self.G.body_slices()):
            cast(SPSDMatrix, blk).set_matrix(D[s, s])  # nn.ModuleList yields nn.Module


class PerBodyDampingNet(nn.Module):
    """Configuration-dependent per-body factors L_b(g_b) (see the module docstring).

    `blocks(g)` -> (D_se (..., m, 6, 6), D_so (..., n, 3, 3)); D_b = L_b L_b^T, exactly symmetric.
    The heads start at `out_scale` of PyTorch's default size, so D(g) starts near c^2 I.
    """

    IN = 12  # 9 rotation entries + 3 position entries (zeros for SO(3) bodies)

    def __init__(
        self, G: ProductGroup, c: float, width: int = 64, depth: int = 3, out_scale: float = 0.1, generator=None
    ):
        super().__init__()
        self.G = G
        self.register_buffer("c", torch.tensor(float(c), dtype=torch.float64))
        trunk = MLP(self.IN, 1, width, depth)
        self.trunk = nn.Sequential(*list(trunk)[:-1])  # hidden GELU layers only: features of width `width`
        bound = out_scale / math.sqrt(width)

        def head(n: int, k: int) -> nn.Parameter | None:
            if n == 0:
                return None
            w = (2 * torch.rand(n, width, k, generator=generator, dtype=torch.float64) - 1) * bound
            return nn.Parameter(w)

        self.w_se3, self.w_so3 = head(G.n_se3, 21), head(G.n_so3, 6)
        self.b_se3 = nn.Parameter(torch.zeros(G.n_se3, 21, dtype=torch.float64)) if G.n_se3 else None
        self.b_so3 = nn.Parameter(torch.zeros(G.n_so3, 6, dtype=torch.float64)) if G.n_so3 else None
        for k, n in (("6", 6), ("3", 3)):
            rows, cols = torch.tril_indices(n, n)
            self.register_buffer(f"_rows{k}", rows, persistent=False)
            self.register_buffer(f"_cols{k}", cols, persistent=False)
            self.register_buffer(f"_eye{k}", (rows == cols).to(torch.float64), persistent=False)
        self.width, self.depth = int(width), int(depth)

    def features(self, g: Pose) -> torch.Tensor:
        """Per-body inputs (..., B, 12) -> trunk features (..., B, width)."""
        R = g.R.flatten(-2)  # (..., B, 9)
        p = torch.cat((g.p, g.p.new_zeros(*g.p.shape[:-2], self.G.n_so3, 3)), -2)
        return self.trunk(torch.cat((R, p), -1))

    def _factor(self, phi, W, b, n: int, key: str) -> torch.Tensor:
        entries = self.c * (getattr(self, f"_eye{key}") + torch.einsum("...bw,bwk->...bk", phi, W) + b)
        L = entries.new_zeros(*entries.shape[:-1], n, n)
        L[..., getattr(self, f"_rows{key}"), getattr(self, f"_cols{key}")] = entries
        return L

    def factors(self, g: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        """(L_se (..., m, 6, 6), L_so (..., n, 3, 3)) lower-triangular factors."""
        phi = self.features(g)
        m = self.G.n_se3
        lead = phi.shape[:-2]
        L_se = self._factor(phi[..., :m, :], self.w_se3, self.b_se3, 6, "6") if m else phi.new_zeros(*lead, 0, 6, 6)
        L_so = (
            self._factor(phi[..., m:, :], self.w_so3, self.b_so3, 3, "3")
            if self.G.n_so3
            else phi.new_zeros(*lead, 0, 3, 3)
        )
        return L_se, L_so

    def blocks(self, g: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        L_se, L_so = self.factors(g)
        return _sym(L_se @ L_se.transpose(-1, -2)), _sym(L_so @ L_so.transpose(-1, -2))

    def describe(self) -> str:
        return f"per body: shared trunk MLP {self.width}x{self.depth} + {self.G.n_bodies} heads"


__all__ = [
    "body_dims",
    "split_bodies",
    "join_bodies",
    "block_diagonal",
    "apply_blocks",
    "PerBodySPSD",
    "PerBodyDampingNet",
]
