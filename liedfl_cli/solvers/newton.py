"""Batched damped Newton for implicit steps: find x with f(x) = 0 row by row.

`x` lives on a manifold (a Pose of increments, or a plain tensor); steps are taken with
`retract(x, delta)` and the Jacobian is d f(retract(x, delta)) / d delta at 0. Every
trajectory of the batch iterates together; a row stops once converged. One entry point,
`solve(problem, opts, reference=False)`; a plain tensor unknown with an autodiff Jacobian is
`NewtonProblem.euclidean(f, x0)`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from ..lie import Pose
from .options import SolverOptions


class Layout:
    """Where a problem's batch lies: here (the default) on the first axis of x (T, n) or a Pose of T
    rows, of r (T, n) and of delta (T, n). A subclass puts it elsewhere (`models.liedflnn.engines.columns`:
    (n, T) columns); the loop of `solve` only reaches the batch through these methods."""

    def size(self, r: torch.Tensor) -> int:
        return r.shape[0]

    def norm(self, r: torch.Tensor) -> torch.Tensor:
        """The residual's 2-norm per row, (T,)."""
        return torch.linalg.vector_norm(r, dim=-1)

    def step_size(self, delta: torch.Tensor) -> torch.Tensor:
        """A step's max norm per row, (T,); NaN/inf where delta is (an inf-norm vector_norm is 10x slower)."""
        return delta.abs().amax(-1)

    def step_tolerance(self, x, tol: float):
        return step_tolerance(x, tol)

    def take(self, x, rows: torch.Tensor):
        return _take(x, rows)

    def put(self, x, rows: torch.Tensor, values):
        return _put(x, rows, values)


ROWS = Layout()


@dataclass
class NewtonProblem:
    """Find x with f(x) = 0 row by row, starting at x0.

    f(x) -> (T, n); jac(x) -> (T, n, n) = d f(retract(x, delta)) / d delta at 0;
    retract(x, delta (T, n)) -> x' (x is a Pose of increments or a plain tensor);
    iterate(x, r = f(x)) -> (delta, singular (T,) bool, x' = retract(x, delta), f(x')), optional:
    one full Newton step computed in one go (a model's fused step); restrict(rows (k,) long) ->
    the NewtonProblem of those rows (x0 and all per-row data indexed), optional.
    layout: where the batch lies (`Layout`; shapes above are the default's). hand_over(rows, x, r,
    rn, opts, max_iter) -> (x, r, converged, iterations) of those rows, optional: solves them from
    the current iteration on in another problem, where an iteration needs care (a singular Jacobian
    or a step without decrease) that this one does not implement (then jac may be None).
    """

    f: Callable[[Any], torch.Tensor]
    jac: Callable[[Any], torch.Tensor] | None
    x0: Any
    retract: Callable[[Any, torch.Tensor], Any]
    iterate: Callable[[Any, torch.Tensor], tuple] | None = None  # optional fused full Newton step
    restrict: Callable[[torch.Tensor], NewtonProblem] | None = None  # optional: the problem of some rows
    layout: Layout = ROWS
    hand_over: Callable[..., tuple] | None = None  # optional: careful iterations done elsewhere

    @classmethod
    def euclidean(cls, f: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor) -> NewtonProblem:
        """A plain-tensor unknown (T, n) with an autodiff Jacobian and x + delta steps."""
        return cls(f, lambda x: jacobian(f, x), x0, lambda x, d: x + d)


@dataclass
class NewtonResult:
    x: Any  # solution (last iterate where not converged), same type as x0
    converged: torch.Tensor  # (T,) bool
    iterations: torch.Tensor  # (T,) int, Newton iterations used
    residual_norm: torch.Tensor  # (T,) max-norm of the residual at x

    @property
    def xi(self):  # tensor problems call the unknown xi
        return self.x


def jacobian(f: Callable[[torch.Tensor], torch.Tensor], xi: torch.Tensor) -> torch.Tensor:
    """Batched Jacobian of f: (T, n) -> (T, n) where row t depends on xi[t] only: (T, n, n).

    One forward pass and n reverse passes (row i = grad of sum_t f_i(xi_t)); on CPU this is
    ~10x faster than vmapped forward-mode for the small n of rigid bodies.
    """
    n = xi.shape[-1]
    with torch.enable_grad():
        x = xi.detach().requires_grad_(True)
        r = f(x)
        rows = [torch.autograd.grad(r[:, i].sum(), x, retain_graph=i < n - 1)[0] for i in range(n)]
    return torch.stack(rows, -2)


