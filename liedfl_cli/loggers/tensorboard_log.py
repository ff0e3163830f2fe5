"""`logger=tensorboard`: the training loop's rows as TensorBoard scalars in `<run>/tensorboard/`.

Tags: `loss/<part>` (loss, del_loss, reg_loss, a baseline's parts), `val/<metric>` (the val_* columns,
on epochs with a validation pass), `lr`, `time/epoch_seconds` (training wall time of the epoch,
validation excluded) and `time/val_seconds`; the step is the epoch.
"""

from __future__ import annotations

import math
from pathlib import Path

_SKIP = ("epoch", "seconds", "val_seconds", "lr")


def tag(key: str) -> str | None:
    """The TensorBoard tag of a train_metrics.csv column (None: not logged as its own scalar)."""
    if key in _SKIP:
        return None
    if key.startswith("val_"):
        return f"val/{key[4:]}"
    return f"loss/{key}"


class TensorBoardLog:
    """SummaryWriter fed the per-epoch rows. purge_after: on resume, the last epoch kept (events of
    later epochs, written before the interruption, are hidden by TensorBoard's purge_step);
    last_seconds: that epoch's cumulative `seconds`."""

    def __init__(self, log_dir: Path, purge_after: int | None = None, last_seconds: float | None = None):
        from torch.utils.tensorboard import SummaryWriter

        log_dir.mkdir(parents=True, exist_ok=True)
        purge = purge_after + 1 if purge_after is not None else None
        self.writer = SummaryWriter(log_dir=str(log_dir), purge_step=purge)
        self.last_seconds = last_seconds  # the `seconds` of the epoch before the first row logged

    def log(self, row: dict) -> None:
        epoch = int(row["epoch"])
        values = {k: float(v) for k, v in row.items() if _number(v)}
        for key, value in values.items():
            name = tag(key)
            if name is not None:
                self.writer.add_scalar(name, value, epoch)
        if "lr" in values:
            self.writer.add_scalar("lr", values["lr"], epoch)
        seconds = values.get("seconds")
        if seconds is not None:
            if self.last_seconds is not None:  # `seconds` is cumulative: the epoch's share is the difference
                self.writer.add_scalar("time/epoch_seconds", seconds - self.last_seconds, epoch)
            elif epoch == 1:
                self.writer.add_scalar("time/epoch_seconds", seconds, epoch)
            self.last_seconds = seconds
        if "val_seconds" in values:
            self.writer.add_scalar("time/val_seconds", values["val_seconds"], epoch)

    def close(self) -> None:
        self.writer.close()


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
