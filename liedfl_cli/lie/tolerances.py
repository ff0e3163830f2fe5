"""All numerical thresholds of the Lie-group code, one table per dtype.

`taylor` is the angle below which closed forms such as sin(t)/t switch to their Taylor
series (kept to t^8, so the truncation error at the threshold is below the dtype's epsilon
while the closed form's cancellation error would not be).
"""

from __future__ import annotations

import torch

TOLERANCES: dict[torch.dtype, dict[str, float]] = {
    torch.float64: {"taylor": 1e-1, "orthogonality": 1e-9, "project_warn": 1e-9, "reject": 1e-3},
    torch.float32: {"taylor": 3e-1, "orthogonality": 1e-5, "project_warn": 1e-5, "reject": 1e-3},
}


def tol(dtype: torch.dtype, name: str) -> float:
    """Threshold `name` for `dtype` (float16/bfloat16 fall back to the float32 row)."""
    return TOLERANCES.get(dtype, TOLERANCES[torch.float32])[name]


PROJECT_POSES: dict[torch.dtype, bool] = {torch.float64: False, torch.float32: True}
"""Whether a rollout re-orthonormalises every composed pose g_{k+1} = g_k W_k, not only the increment
W_k (`so3.orthonormalize`). In float64 the poses stay within ~1e-13 of SO(3) over thousands of steps
without it (and results stay as they were); in float32 they drift 2.5e-4 in 2000 steps without it,
4e-7 with it (README, "Runtime settings"; `scripts/float32_cost.py`)."""


def projects_poses(dtype: torch.dtype) -> bool:
    """`PROJECT_POSES` for `dtype` (other dtypes: True)."""
    return PROJECT_POSES.get(dtype, True)
