"""Numerical checks of a dataset's sampling: how far each body turns in one time step.

The discrete models consume increments W_k = R_kᵀ R_{k+1}. An increment is only determined by the
data when the body turns by less than π per step: past π it aliases to the rotation the other way
round (angle 2π − θ about −u), and close to π the rotation axis is ill-conditioned. So

- above π/2 per step the data are sampled coarsely: `check_step_rotation` emits one `DataWarning`
  with the figures (largest angle, where, how many increments exceed π/2);
- above 0.9 π the increment is ambiguous: `DatasetError`.

Both run at data load (`load_dataset`) and before a dataset is written (`save_dataset`);
`step_rotation_summary` gives the figures for a run's summary.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import DatasetError, DataWarning

WARN_ANGLE = math.pi / 2
"""Largest per-step rotation (rad) accepted without a warning."""
ERROR_ANGLE = 0.9 * math.pi
"""Largest per-step rotation (rad) accepted at all: beyond it the increment is ambiguous."""


def step_angles(R: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad, in [0, π]) of every increment R_kᵀ R_{k+1} of R (T, N+1, B, 3, 3)
    -> (T, N, B). atan2(|axial part|, cosine) is accurate over the whole range (unlike acos near 0, π)."""
    R = np.asarray(R, dtype=np.float64)
    if R.ndim != 5 or R.shape[1] < 2:
        return np.zeros(R.shape[:1] + (0,) + R.shape[2:3])
    W = np.einsum("tkbji,tkbjl->tkbil", R[:, :-1], R[:, 1:])
    cos = 0.5 * (np.trace(W, axis1=-2, axis2=-1) - 1.0)
    ax = np.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(ax, axis=-1)
    return np.arctan2(sin, cos)


def step_rotation_summary(R_or_dataset) -> dict:
    """Figures of the per-step rotation of a dataset (or of R): `max_step_angle` (rad),
    `max_step_angle_over_pi`, `where` {trajectory, step, body} of the largest one,
    `n_increments`, `n_over_half_pi` and `fraction_over_half_pi`. Meant for a run's summary."""
    R = getattr(R_or_dataset, "R", R_or_dataset)
    a = step_angles(R)
    if a.size == 0:
        return {"max_step_angle": 0.0, "max_step_angle_over_pi": 0.0, "where": None, "n_increments": 0,
                "n_over_half_pi": 0, "fraction_over_half_pi": 0.0}  # fmt: skip
    i = np.unravel_index(int(np.argmax(a)), a.shape)
    over = int((a > WARN_ANGLE).sum())
    return {
        "max_step_angle": float(a[i]),
        "max_step_angle_over_pi": float(a[i] / math.pi),
        "where": {"trajectory": int(i[0]), "step": int(i[1]), "body": int(i[2])},
        "n_increments": int(a.size),
        "n_over_half_pi": over,
        "fraction_over_half_pi": over / a.size,
    }


def check_step_rotation(R_or_dataset, source: str, body_names: list[str] | None = None) -> dict:
    """Warn (one DataWarning) above π/2 per step, raise DatasetError above 0.9 π; returns the summary."""
    s = step_rotation_summary(R_or_dataset)
    names = body_names if body_names is not None else getattr(R_or_dataset, "body_names", None)
    if s["where"] is None or s["max_step_angle"] <= WARN_ANGLE:
        return s
    w = s["where"]
    body = f"body {w['body']}" + (f" ({names[w['body']]})" if names and w["body"] < len(names) else "")
    figures = (
        f"largest per-step rotation {s['max_step_angle']:.4g} rad = {s['max_step_angle_over_pi']:.3f} pi "
        f"(trajectory {w['trajectory']}, step {w['step']} -> {w['step'] + 1}, {body}); "
        f"{s['n_over_half_pi']} of {s['n_increments']} increments exceed pi/2"
    )
    if s["max_step_angle"] > ERROR_ANGLE:
        raise DatasetError(
            f"{source}: dataset 'R' turns too far in one step: {figures}; above 0.9 pi the increment "
            "R_k^T R_(k+1) is ambiguous (sample more finely: smaller h)"
        )
    warnings.warn(
        f"{source}: dataset 'R' is sampled coarsely: {figures} (the discrete models need well below pi per step)",
        DataWarning,
        stacklevel=3,
    )
    return s


__all__ = ["WARN_ANGLE", "ERROR_ANGLE", "step_angles", "step_rotation_summary", "check_step_rotation"]
