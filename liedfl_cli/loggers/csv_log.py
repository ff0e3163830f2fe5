"""train_metrics.csv: the run's own record of every epoch (always written, whatever `logger` says)."""

from __future__ import annotations

import csv
from pathlib import Path


class MetricsLog:
    """train_metrics.csv, one row per epoch appended as training goes (the header comes with the
    first row). On resume the rows past the checkpoint's epoch are dropped first."""

    def __init__(self, path: Path, history: list[dict]):
        self.path = path
        self.keys: list[str] | None = None
        path.parent.mkdir(parents=True, exist_ok=True)
        if history:
            self._rewrite(history)
        elif path.exists():
            path.unlink()

    def _rewrite(self, rows: list[dict]) -> None:
        from ..files.io_utils import write_csv

        write_csv(self.path, rows)
        self.keys = list(rows[0])

    def append(self, row: dict) -> None:
        if self.keys is None:
            self._rewrite([row])
            return
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.keys, extrasaction="ignore").writerow(row)

    def log(self, row: dict) -> None:  # the logger interface; `append` is the name fine-tuning and tests use
        self.append(row)

    def close(self) -> None:
        """Nothing to flush: every row is written when it is logged."""
