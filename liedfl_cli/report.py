"""`liedfl report sweep=<multirun dir>`: one table and the paper-style figures over a sweep.

Reads every run directory below `sweep` (any folder holding `.hydra/config.yaml` and `eval.csv`),
and writes `report.csv`, `report.md` and `plots/*.png` into the sweep directory:
error vs training length, drift vs step, predicted trajectories on the sphere per model, and
an error-against-speed scatter (one point per run).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import yaml
from omegaconf import DictConfig

from .errors import ConfigError, DatasetError, LiedflError
from .evaluate import DRIFT_COLUMNS, ERROR_COLUMNS
from .io_utils import markdown_table, write_csv, write_text
from .rollout_file import FILE_NAME, read_rollout
from .ui import console

COLUMNS = [
    "run",
    "model",
    "dataset",
    "train_steps",
    "setting",
    "parameters",
    "train_seconds",
    "seconds_per_epoch",
    "rollout_s_per_step",
    *ERROR_COLUMNS,
    *DRIFT_COLUMNS,
    "newton_failures",
]


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
    from .runs import read_json_object

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
        row = {
            "run": str(run.relative_to(sweep)),
            "model": model_name(cfg),
            "dataset": cfg["dataset"]["name"],
            "train_steps": int(cfg["dataset"]["train_steps"]),
            "setting": " ".join(overrides),
        }
        for k in COLUMNS[5:]:
            row[k] = _number(run / "eval.csv", k, e.get(k))
        summary = run / "summary.json"
        if summary.is_file():
            t = _read(summary, "json").get("timings", {})
            t = t if isinstance(t, dict) else {}
            row.update({k: t.get(k) for k in ("parameters", "train_seconds", "seconds_per_epoch")})
        rows.append(row)
    return rows


def _curves(sweep: Path, row: dict) -> dict:
    path = sweep / row["run"] / "eval_curves.json"
    return json.loads(path.read_text()).get("model", {}) if path.is_file() else {}


def _first_axes(path: Path) -> dict:
    """{name: R e3 of body 0 along the first trajectory (S+1, 3)} from a run's rollout file; {} (with a
    warning) when it is missing or unreadable: the report's table does not depend on it."""
    if not path.is_file():
        return {}
    try:
        rf = read_rollout(path)
    except LiedflError as e:
        console.print(f"[yellow]warning:[/] {e}; its sphere panel is left empty")
        return {}
    return {name: e.R[0, :, 0, :, 2] for name, e in rf.models.items()}


