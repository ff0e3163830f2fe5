"""Settings of the implicit-step solver, written once: this dataclass is also the schema of the
`solver` config section (liedfl_cli/config/typed.py builds it from the config)."""

from __future__ import annotations

from dataclasses import dataclass, field

METHODS = ("newton", "chord")


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
    method: "newton" (the Jacobian at every iterate) or "chord" (simplified Newton: the Jacobian at
    the step's first iterate, factored once and reused by every iteration of that step, so an
    iteration costs one residual and one triangular solve). Chord converges linearly: the error
    left by the last step is about its size times the contraction, not its square, so pair it with
    a smaller tol (on the 5-body tree chord at 1e-8 leaves a solver error of ~2e-9, newton at 1e-5
    ~4e-10, both five orders below the scheme's own error; docs/benchmarks.md "Chord steps"). It
    serves problems solved by the generic loop (the articulated model, and every model's reference
    path); a single body's fused step is one fused Newton step and stays Newton (its Jacobian costs
    next to nothing). A value other than these two is refused here, whoever builds the options.
    """

    tol: float = 1e-5
    max_iter: int = 10
    max_halvings: int = 6
    method: str = field(default="newton", metadata={"choices": METHODS})

    def __post_init__(self) -> None:  # every constructor (config, api, code) refuses a method it would not run
        checks = getattr(super(), "__post_init__", None)  # the config layer's subclass checks its fields first
        if checks is not None:
            checks()
        if self.method not in METHODS:
            raise ValueError(f"solver.method={self.method!r}: choose one of {', '.join(METHODS)}")
