"""Error and drift metrics shared by every model (DESIGN section 5).

All functions take predicted and true trajectories with matching leading dims and return
per-sample values; `trajectory_metrics` averages over bodies and gives per-step curves
(mean over trajectories) plus scalar summaries. Predictions of Euclidean baselines may be
off the manifold: their drift is measured as it is, and the geodesic error uses the nearest
rotation (SVD projection).
"""

from __future__ import annotations

import numpy as np
import torch

from .lie import Pose, so3


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


def trajectory_metrics(pred: Pose, true: Pose) -> dict:
    """Per-step curves (numpy, shape (S+1,), mean over trajectories and bodies) and scalars.

    pred, true: R (T, S+1, B, 3, 3), p (T, S+1, m, 3).
    """
    if not torch.isfinite(pred.R).all():
        bad = (~torch.isfinite(pred.R)).nonzero()[0].tolist()
        nonfinite_at = bad[1]
    else:
        nonfinite_at = None
    rel = relative_rotation_error(pred.R, true.R).mean(-1)  # (T, S+1)
    geo = geodesic_error(torch.nan_to_num(pred.R), true.R).mean(-1)
    orth = orthogonality_drift(pred.R).amax(-1)
    det = det_drift(pred.R).amax(-1)
    curves = {
        "rel_rot_error": rel.mean(0),
        "geodesic_error": geo.mean(0),
        "orth_drift": orth.mean(0),
        "det_drift": det.mean(0),
    }
    scalars = {
        "rel_rot_error_mean": rel.mean(),
        "rel_rot_error_final": rel[:, -1].mean(),
        "geodesic_error_mean": geo.mean(),
        "max_orth_drift": orth.max(),
        "max_det_drift": det.max(),
    }
    if pred.p.shape[-2] > 0:
        pos = position_error(pred.p, true.p).mean(-1)
        curves["position_error"] = pos.mean(0)
        scalars["position_error_mean"] = pos.mean()
        scalars["position_error_final"] = pos[:, -1].mean()
    out_curves = {k: v.detach().cpu().numpy() for k, v in curves.items()}
    out_scalars = {k: float(v) for k, v in scalars.items()}
    out_scalars["nonfinite_step"] = nonfinite_at
    return {"curves": out_curves, "scalars": out_scalars}


def relative_torque_error(tau_hat: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """||tau_hat - tau|| / ||tau|| along a trajectory, shape (...)."""
    return np.linalg.norm(tau_hat - tau, axis=-1) / np.maximum(np.linalg.norm(tau, axis=-1), 1e-300)
