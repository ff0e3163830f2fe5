"""Readable output: the evaluation table in 80/100/120-column terminals, progress displays, the run log,
figures that survive a zero loss part, and the report's helpers."""

from __future__ import annotations

import io
import math
import re

import numpy as np
import pytest
from rich.console import Console

from liedfl_cli.commands.evaluate import COLUMNS, print_eval_table
from liedfl_cli.display import ui
from liedfl_cli.files.io_utils import fmt


def _rows() -> list[dict]:
    """Two rows with every column of eval.md and long model names (the widest case)."""
    base = {
        "rel_rot_error_mean": 1.234567e-3,
        "rel_rot_error_final": 2.2e-2,
        "geodesic_error_mean": 3.3e-3,
        "position_error_mean": 0.1234,
        "max_orth_drift": 1.2e-15,
        "max_det_drift": 3.1e-16,
        "nonfinite_step": 123,
        "newton_failures": 12,
        "first_failure_step": 45,
        "mean_newton_iterations": 3.25,
        "rollout_s_per_step": 1.2e-3,
        "one_step_rot_error_mean": 4.5e-4,
        "one_step_pos_error_mean": 2.5e-3,
        "one_step_vs_cv": 0.1234,
        "rollout_vs_cv": 0.5678,
    }
    return [
        {
            "model": "model",
            "name": "glnn_lie_midpoint",
            **base,
            "train_seconds": 1234.5,
            "seconds_per_epoch": 0.5,
            "parameters": 123456,
        },  # fmt: skip
        {"model": "true_scheme", "name": "true scheme", **{k: v / 7 for k, v in base.items()}},
    ]


@pytest.mark.parametrize("width", [80, 100, 120])
def test_the_eval_table_fits_the_terminal_and_never_breaks_a_number(width):
    rows = _rows()
    cols = [c for c in COLUMNS if any(r.get(c) is not None for r in rows)]
    buf = io.StringIO()
    out = Console(file=buf, width=width, color_system=None, force_terminal=False)
    shown = print_eval_table(rows, cols, "heavy_se3: test rollout (10 x 200 steps)", out=out)
    text = buf.getvalue()
    lines = text.splitlines()
    # the table fits; the title and the note on left-out columns are single lines the terminal folds
    table = [line for line in lines if line[:1] in "┏┃┡│└"]
    assert max(len(line.rstrip()) for line in table) <= width, text
    assert sum(1 for line in lines if "more column(s)" in line) == (len(shown) < len(cols))
    assert shown[0] == "model" and len(shown) >= 5 and "rel_rot_error_mean" in shown
    table_lines = [line for line in lines if line.startswith("│")]
    assert len(table_lines) == 2
    for line, row in zip(table_lines, rows):
        cells = [c.strip() for c in line.strip("│").split("│")]
        assert cells[0] == row["name"]  # named by the model, not "model"
        assert cells[1:] == [fmt(row.get(c)) for c in shown[1:]]  # every number whole, on its line
    if len(shown) < len(cols):
        assert "in eval.md" in " ".join(text.split())  # the note may wrap
    if width == 80:  # what a narrow terminal keeps first
        assert shown[:4] == ["model", "rel_rot_error_mean", "geodesic_error_mean", "position_error_mean"]
    if width >= 100:  # a normal terminal shows the comparison with constant velocity
        assert {"one_step_vs_cv", "rollout_vs_cv"} <= set(shown)
    assert len(shown) >= {80: 5, 100: 7, 120: 9}[width]


def test_fit_columns_keeps_the_first_column_and_the_priority():
    rows = [{"a": "x" * 10, "b": 1.0, "c": 2.0, "d": 3.0}]
    # a: 10 + 3 columns, the others 1 + 3 ("1", "2", "3"), plus the left edge: room for two of them
    shown, left = ui.fit_columns(rows, ["a", "b", "c", "d"], {}, 1 + 13 + 4 + 4, priority=["a", "d", "c", "b"])
    assert shown == ["a", "c", "d"] and left == ["b"]


