"""`liedfl report` on a 16-point sweep: the console table keeps the error and both speed columns on
narrow terminals, paths print unbroken, and the error-vs-speed figure keeps every label inside its
axes with log-axis error bars that stay positive."""

from __future__ import annotations

import io
import math

import pytest
from omegaconf import OmegaConf
from report_sweep import fake_sweep
from rich.console import Console

from liedfl_cli.commands import report
from liedfl_cli.display import ui
from liedfl_cli.display.speed_figure import log_bar

SPEED = ("rollout s/step/traj", "train [s]")


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    # a long path: a table that broke it would show it in pieces
    root = tmp_path_factory.mktemp("report") / ("a_rather_long_folder_name_" * 3) / "multirun"
    root.mkdir(parents=True)
    return fake_sweep(root, points=16, seeds=3)


def _report(sweep, monkeypatch, width: int, plots_on: bool = False) -> str:
    buf = io.StringIO()
    out = Console(file=buf, width=width, color_system=None)
    monkeypatch.setattr(report, "console", out)
    monkeypatch.setattr(ui, "console", out)
    report.run_report(OmegaConf.create({"sweep": str(sweep), "plots": plots_on}))
    return buf.getvalue()


@pytest.mark.parametrize("width", [80, 120, 160])
def test_table_keeps_the_speed_columns_and_prints_paths_whole(sweep, monkeypatch, width):
    text = _report(sweep, monkeypatch, width)
    lines = text.splitlines()
    header = next(line for line in lines if "model / setting" in line)
    for name in ("rel. rot. error", *SPEED):
        assert name in header, (width, header)
    table = [line for line in lines if line[:1] in "┏┃┡│└"]
    assert max(len(line) for line in table) <= width
    # every path whole on one line: the sweep in the title, report.md in the last line
    assert any(f"in {sweep}:" in line for line in lines), text
    assert any(str(sweep / "report.md") in line for line in lines), text
    dropped = [line for line in lines if "more column(s)" in line]
    if width == 80:  # something had to go, and one line says what
        assert len(dropped) == 1 and "report.md" in dropped[0] and "seeds" in dropped[0]
    if width == 160:
        assert not dropped and "seeds" in header


def test_log_bar_never_reaches_zero():
    assert log_bar(1.0, 0.5, [0.6, 1.4]) == (0.5, 1.5, False)
    lo, hi, clipped = log_bar(1.0, 1.6, [0.05, 0.1, 2.85])
    assert clipped and lo == pytest.approx(0.05) and hi == pytest.approx(2.6)
    assert log_bar(2.0, None, [2.0]) == (2.0, 2.0, False)


def test_figure_labels_inside_the_axes_and_apart(sweep):
    keys = report.varying_settings(report.collect(sweep))
    summary = report.summarize(report.collect(sweep), keys)
    assert len(summary) == 16
    fig = report.draw_error_vs_speed(summary)
    assert fig is not None
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    panels = [ax for ax in fig.axes if ax.get_xscale() == "log"]
    assert len(panels) == 2
    for ax in panels:
        frame = ax.get_window_extent(renderer)
        labels = [t for t in ax.texts if t.get_text().isdigit()]  # numbered: more than FULL_LABELS points
        assert sorted(int(t.get_text()) for t in labels) == list(range(1, 17))
        boxes = [t.get_window_extent(renderer) for t in labels]
        for t, b in zip(labels, boxes):
            assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1, t.get_text()
        overlaps = sum(
            1 for i, a in enumerate(boxes) for b in boxes[i + 1 :] if a.overlaps(b) and a.intersection(a, b).width > 1
        )
        assert overlaps == 0
        # error bars: every drawn segment stays at positive values (a log axis has no 0)
        for coll in ax.collections:
            for seg in getattr(coll, "get_segments", lambda: [])():
                assert (seg > 0).all() and all(math.isfinite(v) for v in seg.ravel())
    key = [t.get_text() for t in fig.texts]
    assert sum(1 for k in key if k.split()[0].isdigit()) == 16  # the key under the panels
    assert "smallest seed" in fig._suptitle.get_text()  # the fixture has bars with std > mean


def _cv_lines(fig):
    panels = [ax for ax in fig.axes if ax.get_xscale() == "log"]
    return [[ln for ln in ax.get_lines() if ln.get_label() == "constant velocity"] for ax in panels]


def test_constant_velocity_is_the_error_figures_reference_when_the_runs_share_test_data(tmp_path):
    shared = fake_sweep(tmp_path / "a", points=4, seeds=2, cv=0.7)
    rows = report.collect(shared)
    assert all(r[report.CV_ERROR] == 0.7 for r in rows)
    fig = report.draw_error_vs_speed(report.summarize(rows, report.varying_settings(rows)))
    lines = _cv_lines(fig)
    assert len(lines) == 2 and all(len(ls) == 1 for ls in lines)
    for ax, (line,) in zip([ax for ax in fig.axes if ax.get_xscale() == "log"], lines):
        assert list(line.get_ydata()) == [0.7, 0.7]
        lo, hi = ax.get_ylim()
        assert lo < 0.7 < hi
    assert "constant velocity" in [t.get_text() for t in fig.legends[0].get_texts()]
    # runs evaluated on different test data: no single reference, no line
    mixed = fake_sweep(tmp_path / "b", points=4, seeds=2, cv=lambda job: 0.5 + 0.1 * job)
    rows = report.collect(mixed)
    fig = report.draw_error_vs_speed(report.summarize(rows, report.varying_settings(rows)))
    assert _cv_lines(fig) == [[], []]
    # without constant-velocity rows (older runs): none either
    rows = report.collect(fake_sweep(tmp_path / "c", points=4, seeds=2))
    assert all(r[report.CV_ERROR] is None for r in rows)
    assert report.shared_reference(report.summarize(rows, report.varying_settings(rows)), report.CV_ERROR) is None
