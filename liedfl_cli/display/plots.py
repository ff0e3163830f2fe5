"""Figures of a run (matplotlib, Agg backend): errors, drift, trajectories on the sphere, the loss.

Every axis says what it shows and in which unit (time in s, angles in rad, positions in the data's
length unit, drifts and relative errors dimensionless); every model drawn has a legend entry under
its name (`liedflnn`, `glnn_rk4`, ...; LieDFLNN with its kind on multibody data, "LieDFLNN (articulated)"
or "LieDFLNN (per-body)"; the true-parameter scheme as "true scheme"), the ground truth is black. Curves
stay distinguishable where they coincide: the learned model solid with markers on top, the true scheme
thinner and dashed behind it, the references dotted (`line_style`).

Multibody runs add the error of every body (`draw_error_per_body`: one panel per body, or a heat map of
body x time when there are many, `draw_error_heatmap`) and, for a kinematic tree, the skeleton of one
predicted and recorded frame (`draw_skeleton`).
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
REFERENCE_NAMES = {
    "constant_acceleration": "constant acceleration",
    "constant_velocity_euclidean": "constant velocity (Euclidean p)",
}
DIMENSIONLESS = "dimensionless"
STYLES: dict[str, dict[str, Any]] = {  # per rollout entry; others get the default of `line_style`
    "model": {"linestyle": "-", "linewidth": 1.8, "marker": "o", "markersize": 3.5, "zorder": 4},
    "true_scheme": {"linestyle": "--", "linewidth": 1.0, "marker": None, "zorder": 2, "alpha": 0.9},
    "constant_velocity": {"linestyle": ":", "linewidth": 2.2, "marker": None, "zorder": 1},
    "constant_acceleration": {"linestyle": "-.", "linewidth": 1.0, "marker": None, "zorder": 1},
    "constant_velocity_euclidean": {"linestyle": (0, (1, 3)), "linewidth": 1.0, "marker": "x", "zorder": 1.5},
}
MARKERS = ("s", "^", "D", "v", "P", "X")
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
        elif e in REFERENCE_NAMES:
            out[e] = REFERENCE_NAMES[e]
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
    """Errors against time, one panel per error, one line per model (log scale; styles `line_style`:
    the true scheme dashed behind the model, the constant-velocity reference dotted). Samples 0 and 1
    are the given initial pair (zero error): the lines start at the first prediction."""
    names = names or display_names(curves)
    keys = [k for k in ERROR_LABELS if any(k in c for c in curves.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        title, label, unit = ERROR_LABELS[key]
        for i, (name, c) in enumerate(curves.items()):
            if key in c:
                y = np.asarray(c[key], dtype=np.float64)
                ax.semilogy(
                    np.arange(2, len(y)) * h,
                    _positive(y[2:]),
                    label=names.get(name, name),
                    **line_style(name, i, len(y) - 2),
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
        for i, (name, c) in enumerate(curves.items()):
            if key in c:
                y = np.asarray(c[key], dtype=np.float64)
                ax.semilogy(
                    np.arange(len(y)) * h, _positive(y), label=names.get(name, name), **line_style(name, i, len(y))
                )
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


def line_style(name: str, i: int = 0, n: int = 0) -> dict[str, Any]:
    """Matplotlib keywords of rollout entry `name` (the i-th drawn) on a line of n samples: the model
    solid with round markers in front, the true scheme thin and dashed behind, the references dotted;
    other models (baselines) solid with their own marker. Markers every ~n/12 samples."""
    style = dict(STYLES.get(name, {"linestyle": "-", "linewidth": 1.4, "marker": MARKERS[i % len(MARKERS)],
                                   "markersize": 3.5, "zorder": 3}))  # fmt: skip
    style["color"] = _color(name, i)
    if style.get("marker"):
        style["markevery"] = max(1, n // 12)
    return style


def model_label(model_name: str | None, kinetic: str | None = None, n_bodies: int = 1) -> str | None:
    """The legend name of the learned model: LieDFLNN with its kind on multibody data ("LieDFLNN
    (articulated)": bodies joined by the data's tree, "LieDFLNN (per-body)": each body its own kinetic
    term), other models under their own name. kinetic: the run's resolved `model.kinetic`."""
    if model_name != "liedflnn":
        return model_name
    if kinetic == "articulated":
        return "LieDFLNN (articulated)"
    if n_bodies > 1:
        return "LieDFLNN (per-body)"
    return model_name