def select(mask: torch.Tensor, a, b):
    """Row-wise where(mask, a, b) for tensors or Poses (mask (T,))."""
    if isinstance(a, Pose):
        return Pose(select(mask, a.R, b.R), select(mask, a.p, b.p))
    return torch.where(mask.reshape(-1, *([1] * (a.dim() - 1))), a, b)


ROUNDING_ULPS = 16.0
"""Rounding floor of the convergence test, in units of the float's eps times the unknown's magnitude."""


def step_tolerance(x, tol: float):
    """The largest full Newton step (max-norm) with which a row at x converges: max(tol,
    ROUNDING_ULPS eps max(1, |x|_max)) (`SolverOptions`): a float for rotation increments, else a
    (T,) tensor, equal to tol wherever tol is above the floor. |x|_max: the largest entry of a
    plain unknown (T, n), or of a Pose's translations (rotation entries are at most 1)."""
    v = x.p if isinstance(x, Pose) else x
    floor = ROUNDING_ULPS * torch.finfo(v.dtype).eps
    if v.numel() == 0 or v.dim() < 2:
        return max(tol, floor)
    scale = v.detach().abs().flatten(1).amax(-1)
    return torch.clamp(floor * torch.clamp(scale, min=1.0), min=tol)


def solve(problem: NewtonProblem, opts: SolverOptions | None = None, *, reference: bool = False) -> NewtonResult:
    """Damped Newton with backtracking on ||f||_2 for a batch of T independent problems: the one
    Newton entry point of the package.

    A row converges when the full Newton step of a non-singular Jacobian has max norm <= tol, or
    <= its rounding floor where that is larger (`step_tolerance`; the step is then applied,
    leaving an error ~ tol^2 by quadratic convergence). Rows with a singular Jacobian take a
    least-squares step and cannot converge on that iteration; a step that finds no decrease in
    ||f|| after `max_halvings` halvings is taken in full (tol, max_iter, max_halvings from `opts`).
    The problem's `iterate` (one full Newton step in one go) replaces the composition of `jac`, an
    LU solve, `retract` and `f`; its `restrict` lets the last iterations run on the few rows still
    iterating.

    The loop reads one set of flags per iteration from the tensors (no per-row selects): when
    every row's full step decreases ||f|| and no Jacobian is singular (the usual case) the step
    is taken as is; otherwise the iteration is redone row by row (`_careful_iteration`), with the
    same results, convergence flags and iteration counts as the original loop (rows are
    independent, so working on a subset changes nothing either).

    reference=True runs that original loop instead (row-wise selects and a flag read at every
    halving; `iterate` and `restrict` unused): the baseline of the tests and of the benchmark's
    reference paths (`runtime.fused=false`), with the same contract.
    """
    opts = opts or SolverOptions()
    if reference:
        return _reference_loop(problem, opts)
    r = problem.f(problem.x0)
    rn = torch.linalg.vector_norm(r, dim=-1)
    x, r, converged, iters = _newton_rows(problem, problem.x0, r, rn, opts, opts.max_iter)
    return NewtonResult(x, converged, iters, r.abs().amax(-1))


COMPACT_MIN_ROWS = 64  # below this many rows a batch is not split further
COMPACT_FRACTION = 0.25  # rows still iterating, as a fraction, below which only they are iterated


@dataclass
class Chord:
    """The chord Jacobian of a step (`SolverOptions.method="chord"`): J (T, n, n) at the step's first
    iterate and its LU factors, reused by every iteration of the step (rows as in the problem)."""

    J: torch.Tensor
    LU: torch.Tensor
    pivots: torch.Tensor
    singular: torch.Tensor  # (T,) bool

    @classmethod
    def at(cls, J: torch.Tensor) -> Chord:
        LU, pivots, info = torch.linalg.lu_factor_ex(J)
        return cls(J, LU, pivots, info > 0)

    def step(self, r: torch.Tensor) -> torch.Tensor:
        """The chord step -J^-1 r (T, n); not finite on singular rows."""
        return -torch.linalg.lu_solve(self.LU, self.pivots, r[..., None])[..., 0]

    def rows(self, rows: torch.Tensor) -> Chord:
        return Chord(self.J[rows], self.LU[rows], self.pivots[rows], self.singular[rows])


