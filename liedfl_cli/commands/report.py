"""`liedfl report sweep=<multirun dir>`: one table and the paper-style figures over a sweep.

Reads every run directory below `sweep` (any folder holding `.hydra/config.yaml` and `eval.csv`) and
writes into the sweep directory (a single run's own folder is refused: the report's files would land
among the run's; its evaluation is its eval.md):

- `report.csv`: one row per run, every column;
- `report.md`: one summary line per model and setting (the overrides that differ between runs, the
  seed aside) with mean ± std over its seeds, then the runs with only the columns that vary (the
  constant ones are listed once above the tables), then the failed runs;
- `plots/error_vs_speed.png`: error against speed, one point per model and setting (mean ± std over
  seeds as error bars, labelled; numbered with a key in sweeps of more than 8), the Pareto front
  drawn when it has two points or more; two panels, training time and rollout time per step per
  trajectory (`speed_figure.py`);
- `plots/error_vs_time.png`: rollout error and manifold drift against time, one line per model and
  setting (mean over seeds, ± std band), as in the paper's Exp 1 and Exp 3 panels, with the true
  scheme (dotted) and constant velocity (dashed, error panel) of the first run that has them;
- `plots/error_vs_training_length.png`: error against the training trajectory length, only when the
  sweep ran several lengths;
- `plots/sphere_per_model.png`: the first test trajectory's body axis on the unit sphere, truth and
  prediction, one panel per model.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from omegaconf import DictConfig

from ..config import resolvers  # noqa: F401  (registers the config resolvers)
from ..display import speed_figure
from ..display.speed_figure import pareto_front, plain_log_ticks  # noqa: F401  (pareto_front: part of this module's API)
from ..display.ui import console, print_table, warning_line
from ..errors import ConfigError, DatasetError, LiedflError
from ..evaluation import EvalOutputs
from ..files.io_utils import fmt, markdown_table
from ..files.rollout_file import FILE_NAME, read_rollout
from .evaluate import CONSTANT_VELOCITY, CV_COLUMNS, DRIFT_COLUMNS, ERROR_COLUMNS, ONE_STEP_COLUMNS
from .outputs import write_outputs

if TYPE_CHECKING:
    from matplotlib.figure import Figure

COLUMNS = [
    "run",
    "model",
    "dataset",
    "train_steps",
    "seed",
    "setting",
    "parameters",
    "train_seconds",
    "seconds_per_epoch",
    "rollout_s_per_step",
    "rollout_trajectories",
    "rollout_s_per_step_per_trajectory",
    *ERROR_COLUMNS,
    *ONE_STEP_COLUMNS,
    *CV_COLUMNS,
    *DRIFT_COLUMNS,
    "newton_failures",
]
METRICS = [
    "rel_rot_error_mean",
    "geodesic_error_mean",
    "position_error_mean",
    "one_step_vs_cv",
    "rollout_vs_cv",
    "max_orth_drift",
    "newton_failures",
    "train_seconds",
    "rollout_s_per_step_per_trajectory",
]
"""The columns of the summary (mean ± std over seeds)."""
HEADERS = {
    "rel_rot_error_mean": "rel. rotation error",
    "rel_rot_error_final": "rel. rotation error (end)",
    "geodesic_error_mean": "geodesic error [rad]",
    "position_error_mean": "position error",
    "one_step_rot_error_mean": "one-step rot. error [rad]",
    "one_step_pos_error_mean": "one-step pos. error",
    "one_step_vs_cv": "one-step / const. vel.",
    "rollout_vs_cv": "geodesic / const. vel.",
    "max_orth_drift": "max orth. drift",
    "max_det_drift": "max det. drift",
    "newton_failures": "Newton failures",
    "train_seconds": "training [s]",
    "seconds_per_epoch": "s/epoch",
    "rollout_s_per_step": "rollout [s/step]",
    "rollout_s_per_step_per_trajectory": "rollout [s/step/traj.]",
    "rollout_trajectories": "rollout traj.",
    "train_steps": "train steps",
    "parameters": "parameters",
}
CONSOLE_HEADERS = {
    **HEADERS,
    "rel_rot_error_mean": "rel. rot. error",
    "geodesic_error_mean": "geodesic [rad]",
    "train_seconds": "train [s]",
    "rollout_s_per_step_per_trajectory": "rollout s/step/traj",
}
"""Shorter headers of the console table (report.md keeps HEADERS): the speed columns fit at 80 columns."""
CONSOLE_PRIORITY = ["label", "rel_rot_error_mean", "train_seconds", "rollout_s_per_step_per_trajectory"]
"""The console table's columns kept first on a narrow terminal: the error and both speeds."""
ERROR = "rel_rot_error_mean"
ERROR_LABEL = "mean relative rotation error ‖R̂ − R‖_F/‖R‖_F [dimensionless]"
CV_ERROR = f"cv_{ERROR}"
"""report.csv's column of constant velocity's ERROR on each run's test data (its eval.csv row)."""
NOT_SETTINGS = ("seed", "baseline", "model")
"""Override keys that do not make a setting (the model has its own column; seeds are averaged)."""


