"""Console output: one rich console, progress bars that degrade to one line per phase when disabled,
tables that fit the terminal, and the run log (`train.log`) that mirrors everything printed."""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text


class _Log:
    """The log file every console line is also written to (None: no log)."""

    console: Console | None = None


class MirroredConsole(Console):
    """A rich Console whose `print` also goes to the run log (`log_to`) as plain text."""

    def print(self, *objects, **kwargs) -> None:
        if not objects and not kwargs and not self.is_terminal:
            return  # rich's Progress.stop() ends with an empty print off a terminal: no stray blank line
        super().print(*objects, **kwargs)
        log = _Log.console
        if log is not None and log is not self:
            log.width = self.width  # the same layout as on the terminal (tables are fitted to it)
            log.print(*objects, **kwargs)


# Logs and CI are not terminals: give tables room instead of rich's 80-column default.
console = MirroredConsole(width=None if sys.stdout.isatty() or "COLUMNS" in os.environ else 160)
err_console = MirroredConsole(stderr=True, width=None if sys.stderr.isatty() or "COLUMNS" in os.environ else 160)


@contextlib.contextmanager
def log_to(path, mode: str = "a"):
    """Mirror everything `console` and `err_console` print (messages, tables, warnings, the error
    line) to `path` as plain text while the block runs. Progress bars are not logged; with
    `ui.progress=false` each phase leaves one line (see `progress_bar`), which is."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, mode, encoding="utf-8") as f:
        previous = _Log.console
        _Log.console = Console(
            file=f, width=console.width, color_system=None, force_terminal=False, highlight=False, emoji=False
        )
        try:
            yield path
        finally:
            _Log.console = previous


class _LossColumn(ProgressColumn):
    """`loss 1.234e-02` while a task reports a finite loss (training), followed by the last validation
    pass (`val 1.2e-04 (0.31x CV), roll 3.4e-03`) when the task reports one; nothing otherwise (rollouts)."""

    def render(self, task) -> Text:
        loss = task.fields.get("loss")
        text = f"loss {loss:.3e}" if isinstance(loss, (int, float)) and math.isfinite(loss) else ""
        val = task.fields.get("val")
        if text and val:
            text += f"  {val}"
        return Text(text)


class _PhaseLines:
    """The progress display with `ui.progress=false`: nothing while a phase runs, then one line
    `<description>: <done>/<total> in <seconds> s` (with the last loss, if any) when it ends."""

    def __init__(self) -> None:
        self.tasks: dict[int, dict] = {}

    def add_task(self, description: str = "", total=None, completed=0, **fields):
        i = len(self.tasks)
        self.tasks[i] = {"description": description, "total": total, "completed": completed, "fields": fields,
                         "start": time.perf_counter()}  # fmt: skip
        return i

    def update(self, task=None, *, completed=None, advance=None, **fields):
        t = self.tasks.get(task)
        if t is None:
            return
        if completed is not None:
            t["completed"] = completed
        if advance is not None:
            t["completed"] += advance
        t["fields"].update(fields)

    def finish(self) -> None:
        for t in self.tasks.values():
            line = f"{t['description']}: {t['completed']}"
            if t["total"] is not None:
                line += f"/{t['total']}"
            line += f" in {time.perf_counter() - t['start']:.1f} s"
            loss = t["fields"].get("loss")
            if isinstance(loss, (int, float)) and math.isfinite(loss):
                line += f", loss {loss:.3e}"
                if t["fields"].get("val"):
                    line += f", {t['fields']['val']}"
            console.print(line, highlight=False, markup=False, soft_wrap=True)


def format_duration(seconds: float) -> str:
    """`42 s`, `3 min 05 s`, `1 h 02 min`: a duration for a progress line."""
    s = max(0.0, float(seconds))
    if not math.isfinite(s):
        return "?"
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


def progress_line(epoch: int, total: int, loss: float | None, val: str, elapsed: float, left: float | None) -> str:
    """One plain progress line of a training (see `PlainProgress`):
    `train epoch 120/1000  loss 1.234e-03  val 1.2e-04 (0.31x CV, 1.20x CA)  elapsed 1 min 02 s  left ~8 min 30 s`."""
    parts = [f"train epoch {epoch}/{total}"]
    if isinstance(loss, (int, float)) and math.isfinite(loss):
        parts.append(f"loss {loss:.3e}")
    if val:
        parts.append(val)
    parts.append(f"elapsed {format_duration(elapsed)}")
    if left is not None:
        parts.append(f"left ~{format_duration(left)}")
    return "  ".join(parts)


class PlainProgress:
    """Progress that survives a log file: where the rich bar is invisible (stdout is not a terminal)
    a training prints one plain line per validation pass, or once a minute when passes are rarer
    (`every` seconds), on stdout and in the run log (`train.log`); on a terminal the bar shows the
    progress and the same lines go to the run log only. With `ui.progress=false` the training prints
    its own epoch lines: this prints nothing (`enabled=False`)."""

    def __init__(self, total: int, start_epoch: int = 0, enabled: bool = True, every: float = 60.0,
                 to_stdout: bool | None = None) -> None:  # fmt: skip
        self.total, self.start_epoch, self.enabled, self.every = int(total), int(start_epoch), enabled, float(every)
        self.to_stdout = (not sys.stdout.isatty()) if to_stdout is None else to_stdout
        self.t0 = time.perf_counter()
        self.last = self.t0
        self.lines: list[str] = []

    def update(self, epoch: int, loss: float | None, val: str = "", validated: bool = False) -> str | None:
        """After `epoch`: the line printed (a validation pass, a minute since the last line, or the
        last epoch), or None."""
        if not self.enabled:
            return None
        now = time.perf_counter()
        if not (validated or now - self.last >= self.every or epoch >= self.total):
            return None
        self.last = now
        elapsed = now - self.t0
        done = epoch - self.start_epoch
        left = elapsed / done * (self.total - epoch) if done > 0 else None
        line = progress_line(epoch, self.total, loss, val, elapsed, left)
        self.lines.append(line)
        if self.to_stdout:
            console.print(line, highlight=False, markup=False, soft_wrap=True)  # mirrored to the log
        elif _Log.console is not None:
            _Log.console.print(line, highlight=False, markup=False, soft_wrap=True)
        return line


@contextlib.contextmanager
def progress_bar(enabled: bool = True):
    """A rich progress display (`bar.add_task(description, total=..., loss=...)`, `bar.update(...)`);
    when disabled, one line per task once the block has finished without an error."""
    if not enabled:
        lines = _PhaseLines()
        yield lines
        lines.finish()
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        _LossColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=not sys.stdout.isatty(),
    ) as bar:
        yield bar


# ----------------------------------------------------------------------------- tables
def _cell_width(text: str) -> int:
    from rich.cells import cell_len

    return max((cell_len(part) for part in str(text).splitlines()), default=0)


def _cell_text(value, fmt) -> str:
    """A table cell: strings as they are, anything else through io_utils.fmt."""
    return value if isinstance(value, str) else fmt(value)


def fit_columns(
    rows: list[dict],
    columns: list[str],
    headers: dict[str, str],
    width: int,
    priority: list[str] | None = None,
    wrap: tuple[str, ...] = (),
) -> tuple[list[str], list[str]]:
    """(shown, left out): the columns of a table that fit in `width` terminal columns without
    breaking a cell, taken in `priority` order (default: `columns`), shown in `columns` order.
    The first column is always shown. A rich table with edges takes 1 + sum(width + 3) columns.
    Columns in `wrap` may wrap at spaces: they need only their longest word."""
    from ..files.io_utils import fmt

    def need(c: str) -> int:
        texts = [headers.get(c, c), *(_cell_text(r.get(c), fmt) for r in rows)]
        if c in wrap:
            return max(_cell_width(word) for t in texts for word in (str(t).split() or [""])) + 3
        return max(_cell_width(t) for t in texts) + 3

    order = [c for c in (priority or columns) if c in columns]
    order += [c for c in columns if c not in order]
    first = columns[0]
    shown, used = {first}, 1 + need(first)
    for c in order:
        if c in shown:
            continue
        w = need(c)
        if used + w <= width:
            shown.add(c)
            used += w
    return [c for c in columns if c in shown], [c for c in columns if c not in shown]


def print_table(
    rows: list[dict],
    columns: list[str],
    headers: dict[str, str],
    title: str | None = None,
    priority: list[str] | None = None,
    where: str | None = None,
    out: Console | None = None,
    wrap: tuple[str, ...] = (),
) -> list[str]:
    """Print `rows` as a table that fits the console's width: columns in `priority` order as long as
    they fit, numbers never broken (`wrap`: text columns that may wrap between words); a line names
    the columns left out (all are in `where`). The title and that line are printed unbroken (a path
    in them stays copyable; the terminal folds a long line). Returns the columns shown."""
    from rich.table import Table
    from rich.text import Text

    from ..files.io_utils import fmt

    out = out or console
    shown, left = fit_columns(rows, columns, headers, out.width, priority, wrap)
    if title:
        out.print(title, highlight=False, markup=False, soft_wrap=True)
    table = Table()
    for c in shown:
        table.add_column(
            Text(headers.get(c, c)),
            no_wrap=c not in wrap,
            overflow="fold" if c in wrap else "ellipsis",
            justify="left" if c == columns[0] else "right",
        )
    for r in rows:
        table.add_row(*[Text(_cell_text(r.get(c), fmt)) for c in shown])
    out.print(table)
    if left:
        note = f"{len(left)} more column(s) ({', '.join(headers.get(c, c) for c in left)})"
        note += (f" in {where}" if where else "") + "; a wider terminal shows more"
        out.print(note, style="dim", highlight=False, markup=False, soft_wrap=True)
    return shown


# ----------------------------------------------------------------------------- one-line messages
def error_line(message: str) -> None:
    """Print `error: <message>` on one stderr line.

    The message is printed literally (square brackets in paths or lists are not rich markup) and
    on one line (line breaks of wrapped exception texts are joined)."""
    from rich.markup import escape

    one_line = " ".join(part.strip() for part in str(message).splitlines() if part.strip())
    err_console.print(f"[bold red]error:[/] {escape(one_line)}", highlight=False, soft_wrap=True)


def warning_line(message: str) -> None:
    """Print `warning: <message>` on one stderr line."""
    from rich.markup import escape

    one_line = " ".join(part.strip() for part in str(message).splitlines() if part.strip())
    err_console.print(f"[bold yellow]warning:[/] {escape(one_line)}", highlight=False, soft_wrap=True)


def fail(message: str, code: int = 2):
    """Print a one-line error (see `error_line`) and exit non-zero."""
    error_line(message)
    raise SystemExit(code)