def _newton_rows(problem: NewtonProblem, x, r, rn, opts: SolverOptions, max_iter: int, chord: Chord | None = None):
    """The loop of `solve` from (x, r = f(x), rn = |r|) for `max_iter` iterations ->
    (x, r, converged, iterations), in the problem's layout. `chord`: the rows' chord Jacobian
    (method "chord"; computed at x when not given)."""
    f, jac, retract, L = problem.f, problem.jac, problem.retract, problem.layout
    iterate = problem.iterate
    if iterate is None and opts.method == "chord" and L.size(r):
        assert jac is not None
        if chord is None:
            chord = Chord.at(jac(x))
        fixed = chord

        def iterate(x, r):
            delta = fixed.step(r)
            cand = retract(x, delta)
            return delta, fixed.singular, cand, f(cand)

    elif iterate is None:
        assert jac is not None
        chord = None

        def iterate(x, r):
            sol, info = torch.linalg.solve_ex(jac(x), r[..., None])
            delta = -sol[..., 0]
            cand = retract(x, delta)
            return delta, info > 0, cand, f(cand)

    tol = opts.tol
    T = L.size(r)
    big = torch.finfo(r.dtype).max
    converged = torch.zeros(T, dtype=torch.bool, device=r.device)
    common = 0  # iterations every row took while all were active (no per-iteration kernel)
    iters = torch.zeros(T, dtype=torch.long, device=r.device)
    any_converged = False
    for it in range(max_iter):
        if T == 0:
            break
        step_tol = L.step_tolerance(x, tol)
        delta, singular, cand, rc = iterate(x, r)
        rcn = L.norm(rc)
        full_step = L.step_size(delta)
        # decrease with a finite residual: NaN compares false, and the bound is capped so that an
        # infinite residual never passes
        ok = rcn <= torch.mul(rn, 1 - 1e-4).add_(1e-300).clamp_(max=big)
        irregular = singular | ~(ok & (full_step <= big))
        # used only when no row is irregular, where every active row's residual is finite
        new_converged = full_step <= step_tol
        if any_converged:  # rows that converged earlier take no part
            active = ~converged
            irregular = irregular & active
            new_converged = converged | (active & new_converged)
        else:
            active = torch.ones_like(converged)
        if bool(irregular.any()):  # a singular Jacobian or a step without decrease: redo row by row
            if problem.hand_over is not None:  # ... in another problem, from this iteration to the end
                x, r, converged, iters = _solve_apart(
                    problem.hand_over, L, x, r, rn, converged, iters, opts, max_iter - it
                )
                break
            J = None if chord is None else chord.J
            x, r, rn, singular, full_step = _careful_iteration(problem, x, r, rn, active, opts, J)
            iters = iters + active.long()
            converged = converged | (active & ~singular & (full_step <= step_tol) & torch.isfinite(rn))
            n_converged = int(converged.sum())
        else:
            if any_converged:  # the few rows that converged earlier keep their iterate
                rows = converged.nonzero()[:, 0]
                x, r, rn = (
                    L.put(cand, rows, L.take(x, rows)),
                    L.put(rc, rows, L.take(r, rows)),
                    rcn.index_copy(0, rows, rn[rows]),
                )
                iters = iters + active
            else:
                x, r, rn = cand, rc, rcn
                common += 1
            converged = new_converged
            n_converged = int(new_converged.sum())
        any_converged = n_converged > 0
        if n_converged == T:
            break
        left = max_iter - it - 1
        if left and problem.restrict is not None and T >= COMPACT_MIN_ROWS and T - n_converged <= COMPACT_FRACTION * T:
            compacted = functools.partial(_solve_restricted, problem.restrict, chord)
            x, r, converged, iters = _solve_apart(compacted, L, x, r, rn, converged, iters, opts, left)
            break
    if common:
        iters = iters + common
    return x, r, converged, iters


def _solve_restricted(
    restrict: Callable[[torch.Tensor], NewtonProblem],
    chord: Chord | None,
    rows: torch.Tensor,
    x,
    r,
    rn,
    opts: SolverOptions,
    max_iter: int,
):
    """The rows' own problem from their iterate on; a chord step's rows keep their rows of its factor."""
    return _newton_rows(restrict(rows), x, r, rn, opts, max_iter, None if chord is None else chord.rows(rows))


