"""Fused hot paths of LieDFLNN, part 4 (see `models.liedflnn.engines.core`): the rollout of a single rigid body on
SO(3) with a linear Newton residual (no force, or constant Rayleigh damping) in *column* layout.

Layout: a batch of T rotations is held as one (3, 3, T) tensor, entry (i, j) of trajectory t at
[i, j, t] (structure of arrays), instead of the (T, 1, 3, 3) of the rest of the package. Every
3x3 product is then three broadcast multiply-adds over contiguous rows of length T, and every
linear map of the 9 entries one wide (k x 9) @ (9 x T) product. On a CPU this is several times
faster than the row layout at large batches, where a (T, 3, 3) batched product runs one tiny
matrix at a time (measured: 10,000 products, 0.12 ms against 0.8-1.2 ms; docs/benchmarks.md).

What it computes is `fused_rollout`'s step, term by term and in the same order of operations
where it matters (residual W.flatten() @ lin_f + const, Jacobian W.flatten() @ lin_J, closed-form
3x3 solve, retraction R exp(hat(delta)), Newton-Schulz cleaning of the increment, g_{k+1} = g_k W),
and its Newton loop is `solvers.newton`'s, in the layout `COLUMNS` (the same acceptance and
convergence tests, iteration counts and compaction to the rows still iterating). The rare iteration that needs care
(a singular Jacobian, or a full step without decrease) hands the rows still iterating to the row
layout's loop (`FusedStep.from_parts`), which takes them to the end: same algorithm, same results.

    applies(model, g0)                       whether a rollout takes this path
    rollout(model, g0, g1, steps, opts)      `solvers.rollout.rollout_implicit` for those models
"""

from __future__ import annotations

import time

import torch

from ....lie import Pose
from ....lie.batched import HISTORY, TRUST
from ....lie.tolerances import projects_poses
from ....mechanics.forces import RayleighForce
from ....mechanics.potentials import MLPPotential
from ....solvers import newton
from ....solvers.options import SolverOptions
from ....solvers.rollout import Rollout
from ... import mlp_derivatives
from .maps import _constants, potential_covector
from .rollout import FusedStep, RolloutMaps, rollout_maps

MIN_ROWS = 32
"""Batches below this many trajectories keep the row layout: fewer kernel calls per step, which is
what counts there (idle, 2026-11-27, SO(3) MLP 10x2: rows 1.37 / 0.13 ms per step at batch 1 / 10
against 1.87 / 0.16 in columns; columns faster from 32 on; docs/benchmarks.md)."""


def applies(model, g0: Pose) -> bool:
    """Whether `model`'s rollout from g0 takes the column path: a LieDFLNN on the fused path of
    one SO(3) body, with no force or only constant Rayleigh damping, poses (T, 1, 3, 3) of a dtype
    whose poses need no re-projection (float64), T >= MIN_ROWS."""
    return single_linear_so3(model, g0) and g0.R.shape[0] >= MIN_ROWS and not projects_poses(g0.R.dtype)


def single_linear_so3(model, g0: Pose) -> bool:
    """A LieDFLNN on the fused path of one SO(3) body whose Newton residual is linear in the increment
    (no force, or only constant Rayleigh damping), poses (T, 1, 3, 3): what the column layout and the
    float path (`fused_scalar`) both need."""
    G = model.G
    return (
        model._fused()
        and G.n_bodies == 1
        and G.n_se3 == 0
        and g0.R.dim() == 4
        and all(isinstance(f, RayleighForce) for f in model.forces)
    )


# ---------------------------------------------------------------------------- column algebra
def to_columns(R: torch.Tensor) -> torch.Tensor:
    """(T, 1, 3, 3) rotations -> (3, 3, T) columns (a copy)."""
    return R[:, 0].permute(1, 2, 0).contiguous()