def draw_sphere(
    truth_R: np.ndarray,
    preds: dict[str, np.ndarray],
    axis: int = 2,
    n_traj: int = 3,
    body: int = 0,
    names: dict[str, str] | None = None,
) -> Figure:
    """Body axis R e_axis of the first trajectories on the unit sphere: the truth (black) and every
    model (`line_style`), each in the legend. R arrays (T, S+1, B, 3, 3)."""
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
            style = line_style(name, i, len(y))
            style.pop("zorder", None)  # 3-D axes draw in depth order
            ax.plot(*_on_sphere(y).T, label=names.get(name, name) if t == 0 else None, **style)
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
        ax.plot(np.arange(S) * h, truth.R[traj, :, body, j, 2], color="black", lw=2.4, alpha=0.6, label="truth")
        for i, (name, P) in enumerate(preds.items()):
            s = P.R.shape[1]
            ax.plot(np.arange(s) * h, P.R[traj, :, body, j, 2], label=names.get(name, name), **line_style(name, i, s))
        ax.set_ylabel(f"(R e3)_{j + 1} [{DIMENSIONLESS}]")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        if has_p:
            ax = axes[1][j]
            ax.plot(np.arange(S) * h, truth.p[traj, :, body, j], color="black", lw=2.4, alpha=0.6)
            for i, (name, P) in enumerate(preds.items()):
                ax.plot(np.arange(P.p.shape[1]) * h, P.p[traj, :, body, j], **line_style(name, i, P.p.shape[1]))
            ax.set_ylabel(f"p_{j + 1} {length_label(length_unit)}")
            ax.set_xlabel("time [s]")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"test trajectory {traj}, body {body}: predicted (coloured) and true (black)", fontsize=10)
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


BODY_ERRORS = {  # key: (axis label, unit; None: the data's length unit)
    "geodesic_error": ("geodesic error |log(R̂ᵀR)|", "rad"),
    "position_error": ("position error |p̂ − p|", None),
}
HEATMAP_ABOVE = 8
"""Multibody error figures: one panel per body up to this many bodies, a heat map of body x time above."""


def body_errors(truth: ArrayPose, pred: ArrayPose) -> dict[str, np.ndarray]:
    """Per-body errors of a prediction, mean over trajectories (non-finite samples left out):
    {"geodesic_error": (B, S) in rad, "position_error": (m, S) in the data's length unit} over the
    samples both have (S = the shorter length), for the m bodies with a position (every body of world
    poses from forward kinematics, the SE(3) bodies of coordinates)."""
    S = min(truth.R.shape[1], pred.R.shape[1])
    Rt, Rp = truth.R[:, :S], np.asarray(pred.R[:, :S], dtype=np.float64)
    cos = (np.einsum("...ji,...ji->...", Rp, Rt) - 1.0) / 2.0  # tr(R̂ᵀR) = sum_ij R̂_ji R_ji
    with np.errstate(invalid="ignore"):
        geo = np.arccos(np.clip(cos, -1.0, 1.0))
    geo[~np.isfinite(cos)] = np.nan
    out = {"geodesic_error": _nanmean0(geo).T}
    m = min(truth.p.shape[-2], pred.p.shape[-2])
    if m:
        d = np.linalg.norm(np.asarray(pred.p[:, :S, :m], dtype=np.float64) - truth.p[:, :S, :m], axis=-1)
        out["position_error"] = _nanmean0(d).T
    return out