def _solve_apart(solve_rows, L: Layout, x, r, rn, converged, iters, opts: SolverOptions, max_iter: int):
    """The rows not yet converged solved by solve_rows(rows, x, r, rn, opts, max_iter) (their own
    problem: compaction, or a hand-over) and put back -> (x, r, converged, iterations)."""
    rows = (~converged).nonzero()[:, 0]
    xs, rs, cs, its = solve_rows(rows, L.take(x, rows), L.take(r, rows), rn[rows], opts, max_iter)
    x, r = L.put(x, rows, xs), L.put(r, rows, rs)
    return x, r, converged.index_copy(0, rows, cs), iters.index_add(0, rows, its)


def _take(x, rows: torch.Tensor):
    if isinstance(x, Pose):
        return Pose(x.R.index_select(0, rows), x.p.index_select(0, rows))
    return x.index_select(0, rows)


def _put(x, rows: torch.Tensor, values):
    if isinstance(x, Pose):
        return Pose(x.R.index_copy(0, rows, values.R), x.p.index_copy(0, rows, values.p))
    return x.index_copy(0, rows, values)


def _careful_iteration(problem: NewtonProblem, x, r, rn, active, opts: SolverOptions, J: torch.Tensor | None = None):
    """One iteration of the reference loop (least squares for singular rows, backtracking per
    row): (x, r, rn, singular, full_step) with inactive rows unchanged. J: the step's chord
    Jacobian (method "chord"), else the Jacobian at x."""
    f, jac, retract = problem.f, problem.jac, problem.retract
    assert jac is not None and problem.layout is ROWS, "careful iterations need a Jacobian, in rows"
    max_halvings = opts.max_halvings
    T = r.shape[0]
    if J is None:
        J = jac(x)
    sol, info = torch.linalg.solve_ex(J, r[..., None])
    singular = info > 0
    delta = -sol[..., 0]
    if singular.any():
        delta_ls = -torch.linalg.lstsq(J, r[..., None], driver="gelsd").solution[..., 0]
        delta = torch.where(singular[:, None], delta_ls, delta)
    bad = ~torch.isfinite(delta).all(-1)
    singular = singular | bad
    delta = torch.where(bad[:, None], torch.zeros_like(delta), delta)
    full_step = delta.abs().amax(-1)
    alpha = torch.ones(T, dtype=r.dtype, device=r.device)
    accepted = ~active
    new_x, new_r, new_rn = x, r, rn
    for _h in range(max_halvings + 1):
        cand = retract(x, alpha[:, None] * delta)
        rc = f(cand)
        rcn = torch.linalg.vector_norm(rc, dim=-1)
        ok = (~accepted) & torch.isfinite(rcn) & (rcn <= rn * (1 - 1e-4 * alpha) + 1e-300)
        new_x, new_r = select(ok, cand, new_x), select(ok, rc, new_r)
        new_rn = torch.where(ok, rcn, new_rn)
        accepted = accepted | ok
        if accepted.all():
            break
        alpha = torch.where(accepted, alpha, 0.5 * alpha)
    fallback = ~accepted
    if fallback.any():
        cand = retract(x, delta)
        rc = f(cand)
        rcn = torch.linalg.vector_norm(rc, dim=-1)
        fin = fallback & torch.isfinite(rcn)
        new_x, new_r = select(fin, cand, new_x), select(fin, rc, new_r)
        new_rn = torch.where(fin, rcn, new_rn)
    x, r = select(active, new_x, x), select(active, new_r, r)
    rn = torch.where(active, new_rn, rn)
    return x, r, rn, singular, full_step


def _reference_loop(problem: NewtonProblem, opts: SolverOptions) -> NewtonResult:
    """`solve(..., reference=True)`: the original loop, `_careful_iteration` at every iteration."""
    tol, max_iter = opts.tol, opts.max_iter
    x = problem.x0
    r = problem.f(x)
    T = r.shape[0]
    rn = torch.linalg.vector_norm(r, dim=-1)
    converged = torch.zeros(T, dtype=torch.bool, device=r.device)
    iters = torch.zeros(T, dtype=torch.long, device=r.device)
    J = None
    if opts.method == "chord" and T:
        assert problem.jac is not None
        J = problem.jac(x)
    for _ in range(max_iter):
        active = ~converged
        if not active.any():
            break
        step_tol = step_tolerance(x, tol)
        x, r, rn, singular, full_step = _careful_iteration(problem, x, r, rn, active, opts, J)
        iters = iters + active.long()
        converged = converged | (active & ~singular & (full_step <= step_tol) & torch.isfinite(rn))
    return NewtonResult(x, converged, iters, r.abs().amax(-1))
