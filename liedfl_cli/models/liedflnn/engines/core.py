"""Fused hot paths of LieDFLNN: the same residual, regularity and Newton step as the reference
methods of `models.liedflnn`, computed once and with few kernel calls.

Compute once
    `derive(model)` builds the derived parameters (J_d, m, rho, the constant Rayleigh D) once per
    optimiser step and once per rollout; the reference path rebuilds them in every residual call.
    `IncrementSet` stores the training triplets as what the loss needs, once at load: the summed
    rotational increments A = W_1 + W_2^T (the kinetic residual of a rotation block is linear in
    it), the SE(3) bodies' increments, the velocity estimates, and only the poses that a
    configuration-dependent part (a potential network, a configuration-dependent force) reads.
    Parts without trainable parameters (a known potential or force) are evaluated at load.

Fewer kernels
    Every rotational quantity that is linear in a rotation-like matrix (the kinetic residual
    vee(J_d W^T - W J_d)/h, the mixed Hessian block, the velocity estimate and its Jacobian) is a
    linear map of the 9 entries, built once from J_d (and D) by evaluating the reference formula
    on the 9 basis matrices, then applied to the whole batch as one matrix product. For SO(3)
    bodies with constant Rayleigh damping, the Newton residual and its Jacobian are one product
    each; the Newton step solves 3x3 systems in closed form.

Numbers: equal to the reference path to rounding (tests/test_fused.py checks <= 1e-12 relative).

Files (this module only re-exports them: the rest of the code imports `models.liedflnn.engines.core` alone)
    maps.py            small closed forms (exp coefficients, group exp/retract, 3x3 solves), the
                       constants cached per dtype/device, the derived parameters (`Derived`,
                       `derive`; J_d and SPSD matrices with hand-written gradients), the kinetic
                       residual and mixed-Hessian maps, the potential's covector
    training.py        `IncrementSet` / `IncrementBatch`, the training residual, the regularity
                       slogdet, the SO(3)-only loss with its hand-written gradient (`gradient.py`)
    rollout.py         `RolloutMaps` / `RolloutState`, the Newton step `FusedStep` (residual,
                       Jacobian, iteration), the rollout's problem and advance
    columns.py         the whole rollout of a single SO(3) body with at most constant Rayleigh
                       damping in column layout ((3, 3, T) rotations: 3x3 products as broadcast
                       multiply-adds over rows of length T)
    scalar.py          the same rollout for one to six trajectories in Python floats (a batch-1
                       step is torch's per-call cost, not arithmetic)
    native.py          the rollout of one body or a product of bodies (constant Rayleigh damping, a learned
                       force; an MLP and/or gravity potential) in C++ (`native_body.cpp`), built on first use
    choose.py          which of them serves a training run or a rollout (`LieDFLNN.rollout` asks it)
"""

from __future__ import annotations

from ....lie.batched import compose, exp_coefficients, group_exp, group_retract, vee2
from .maps import (
    SCALAR_BODIES,
    SCALAR_DIM,
    Derived,
    _apply_map,
    _InertiaJd,
    _InertiaJdScalar,
    _map_contraction,
    _SPSDScalar,
    derive,
    hessian_map,
    inertia_jd,
    kinetic_residual_map,
    potential_covector,
    solve_small,
    spsd_matrix,
    training_maps,
    warm_caches,
)
from .rollout import (
    AFFINE_FORCES,
    FusedStep,
    RolloutMaps,
    RolloutState,
    kinetic_blocks,
    kinetic_d1,
    kinetic_d2,
    rollout_advance,
    rollout_maps,
    rollout_problem,
    rollout_start,
    step_iterate,
    step_jacobian,
    step_residual,
    velocity_jacobian_blocks,
)
from .training import (
    IncrementBatch,
    IncrementSet,
    _penalty_and_slope,
    _RotationalLoss,
    batch_forces,
    force_value,
    regularity_slogdet,
    residual_and_logdet,
    rotational_loss,
    rotational_only,
    training_residual,
)

# the private names are used by `models.liedflnn.losses` and the tests
__all__ = [
    "_apply_map",
    "_InertiaJd",
    "_InertiaJdScalar",
    "_map_contraction",
    "_SPSDScalar",
    "compose",
    "derive",
    "Derived",
    "exp_coefficients",
    "group_exp",
    "group_retract",
    "hessian_map",
    "inertia_jd",
    "kinetic_residual_map",
    "potential_covector",
    "SCALAR_BODIES",
    "SCALAR_DIM",
    "solve_small",
    "spsd_matrix",
    "training_maps",
    "vee2",
    "warm_caches",
    "_penalty_and_slope",
    "_RotationalLoss",
    "batch_forces",
    "force_value",
    "IncrementBatch",
    "IncrementSet",
    "regularity_slogdet",
    "residual_and_logdet",
    "rotational_loss",
    "rotational_only",
    "training_residual",
    "AFFINE_FORCES",
    "FusedStep",
    "kinetic_blocks",
    "kinetic_d1",
    "kinetic_d2",
    "rollout_advance",
    "rollout_maps",
    "rollout_problem",
    "rollout_start",
    "RolloutMaps",
    "RolloutState",
    "step_iterate",
    "step_jacobian",
    "step_residual",
    "velocity_jacobian_blocks",
]