def model_name(cfg: dict) -> str:
    name = (cfg.get("model") or {}).get("name")
    if name is None:  # runs written before model configs carried their name
        name = (cfg.get("baseline") or {}).get("name", "none")
    return "liedflnn" if name == "none" else str(name)


def find_runs(sweep: Path) -> list[Path]:
    return sorted(
        {p.parent.parent for p in sweep.rglob(".hydra/config.yaml") if (p.parent.parent / "eval.csv").is_file()},
        key=lambda p: str(p),
    )


def _read(path: Path, kind: str):
    """A run file as parsed YAML / CSV rows / JSON; DatasetError naming the file when garbled."""
    from ..config.runs import read_json_object

    try:
        if kind == "json":
            return read_json_object(path)
        text = path.read_text()
        if kind == "yaml":
            return yaml.safe_load(text)
        rows = list(csv.DictReader(text.splitlines()))
        if rows and "model" not in rows[0]:
            raise DatasetError(f"{path}: column 'model' is missing")
        return rows
    except (UnicodeDecodeError, yaml.YAMLError, csv.Error) as e:
        raise DatasetError(f"{path}: not a valid {kind.upper()} file ({type(e).__name__})") from None


def _number(path: Path, key: str, v):
    try:
        return float(v) if v not in (None, "") else None
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: column '{key}' holds {v!r}, not a number") from None


def _overrides(items) -> dict[str, str]:
    out = {}
    for s in items or []:
        key, sep, value = str(s).partition("=")
        if sep:
            out[key.lstrip("+~")] = value
    return out


def collect(sweep: Path) -> list[dict]:
    rows = []
    for run in find_runs(sweep):
        cfg = _read(run / ".hydra" / "config.yaml", "yaml")
        if not isinstance(cfg, dict) or not isinstance(cfg.get("dataset"), dict):
            raise DatasetError(f"{run / '.hydra' / 'config.yaml'}: not a liedfl train config (no 'dataset' section)")
        overrides: list = []
        ov = run / ".hydra" / "overrides.yaml"
        if ov.is_file():
            overrides = _read(ov, "yaml") or []
        evals = {r["model"]: r for r in _read(run / "eval.csv", "csv")}
        if "model" not in evals:
            continue
        e = evals["model"]
        summary = _read(run / "summary.json", "json") if (run / "summary.json").is_file() else {}
        steps = cfg["dataset"].get("train_steps")
        if steps is None:  # a file / import scene: "all the steps", recorded by the run
            steps = (summary.get("dataset") or {}).get("train_steps")
        row = {
            "run": str(run.relative_to(sweep)),
            "model": model_name(cfg),
            "dataset": cfg["dataset"]["name"],
            "train_steps": int(steps) if steps is not None else None,
            "seed": cfg.get("seed"),
            "setting": " ".join(f"{k}={v}" for k, v in _overrides(overrides).items() if k != "seed"),
        }
        for k in COLUMNS[6:]:
            row[k] = _number(run / "eval.csv", k, e.get(k))
        cv = evals.get(CONSTANT_VELOCITY)  # the same error of constant velocity on this run's test data
        row[CV_ERROR] = _number(run / "eval.csv", ERROR, cv.get(ERROR)) if cv else None
        t = summary.get("timings", {})
        t = t if isinstance(t, dict) else {}
        row.update({k: t.get(k) for k in ("parameters", "train_seconds", "seconds_per_epoch") if t.get(k) is not None})
        if row.get("rollout_trajectories") is None:  # eval.csv of an older liedfl: count them in the file
            row["rollout_trajectories"] = _rollout_trajectories(run / FILE_NAME)
        sps, n = row.get("rollout_s_per_step"), row.get("rollout_trajectories")
        row["rollout_s_per_step_per_trajectory"] = sps / n if sps is not None and n else None
        rows.append(row)
    return rows


