"""Figures of a run (matplotlib, Agg backend): errors, drift, trajectories on the sphere, the loss.

Every axis says what it shows and in which unit (time in s, angles in rad, positions in the data's
length unit, drifts and relative errors dimensionless); every model drawn has a legend entry under
its name (`liedflnn`, `glnn_rk4`, ...; the true-parameter scheme as "true scheme"), the ground truth
is black.
"""

from __future__ import annotations

import functools
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ..files.io_utils import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@functools.cache
def _pyplot() -> ModuleType:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot

    return matplotlib.pyplot


class _LazyPyplot:
    """`matplotlib.pyplot` on the Agg backend, imported at the first attribute read: loading matplotlib
    costs ~0.5 s of every `liedfl` start, and most commands (data, rollout, eval.plots=false) draw
    nothing."""

    def __getattr__(self, name: str) -> Any:
        return getattr(_pyplot(), name)


plt: Any = _LazyPyplot()


class ArrayPose(NamedTuple):
    """A `lie.Pose` as numpy arrays, as the plots read it: R (..., B, 3, 3), p (..., m, 3)."""

    R: np.ndarray
    p: np.ndarray


COLORS = {"truth": "black", "model": "tab:blue", "true_scheme": "tab:orange", "constant_velocity": "0.35"}
TRUE_SCHEME = "true scheme"
"""Display name of the rollout entry `true_scheme` (the scene's true-parameter discrete scheme)."""
CONSTANT_VELOCITY = "constant velocity"
"""Display name of the evaluation's `constant_velocity` reference (the last increment repeated); drawn dashed."""
DIMENSIONLESS = "dimensionless"
ERROR_LABELS = {  # key: (title, axis label, unit; None: the data's length unit)
    "rel_rot_error": ("relative rotation error ‖R̂ − R‖_F / ‖R‖_F", "relative rotation error", DIMENSIONLESS),
    "geodesic_error": ("geodesic rotation error |log(R̂ᵀR)|", "geodesic error", "rad"),
    "position_error": ("position error |p̂ − p|", "position error", None),
}


def display_names(entries, model_name: str | None = None) -> dict[str, str]:
    """{rollout entry: legend name}: `model` -> the model's name, `true_scheme` -> "true scheme"."""
    out = {}
    for e in entries:
        if e == "model":
            out[e] = model_name or "model"
        elif e == "true_scheme":
            out[e] = TRUE_SCHEME
        elif e == "constant_velocity":
            out[e] = CONSTANT_VELOCITY
        else:
            out[e] = str(e)
    return out


