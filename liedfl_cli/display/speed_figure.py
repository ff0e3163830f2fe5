"""`plots/error_vs_speed.png` of `liedfl report`: error against training time and against rollout
time per step per trajectory, one point per model and setting (mean ± std over its seeds).

Readable at any sweep size: up to `FULL_LABELS` points each carries its label; beyond, a number,
with a key (number -> model / setting) under the panels. A label goes at the first of a few offsets
around its point where it overlaps neither an earlier label nor leaves the axes (measured with the
renderer, not estimated); if none fits, at the least crowded offset, moved inside the axes. Error
bars on the log axes never reach zero: where mean − std ≤ 0 the lower bar ends at the smallest
seed's value instead, marked by an open triangle (said in the caption).
"""

from __future__ import annotations

import math

FULL_LABELS = 8
"""Sweeps with at most this many points are labelled in full; larger ones by number plus a key."""
OFFSETS = ((5, 4), (5, -12), (-5, 4), (-5, -12), (5, 14), (5, -22), (-5, 14), (-5, -22), (0, 24), (0, -32))
"""Label offsets from the point in points (x, y); negative x: the label ends left of the point."""


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both coordinates (smaller is better), sorted by x."""
    front, best = [], math.inf
    for x, y in sorted(points):
        if y < best:
            front.append((x, y))
            best = y
    return front


def log_bar(mean: float, std: float | None, values: list[float]) -> tuple[float, float, bool]:
    """(lower, upper, clipped) ends of a ± std bar drawn on a log axis: mean ± std, except that a lower
    end ≤ 0 (no place on a log axis) becomes the smallest positive seed value (clipped=True)."""
    std = std or 0.0
    lower, clipped = mean - std, False
    if lower <= 0:
        positive = [v for v in values if v > 0]
        lower, clipped = (min(positive) if positive else mean), True
    return min(lower, mean), mean + std, clipped


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def _overlap_area(a, b) -> float:
    return max(0.0, min(a.x1, b.x1) - max(a.x0, b.x0)) * max(0.0, min(a.y1, b.y1) - max(a.y0, b.y0))


def place_labels(ax, pts: list[tuple[float, float, str, object]], fontsize: float = 7) -> list:
    """Annotate each (x, y, text, color) of `pts` inside the axes, avoiding labels placed before; returns
    the annotations (their window extents lie inside the axes' once drawn)."""
    fig = ax.figure
    fig.canvas.draw()  # final limits and transforms
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    placed: list = []
    out = []
    for x, y, text, color in sorted(pts, key=lambda p: (p[0], p[1])):
        best = None
        for dx, dy in OFFSETS:
            ann = ax.annotate(
                text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize, color=color,
                ha="left" if dx >= 0 else "right", va="bottom", annotation_clip=False, zorder=5,
            )  # fmt: skip
            box = ann.get_window_extent(renderer)
            inside = frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1
            crowd = sum(_overlap_area(box, b) for b in placed)
            score = (not inside, crowd)
            if best is None or score < best[0]:
                if best is not None:
                    best[1].remove()
                best = (score, ann, box)
            else:
                ann.remove()
            if inside and crowd == 0:
                break
        assert best is not None
        _, ann, box = best
        if best[0][0]:  # nowhere inside: shift the least crowded one in (the label leaves its point a little)
            shift_x = max(frame.x0 - box.x0, 0.0) - max(box.x1 - frame.x1, 0.0)
            shift_y = max(frame.y0 - box.y0, 0.0) - max(box.y1 - frame.y1, 0.0)
            px_per_pt = fig.dpi / 72.0
            ox, oy = ann.xyann
            ann.xyann = (ox + shift_x / px_per_pt, oy + shift_y / px_per_pt)
            box = ann.get_window_extent(renderer)
        placed.append(box)
        out.append(ann)
    return out


def plain_log_ticks(ax) -> None:
    """Log-axis tick labels as plain numbers (0.5, 1, 2, 5, ...; 1e-05 when small), labelling the 2s and
    5s between decades only when the axis spans less than two decades (else they would overlap)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for axis, (lo, hi) in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        if axis.get_scale() != "log" or lo <= 0:
            continue
        axis.set_major_formatter(plain)
        axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
        axis.set_minor_formatter(plain if math.log10(hi / lo) < 2 else NullFormatter())


def _seed_values(s: dict, key: str) -> list[float]:
    return [float(r[key]) for r in s.get("runs", []) if r.get(key) is not None and math.isfinite(float(r[key]))]


def draw_error_vs_speed(summary: list[dict], error: str, error_label: str, constant_velocity: float | None = None):
    """The figure for `summary` (report.summarize rows: `label`, `model`, `runs`, and per metric
    (mean, std, n)); `error`: the metric on the y axis; `constant_velocity`: that error of the
    constant-velocity guess on the same test data, drawn as a horizontal line (a model above it
    predicts worse than repeating the last increment). None without a point."""
    from .plots import plt

    axes_spec = [
        ("train_seconds", "training time [s]"),
        ("rollout_s_per_step_per_trajectory", "rollout time per step per trajectory [s]"),
    ]
    if not any(s[error][0] is not None and s[k][0] for s in summary for k, _ in axes_spec):
        return None
    models = sorted({s["model"] for s in summary})
    colors = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(models)}
    numbered = len(summary) > FULL_LABELS
    key_rows = math.ceil(len(summary) / 3) if numbered else 0
    height = 4.9 + 0.19 * key_rows
    fig, axes = plt.subplots(1, 2, figsize=(11, height))
    any_clipped, panel_pts = False, []
    for ax, (key, xlabel) in zip(axes, axes_spec):
        pts: list[tuple[float, float, str, object]] = []
        shown: set[str] = set()
        lo_x, hi_x, lo_y, hi_y = [], [], [], []  # the bars' ends: the axes' limits
        panel_pts.append(pts)
        for i, s in enumerate(summary, start=1):
            (x, dx, _), (y, dy, _) = s[key], s[error]
            if x is None or y is None or x <= 0 or y <= 0:
                continue
            m = s["model"]
            (x0, x1, cx), (y0, y1, cy) = log_bar(x, dx, _seed_values(s, key)), log_bar(y, dy, _seed_values(s, error))
            ax.errorbar(
                x, y, xerr=[[x - x0], [x1 - x]] if dx else None, yerr=[[y - y0], [y1 - y]] if dy else None,
                fmt="o", color=colors[m], capsize=3, ms=5, label=m if m not in shown else None, zorder=3,
            )  # fmt: skip
            if cx:
                ax.plot(x0, y, "<", mfc="white", mec=colors[m], ms=5, zorder=3)
            if cy:
                ax.plot(x, y0, "v", mfc="white", mec=colors[m], ms=5, zorder=3)
            any_clipped = any_clipped or cx or cy
            lo_x.append(x0 if dx else x)
            hi_x.append(x1 if dx else x)
            lo_y.append(y0 if dy else y)
            hi_y.append(y1 if dy else y)
            shown.add(m)
            pts.append((x, y, str(i) if numbered else s["label"], colors[m]))
        if constant_velocity is not None and constant_velocity > 0 and pts:
            ax.axhline(constant_velocity, color="0.35", ls=":", lw=1.4, label="constant velocity", zorder=1)
            lo_y.append(constant_velocity)
            hi_y.append(constant_velocity)
        front = pareto_front([(x, y) for x, y, _, _ in pts])
        if len(front) >= 2:  # one point is no front (no legend entry for it)
            fx, fy = zip(*front)
            ax.step(fx, fy, where="post", color="black", ls="--", lw=1.2, label="Pareto front", zorder=2)
            ax.plot(fx, fy, "o", ms=10, mfc="none", mec="black", zorder=4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        if pts:  # room around the outermost points and bars for the labels (a quarter decade each way)
            ax.set_xlim(min(lo_x) / 10**0.25, max(hi_x) * 10**0.25)
            ax.set_ylim(min(lo_y) / 10**0.25, max(hi_y) * 10**0.35)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(error_label, fontsize=8)
        ax.grid(alpha=0.3, which="both")
        plain_log_ticks(ax)
    n_max = max(s[error][2] for s in summary)
    caption = (
        "error against speed: one point per model and setting"
        + (f", mean ± std over up to {n_max} seeds" if n_max > 1 else "")
        + " (lower left is better)"
    )
    if any_clipped:
        caption += "\n▽ / ◁: mean − std ≤ 0, the bar stops at the smallest seed's value (a log axis has no 0)"
    fig.suptitle(caption, fontsize=10)
    handles: dict = {}
    for ax in axes:  # one legend for both panels, below them (inside, it would hide points and labels)
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    legend_h, row_h = 0.35, 0.19  # inches
    bottom = (legend_h + row_h * key_rows + (0.1 if numbered else 0.0)) / height
    fig.tight_layout(rect=(0, bottom, 1, 1))
    fig.legend(
        list(handles.values()), list(handles), loc="upper center", bbox_to_anchor=(0.5, bottom),
        ncol=min(len(handles), 6), fontsize=8, frameon=False,
    )  # fmt: skip
    for i, s in enumerate(summary if numbered else []):  # the key: number -> model / setting
        col, row = divmod(i, key_rows)
        fig.text(
            0.03 + 0.33 * col, bottom - (legend_h + row_h * (row + 1)) / height, f"{i + 1}  {s['label']}",
            fontsize=7.5, color=colors[s["model"]], va="bottom",
        )  # fmt: skip
    for ax, pts in zip(axes, panel_pts):  # after the layout: label positions depend on the final axes size
        place_labels(ax, pts)
    return fig