def _rollout_trajectories(path: Path) -> int | None:
    try:
        return len(read_rollout(path).traj_index)
    except LiedflError:
        return None


# ----------------------------------------------------------------------------- grouping
def varying_settings(rows: list[dict]) -> list[str]:
    """Override keys whose value differs between runs (seed, baseline and model aside)."""
    settings = [_overrides(r["setting"].split()) for r in rows]
    keys = list(dict.fromkeys(k for s in settings for k in s))
    return [k for k in keys if k not in NOT_SETTINGS and len({s.get(k) for s in settings}) > 1]


def _label(row: dict, keys: list[str]) -> str:
    s = _overrides(row["setting"].split())
    return " ".join([row["model"], *(f"{k.rsplit('.', 1)[-1]}={s[k]}" for k in keys if k in s)])


def groups(rows: list[dict], keys: list[str]) -> dict[str, list[dict]]:
    """{label: runs} for each model and setting (`keys`: the override keys that make a setting)."""
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(_label(r, keys), []).append(r)
    return out


def mean_std(values) -> tuple[float | None, float | None, int]:
    """(mean, sample standard deviation (0 for one value), n) of the finite values; (None, None, 0) if none."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    if not v:
        return None, None, 0
    return float(np.mean(v)), float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, len(v)


def summarize(rows: list[dict], keys: list[str]) -> list[dict]:
    """One row per model and setting: for each metric, mean and std over its seeds."""
    out = []
    for label, runs in groups(rows, keys).items():
        s = {"label": label, "model": runs[0]["model"], "seeds": len(runs), "runs": runs}
        for m in METRICS:
            s[m] = mean_std(r.get(m) for r in runs)
        out.append(s)
    return out


def pm(stat) -> str:
    mean, std, n = stat
    if mean is None:
        return "–"
    return fmt(mean) if n < 2 else f"{fmt(mean)} ± {fmt(std)}"


def pm_short(stat) -> str:
    """`pm` with 3 significant digits (2 for the std): the console table's cells (report.md has 4)."""
    mean, std, n = stat
    if mean is None:
        return "–"
    return f"{mean:.3g}" if n < 2 else f"{mean:.3g} ± {std:.2g}"


# ----------------------------------------------------------------------------- figures
def _colors(models: list[str]):
    from ..display.plots import plt

    return {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(models)}


def draw_error_vs_speed(summary: list[dict]) -> Figure | None:
    """plots/error_vs_speed.png (speed_figure.py); None without a point. With constant velocity's
    error, when every run that has it shares it (one test set), as a horizontal reference."""
    return speed_figure.draw_error_vs_speed(summary, ERROR, ERROR_LABEL, shared_reference(summary, CV_ERROR))


def shared_reference(summary: list[dict], key: str) -> float | None:
    """The value of `key` in the runs of `summary` when they all agree (to 1e-9 relative: the same
    test data), else None (none has it, or the runs were evaluated on different data)."""
    values = [float(r[key]) for s in summary for r in s.get("runs", []) if r.get(key) is not None]
    if not values or max(values) - min(values) > 1e-9 * max(abs(v) for v in values):
        return None
    return values[0]


def _curves(sweep: Path, row: dict) -> dict:
    path = sweep / row["run"] / "eval_curves.json"
    try:
        return json.loads(path.read_text()) if path.is_file() else {}
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {}


def _h(sweep: Path, row: dict) -> float | None:
    """The run's time step: from its config, else from its rollout file."""
    try:
        h = yaml.safe_load((sweep / row["run"] / ".hydra" / "config.yaml").read_text())["dataset"].get("h")
        if isinstance(h, (int, float)) and h > 0:
            return float(h)
        return float(read_rollout(sweep / row["run"] / FILE_NAME).h)
    except (LiedflError, OSError, KeyError, TypeError, yaml.YAMLError):
        return None


