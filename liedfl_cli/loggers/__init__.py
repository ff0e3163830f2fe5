"""Per-epoch metric loggers of `liedfl train` (the `logger` config group).

A logger takes the training loop's rows (`log(row)`: a dict of the epoch's metrics, `epoch` included)
and is closed once training ends. train_metrics.csv is always written (`csv_log.MetricsLog`);
`logger=tensorboard` adds TensorBoard event files beside it (`tensorboard_log.TensorBoardLog`).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Protocol

from ..errors import ConfigError
from .csv_log import MetricsLog

NAMES = ("csv", "tensorboard")
TENSORBOARD_DIR = "tensorboard"
INSTALL_HINT = "pip install liedfl[tensorboard]"


class Logger(Protocol):
    def log(self, row: dict) -> None: ...

    def close(self) -> None: ...


class Loggers:
    """Several loggers fed the same rows (the CSV first: it is the run's record)."""

    def __init__(self, loggers: list[Logger]):
        self.loggers = loggers

    def log(self, row: dict) -> None:
        for lg in self.loggers:
            lg.log(row)

    def close(self) -> None:
        for lg in self.loggers:
            lg.close()


def require_tensorboard() -> None:
    """ConfigError (one line) when the `tensorboard` package is missing; checked before a run starts."""
    if importlib.util.find_spec("tensorboard") is None:
        raise ConfigError(f"logger=tensorboard needs the tensorboard package: {INSTALL_HINT}")


def make_loggers(name: str, out: Path, history: list[dict]) -> Loggers:
    """The loggers of `logger=<name>` writing into run directory `out`; `history`: the rows kept on
    resume (the CSV is rewritten with them; TensorBoard drops its events past the last of them)."""
    if name not in NAMES:
        raise ConfigError(f"logger={name!r}: choose one of {', '.join(NAMES)}")
    loggers: list[Logger] = [MetricsLog(out / "train_metrics.csv", history)]
    if name == "tensorboard":
        require_tensorboard()
        from .tensorboard_log import TensorBoardLog

        last = history[-1] if history else None
        loggers.append(
            TensorBoardLog(
                out / TENSORBOARD_DIR,
                purge_after=int(last["epoch"]) if last else None,
                last_seconds=float(last["seconds"]) if last and last.get("seconds") is not None else None,
            )
        )
    return Loggers(loggers)
