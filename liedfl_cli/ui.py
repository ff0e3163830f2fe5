"""Console output: one rich console, progress bars that degrade to nothing when disabled."""
from __future__ import annotations

import contextlib
import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console()
err_console = Console(stderr=True)


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
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.3e}"), TimeElapsedColumn(), TimeRemainingColumn(),
        console=console, transient=not sys.stdout.isatty(),
    ) as bar:
        yield bar


def fail(message: str, code: int = 2):
    """Print a one-line error and exit non-zero."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise SystemExit(code)
