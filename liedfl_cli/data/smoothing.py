"""Savitzky–Golay smoothing of pose tracks that keeps every sample on its group.

Positions (vectors) are filtered entry by entry, exactly like `scipy.signal.savgol_filter(...,
mode="interp")`: a polynomial of degree `order` is least-squares fitted to the `window` samples
centred on sample k and evaluated at k; within half a window of either end the fit to the first
(last) `window` samples is evaluated at the sample's own position.

Rotations are filtered in the tangent space at the centre of each sample's window (a "local-chart"
Savitzky–Golay):

    xi_{k,i} = log(R_c^T R_i)            for the samples i of k's window, c its centre (c = k except
                                          within half a window of either end),
    eta_k    = sum_i c_{k,i} xi_{k,i}     (the same Savitzky–Golay weights as for positions),
    R~_k     = R_c exp(eta_k).

Why this construction:
* every output is a rotation by construction (a product of two rotations; ||R^T R - I|| at rounding
  level, det = 1), no projection needed;
* nothing wraps: only relative rotations within one window are logged, so a body that turns through
  360 degrees or more (cartwheels) is handled like any other motion -- unlike filtering an unwrapped
  rotation-vector or Euler-angle track, which breaks at |theta| = pi or at gimbal lock.  The only
  requirement is that a body turns by less than pi within half a window (checked: `ValueError`);
* a rotation at constant angular velocity (R_i = R_0 exp(i h w), any axis, any speed within that
  limit) is a straight line in every chart, which a filter of order >= 1 reproduces exactly, so
  uniform rotations are returned unchanged; smooth tracks change by O(h^(order+1)) only;
* it is equivariant under fixed rotations on either side (Q R_i P -> Q R~_i P), so the choice of world
  frame or of body axes does not matter.
(Filtering the nine matrix entries and projecting back by SVD is also equivariant and wrap-free, but it
shrinks uniform rotations -- entries are sines and cosines, not polynomials -- before projection.)

The window must be odd: scipy accepts an even `window_length` but then evaluates the fit half a sample
off centre, i.e. shifts the whole track by h/2 in time.  The paper's "window 50" is therefore run as 51.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..lie import so3


def check_window(window: int, order: int, n: int | None = None) -> None:
    """ValueError unless `window` is an odd integer > `order` >= 0 (and <= n samples, if given)."""
    if isinstance(window, bool) or int(window) != window or window < 1:
        raise ValueError(f"Savitzky-Golay window must be a positive integer, got {window!r}")
    if window % 2 == 0:
        raise ValueError(
            f"Savitzky-Golay window must be odd (an even window shifts the track by half a "
            f"sample); got {window}, use {window + 1}"
        )
    if isinstance(order, bool) or int(order) != order or not 0 <= order < window:
        raise ValueError(f"Savitzky-Golay order must be an integer in [0, window={window}), got {order!r}")
    if n is not None and window > n:
        raise ValueError(f"Savitzky-Golay window {window} is longer than the track ({n} samples)")


def savgol_table(window: int, order: int) -> np.ndarray:
    """(window, window): row `pos` holds the weights that evaluate at sample `pos` the degree-`order`
    least-squares polynomial fitted to `window` equally spaced samples.

    Computed in a Legendre basis on [-1, 1] (well conditioned), so the weights reproduce polynomials of
    degree <= order to rounding error; `scipy.signal.savgol_coeffs` uses raw powers of the sample index
    and is off by ~1e-7 for window 51, order 6 at the edge positions.
    """
    check_window(window, order)
    half = window // 2
    t = (np.arange(window) - half) / max(half, 1)
    V = np.polynomial.legendre.legvander(t, order)  # (window, order + 1)
    return V @ np.linalg.pinv(V)  # symmetric projector; row pos = weights at pos


def savgol_weights(n: int, window: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Windows and weights of the filter on n samples: (idx (n, window) int, c (n, window) float).

    Output k = sum_i c[k, i] * x[idx[k, i]] (scipy's `mode="interp"` edge handling).
    """
    check_window(window, order, n)
    half = window // 2
    table = savgol_table(window, order)
    k = np.arange(n)
    start = np.clip(k - half, 0, n - window)
    idx = start[:, None] + np.arange(window)[None, :]
    return idx, table[k - start]


def savgol_positions(x: np.ndarray, window: int, order: int) -> np.ndarray:
    """Savitzky–Golay filter along axis 0 of x (n, ...) (same as scipy's savgol_filter, mode="interp")."""
    x = np.asarray(x, dtype=np.float64)
    idx, c = savgol_weights(x.shape[0], window, order)
    return np.einsum("kw,kw...->k...", c, x[idx])


def savgol_rotations(R: np.ndarray, window: int, order: int, max_angle: float = 0.95 * math.pi) -> np.ndarray:
    """Local-chart Savitzky–Golay filter of rotations R (n, ..., 3, 3) along axis 0 (see module docstring).

    Raises ValueError if a rotation relative to a window's centre sample exceeds `max_angle` (the
    track turns too fast for the window: use a shorter window).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 3 or R.shape[-2:] != (3, 3):
        raise ValueError(f"savgol_rotations expects rotations of shape (n, ..., 3, 3), got {R.shape}")
    n = R.shape[0]
    idx, c = savgol_weights(n, window, order)
    centre = idx[:, window // 2]  # = k except near the ends
    Rc = R[centre]
    rel = np.swapaxes(Rc, -1, -2)[:, None] @ R[idx]  # (n, window, ..., 3, 3)
    xi, angle = _log_below_pi(rel)  # (n, window, ..., 3)
    if angle.max() > max_angle:
        pos = np.unravel_index(int(np.argmax(angle)), angle.shape)
        raise ValueError(
            f"rotation track turns by {angle.max():.3f} rad between samples {int(centre[pos[0]])} "
            f"and {int(idx[pos[0], pos[1]])} (index {tuple(int(i) for i in pos[2:])} of the other "
            f"axes), more than {max_angle:.3f} rad within half a window of {window}; use a shorter window"
        )
    eta = np.einsum("kw,kw...->k...", c, xi)
    return Rc @ so3.exp(torch.from_numpy(eta)).numpy()


def _log_below_pi(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3, 3) -> (log (..., 3), angle (...)) for rotations by less than pi.

    sin(t) u = vee of the skew part and cos(t) = (tr R - 1)/2, t = atan2(sin, cos): accurate for small
    angles (no arccos) and up to close to pi (where the axis gets ill-determined; callers reject angles
    above 0.95 pi).  Much cheaper than the branch-free quaternion route of `so3.log` on ~10^6 matrices.
    """
    s = 0.5 * np.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    sn = np.linalg.norm(s, axis=-1)
    cs = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    angle = np.arctan2(sn, cs)
    scale = np.where(sn > 0, angle / np.where(sn > 0, sn, 1.0), 1.0)
    return scale[..., None] * s, angle


def smooth_pose(R: np.ndarray, p: np.ndarray, window: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth a pose track (R (n, B, 3, 3), p (n, m, 3)) along time; returns new arrays."""
    p = np.asarray(p, dtype=np.float64)
    p_s = savgol_positions(p, window, order) if p.size else p.copy()
    return savgol_rotations(R, window, order), p_s


__all__ = ["check_window", "savgol_table", "savgol_weights", "savgol_positions", "savgol_rotations", "smooth_pose"]