def draw_error_vs_time(sweep: Path, summary: list[dict]) -> Figure | None:
    from ..display.plots import plt

    panels = [
        ("rel_rot_error", "relative rotation error [dimensionless]"),
        ("orth_drift", "‖RᵀR − I‖_F [dimensionless]"),
    ]
    colors = _colors(sorted({s["model"] for s in summary}))
    styles = ["-", "--", ":", "-."]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.0))
    drawn, reference, cv_reference = False, None, None
    per_model: dict[str, int] = {}
    for s in summary:
        curves = [_curves(sweep, r) for r in s["runs"]]
        h = _h(sweep, s["runs"][0])
        if h is None:
            continue
        k = per_model.setdefault(s["model"], 0)
        per_model[s["model"]] += 1
        if reference is None:
            reference = next((c["true_scheme"] for c in curves if "true_scheme" in c), None), h
        if cv_reference is None:
            cv_reference = next((c["constant_velocity"] for c in curves if "constant_velocity" in c), None), h
        for ax, (key, _) in zip(axes, panels):
            ys = [np.asarray(c.get("model", {}).get(key, []), dtype=np.float64) for c in curves]
            ys = [y for y in ys if y.size]
            if not ys:
                continue
            n = min(len(y) for y in ys)
            Y = np.stack([y[:n] for y in ys])
            t = h * np.arange(n)
            start = 2 if key != "orth_drift" else 0  # errors: samples 0, 1 are the given pair
            mean = Y.mean(0)
            mean[~(mean > 0)] = np.nan
            line = ax.plot(t[start:], mean[start:], styles[k % 4], color=colors[s["model"]], lw=1.2, label=s["label"])
            if len(ys) > 1:
                lo, hi = (Y.mean(0) - Y.std(0, ddof=1)), (Y.mean(0) + Y.std(0, ddof=1))
                lo = np.where(lo > 0, lo, np.nan)
                ax.fill_between(t[start:], lo[start:], hi[start:], color=line[0].get_color(), alpha=0.15, lw=0)
            drawn = True
    if not drawn:
        plt.close(fig)
        return None
    ref, h = reference if reference else (None, None)
    for ax, (key, ylabel) in zip(axes, panels):
        if ref and h is not None and key in ref:
            y = np.asarray(ref[key], dtype=np.float64)
            y[~(y > 0)] = np.nan
            start = 2 if key != "orth_drift" else 0
            ax.plot(h * np.arange(len(y))[start:], y[start:], color="0.5", lw=1, ls=":", label="true scheme")
        cv, h_cv = cv_reference if cv_reference else (None, None)
        if cv and h_cv is not None and key in cv and key != "orth_drift":  # an error reference, not a drift one
            y = np.asarray(cv[key], dtype=np.float64)
            y[~(y > 0)] = np.nan
            ax.plot(h_cv * np.arange(len(y))[2:], y[2:], color="0.3", lw=1, ls="--", label="constant velocity")
        ax.set_yscale("log")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    axes[0].set_title("rollout error (mean over test trajectories)", fontsize=10)
    axes[1].set_title("manifold drift (max over trajectories and bodies)", fontsize=10)
    fig.tight_layout()
    return fig