def _nanmean0(x: np.ndarray) -> np.ndarray:
    """Mean over axis 0 ignoring NaN, NaN (no warning) where every entry is."""
    n = np.isfinite(x).sum(0)
    total = np.where(np.isfinite(x), x, 0.0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _error_unit(key: str, length_unit: str | None) -> str:
    label, unit = BODY_ERRORS[key]
    return f"{label} [{unit}]" if unit else f"{label} {length_label(length_unit)}"


def draw_error_per_body(
    errors: dict[str, dict[str, np.ndarray]],
    h: float,
    body_names: list[str],
    key: str = "geodesic_error",
    names: dict[str, str] | None = None,
    length_unit: str | None = "m",
) -> Figure:
    """Small multiples: one panel per body (in `body_names` order, titled with the body's index and
    name), the error `key` of every model against time on a log scale (`line_style`: the model solid
    with markers, the true scheme dashed behind). errors: {entry: `body_errors(...)`}; a key's rows are
    the first bodies when it covers fewer (positions of SE(3) bodies only)."""
    names = names or display_names(errors)
    n = max(e[key].shape[0] for e in errors.values() if key in e)
    cols = n if n <= 4 else (3 if n <= 6 else 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.5 * rows + 0.6), squeeze=False)
    for b in range(rows * cols):
        ax = axes[b // cols][b % cols]
        if b >= n:
            ax.set_visible(False)
            continue
        for i, (entry, e) in enumerate(errors.items()):
            if key in e and b < e[key].shape[0]:
                y = e[key][b, 2:]
                ax.semilogy(np.arange(2, 2 + len(y)) * h, _positive(y), label=names.get(entry, entry),
                            **line_style(entry, i, len(y)))  # fmt: skip
        name = body_names[b] if b < len(body_names) else ""
        ax.set_title(f"body {b}" + (f": {name}" if name and name != f"body{b}" else ""), fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(which="both", labelsize=7)
        if b % cols == 0:
            ax.set_ylabel(_error_unit(key, length_unit), fontsize=8)
        ax.set_xlabel("time [s]", fontsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 5), fontsize=8, bbox_to_anchor=(0.5, 1.0))
    what = "rotation" if key == "geodesic_error" else "position"
    fig.suptitle(f"{what} error of each body, mean over the test trajectories", fontsize=10, y=1.04)
    fig.tight_layout()
    return fig


def draw_error_heatmap(
    errors: dict[str, dict[str, np.ndarray]],
    h: float,
    body_names: list[str],
    key: str = "geodesic_error",
    names: dict[str, str] | None = None,
    length_unit: str | None = "m",
) -> Figure:
    """Many bodies: the error `key` as a heat map of body (rows, labelled with index and name) x time,
    one panel per model, one shared logarithmic colour scale."""
    from matplotlib.colors import LogNorm

    names = names or display_names(errors)
    entries = [k for k, e in errors.items() if key in e]
    vals = np.concatenate([errors[k][key][:, 2:].ravel() for k in entries])
    vals = vals[np.isfinite(vals) & (vals > 0)]
    norm = LogNorm(vmin=vals.min(), vmax=vals.max()) if len(vals) else None
    n = max(errors[k][key].shape[0] for k in entries)
    fig, axes = plt.subplots(1, len(entries), figsize=(4.2 * len(entries) + 1, 1.2 + 0.22 * n), squeeze=False)
    image = None
    for ax, entry in zip(axes[0], entries):
        y = errors[entry][key][:, 2:]
        extent = (1.5 * h, (y.shape[1] + 1.5) * h, y.shape[0] - 0.5, -0.5)
        image = ax.imshow(
            _positive(y), aspect="auto", norm=norm, cmap="viridis", interpolation="nearest", extent=extent
        )
        ax.set_yticks(range(y.shape[0]))
        ax.set_yticklabels([f"{b} {body_names[b]}" if b < len(body_names) else str(b) for b in range(y.shape[0])],
                           fontsize=6)  # fmt: skip
        ax.set_xlabel("time [s]")
        ax.set_title(names.get(entry, entry), fontsize=9)
    axes[0][0].set_ylabel("body")
    if image is not None:
        fig.colorbar(image, ax=list(axes[0]), label=_error_unit(key, length_unit), shrink=0.9)
    what = "rotation" if key == "geodesic_error" else "position"
    fig.suptitle(f"{what} error of each body against time, mean over the test trajectories", fontsize=10)
    return fig


def draw_body_errors(errors, h, body_names, key="geodesic_error", names=None, length_unit="m") -> Figure:
    """`draw_error_per_body` up to `HEATMAP_ABOVE` bodies, `draw_error_heatmap` above."""
    n = max(e[key].shape[0] for e in errors.values() if key in e)
    draw = draw_error_per_body if n <= HEATMAP_ABOVE else draw_error_heatmap
    return draw(errors, h, body_names, key=key, names=names, length_unit=length_unit)


def skeleton_frame(truth_p: np.ndarray, preds_p: dict[str, np.ndarray], traj: int = 0) -> int:
    """The sample the skeleton shows: the last one where the truth and every prediction are finite."""
    S = min([truth_p.shape[1], *(p.shape[1] for p in preds_p.values())])
    ok = np.isfinite(truth_p[traj, :S]).all((-1, -2))
    for p in preds_p.values():
        ok &= np.isfinite(p[traj, :S]).all((-1, -2))
    good = np.flatnonzero(ok)
    return int(good[-1]) if len(good) else 0


def draw_skeleton(
    truth_p: np.ndarray,
    preds_p: dict[str, np.ndarray],
    parents: list[int] | tuple[int, ...],
    h: float,
    traj: int = 0,
    step: int | None = None,
    body_names: list[str] | None = None,
    names: dict[str, str] | None = None,
    length_unit: str | None = "m",
) -> Figure:
    """One frame of a kinematic tree, predicted against recorded: the world position of every body's
    joint (forward kinematics), each joined to its parent's, in 3-D and in the two projections x-y and
    x-z (equal scales), the recorded skeleton black and thick behind, each model in its colour and
    style, bodies numbered on the truth. p arrays (T, S+1, B, 3) of world joint positions; step: the
    sample (default `skeleton_frame`, the last one every skeleton has)."""
    names = names or display_names(preds_p)
    step = skeleton_frame(truth_p, preds_p, traj) if step is None else step
    fig = plt.figure(figsize=(13, 4.4))
    ax3 = fig.add_subplot(1, 3, 1, projection="3d")
    ax_xy, ax_xz = fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    frames = {"truth": truth_p[traj, step], **{k: v[traj, step] for k, v in preds_p.items()}}
    pts = np.concatenate([f[np.isfinite(f).all(-1)] for f in frames.values()])
    centre, half = (pts.max(0) + pts.min(0)) / 2, max(float((pts.max(0) - pts.min(0)).max()) / 2 * 1.15, 1e-9)
    for i, (entry, x) in enumerate(frames.items()):
        if entry == "truth":
            style: dict[str, Any] = {"color": "black", "linewidth": 4.0, "alpha": 0.45, "marker": "o", "markersize": 7,
                                     "zorder": 1}  # fmt: skip
            label = "recorded"
        else:
            style = line_style(entry, i - 1, 0)
            style.update(markevery=1, markersize=5, linewidth=max(style.get("linewidth", 1.4), 1.4))
            off = np.linalg.norm(x - frames["truth"], axis=-1)
            far = f"{np.nanmax(off):.2g}" if np.isfinite(off).any() else "nan"
            label = f"{names.get(entry, entry)} (joints off by ≤ {far} {length_unit or 'length units'})"
        for b, q in enumerate(parents):
            seg = x[[q, b]] if q >= 0 else x[[b]]
            lab = label if b == 0 else None
            kw = {k: v for k, v in style.items() if k != "zorder"}
            ax3.plot(*seg.T, label=lab, **kw)
            ax_xy.plot(seg[:, 0], seg[:, 1], **style)
            ax_xz.plot(seg[:, 0], seg[:, 2], **style)
    for ax, (u, v) in ((ax_xy, (0, 1)), (ax_xz, (0, 2))):
        placed: list[np.ndarray] = []  # bodies whose joints coincide in a projection: tags stacked
        for b in range(len(parents)):
            x = frames["truth"][b]
            tag = str(b) if not body_names or b >= len(body_names) else f"{b} {body_names[b]}"
            near = sum(np.hypot(*(q - x[[u, v]])) < 0.04 * half for q in placed)
            placed.append(x[[u, v]])
            ax.annotate(tag, (x[u], x[v]), xytext=(5, 5 - 9 * near), textcoords="offset points", fontsize=7)
    unit = length_label(length_unit)
    for ax, (a, c) in ((ax_xy, ("x", "y")), (ax_xz, ("x", "z"))):
        i, j = "xyz".index(a), "xyz".index(c)
        ax.set_xlim(centre[i] - half, centre[i] + half)
        ax.set_ylim(centre[j] - half, centre[j] + half)
        ax.set_aspect("equal")
        ax.set_xlabel(f"{a} {unit}")
        ax.set_ylabel(f"{c} {unit}")
        ax.set_title(f"projection on {a}-{c}", fontsize=9)
        ax.grid(alpha=0.3)
    for k, setter in enumerate((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim)):
        setter(centre[k] - half, centre[k] + half)
    ax3.set_box_aspect((1, 1, 1))
    for k, setter in enumerate((ax3.set_xlabel, ax3.set_ylabel, ax3.set_zlabel)):
        setter(f"{'xyz'[k]} {unit}", fontsize=7, labelpad=-4)
    ax3.tick_params(labelsize=6, pad=-2)
    ax3.legend(loc="upper left", fontsize=7)
    fig.suptitle(
        f"test trajectory {traj} at t = {step * h:.3g} s (sample {step}): every body's joint joined to its parent's, "
        "predicted against recorded",
        fontsize=10,
    )
    fig.tight_layout()
    return fig