def matmul(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """A B for columns (3, 3, T) (either may be a transposed view): C_ij = sum_k A_ik B_kj."""
    C = torch.mul(A[:, 0:1], B[0:1], out=A.new_empty(3, 3, A.shape[-1]))  # contiguous whatever T
    C.addcmul_(A[:, 1:2], B[1:2])
    return C.addcmul_(A[:, 2:3], B[2:3])


def adjugate_index() -> list[int]:
    """Which of a 3x3 J's 9 entries (row major) `adjugate_rows` reads, in its order: the rows b x c,
    c x a, a x b of the adjugate from J's rows a, b, c, each cross product's two terms."""
    nxt = [(i + 1) % 3 for i in range(3)]
    nnx = [(i + 2) % 3 for i in range(3)]
    pairs = [(1, 2), (2, 0), (0, 1)]
    u1 = [3 * p + nxt[i] for p, _ in pairs for i in range(3)]
    v2 = [3 * q + nnx[i] for _, q in pairs for i in range(3)]
    u2 = [3 * p + nnx[i] for p, _ in pairs for i in range(3)]
    v1 = [3 * q + nxt[i] for _, q in pairs for i in range(3)]
    return u1 + v2 + u2 + v1


def adjugate_rows(G: torch.Tensor) -> torch.Tensor:
    """(b x c, c x a, a x b) of the rows a, b, c of a 3x3 J, as (9, T), from G (36, T) = J's
    entries gathered by `adjugate_index()` (`ColumnMaps.J_gathered` @ W)."""
    G = G.view(4, 9, -1)
    return torch.addcmul(G[0] * G[1], G[2], G[3], value=-1.0)


def row_cross_sum(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """sum_k A_k x B_k over the rows k of 3x3 columns A, B (9, T) -> (3, T), as vee(B^T A - A^T B):
    hat(a x b) = b a^T - a b^T, and B^T A = sum_k b_k a_k^T (one column product, no gathers)."""
    A3, B3 = A.view(3, 3, -1), B.view(3, 3, -1)
    M = matmul(B3.transpose(0, 1), A3).view(9, -1)
    c = A.new_empty(3, A.shape[-1])
    torch.sub(M[7], M[5], out=c[0])  # vee(X) = (X_21, X_02, X_10) of X = M - M^T
    torch.sub(M[2], M[6], out=c[1])
    torch.sub(M[3], M[1], out=c[2])
    return c


def norm(a: torch.Tensor) -> torch.Tensor:
    """The 2-norm along the first axis, (n, T) -> (T,) (`vector_norm(dim=0)` is 30x slower here)."""
    return (a * a).sum(0).sqrt_()


class ColumnStep:
    """The Newton problem of one step in column layout: the unknown increment W (9, T) (W's rows
    flattened), the residual const + lin_f^T W (3, T), its Jacobian lin_J^T W (9, T) (entry (i, j)
    at row 3 i + j)."""

    def __init__(self, cols: ColumnMaps, const: torch.Tensor, g: torch.Tensor):
        self.cols, self.const, self.g = cols, const, g  # const (3, T), g (9, T): g_k

    def f(self, W: torch.Tensor) -> torch.Tensor:
        return torch.addmm(self.const, self.cols.f, W)

    def iterate(self, W: torch.Tensor, r: torch.Tensor):
        """One full Newton step from W: (delta (3, T), singular (T,), W', residual at W')."""
        JG = self.cols.J_gathered @ W  # (39, T): the entries the adjugate needs, then J's first row
        adj = adjugate_rows(JG[:36])  # rows: b x c, c x a, a x b of J's rows a, b, c (`fused_maps.solve_small`)
        det = (JG[36:] * adj[0:3]).sum(0)
        delta = (adj.view(3, 3, -1) * r[:, None]).sum(0).div_(det).neg_()
        cand = self.retract(W, delta)
        return delta, det == 0, cand, self.f(cand)

    def problem(self) -> newton.NewtonProblem:
        """This step as `solvers.newton`'s problem in `COLUMNS` (no Jacobian: careful iterations are
        handed over; x0 unused: the loop starts from the W it is given)."""
        return newton.NewtonProblem(
            self.f, None, None, self.retract, self.iterate, self.restrict, layout=COLUMNS, hand_over=self.hand_over
        )

    def retract(self, W: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        return retract(W, delta, self.cols)

    def restrict(self, rows: torch.Tensor) -> newton.NewtonProblem:
        return ColumnStep(self.cols, self.const.index_select(1, rows), self.g.index_select(1, rows)).problem()

    def hand_over(self, rows: torch.Tensor, W: torch.Tensor, r: torch.Tensor, rn: torch.Tensor, opts, max_iter: int):
        """The rows solved from W (9, k) on in row layout (`fused_rollout.FusedStep`, whose loop does
        the careful iterations) -> (W, r, converged, iterations) in columns."""
        const = self.const.index_select(1, rows).T.contiguous()
        g = self.g.index_select(1, rows).T.reshape(-1, 1, 3, 3)
        step = FusedStep.from_parts(self.cols.model, self.cols.maps, Pose(g, g.new_zeros(g.shape[0], 0, 3)), const)
        x0 = Pose(W.T.reshape(-1, 1, 3, 3), W.new_zeros(W.shape[1], 0, 3))
        xs, rs, cs, its = newton._newton_rows(step.problem(None), x0, r.T.contiguous(), rn, opts, max_iter)
        return xs.R.reshape(-1, 9).T, rs.T, cs, its


class ColumnMaps:
    """The linear maps of `RolloutMaps.linear`, transposed for columns: f (3, 9), the Jacobian's
    gathered entries J_gathered (39, 9), c (3, 9), and the constants of the retraction."""

    def __init__(self, model, maps: RolloutMaps):
        assert maps.linear is not None
        lin_f, lin_J, lin_c = maps.linear
        self.model, self.maps = model, maps
        self.f, self.c = lin_f.T.contiguous(), lin_c.T.contiguous()
        J = lin_J.T  # (9, 9): the Jacobian's entries from W
        # J's entries in the order the adjugate reads them, and its first row: one product per iteration
        self.J_gathered = torch.cat((J[adjugate_index()], J[0:3])).contiguous()
        self.hat_t = _constants(lin_f.dtype, lin_f.device)["hat"].T.contiguous()  # (9, 3): hat(w).flatten() = hat_t @ w


def retract(W: torch.Tensor, delta: torch.Tensor, cols: ColumnMaps) -> torch.Tensor:
    """W exp(hat(delta)) for W (9, T), delta (3, T): `lie.batched.retract_increment`'s closed form,
    exp(hat(w)) = cos t I + sinc(t) hat(w) + cosc(t) w w^T (t = |w|; at t = 0, w = 0)."""
    t = norm(delta).clamp_(min=torch.finfo(delta.dtype).tiny)
    sinc = torch.sin(t).div_(t)
    cosc = torch.sin(0.5 * t).div_(t).square_().mul_(2.0)
    E = torch.mul((cosc * delta)[:, None], delta[None], out=delta.new_empty(3, 3, delta.shape[-1]))  # cosc w w^T
    E9 = E.view(9, -1)
    E9.add_(cols.hat_t @ (sinc * delta))
    E9[0::4].add_(torch.cos(t))
    return matmul(W.view(3, 3, -1), E).view(9, -1)


def newton_schulz(W: torch.Tensor) -> torch.Tensor:
    """W (3 I - W^T W) / 2 for W (9, T): one Newton-Schulz step towards SO(3) (`rollout_advance`)."""
    W3 = W.view(3, 3, -1)
    M = matmul(W3.transpose(0, 1), W3).neg_()
    M.view(9, -1)[0::4].add_(3.0)
    return matmul(W3, M).mul_(0.5).view(9, -1)


def extrapolate_columns(incs: list[torch.Tensor]) -> torch.Tensor:
    """`lie.batched.extrapolate_increments` for increments as columns (9, T), oldest first: W, or E W with
    E = D (two increments) or D D'^T D (three; D = W W_1^T, D' = W_1 W_2^T); W in the columns where E is
    further from the identity than `TRUST` times W (3 - tr) or is not finite."""
    W = incs[-1]
    if len(incs) == 1:
        return W
    W3, W1 = W.view(3, 3, -1), incs[-2].view(3, 3, -1)
    E = matmul(W3, W1.transpose(0, 1))
    if len(incs) == 3:
        E = matmul(matmul(E, matmul(W1, incs[-3].view(3, 3, -1).transpose(0, 1)).transpose(0, 1)), E)
    guess = matmul(E, W3).view(9, -1)
    Ef = E.view(9, -1)
    ok = (3.0 - (Ef[0] + Ef[4] + Ef[8])) <= (TRUST * TRUST) * (3.0 - (W[0] + W[4] + W[8]))  # NaN: False
    return guess if bool(ok.all()) else torch.where(ok, guess, W)


def potential_columns(model, maps: RolloutMaps, g: torch.Tensor) -> torch.Tensor | None:
    """-h dV(g exp(eta))/d eta at 0 as columns (3, T), g (9, T); None without a potential.
    An MLP potential without a graph is evaluated in columns (`mlp_derivatives`); any other
    through the row layout."""
    if model.potential is None:
        return None
    if maps.potential_layers is not None and isinstance(model.potential, MLPPotential):
        dx = mlp_derivatives.gradient_columns(maps.potential_layers, g, -model.h)  # (9, T)
        return row_cross_sum(dx, g)  # `mlp_derivatives.left_covector`: sum over rows k of dR_k x R_k
    R = g.T.reshape(-1, 1, 3, 3)
    return potential_covector(model, Pose(R, R.new_zeros(R.shape[0], 0, 3))).detach().T


# ---------------------------------------------------------------------------- the Newton loop
class Columns(newton.Layout):
    """The batch on the last axis: W (9, T), r (3, T), delta (3, T); W holds rotation increments,
    whose entries are at most 1, so the rounding floor of the convergence test is the float's."""

    def size(self, r: torch.Tensor) -> int:
        return r.shape[1]

    def norm(self, r: torch.Tensor) -> torch.Tensor:
        return norm(r)

    def step_size(self, delta: torch.Tensor) -> torch.Tensor:
        return delta.abs().amax(0)

    def step_tolerance(self, x, tol: float):
        return max(tol, newton.ROUNDING_ULPS * torch.finfo(x.dtype).eps)  # `newton.step_tolerance` of rotations

    def take(self, x, rows: torch.Tensor):
        return x.index_select(1, rows)

    def put(self, x, rows: torch.Tensor, values):
        return x.index_copy(1, rows, values)


COLUMNS = Columns()


def solve(step: ColumnStep, W: torch.Tensor, r: torch.Tensor, rn: torch.Tensor, opts: SolverOptions, max_iter: int):
    """`solvers.newton`'s loop in columns from (W, r = f(W), rn = |r|) ->
    (W, r, converged (T,), iterations (T,))."""
    return newton._newton_rows(step.problem(), W, r, rn, opts, max_iter)


# ---------------------------------------------------------------------------- the rollout
@torch.no_grad()
def rollout(model, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout:
    """`rollout_implicit(model, ...)` in column layout (`applies(model, g0)` must hold); a rollout
    the plan compiles takes the rows engine instead (`engines/choose.py`)."""
    t0 = time.perf_counter()
    T = g0.R.shape[0]
    maps = rollout_maps(model)
    cols = ColumnMaps(model, maps)
    n_poses = max(steps, 1) + 1  # g0, g1 and g2..g_steps
    out = g0.R.new_empty(n_poses, 9, T)
    out[0], out[1] = to_columns(g0.R).view(9, T), to_columns(g1.R).view(9, T)
    g = out[1]
    W_prev = to_columns(model.G.increment(g0, g1).R).view(9, T)
    history = [W_prev]  # the last increments, oldest first (warm start)
    conv, its, res = [], [], []
    for k in range(1, steps):
        cov = potential_columns(model, maps, g)
        const = cols.c @ W_prev if cov is None else torch.addmm(cov, cols.c, W_prev)
        step = ColumnStep(cols, const, g)
        W0 = extrapolate_columns(history)
        r = step.f(W0)
        W, r, converged, iterations = solve(step, W0, r, norm(r), opts, opts.max_iter)
        W_prev = newton_schulz(W)
        history = [*history, W_prev][-HISTORY:]
        g = out[k + 1]
        g.view(3, 3, T).copy_(matmul(out[k].view(3, 3, T), W_prev.view(3, 3, T)))
        conv.append(converged)
        its.append(iterations)
        res.append(r.abs().amax(0))
        if progress is not None:
            progress(k)
    n = max(steps - 1, 0)
    R = out.permute(2, 0, 1).reshape(T, n_poses, 1, 3, 3)
    pose = Pose(R, g0.p.new_zeros(T, n_poses, 0, 3))

    def stacked(xs, dtype):
        return torch.stack(xs, 1) if xs else torch.zeros(T, n, dtype=dtype, device=g0.R.device)

    return Rollout(
        pose,
        stacked(conv, torch.bool),
        stacked(its, torch.long),
        stacked(res, g0.R.dtype),
        time.perf_counter() - t0,
    )
