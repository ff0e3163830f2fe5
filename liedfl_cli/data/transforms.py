"""Dataset options that apply to any scene after it is generated: measurement noise and the
group-preserving Savitzky-Golay smoother (`smoothing.py`).

Dataset config keys (every conf/dataset/*.yaml has them; off = null, or zeros for the noise, and then
they are not part of the cache hash, so existing cached datasets keep their names):

  noise:     {rotation: sigma_R, position: sigma_p}   R <- R exp(sigma_R n), n ~ N(0, I_3) per sample
             and body (sigma_R rad per axis); p <- p + sigma_p N(0, I_3). Drawn from the dataset seed
             (its own stream). The clean poses are kept as extras `R_clean`, `p_clean` (evaluation
             only). For simulated scenes: a noise study (scripts/noise_study.py).
  smoothing: {window, order}   Savitzky-Golay along time on every trajectory over its whole generated
             length (window: odd number of samples; order: polynomial degree < window); rotations in
             the tangent space at each window's centre (they stay rotations), positions entry-wise.
             Applied after the noise. Recorded in params["smoothing"]. The mocap import applies its
             own `smoothing` to the whole recordings before cropping (same filter).

Order of operations: scene generator -> noise -> smoothing -> save.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from ..errors import ConfigError, DatasetError
from ..lie import so3
from .hdf5 import Dataset
from .smoothing import check_window, smooth_pose

OPTION_KEYS = ("noise", "smoothing")
"""Optional keys of every dataset config handled here."""

NOISE_STREAM = 7919
"""Mixed into the dataset seed for the noise stream (independent of initial conditions and split)."""


def smoothing_spec(value) -> dict | None:
    """Validated `dataset.smoothing`: None or {window: odd int, order: int} (ConfigError otherwise)."""
    if value is None:
        return None
    if not isinstance(value, Mapping) or set(value) != {"window", "order"}:
        raise ConfigError(f"dataset.smoothing must be null or {{window: <odd int>, order: <int>}}, got {value!r}")
    try:
        check_window(value["window"], value["order"])
    except ValueError as exc:
        raise ConfigError(f"dataset.smoothing: {exc}") from None
    return {"window": int(value["window"]), "order": int(value["order"])}


def noise_spec(value) -> dict | None:
    """Validated `dataset.noise`: None (off; also for all-zero values) or {rotation: >= 0, position: >= 0}
    (ConfigError otherwise)."""
    if value is None:
        return None
    if not isinstance(value, Mapping) or not set(value) <= {"rotation", "position"} or not value:
        raise ConfigError(f"dataset.noise must be null or {{rotation: <rad>, position: <length>}}, got {value!r}")
    out = {}
    for k in ("rotation", "position"):
        v = value.get(k, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise ConfigError(f"dataset.noise.{k} must be a non-negative number, got {v!r}")
        out[k] = float(v)
    return out if any(out.values()) else None


def add_noise(ds: Dataset, spec: dict, seed: int) -> Dataset:
    """R <- R exp(sigma_R n), p <- p + sigma_p n' (see the module docstring); clean poses to extras."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, NOISE_STREAM])
    R, p = ds.R, ds.p
    ds.extras["R_clean"], ds.extras["p_clean"] = R.copy(), p.copy()
    if spec["rotation"] > 0:
        eta = spec["rotation"] * rng.standard_normal(R.shape[:-2] + (3,))
        ds.R = R @ so3.exp(torch.from_numpy(eta)).numpy()
    if spec["position"] > 0 and p.size:
        ds.p = p + spec["position"] * rng.standard_normal(p.shape)
    ds.params["noise"] = {**spec, "model": "R exp(sigma_R N(0, I)), p + sigma_p N(0, I) per sample and body"}
    return ds


def smooth(ds: Dataset, spec: dict) -> Dataset:
    """Savitzky-Golay smoothing of every trajectory along time (see the module docstring)."""
    R = np.moveaxis(ds.R, 1, 0)  # (N+1, T, B, 3, 3): time first
    p = np.moveaxis(ds.p, 1, 0)
    try:
        Rs, ps = smooth_pose(R, p, spec["window"], spec["order"])
    except ValueError as exc:
        raise DatasetError(f"{ds.scene}: smoothing failed: {exc}") from None
    ds.R, ds.p = np.ascontiguousarray(np.moveaxis(Rs, 0, 1)), np.ascontiguousarray(np.moveaxis(ps, 0, 1))
    ds.params["smoothing"] = {
        **spec,
        "method": "Savitzky-Golay along time over each whole trajectory; rotations in the tangent space at "
        "each window's centre, positions plain; after any noise",
    }
    return ds


def apply(ds: Dataset, c: dict, smoothing_done: bool = False) -> Dataset:
    """Apply `noise` then `smoothing` of the dataset config `c` to a freshly generated dataset.
    smoothing_done: the scene applied `smoothing` itself (the mocap import)."""
    noise, sm = noise_spec(c.get("noise")), smoothing_spec(c.get("smoothing"))
    if noise is not None:
        if smoothing_done and sm is not None:
            raise ConfigError(
                f"dataset.noise with scene {c['name']!r}: its import smooths the recordings before any noise "
                "could be added; use smoothing: null to study noise on it"
            )
        ds = add_noise(ds, noise, int(c.get("seed", 0)))
    if sm is not None and not smoothing_done:
        ds = smooth(ds, sm)
    return ds


__all__ = ["OPTION_KEYS", "smoothing_spec", "noise_spec", "add_noise", "smooth", "apply"]