def make_plots(sweep: Path, rows: list[dict]) -> list[Path]:
    from .plots import draw_unit_sphere, plt, save_figure

    out = []
    pdir = sweep / "plots"
    models = sorted({r["model"] for r in rows})
    colors = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(models)}

    # error vs training length (mean over runs of the same model and length)
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for m in models:
        pts: dict = {}
        for r in rows:
            if r["model"] == m and r["rel_rot_error_mean"] is not None:
                pts.setdefault(r["train_steps"], []).append(r["rel_rot_error_mean"])
        xs = sorted(pts)
        ax.semilogy(xs, [np.mean(pts[x]) for x in xs], "o-", label=m, color=colors[m])
    ax.set_xlabel("training trajectory length (steps)")
    ax.set_ylabel("mean relative rotation error")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    save_figure(fig, pdir / "error_vs_training_length.png")
    out.append(pdir / "error_vs_training_length.png")

    # drift vs step, first run of each model
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for m in models:
        r = next(r for r in rows if r["model"] == m)
        c = _curves(sweep, r)
        for ax, key in zip(axes, ("orth_drift", "det_drift")):
            if key in c:
                y = np.asarray(c[key])
                ax.semilogy(np.arange(len(y)), np.maximum(y, 1e-18), label=m, color=colors[m])
    axes[0].set_title("||R^T R - I||_F")
    axes[1].set_title("|det R - 1|")
    for ax in axes:
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    save_figure(fig, pdir / "drift_vs_step.png")
    out.append(pdir / "drift_vs_step.png")

    # predicted trajectories on the sphere, one panel per model (first test trajectory)
    fig = plt.figure(figsize=(3.2 * len(models), 3.4))
    for i, m in enumerate(models):
        r = next(r for r in rows if r["model"] == m)
        ax = fig.add_subplot(1, len(models), i + 1, projection="3d")
        draw_unit_sphere(ax)
        axes_e3 = _first_axes(sweep / r["run"] / FILE_NAME)
        if "true_scheme" in axes_e3:
            ax.plot(*axes_e3["true_scheme"].T, color="0.6", lw=0.8, label="true scheme")
        if "model" in axes_e3:
            ax.plot(*axes_e3["model"].T, color=colors[m], lw=1.0, label=m)
        ax.set_title(m, fontsize=9)
    save_figure(fig, pdir / "sphere_per_model.png")
    out.append(pdir / "sphere_per_model.png")

    # error against speed
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.6))
    for ax, key, label in zip(
        axes, ("train_seconds", "rollout_s_per_step"), ("training wall time (s)", "rollout time per step (s)")
    ):
        for m in models:
            speed_error = [
                (r[key], r["rel_rot_error_mean"])
                for r in rows
                if r["model"] == m and r.get(key) and r["rel_rot_error_mean"]
            ]
            if speed_error:
                ax.loglog(*zip(*speed_error), "o", label=m, color=colors[m])
        ax.set_xlabel(label)
        ax.set_ylabel("mean relative rotation error")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    save_figure(fig, pdir / "error_vs_speed.png")
    out.append(pdir / "error_vs_speed.png")
    return out


def run_report(cfg: DictConfig) -> dict:
    sweep = Path(str(cfg.sweep))
    if str(cfg.sweep) in ("", "???") or not sweep.is_dir():
        raise ConfigError(
            f"sweep={cfg.sweep}: not a directory (give a multirun directory, e.g. outputs/multirun/<date>)"
        )
    from .status import failed_runs

    rows = collect(sweep)
    failed = [(str(d.relative_to(sweep)), err) for d, err in failed_runs(sweep)]
    if not rows and not failed:
        raise ConfigError(f"sweep={sweep}: no finished runs found (folders with .hydra/config.yaml and eval.csv)")
    rows.sort(key=lambda r: (r["dataset"], r["model"], r["train_steps"], r["run"]))
    if rows:
        write_csv(sweep / "report.csv", rows)
    cols = [c for c in COLUMNS if any(r.get(c) not in (None, "") for r in rows)]
    md = f"# Report: {sweep}\n\n{len(rows)} runs" + (f", {len(failed)} failed" if failed else "") + ".\n\n"
    md += markdown_table(rows, cols) if rows else ""
    if failed:
        md += "\n## Failed runs\n\n" + markdown_table([{"run": d, "error": e} for d, e in failed], ["run", "error"])
    write_text(sweep / "report.md", md)
    plots = make_plots(sweep, rows) if cfg.plots and rows else []
    from rich.table import Table

    from .io_utils import fmt

    table = Table(title=f"{len(rows)} runs in {sweep}")
    short = [
        "model",
        "dataset",
        "train_steps",
        "rel_rot_error_mean",
        "max_orth_drift",
        "newton_failures",
        "train_seconds",
        "rollout_s_per_step",
    ]
    for c in short:
        table.add_column(c.replace("_", " "))
    for r in rows:
        table.add_row(*[fmt(r.get(c)) for c in short])
    if rows:
        console.print(table)
    if failed:
        console.print(f"[bold red]failed runs[/] ({len(failed)}):", highlight=False)
        for d, e in failed:
            console.print(f"  {d}: {e}", highlight=False, markup=False, soft_wrap=True)
    written = f"{sweep / 'report.md'}" + (f" and {sweep / 'report.csv'}" if rows else "")
    console.print(f"report written to {written}; plots: {len(plots)}")
    return {"rows": rows, "plots": [str(p) for p in plots], "failed": failed}