def draw_error_vs_training_length(rows: list[dict], keys: list[str]) -> Figure | None:
    lengths = sorted({r["train_steps"] for r in rows if r["train_steps"] is not None})
    if len(lengths) < 2:
        return None
    from ..display.plots import plt

    other = [k for k in keys if k != "dataset.train_steps"]
    colors = _colors(sorted({r["model"] for r in rows}))
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, runs in groups(rows, other).items():
        xs, ys, es = [], [], []
        for L in lengths:
            mean, std, n = mean_std(r[ERROR] for r in runs if r["train_steps"] == L)
            if mean is not None and mean > 0:
                xs.append(L)
                ys.append(mean)
                es.append(std if std is not None and n > 1 else 0.0)
        if xs:
            ax.errorbar(xs, ys, yerr=es, fmt="o-", color=colors[runs[0]["model"]], capsize=3, label=label)
    ax.set_yscale("log")
    ax.set_xticks(lengths)
    ax.set_xlabel("training trajectory length [steps]")
    ax.set_ylabel(ERROR_LABEL, fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    ax.set_title("error against training length (mean ± std over seeds)", fontsize=10)
    plain_log_ticks(ax)
    return fig


def _sphere_tracks(run: Path, warnings: list[str]) -> tuple[dict, np.ndarray | None]:
    """({entry: R e3 of body 0 along the first rollout trajectory}, truth or None) of a run; ({}, None)
    when its files are missing or unreadable, with a warning added to `warnings` for an unreadable
    rollout file (the report does not depend on them)."""
    path = run / FILE_NAME
    if not path.is_file():
        return {}, None
    try:
        rf = read_rollout(path)
    except LiedflError as e:
        warnings.append(f"{e}; its sphere panel is left empty")
        return {}, None
    tracks = {name: e.R[0, :, 0, :, 2] for name, e in rf.models.items()}
    truth = None
    try:
        from ..data.hdf5 import load_dataset

        ds_path = _read(run / "summary.json", "json").get("dataset_path") if (run / "summary.json").is_file() else None
        if ds_path and Path(ds_path).is_file():
            ds = load_dataset(ds_path)
            n = min(ds.n_steps, rf.steps) + 1
            truth = ds.R[int(rf.traj_index[0]), :n, 0, :, 2]
    except LiedflError:
        truth = None
    return tracks, truth


def draw_sphere_per_model(sweep: Path, rows: list[dict], warnings: list[str]) -> Figure:
    from ..display.plots import _on_sphere, draw_unit_sphere, plt

    models = sorted({r["model"] for r in rows})
    colors = _colors(models)
    fig = plt.figure(figsize=(3.6 * len(models), 3.9))
    for i, m in enumerate(models):
        r = next(r for r in rows if r["model"] == m)
        ax = fig.add_subplot(1, len(models), i + 1, projection="3d")
        draw_unit_sphere(ax)
        tracks, truth = _sphere_tracks(sweep / r["run"], warnings)
        if truth is not None:
            ax.plot(*_on_sphere(truth).T, color="black", lw=1.2, label="truth")
        if "true_scheme" in tracks:
            ax.plot(*_on_sphere(tracks["true_scheme"]).T, color="0.6", lw=0.8, ls=":", label="true scheme")
        if "model" in tracks:
            ax.plot(*_on_sphere(tracks["model"]).T, "--", color=colors[m], lw=1.0, label=m)
        ax.set_title(f"{m} (run {r['run']}): body axis R e3", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle("first test trajectory of each model's first run on the unit sphere", fontsize=9)
    return fig


def report_figures(sweep: Path, rows: list[dict], warnings: list[str] | None = None) -> dict[str, Figure]:
    """{"plots/<name>.png": Figure} of the figures that have something to show (drawn, not saved);
    what a reader should know (an unreadable rollout file) is added to `warnings`, not printed."""
    warnings = [] if warnings is None else warnings
    keys = varying_settings(rows)
    summary = summarize(rows, keys)
    out = {}
    for name, draw in (
        ("error_vs_speed", lambda: draw_error_vs_speed(summary)),
        ("error_vs_time", lambda: draw_error_vs_time(sweep, summary)),
        ("error_vs_training_length", lambda: draw_error_vs_training_length(rows, keys)),
        ("sphere_per_model", lambda: draw_sphere_per_model(sweep, rows, warnings)),
    ):
        fig = draw()
        if fig is not None:
            out[f"plots/{name}.png"] = fig
    return out


# ----------------------------------------------------------------------------- tables
def report_markdown(sweep: Path, rows: list[dict], failed: list[tuple[str, str]]) -> str:
    keys = varying_settings(rows)
    summary = summarize(rows, keys)
    md = f"# Report: {sweep}\n\n{len(rows)} runs" + (f", {len(failed)} failed" if failed else "") + ".\n\n"
    if rows:
        n_models = len({r["model"] for r in rows})
        md += f"{n_models} model(s), {len(summary)} model/setting combination(s).\n\n"
        constant = {
            c: rows[0].get(c)
            for c in ("dataset", "train_steps", "parameters")
            if len({str(r.get(c)) for r in rows}) == 1 and rows[0].get(c) is not None
        }
        common = {
            k: v for k, v in _overrides(rows[0]["setting"].split()).items() if k not in keys and k not in NOT_SETTINGS
        }
        if constant or common:
            md += (
                "Same in every run: "
                + ", ".join(
                    [*(f"{c} {fmt(v)}" for c, v in constant.items()), *(f"`{k}={v}`" for k, v in common.items())]
                )
                + ".\n\n"
            )
        metrics = [m for m in METRICS if any(s[m][0] is not None for s in summary)]
        md += "## Summary: one line per model and setting, mean ± std over seeds\n\n"
        srows = [
            {"model / setting": s["label"], "seeds": s["seeds"], **{HEADERS[m]: pm(s[m]) for m in metrics}}
            for s in summary
        ]
        md += markdown_table(srows, ["model / setting", "seeds", *(HEADERS[m] for m in metrics)])
        md += (
            "\nrel. rotation error: mean over the steps with ground truth of ‖R̂ − R‖_F/‖R‖_F; geodesic error: mean "
            "|log(R̂ᵀR)|; orth. drift: largest ‖RᵀR − I‖_F over the rollout; rollout [s/step/traj.]: wall time per "
            "step divided by the trajectories rolled out together; one-step / const. vel. and geodesic / const. "
            "vel.: the teacher-forced one-step and the rollout geodesic error over those of constant velocity "
            "(the last increment repeated) on the same test data (< 1: better than constant velocity; a model "
            "that does not beat it has learned nothing; '–': eval.csv written without them).\n\n"
        )
        # the runs: the settings that differ (one column per override key; model and train_steps have their
        # own) and the numbers that differ
        own = ("dataset.train_steps", "baseline", "model")
        extra = [k for k in keys if k not in own]
        runs = [{**r, **{k: _overrides(r["setting"].split()).get(k) for k in extra}} for r in rows]
        varying = [c for c in COLUMNS if c == "run" or len({str(r.get(c)) for r in rows}) > 1]
        varying = [c for c in varying if c != "setting" and any(r.get(c) not in (None, "") for r in rows)]
        varying[1:1] = extra
        md += "## Runs (the columns that differ between runs)\n\n" + markdown_table(runs, varying)
    if failed:
        md += "\n## Failed runs\n\n" + markdown_table([{"run": d, "error": e} for d, e in failed], ["run", "error"])
    return md


def print_summary_table(summary: list[dict], metrics: list[str], title: str, out=None) -> list[str]:
    """The console summary: error and both speed columns kept first when the terminal is narrow (the
    label wraps between words, the others are dropped, named in one line); returns the columns shown."""
    table_rows = [{"label": s["label"], "seeds": s["seeds"], **{m: pm_short(s[m]) for m in metrics}} for s in summary]
    return print_table(
        table_rows,
        ["label", "seeds", *metrics],
        {"label": "model / setting", "seeds": "seeds", **{m: CONSOLE_HEADERS[m] for m in metrics}},
        title=title,
        priority=CONSOLE_PRIORITY,
        where="report.md",
        out=out,
        wrap=("label",),
    )


def run_report(cfg: DictConfig) -> dict:
    from ..config.typed import typed

    command = typed(cfg, "report")  # this command's settings, typed once
    given = command.top.get("sweep")
    sweep = Path(str(given))
    if str(given) in ("", "???") or not sweep.is_dir():
        raise ConfigError(f"sweep={given}: not a directory (give a multirun directory, e.g. outputs/multirun/<date>)")
    if (sweep / ".hydra" / "config.yaml").is_file() or (sweep / "summary.json").is_file():
        # one run: a report would write report.md/csv and figures among the run's own files
        raise ConfigError(
            f"sweep={given}: a single run's folder, not a sweep; liedfl report compares the runs below a folder "
            f"(e.g. outputs/multirun/<date>, or the folder holding several runs); this run's own evaluation is "
            f"{sweep / 'eval.md'} (liedfl eval run={given} redoes it)"
        )
    from ..files.signals import set_phase
    from .status import failed_runs

    set_phase("report", "each file of the report is whole (old or new); rerun liedfl report to redo it")
    rows = collect(sweep)
    failed = [(str(d.relative_to(sweep)), err) for d, err in failed_runs(sweep)]
    if not rows and not failed:
        raise ConfigError(f"sweep={sweep}: no finished runs found (folders with .hydra/config.yaml and eval.csv)")
    rows.sort(key=lambda r: (r["dataset"], r["model"], r["train_steps"] or 0, r["run"]))
    result = EvalOutputs({"rows": rows, "failed": failed}, sweep)
    if rows:
        result.add("report.csv", rows)
    result.add("report.md", report_markdown(sweep, rows, failed))
    if command.top.get("plots") and rows:
        warnings: list[str] = []
        for name, fig in report_figures(sweep, rows, warnings).items():
            result.add(name, fig)
        for w in warnings:
            warning_line(w)
    plots = [p for p in write_outputs(result) if p.suffix == ".png"]
    if rows:
        keys = varying_settings(rows)
        summary = summarize(rows, keys)
        metrics = [m for m in METRICS if any(s[m][0] is not None for s in summary)]
        print_summary_table(summary, metrics, f"{len(rows)} runs in {sweep}: mean ± std over seeds")
    if failed:
        console.print(f"[bold red]failed runs[/] ({len(failed)}):", highlight=False)
        for d, e in failed:
            console.print(f"  {d}: {e}", highlight=False, markup=False, soft_wrap=True)
    written = f"{sweep / 'report.md'}" + (f" and {sweep / 'report.csv'}" if rows else "")
    console.print(f"report written to {written}; plots: {len(plots)}", soft_wrap=True)
    return {"rows": rows, "plots": [str(p) for p in plots], "failed": failed}
