"""Settings of the implicit-step solver, written once: this dataclass is also the schema of the
`solver` config section (liedfl_cli/config/typed.py builds it from the config)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SolverOptions:
    """Damped Newton for implicit steps (paper: tolerance 1e-5, at most 10 iterations).

    tol: a row converges when the max-norm of its full Newton step is <= tol, or <= its rounding
    floor 16 eps max(1, |x|_max) where that is larger (`newton.step_tolerance`; |x|_max: the
    largest entry of the unknown, of its translations for group increments, whose rotation
    entries are at most 1). A step cannot shrink below the rounding of its unknown, so without
    the floor a tol under ~1e-15 flags converged steps as failures; above the floor (the default
    1e-5, and 1e-12) flags and iteration counts are those of the plain test `step <= tol`.
    max_iter: Newton iterations per step. max_halvings: backtracking halvings of a step that
    does not reduce ||residual||_2 before the full step is taken anyway.
    """

    tol: float = 1e-5
    max_iter: int = 10
    max_halvings: int = 6
