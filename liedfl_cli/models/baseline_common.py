"""Small pieces shared by the baseline models (config options, pose layout, explicit rollouts)."""

from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf

from ..errors import ConfigError
from ..lie import Pose
from ..solvers.rollout import Rollout
from .build import resolve_potential

WINDOWS = ("triplet", "trajectory")


def options(cfg, defaults: dict) -> dict:
    """`cfg.baseline` merged over `defaults`; an unknown key is a ConfigError naming it."""
    raw = cfg.baseline
    given = OmegaConf.to_container(raw, resolve=True) if isinstance(raw, DictConfig) else dict(raw)
    name = given.pop("name", "?")
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise ConfigError(f"baseline={name}: unknown key(s) {unknown}; expected some of {sorted(defaults)}")
    out = {**defaults, **given}
    if out.get("window") is not None and out["window"] not in WINDOWS:
        raise ConfigError(f"baseline.window={out['window']!r}: choose one of {', '.join(WINDOWS)}")
    if "potential" in out and out["potential"] not in ("auto", "mlp", "none"):
        raise ConfigError(f"baseline.potential={out['potential']!r}: choose one of auto, mlp, none")
    if "damping" in out and out["damping"] not in ("auto", True, False):
        raise ConfigError(f"baseline.damping={out['damping']!r}: choose auto, true or false")
    return out


def use_potential(opt: dict, dataset) -> bool:
    """`potential: auto` follows `models.build.resolve_potential` (no network for a free body)."""
    return resolve_potential({"potential": opt["potential"]}, dataset) == "mlp"


def use_damping(opt: dict, cfg) -> bool:
    """`damping: auto` -> learned Rayleigh damping iff the `force` group contains rayleigh."""
    if opt["damping"] == "auto":
        forces = cfg.get("force") or {}
        return "rayleigh" in forces
    return bool(opt["damping"])


def init_scale(h: float, epsilon: float, n: int) -> float:
    """Kinetic scale s with n log(s / h) = epsilon: the mixed Hessian ~ -(s/h) I_n then starts
    at the regularity threshold log|det H| = epsilon (as LieDFLNN does)."""
    import math

    return h * math.exp(epsilon / n)


def single_so3(G, name: str) -> None:
    if G.n_se3 != 0 or G.n_so3 != 1:
        raise ConfigError(f"baseline={name} models a single rigid body on SO(3); this dataset's group is {G.name}")


def so3_pose(R: torch.Tensor) -> Pose:
    """Rotations (..., 3, 3) of one SO(3) body -> Pose R (..., 1, 3, 3), p (..., 0, 3)."""
    return Pose(R[..., None, :, :], R.new_zeros(*R.shape[:-2], 0, 3))


def triplet_sequence(batch) -> Pose:
    """(prev, cur, nxt) Poses with leading (N,) -> one Pose sequence (N, 3, ...)."""
    prev, cur, nxt = batch
    return Pose(torch.stack((prev.R, cur.R, nxt.R), 1), torch.stack((prev.p, cur.p, nxt.p), 1))


def explicit_rollout(pose: Pose, seconds: float) -> Rollout:
    """Rollout record of an explicit integrator: every step 'converged' with 0 iterations."""
    T, S1 = pose.R.shape[:2]
    n = max(S1 - 2, 0)
    return Rollout(
        pose,
        torch.ones(T, n, dtype=torch.bool),
        torch.zeros(T, n, dtype=torch.long),
        torch.zeros(T, n, dtype=pose.R.dtype),
        seconds,
    )


def with_data_start(pred: Pose, g0: Pose, g1: Pose) -> Pose:
    """Predicted sequence (T, S+1, ...) with its first two entries replaced by the given g0, g1
    (the rollout protocol: every model's output starts with the observed pair)."""
    R, p = pred.R.clone(), pred.p.clone()
    R[:, 0], R[:, 1] = g0.R, g1.R
    p[:, 0], p[:, 1] = g0.p, g1.p
    return Pose(R, p)
