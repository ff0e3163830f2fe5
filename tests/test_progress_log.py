"""Progress that survives a log file (issue 38): with stdout not a terminal, `liedfl train` prints
one plain line per validation pass (or once a minute) with the epoch, the loss, the validation
figure against constant velocity, the elapsed and the estimated remaining time; the same lines go
to the run's train.log. Content only, never timing."""

from __future__ import annotations

import re

from liedfl_cli.display import ui

LINE = re.compile(r"train epoch (\d+)/(\d+)  loss \S+  val \S+ \(\S+x CV.*\).*  elapsed .+  left ~.+")


def test_progress_line_has_everything():
    line = ui.progress_line(120, 1000, 1.234e-3, "val 1.20e-04 (0.31x CV, 1.20x CA)", 62.0, 510.0)
    assert line == (
        "train epoch 120/1000  loss 1.234e-03  val 1.20e-04 (0.31x CV, 1.20x CA)  elapsed 1 min 02 s  left ~8 min 30 s"
    )
    assert ui.format_duration(3725) == "1 h 02 min" and ui.format_duration(4.2) == "4 s"
    assert "loss" not in ui.progress_line(1, 2, float("nan"), "", 1.0, None)  # no NaN loss, no estimate


def test_plain_progress_prints_on_passes_and_the_last_epoch(monkeypatch):
    printed: list[str] = []
    monkeypatch.setattr(ui.console, "print", lambda text, **kw: printed.append(text))
    p = ui.PlainProgress(10, enabled=True, every=1e9, to_stdout=True)
    for epoch in range(1, 11):
        p.update(epoch, 0.5, "val 1.00e-03 (0.50x CV)" if epoch % 5 == 0 else "", validated=epoch % 5 == 0)
    assert [int(LINE.match(x).group(1)) for x in printed] == [5, 10]  # type: ignore[union-attr]
    assert printed == p.lines
    off = ui.PlainProgress(10, enabled=False, to_stdout=True)
    assert off.update(10, 0.5, validated=True) is None and printed == p.lines
    minute = ui.PlainProgress(10, enabled=True, every=0.0, to_stdout=True)  # no pass due: once per `every`
    assert minute.update(1, 0.5) is not None


def test_train_with_stdout_not_a_terminal_prints_lines_and_logs_them(tmp_path, run_main):
    (tmp_path / "run").mkdir()  # (train.log is written into an output folder that exists at the start)
    proc = run_main(
        "train", "budget=smoke", "eval.plots=false", "rollout.enabled=false", "train.epochs=3", "train.val_every=1",
        f"paths.output_dir={tmp_path / 'run'}", f"paths.data_dir={tmp_path / 'data'}", cwd=tmp_path, ok=True,
    )  # fmt: skip
    lines = [x for x in proc.stdout.splitlines() if x.startswith("train epoch")]
    assert [LINE.fullmatch(x) is not None for x in lines] == [True] * 3, proc.stdout
    assert [x.split()[2] for x in lines] == ["1/3", "2/3", "3/3"]
    log = (tmp_path / "run" / "train.log").read_text()
    assert all(x in log for x in lines), log
