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
from typing import NoReturn

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


# ---------------------------------------------------------------------------- declared physics
def _fail(error: type[Exception], head: str, field: str, problem: str) -> NoReturn:
    raise error(f"{head}{field} {problem}")


def _numbers(x, head: str, field: str, error: type[Exception]) -> np.ndarray:
    """x as a float64 array of finite numbers (bools and strings refused)."""
    try:
        bad = isinstance(x, (str, bytes, bool)) or x is None
        a = np.asarray(x, dtype=np.float64) if not bad else None
    except (TypeError, ValueError):
        a = None
    if a is None or (a.dtype == object):
        _fail(error, head, field, f"must be a number or an array of numbers, got {x!r:.80}")
    assert a is not None
    if isinstance(x, (list, tuple)) and any(isinstance(v, bool) for v in np.asarray(x, dtype=object).reshape(-1)):
        _fail(error, head, field, f"must hold numbers, got {x!r:.80}")
    if not np.isfinite(a).all():
        _fail(error, head, field, f"has a non-finite value: {x!r:.80}")
    return a


def _inertia(J: np.ndarray, head: str, field: str, error: type[Exception]) -> None:
    """J (3, 3): symmetric, positive definite, principal moments obeying the triangle inequality."""
    scale = max(1.0, float(np.abs(J).max()))
    Js = J / scale  # every check below is scale-invariant; entries near 1e308 would overflow unscaled
    if np.abs(Js - Js.T).max() > 1e-9:
        _fail(error, head, field, f"must be symmetric, got {J.tolist()}")
    lam = np.linalg.eigvalsh(0.5 * (Js + Js.T))
    if lam.min() <= 0:
        _fail(error, head, field, f"must be positive definite (principal moments {(lam * scale).tolist()})")
    if lam[2] > lam[0] + lam[1] + 1e-9 * lam.sum():
        lam = lam * scale
        _fail(
            error,
            head,
            field,
            f"violates the triangle inequality (principal moments {lam.tolist()}: the largest exceeds the sum of "
            "the other two; no mass distribution has it)",
        )


def _per_body_inertia(J, n_bodies: int, head: str, field: str, error: type[Exception]) -> None:
    a = _numbers(J, head, field, error)
    if a.shape == (3,):
        mats = [np.diag(a)] * n_bodies
    elif a.shape == (3, 3):
        mats = [a] * n_bodies
    elif a.shape == (n_bodies, 3):
        mats = [np.diag(r) for r in a]
    elif a.shape == (n_bodies, 3, 3):
        mats = list(a)
    else:
        _fail(error, head, field, f"has shape {a.shape}; expected (3,), (3, 3), ({n_bodies}, 3) or ({n_bodies}, 3, 3)")
    for b, M in enumerate(mats):
        _inertia(M, head, f"{field}" if n_bodies == 1 or a.ndim == 1 or a.shape == (3, 3) else f"{field}[{b}]", error)


def check_physics(
    physics,
    n_bodies: int,
    dim: int,
    tree=None,
    source: str | None = None,
    prefix: str = "params.physics",
    error: type[Exception] = DatasetError,
) -> None:
    """Validate a declared physics (a dataset's params["physics"] or a scene's `dataset.physics`) for
    a group of `n_bodies` bodies and tangent dimension `dim`; `tree`: the file's kinematic tree (the
    articulated schema needs one). Raises `error` with one line `<source>: <prefix>.<field> <problem>`.

    Two schemas (docs/data_format.md): per body (mechanics.scene_physics: J, m, rho, g, D,
    interaction, control) and `kind: "articulated"` (models.articulated: bodies, joint_damping, ...)."""
    # finite but huge values (1e308) overflow in the sums below: inf compares as it should, and numpy's
    # RuntimeWarning would only add a second line to the user's message
    with np.errstate(over="ignore"):
        _check_physics(physics, n_bodies, dim, tree, source, prefix, error)


