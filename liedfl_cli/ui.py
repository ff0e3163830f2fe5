"""Console output: one rich console, progress bars that degrade to nothing when disabled."""

from __future__ import annotations

import contextlib
import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

# Logs and CI are not terminals: give tables room instead of rich's 80-column default.
console = Console(width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 160)


class _NullBar:
    def add_task(self, *a, **k):
        return 0

    def update(self, *a, **k):
        pass


@contextlib.contextmanager
def progress_bar(enabled: bool = True):
    if not enabled:
        yield _NullBar()
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.3e}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=not sys.stdout.isatty(),
    ) as bar:
        yield bar


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
