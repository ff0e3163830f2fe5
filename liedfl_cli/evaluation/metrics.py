"""Error and drift metrics shared by every model (DESIGN section 5).

All functions take predicted and true trajectories with matching leading dims and return
per-sample values; `error_metrics` (against ground truth) and `drift_metrics` (distance from the
group, no ground truth needed) average over bodies and give per-step curves (mean over trajectories)
plus scalar summaries. Predictions of Euclidean baselines may be off the manifold: their drift is
measured as it is, and the geodesic error uses the nearest rotation (SVD projection).
"""

from __future__ import annotations

import torch

from ..lie import Pose, so3


def relative_rotation_error(R_hat: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """||R_hat - R||_F / ||R||_F, shape (...) for inputs (..., 3, 3)."""
    return torch.linalg.matrix_norm(R_hat - R) / torch.linalg.matrix_norm(R)


def geodesic_error(R_hat: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """|log(P(R_hat)^T R)| in radians with P the projection onto SO(3), shape (...)."""
    return so3.geodesic_distance(so3.project(R_hat), R)


def position_error(p_hat: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """||p_hat - p||_2, shape (...)."""
    return torch.linalg.vector_norm(p_hat - p, dim=-1)


def det_drift(R_hat: torch.Tensor) -> torch.Tensor:
    """|det R_hat - 1|, shape (...)."""
    return (torch.linalg.det(R_hat) - 1.0).abs()


def orthogonality_drift(R_hat: torch.Tensor) -> torch.Tensor:
    """||R_hat^T R_hat - I||_F, shape (...)."""
    return so3.orthogonality_error(R_hat)


def masked_mean(x: torch.Tensor, valid: torch.Tensor | None, dim: int | None = None) -> torch.Tensor:
    """Mean of `x` over the entries where `valid` (same shape, bool) holds (all when None); NaN where
    no entry is valid. Entries outside `valid` may be non-finite: they are never added."""
    if valid is None:
        return x.mean() if dim is None else x.mean(dim)
    w = valid.to(x.dtype)
    total = torch.where(valid, x, torch.zeros_like(x))
    if dim is None:
        return total.sum() / w.sum()  # 0 / 0 = NaN: nothing valid
    return total.sum(dim) / w.sum(dim)


def error_metrics(pred: Pose, true: Pose, valid: torch.Tensor | None = None) -> dict:
    """Errors against ground truth: per-step curves (numpy, shape (S+1,), mean over trajectories and
    bodies) and scalars (means over trajectories, steps and bodies; `*_final` at the last step).

    pred, true: R (T, S+1, B, 3, 3), p (T, S+1, m, 3), over the steps where ground truth exists.
    valid: (T, S+1) bool, the samples the errors cover (a rollout's steps up to its first Newton
    failure, `valid_steps`); None = all. `*_final` averages the trajectories valid at the last step.
    """
    rel = relative_rotation_error(pred.R, true.R).mean(-1)  # (T, S+1)
    geo = geodesic_error(torch.nan_to_num(pred.R), true.R).mean(-1)
    last = None if valid is None else valid[:, -1]
    curves = {"rel_rot_error": masked_mean(rel, valid, 0), "geodesic_error": masked_mean(geo, valid, 0)}
    scalars = {
        "rel_rot_error_mean": masked_mean(rel, valid),
        "rel_rot_error_final": masked_mean(rel[:, -1], last),
        "geodesic_error_mean": masked_mean(geo, valid),
    }
    if pred.p.shape[-2] > 0:
        pos = position_error(pred.p, true.p).mean(-1)
        curves["position_error"] = masked_mean(pos, valid, 0)
        scalars["position_error_mean"] = masked_mean(pos, valid)
        scalars["position_error_final"] = masked_mean(pos[:, -1], last)
    return {"curves": _numpy(curves), "scalars": {k: float(v) for k, v in scalars.items()}}


def valid_steps(converged: torch.Tensor, n: int) -> torch.Tensor:
    """(T, n+1) bool: the samples 0..n of each trajectory up to its first Newton failure (excluded).

    converged: (T, S-1) bool, converged[:, j] for the solve that produced sample j + 2 (a rollout's
    flags); samples 0 and 1 are the data's. A failed step's pose is the last iterate, and every later
    pose is predicted from it: neither is a prediction of the model."""
    T = converged.shape[0]
    ok = torch.cumprod(converged.to(torch.int64), dim=1).bool()
    full = torch.cat([torch.ones(T, 2, dtype=torch.bool), ok], dim=1)
    return full[:, : n + 1]


def valid_horizons(valid: torch.Tensor) -> list[int]:
    """Per trajectory, the last sample index the errors cover (its valid horizon; n without failure)."""
    return [int(v.sum()) - 1 for v in valid]


def one_step_metrics(pred: Pose, true: Pose, converged: torch.Tensor | None = None) -> dict:
    """Teacher-forced one-step errors: the geodesic rotation error (rad) and, with SE(3) bodies, the
    position error, each the mean over bodies, predicted samples and trajectories.

    pred, true: R (T, K, B, 3, 3), p (T, K, m, 3): the K one-step predictions and the true poses they predict.
    converged: (T, K) bool, the predictions whose Newton solve converged (the others are left out); None = all.
    """
    geo = geodesic_error(torch.nan_to_num(pred.R), true.R).mean(-1)  # (T, K)
    out = {"one_step_rot_error_mean": float(masked_mean(geo, converged))}
    if pred.p.shape[-2] > 0:
        out["one_step_pos_error_mean"] = float(masked_mean(position_error(pred.p, true.p).mean(-1), converged))
    return out


def drift_metrics(pred: Pose) -> dict:
    """Distance from the group, over the whole rollout: per-step curves (numpy, shape (S+1,), mean over
    trajectories of the maximum over bodies), the maxima, and the first step holding a non-finite
    rotation entry in any trajectory (None if there is none).

    pred: R (T, S+1, B, 3, 3).
    """
    finite = torch.isfinite(pred.R).flatten(2).all(-1)  # (T, S+1)
    bad_steps = (~finite).any(0).nonzero()
    orth = orthogonality_drift(pred.R).amax(-1)
    det = det_drift(pred.R).amax(-1)
    return {
        "curves": _numpy({"orth_drift": orth.mean(0), "det_drift": det.mean(0)}),
        "scalars": {
            "max_orth_drift": float(orth.max()),
            "max_det_drift": float(det.max()),
            "nonfinite_step": int(bad_steps[0]) if len(bad_steps) else None,
        },
    }


def _numpy(curves: dict) -> dict:
    return {k: v.detach().cpu().numpy() for k, v in curves.items()}