def _check_physics(physics, n_bodies: int, dim: int, tree, source, prefix: str, error: type[Exception]) -> None:
    head = f"{source}: " if source else ""
    if not isinstance(physics, dict):
        _fail(error, head, prefix, f"must be a JSON object, got {type(physics).__name__}")
    kind = physics.get("kind")
    if kind == "articulated":
        _check_articulated(physics, n_bodies, tree, head, prefix, error)
        return
    if kind is not None:
        _fail(error, head, f"{prefix}.kind", f"is {kind!r}; the only kind is 'articulated' (or none: per body)")
    B = n_bodies
    if "J" not in physics:
        _fail(error, head, f"{prefix}.J", "is missing (the inertia: 3 diagonal entries, 3x3, or one per body)")
    _per_body_inertia(physics["J"], B, head, f"{prefix}.J", error)
    if "m" in physics:
        m = _numbers(physics["m"], head, f"{prefix}.m", error)
        if m.shape not in ((), (B,)):
            _fail(error, head, f"{prefix}.m", f"has shape {m.shape}; expected one mass or {B}")
        if (m <= 0).any():
            _fail(error, head, f"{prefix}.m", f"must be positive, got {physics['m']!r}")
    if "rho" in physics:
        rho = _numbers(physics["rho"], head, f"{prefix}.rho", error)
        if rho.shape not in ((3,), (B, 3)):
            _fail(error, head, f"{prefix}.rho", f"has shape {rho.shape}; expected (3,) or ({B}, 3)")
    if physics.get("g") is not None and _numbers(physics["g"], head, f"{prefix}.g", error).shape != ():
        _fail(error, head, f"{prefix}.g", f"must be one number, got {physics['g']!r}")
    if "D" in physics:
        D = _numbers(physics["D"], head, f"{prefix}.D", error)
        if D.shape == (dim,):
            if (D < 0).any():
                _fail(error, head, f"{prefix}.D", f"must be non-negative, got entry {int(np.argmin(D))} = {D.min()}")
        elif D.shape == (dim, dim):
            Ds = D / max(1.0, float(np.abs(D).max()))  # scaled: no overflow of huge entries
            if np.abs(Ds - Ds.T).max() > 1e-9:
                _fail(error, head, f"{prefix}.D", "must be symmetric")
            if np.linalg.eigvalsh(0.5 * (Ds + Ds.T)).min() < -1e-9:
                _fail(error, head, f"{prefix}.D", "must be positive semidefinite")
        else:
            _fail(
                error, head, f"{prefix}.D", f"has shape {D.shape}; expected ({dim},) or ({dim}, {dim}) for this group"
            )
    inter = physics.get("interaction")
    if inter:
        f = f"{prefix}.interaction"
        if not isinstance(inter, dict):
            _fail(error, head, f, f"must be an object, got {type(inter).__name__}")
        if not isinstance(inter.get("kind"), str):
            _fail(error, head, f"{f}.kind", f"must be a string, got {inter.get('kind')!r}")
        if _numbers(inter.get("mu"), head, f"{f}.mu", error).shape != ():
            _fail(error, head, f"{f}.mu", "must be one number")
        bodies = inter.get("bodies", [0, 1])
        if (
            not isinstance(bodies, list)
            or len(bodies) != 2
            or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < B for i in bodies)
            or bodies[0] == bodies[1]
        ):
            _fail(error, head, f"{f}.bodies", f"must be 2 distinct body indices in [0, {B}), got {bodies!r}")
    ctrl = physics.get("control")
    if ctrl:
        f = f"{prefix}.control"
        if not isinstance(ctrl, dict):
            _fail(error, head, f, f"must be an object, got {type(ctrl).__name__}")
        for key in ("R_f", "K_R", "K_w"):
            if key not in ctrl:
                _fail(error, head, f"{f}.{key}", "is missing")
        if _numbers(ctrl["R_f"], head, f"{f}.R_f", error).shape != (3,):
            _fail(error, head, f"{f}.R_f", f"must be a rotation vector of 3 numbers, got {ctrl['R_f']!r}")
        _numbers(ctrl["K_R"], head, f"{f}.K_R", error)
        _numbers(ctrl["K_w"], head, f"{f}.K_w", error)


def _check_articulated(physics: dict, B: int, tree, head: str, prefix: str, error: type[Exception]) -> None:
    if tree is None:
        _fail(
            error,
            head,
            f"{prefix}.kind",
            "is 'articulated' but the file has no kinematic tree (attribute 'parents', dataset 'joint_offsets')",
        )
    bodies = physics.get("bodies")
    if not isinstance(bodies, list) or len(bodies) != B:
        n = len(bodies) if isinstance(bodies, list) else type(bodies).__name__
        _fail(error, head, f"{prefix}.bodies", f"must list {B} bodies (mass, com, inertia), got {n}")
    for b, body in enumerate(bodies):
        f = f"{prefix}.bodies[{b}]"
        if not isinstance(body, dict):
            _fail(error, head, f, f"must be an object with mass, com, inertia, got {type(body).__name__}")
        for key in ("mass", "com", "inertia"):
            if key not in body:
                _fail(error, head, f"{f}.{key}", "is missing")
        mass = _numbers(body["mass"], head, f"{f}.mass", error)
        if mass.shape != () or not mass > 0:
            _fail(error, head, f"{f}.mass", f"must be one positive number, got {body['mass']!r}")
        if _numbers(body["com"], head, f"{f}.com", error).shape != (3,):
            _fail(error, head, f"{f}.com", f"must be 3 numbers, got {body['com']!r:.80}")
        J = _numbers(body["inertia"], head, f"{f}.inertia", error)
        if J.shape != (3, 3):
            _fail(error, head, f"{f}.inertia", f"has shape {J.shape}; expected (3, 3)")
        _inertia(J, head, f"{f}.inertia", error)
    jd = physics.get("joint_damping")
    if jd is not None:
        d = _numbers(jd, head, f"{prefix}.joint_damping", error)
        if d.shape != (B - 1,):
            _fail(
                error,
                head,
                f"{prefix}.joint_damping",
                f"must have {B - 1} entries (one per non-root body), got {d.shape}",
            )
        if (d < 0).any():
            i = int(np.argmin(d))
            _fail(error, head, f"{prefix}.joint_damping[{i}]", f"must be >= 0, got {d[i]}")
    for key in ("root_damping", "g"):
        if physics.get(key) is not None:
            v = _numbers(physics[key], head, f"{prefix}.{key}", error)
            if v.shape != ():
                _fail(error, head, f"{prefix}.{key}", f"must be one number, got {physics[key]!r}")
            if key == "root_damping" and v < 0:
                _fail(error, head, f"{prefix}.{key}", f"must be >= 0, got {float(v)}")


__all__ = [
    "WARN_ANGLE",
    "ERROR_ANGLE",
    "step_angles",
    "step_rotation_summary",
    "check_step_rotation",
    "check_physics",
]