def save_figure(fig, path: Path, dpi: int = 120) -> None:
    """Write `fig` as a PNG to `path` atomically and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)


def draw_unit_sphere(ax, labels: bool = True) -> None:
    """The unit sphere as a light wireframe on a 3-D axis, with equal aspect and fixed limits: the
    backdrop of every plot of a direction (a body axis R e_i, a bone direction) over time."""
    u, v = np.mgrid[0 : 2 * np.pi : 30j, 0 : np.pi : 15j]
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.75", linewidth=0.4)
    ax.set_box_aspect((1, 1, 1))
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-1.1, 1.1)
    if labels:
        ax.set_xlabel("x (dimensionless)", fontsize=7, labelpad=-6)
        ax.set_ylabel("y (dimensionless)", fontsize=7, labelpad=-6)
        ax.set_zlabel("z (dimensionless)", fontsize=7, labelpad=-6)
        ax.tick_params(labelsize=6, pad=-2)


def _on_sphere(x: np.ndarray) -> np.ndarray:
    """A direction track (S, 3) for a sphere plot: non-finite samples become gaps, points far off the
    sphere (a prediction that left the group) are kept but clipped to the plot box."""
    x = np.array(x, dtype=np.float64)
    x[~np.isfinite(x).all(-1)] = np.nan
    return np.clip(x, -1.1, 1.1)


def length_label(unit: str | None) -> str:
    return f"[{unit}]" if unit else "[data length unit]"


def draw_error_vs_step(
    curves: dict[str, dict], h: float, names: dict[str, str] | None = None, length_unit: str | None = "m"
) -> Figure:
    """Errors against time, one panel per error, one line per model (log scale); the constant-velocity
    reference dashed. Samples 0 and 1 are the given initial pair (zero error): the lines start at the
    first prediction."""
    names = names or display_names(curves)
    keys = [k for k in ERROR_LABELS if any(k in c for c in curves.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        title, label, unit = ERROR_LABELS[key]
        for name, c in curves.items():
            if key in c:
                y = np.asarray(c[key], dtype=np.float64)
                ax.semilogy(
                    np.arange(2, len(y)) * h,
                    _positive(y[2:]),
                    "--" if name == "constant_velocity" else "-",
                    label=names.get(name, name),
                    color=_color(name),
                )
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{label} [{unit}]" if unit else f"{label} {length_label(length_unit)}")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("rollout errors, mean over the test trajectories", fontsize=10)
    fig.tight_layout()
    return fig


def draw_drift_vs_step(curves: dict[str, dict], h: float, names: dict[str, str] | None = None) -> Figure:
    """Distance of the predicted rotations from SO(3) against time (largest over trajectories and bodies)."""
    names = names or display_names(curves)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, label in zip(axes, ("orth_drift", "det_drift"), ("‖RᵀR − I‖_F", "|det R − 1|")):
        for name, c in curves.items():
            if key in c:
                y = np.asarray(c[key], dtype=np.float64)
                ax.semilogy(np.arange(len(y)) * h, _positive(y), label=names.get(name, name), color=_color(name))
        ax.set_title(f"manifold drift {label}", fontsize=10)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{label} [{DIMENSIONLESS}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def _positive(y: np.ndarray) -> np.ndarray:
    """y for a log axis: exact zeros (drift at rounding level 0, a loss part switched off) become gaps
    instead of a clamp that would stretch the axis down to 1e-300."""
    y = np.array(y, dtype=np.float64)
    y[~(y > 0)] = np.nan
    return y


def _color(name: str, i: int = 0):
    return COLORS.get(name, plt.get_cmap("tab10")((i + 2) % 10))


def draw_sphere(
    truth_R: np.ndarray,
    preds: dict[str, np.ndarray],
    axis: int = 2,
    n_traj: int = 3,
    body: int = 0,
    names: dict[str, str] | None = None,
) -> Figure:
    """Body axis R e_axis of the first trajectories on the unit sphere: the truth (black) and every
    model (dashed), each in the legend. R arrays (T, S+1, B, 3, 3)."""
    names = names or display_names(preds)
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    draw_unit_sphere(ax)
    n = min(n_traj, truth_R.shape[0])
    for t in range(n):
        x = truth_R[t, :, body, :, axis]
        ax.plot(*_on_sphere(x).T, color="black", linewidth=1.2, label="truth" if t == 0 else None)
        ax.scatter(*x[0], color="black", s=12)
        for i, (name, R) in enumerate(preds.items()):
            y = R[t, :, body, :, axis]
            ax.plot(
                *_on_sphere(y).T,
                "--",
                color=_color(name, i),
                linewidth=1.0,
                label=names.get(name, name) if t == 0 else None,
            )
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(f"body {body} axis R e{axis + 1} on the unit sphere ({n} test trajectories; dot = start)", fontsize=9)
    return fig


def draw_predicted_vs_true(
    truth: ArrayPose,
    preds: dict[str, ArrayPose],
    h: float,
    traj: int = 0,
    body: int = 0,
    names: dict[str, str] | None = None,
    length_unit: str | None = "m",
) -> Figure:
    """Components of R e3 (and p for SE(3) bodies) over time for one trajectory."""
    names = names or display_names(preds)
    has_p = truth.p.shape[-2] > body
    rows = 2 if has_p else 1
    fig, axes = plt.subplots(rows, 3, figsize=(12, 3 * rows), squeeze=False)
    S = truth.R.shape[1]
    for j in range(3):
        ax = axes[0][j]
        ax.plot(np.arange(S) * h, truth.R[traj, :, body, j, 2], color="black", label="truth")
        for i, (name, P) in enumerate(preds.items()):
            s = P.R.shape[1]
            ax.plot(
                np.arange(s) * h, P.R[traj, :, body, j, 2], "--", color=_color(name, i), label=names.get(name, name)
            )
        ax.set_ylabel(f"(R e3)_{j + 1} [{DIMENSIONLESS}]")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        if has_p:
            ax = axes[1][j]
            ax.plot(np.arange(S) * h, truth.p[traj, :, body, j], color="black")
            for i, (name, P) in enumerate(preds.items()):
                ax.plot(np.arange(P.p.shape[1]) * h, P.p[traj, :, body, j], "--", color=_color(name, i))
            ax.set_ylabel(f"p_{j + 1} {length_label(length_unit)}")
            ax.set_xlabel("time [s]")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"test trajectory {traj}, body {body}: predicted (dashed) and true (black)", fontsize=10)
    fig.tight_layout()
    return fig


def draw_loss_curve(history: list[dict]) -> Figure:
    """Training loss and its parts against the epoch (log scale). A part that reaches exactly 0 (the
    regularity penalty once every sampled pair is regular) is drawn where positive and marked by
    triangles on the bottom edge where it is 0, so the other curves keep their scale."""
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ep = np.asarray([h["epoch"] for h in history], dtype=np.float64)
    # baselines log other loss parts than LieDFLNN's del_loss / reg_loss: plot the ones present
    keys = [k for k in ("loss", "del_loss", "reg_loss") if all(k in h for h in history)]
    keys += sorted(
        {k for h in history for k in h if k.endswith("_loss") and k not in keys and all(k in hh for hh in history)}
    )
    zeros: dict[str, tuple] = {}
    for i, key in enumerate(keys):
        y = np.asarray([h[key] for h in history], dtype=np.float64)
        color = plt.get_cmap("tab10")(i % 10)
        zero = ~(y > 0) & np.isfinite(y)
        label = key + (f" (0 at {int(zero.sum())} of {len(y)} epochs)" if zero.any() else "")
        if (y > 0).any():
            ax.plot(ep, _positive(y), label=label, color=color, marker="." if len(ep) < 30 else None)
        if zero.any():
            zeros[key] = (ep[zero], color, label if not (y > 0).any() else None)
    positive = [h[k] for h in history for k in keys if h[k] > 0 and np.isfinite(h[k])]
    ax.set_yscale("log")
    if positive:
        lo, hi = min(positive), max(positive)
        ax.set_ylim(lo / 3, hi * 3)
    for _key, (x, color, label) in zeros.items():
        ax.plot(x, np.full(len(x), ax.get_ylim()[0]), "v", color=color, ms=5, clip_on=False, label=label)
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (mean over batches) [model units]")
    ax.set_title("training loss" + ("; ▼ = part exactly 0" if zeros else ""), fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    return fig