def test_progress_shows_no_loss_nan_and_one_line_per_phase_without_bars(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(ui, "console", ui.MirroredConsole(file=buf, width=100, color_system=None))
    # the loss column renders a finite loss only (rollouts have none)
    col = ui._LossColumn()

    class Task:
        fields = {"loss": float("nan")}

    assert str(col.render(Task())) == ""
    Task.fields = {"loss": 0.5}
    assert str(col.render(Task())) == "loss 5.000e-01"
    # ui.progress=false: one line per phase when it ends
    with ui.progress_bar(False) as bar:
        t = bar.add_task("rollout liedflnn", total=11, loss=float("nan"))
        for k in range(1, 12):
            bar.update(t, completed=k)
        u = bar.add_task("train", total=3, completed=0, loss=float("nan"))
        for _ in range(3):
            bar.update(u, advance=1, loss=0.25)
    out = buf.getvalue().splitlines()
    assert re.fullmatch(r"rollout liedflnn: 11/11 in \d+\.\d s", out[0]), out
    assert re.fullmatch(r"train: 3/3 in \d+\.\d s, loss 2\.500e-01", out[1]), out
    assert "nan" not in buf.getvalue()


def test_the_log_mirrors_what_is_printed(tmp_path, monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(ui, "console", ui.MirroredConsole(file=buf, width=90, color_system=None))
    monkeypatch.setattr(ui, "err_console", ui.MirroredConsole(file=io.StringIO(), width=90, color_system=None))
    log = tmp_path / "run" / "train.log"
    with ui.log_to(log):
        ui.console.print("[bold]model[/] liedflnn [with brackets]")
        ui.warning_line("data [projected]")
        ui.print_table([{"model": "liedflnn", "x": 1.5}], ["model", "x"], {"x": "err [rad]"}, title="t")
    ui.console.print("after the log")
    text = log.read_text()
    assert "model liedflnn" in text and "warning: data [projected]" in text and "err [rad]" in text
    assert "after the log" not in text and "\x1b[" not in text  # plain text, no colour codes
    with ui.log_to(log):  # a resumed run appends
        ui.console.print("resumed")
    assert log.read_text().startswith(text) and "resumed" in log.read_text()


# ----------------------------------------------------------------------------- figures
def test_loss_plot_with_a_part_that_reaches_zero(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from liedfl_cli.commands.outputs import write_outputs
    from liedfl_cli.display import plots
    from liedfl_cli.evaluation import EvalOutputs

    history = [
        {"epoch": e, "loss": 1.0 / e, "del_loss": 0.5 / e, "reg_loss": max(0.0, 0.3 - 0.1 * e)} for e in range(1, 11)
    ]
    fig = plots.draw_loss_curve(history)
    ax = fig.axes[0]
    lo, hi = ax.get_ylim()
    assert lo > 1e-3 and hi < 10  # not stretched down to 1e-300
    assert any("reg_loss (0 at 8 of 10 epochs)" in t.get_text() for t in ax.get_legend().get_texts())
    assert ax.get_xlabel() == "epoch" and "loss" in ax.get_ylabel()
    write_outputs(EvalOutputs({}, tmp_path, {"loss.png": fig}))  # the one writer of figures
    assert (tmp_path / "loss.png").stat().st_size > 1000


def test_every_run_figure_has_labelled_axes_with_units():
    import matplotlib

    matplotlib.use("Agg")
    from liedfl_cli.display import plots

    S = 12
    curves = {
        "model": {
            "rel_rot_error": np.linspace(0, 1e-2, S + 1),
            "geodesic_error": np.linspace(0, 1e-2, S + 1),
            "position_error": np.linspace(0, 0.1, S + 1),
            "orth_drift": np.zeros(S + 1),
            "det_drift": np.full(S + 1, 1e-16),
        },  # fmt: skip
    }
    curves["true_scheme"] = dict(curves["model"])
    names = plots.display_names(curves, "liedflnn")
    assert names == {"model": "liedflnn", "true_scheme": "true scheme"}
    from liedfl_cli.lie import so3

    R = so3.random((2, S + 1, 1)).numpy()
    p = np.zeros((2, S + 1, 1, 3))
    R_bad = R.copy()
    R_bad[0, 5:] = np.nan  # a diverged prediction leaves a gap, not an error
    pose = plots.ArrayPose(R, p)
    figures = {
        "e.png": plots.draw_error_vs_step(curves, 0.05, names),
        "d.png": plots.draw_drift_vs_step(curves, 0.05, names),
        "s.png": plots.draw_sphere(R, {"model": R_bad, "true_scheme": R}, names=names),
        "p.png": plots.draw_predicted_vs_true(pose, {"model": pose}, 0.05, names=names),
    }
    axes = [(name, ax) for name, fig in figures.items() for ax in fig.axes]
    for fig in figures.values():
        fig.canvas.draw()  # a diverged prediction's NaNs render too
        plots.plt.close(fig)
    unit = re.compile(r"\[(s|rad|m|dimensionless)\]|\(dimensionless\)")
    legends = {}
    for name, ax in axes:
        assert unit.search(ax.get_xlabel()), (name, ax.get_xlabel())
        assert unit.search(ax.get_ylabel()), (name, ax.get_ylabel())
        if ax.get_legend() is not None:
            legends.setdefault(name, set()).update(t.get_text() for t in ax.get_legend().get_texts())
    assert legends["e.png"] == legends["d.png"] == {"liedflnn", "true scheme"}
    assert legends["s.png"] == {"truth", "liedflnn", "true scheme"}
    assert legends["p.png"] == {"truth", "liedflnn"}


# ----------------------------------------------------------------------------- report
def test_report_helpers():
    from liedfl_cli.commands.report import mean_std, pareto_front, pm, summarize, varying_settings

    assert pareto_front([(1, 5), (2, 3), (3, 4), (4, 1), (0.5, 9)]) == [(0.5, 9), (1, 5), (2, 3), (4, 1)]
    mean, std, n = mean_std([1.0, 2.0, None, float("nan"), 3.0])
    assert (mean, n) == (2.0, 3) and math.isclose(std, 1.0)
    assert pm((2.0, 1.0, 3)) == "2 ± 1" and pm((2.0, 0.0, 1)) == "2" and pm((None, None, 0)) == "–"
    rows = [
        {"model": m, "setting": f"budget=smoke baseline={b} dataset.train_steps={L} seed={s}", "rel_rot_error_mean": e}
        for m, b in (("liedflnn", "none"), ("glnn_rk4", "glnn_rk4"))
        for L in (4, 8)
        for s, e in ((0, 1.0), (1, 3.0))
    ]
    keys = varying_settings(rows)
    assert keys == ["dataset.train_steps"]
    summary = summarize(rows, keys)
    assert [s["label"] for s in summary] == [
        "liedflnn train_steps=4", "liedflnn train_steps=8", "glnn_rk4 train_steps=4", "glnn_rk4 train_steps=8"
    ]  # fmt: skip
    assert all(s["seeds"] == 2 and s["rel_rot_error_mean"][:2] == (2.0, math.sqrt(2.0)) for s in summary)
