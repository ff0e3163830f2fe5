"""Figures of a run (matplotlib, Agg backend): errors, drift, trajectories on the sphere."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .io_utils import atomic_path


class ArrayPose(NamedTuple):
    """A `lie.Pose` as numpy arrays, as the plots read it: R (..., B, 3, 3), p (..., m, 3)."""

    R: np.ndarray
    p: np.ndarray


COLORS = {"truth": "black", "model": "tab:blue", "true_scheme": "tab:orange"}


def save_figure(fig, path: Path) -> None:
    """Write `fig` as a PNG to `path` atomically and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)


def draw_unit_sphere(ax) -> None:
    """The unit sphere as a light wireframe on a 3-D axis, with equal aspect: the backdrop of every plot
    of a direction (a body axis R e_i, a bone direction) over time."""
    u, v = np.mgrid[0 : 2 * np.pi : 30j, 0 : np.pi : 15j]
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85", linewidth=0.4)
    ax.set_box_aspect((1, 1, 1))


def error_vs_step(curves: dict[str, dict], h: float, path: Path) -> None:
    keys = [k for k in ("rel_rot_error", "geodesic_error", "position_error") if any(k in c for c in curves.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for name, c in curves.items():
            if key in c:
                y = c[key]
                # steps 0 and 1 are the given initial pair (zero error): start at the first prediction
                ax.semilogy(np.arange(2, len(y)) * h, np.maximum(y[2:], 1e-17), label=name, color=COLORS.get(name))
        ax.set_xlabel("time")
        ax.set_title(key.replace("_", " "))
        ax.grid(alpha=0.3)
    axes[0][0].legend()
    save_figure(fig, path)


def drift_vs_step(curves: dict[str, dict], h: float, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, title in zip(axes, ("orth_drift", "det_drift"), ("||R^T R - I||_F", "|det R - 1|")):
        for name, c in curves.items():
            y = c[key]
            ax.semilogy(np.arange(len(y)) * h, np.maximum(y, 1e-18), label=name, color=COLORS.get(name))
        ax.set_title(title)
        ax.set_xlabel("time")
        ax.grid(alpha=0.3)
    axes[0].legend()
    save_figure(fig, path)


def sphere(
    truth_R: np.ndarray, preds: dict[str, np.ndarray], path: Path, axis: int = 2, n_traj: int = 3, body: int = 0
) -> None:
    """Body axis R e_axis of the first trajectories on the unit sphere. R arrays (T, S+1, B, 3, 3)."""
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    draw_unit_sphere(ax)
    for t in range(min(n_traj, truth_R.shape[0])):
        x = truth_R[t, :, body, :, axis]
        ax.plot(*x.T, color="black", linewidth=1.2, label="truth" if t == 0 else None)
        for name, R in preds.items():
            y = R[t, :, body, :, axis]
            ax.plot(*y.T, "--", color=COLORS.get(name), linewidth=1.0, label=name if t == 0 else None)
    ax.legend(loc="upper left")
    ax.set_title(f"body {body} axis e{axis + 1} on the unit sphere")
    save_figure(fig, path)


def predicted_vs_true(
    truth: ArrayPose, preds: dict[str, ArrayPose], h: float, path: Path, traj: int = 0, body: int = 0
) -> None:
    """Components of R e3 (and p for SE(3) bodies) over time for one trajectory."""
    has_p = truth.p.shape[-2] > body
    rows = 2 if has_p else 1
    fig, axes = plt.subplots(rows, 3, figsize=(12, 3 * rows), squeeze=False)
    S = truth.R.shape[1]
    for j in range(3):
        ax = axes[0][j]
        ax.plot(np.arange(S) * h, truth.R[traj, :, body, j, 2], color="black", label="truth")
        for name, P in preds.items():
            s = P.R.shape[1]
            ax.plot(np.arange(s) * h, P.R[traj, :, body, j, 2], "--", color=COLORS.get(name), label=name)
        ax.set_title(f"(R e3)_{j + 1}")
        if has_p:
            ax = axes[1][j]
            ax.plot(np.arange(S) * h, truth.p[traj, :, body, j], color="black")
            for name, P in preds.items():
                ax.plot(np.arange(P.p.shape[1]) * h, P.p[traj, :, body, j], "--", color=COLORS.get(name))
            ax.set_title(f"p_{j + 1}")
    axes[0][0].legend()
    save_figure(fig, path)


def loss_curve(history: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(5, 3.4))
    ep = [h["epoch"] for h in history]
    # baselines log other loss parts than LieDFLNN's del_loss / reg_loss: plot the ones present
    keys = [k for k in ("loss", "del_loss", "reg_loss") if all(k in h for h in history)]
    keys += sorted(
        {k for h in history for k in h if k.endswith("_loss") and k not in keys and all(k in hh for hh in history)}
    )
    for key in keys:
        ax.semilogy(ep, np.maximum([h[key] for h in history], 1e-300), label=key)
    ax.set_xlabel("epoch")
    ax.legend()
    ax.grid(alpha=0.3)
    save_figure(fig, path)
