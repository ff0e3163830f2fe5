"""Errors that guide (issue 38): a misspelt command, a file given as `dataset=`, a CSV given to
`dataset=file`, a value of the wrong type; each one line in our own words."""

from __future__ import annotations

import pytest


def _one_error_line(proc) -> str:
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("error: ") and lines[0].strip(), proc.stderr
    return lines[0]


def test_a_misspelt_command_gets_a_suggestion(tmp_path, run_main):
    assert _one_error_line(run_main("trian", cwd=tmp_path)) == "error: unknown command 'trian' (did you mean train?)"
    assert "did you mean" not in _one_error_line(run_main("zzzz", cwd=tmp_path))


@pytest.mark.parametrize(
    ("arg", "hint"),
    [
        ("dataset=chain.h5", "for this file: dataset=file dataset.path=chain.h5"),
        ("dataset=log.csv", "for this file: dataset=import dataset.path=log.csv dataset.rotation=wxyz"),
    ],
)
def test_a_file_as_the_dataset_choice(tmp_path, run_main, arg, hint):
    line = _one_error_line(run_main("train", arg, cwd=tmp_path))
    assert (
        line.startswith(f"error: {arg}: dataset= takes a scene name, not a file")
        and line.endswith(hint)
        or hint in line
    )


def test_a_csv_given_to_dataset_file_points_to_import(tmp_path, run_main):
    (tmp_path / "log.csv").write_text("t,q0,q1,q2,q3\n0,1,0,0,0\n")
    proc = run_main("train", "dataset=file", "dataset.path=log.csv", "ui.progress=false", cwd=tmp_path)
    line = _one_error_line(proc)
    assert proc.stderr.splitlines() == [line]  # one line, no stray blank line before it
    assert "log.csv: a recording, not an HDF5 dataset" in line and "dataset=import dataset.path=log.csv" in line


@pytest.mark.parametrize(
    ("arg", "want"),
    [
        ("train.optimizer.lr=abc", "error: train.optimizer.lr=abc: must be a number (e.g. 1e-3)"),
        ("train.epochs=x", "error: train.epochs=x: must be an integer"),
        ("train.full_batch=maybe", "error: train.full_batch=maybe: must be true or false"),
    ],
)
def test_a_value_of_the_wrong_type_in_our_words(tmp_path, run_main, arg, want):
    assert _one_error_line(run_main("train", arg, cwd=tmp_path)).replace("'", "") == want  # (quoted or not)


def test_report_of_a_single_run_folder_is_refused(tmp_path, run_main):
    from report_sweep import fake_sweep

    sweep = fake_sweep(tmp_path / "sweep", points=2, seeds=1)
    run = next(p.parent.parent for p in sweep.rglob(".hydra/config.yaml"))
    before = sorted(p.name for p in run.iterdir())
    line = _one_error_line(run_main("report", f"sweep={run}", "plots=false", cwd=tmp_path))
    assert f"sweep={run}: a single run's folder, not a sweep" in line and "eval.md" in line
    assert sorted(p.name for p in run.iterdir()) == before  # nothing written into the run
    run_main("report", f"sweep={sweep}", "plots=false", cwd=tmp_path, ok=True)  # the sweep itself: as before


def test_no_pareto_front_for_one_point(tmp_path):
    from report_sweep import fake_sweep

    from liedfl_cli.commands import report
    from liedfl_cli.display.plots import plt

    def labels(points: int) -> list[str]:
        rows = report.collect(fake_sweep(tmp_path / str(points), points=points, seeds=1))
        fig = report.draw_error_vs_speed(report.summarize(rows, report.varying_settings(rows)))
        assert fig is not None
        lines = [ln.get_label() for ax in fig.axes for ln in ax.get_lines()]
        lines += [t.get_text() for lg in fig.legends for t in lg.get_texts()]
        plt.close(fig)
        return lines

    assert "Pareto front" not in labels(1)
    assert "Pareto front" in labels(3)
