"""Why a training stops before its last epoch: a signal (`graceful_stop` turns SIGINT/SIGTERM, and
submitit's warning signal in a cluster job, into a `StopRequest` that the checkpoint callback answers
with a checkpoint and `TrainingInterrupted`) or a non-finite loss (`TrainingDiverged`)."""

from __future__ import annotations

import contextlib
import signal
import threading

from ..display.ui import console
from ..errors import LiedflError


class TrainingInterrupted(LiedflError):
    """Training stopped by SIGINT/SIGTERM after saving a checkpoint."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


class TrainingDiverged(LiedflError):
    """The training loss became non-finite (or overflowed): the learning rate is too large, or the
    weights it started from are unusable. `first`: on the first step of this `fit` call."""

    def __init__(self, epoch: int, batch: int | None, value: str, first: bool, saved: int | None):
        where = f"epoch {epoch}, batch {batch}" if batch is not None else f"the end of epoch {epoch}"
        super().__init__(f"training diverged at {where}: the loss became {value}")
        self.epoch, self.batch, self.value, self.first, self.saved = epoch, batch, value, first, saved


class StopRequest:
    """Set by the signal handlers of `graceful_stop`; read after each epoch by the checkpoint callback
    (`callbacks.CheckpointCallback`), which saves a checkpoint and stops the training."""

    def __init__(self) -> None:
        self.signum: int | None = None


def _cluster_warning_signal() -> int | None:
    """The signal submitit sends a job shortly before its time limit or a preemption (SIGUSR2 unless
    SUBMITIT_PREEMPT_SIGNAL says otherwise; `hydra.launcher.signal_delay_s` before the limit on SLURM);
    None outside a submitit job."""
    import os

    if not os.environ.get("SUBMITIT_EXECUTOR"):
        return None
    return getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2"), None)


def stop_reason(signum: int) -> str:
    name = signal.Signals(signum).name
    if signum == _cluster_warning_signal():
        return f"{name} (submitit: the job's time limit is near, or it is preempted)"
    return name


@contextlib.contextmanager
def graceful_stop():
    """SIGINT/SIGTERM -> finish the epoch, checkpoint, stop; a second signal stops at once. In a
    submitit job (sweeps on SLURM, `hydra/launcher=liedfl_local`) also submitit's warning signal, so
    that a job reaching its time limit saves a checkpoint it can be resumed from. A SIGINT that the
    process inherited ignored (`nohup`, a background job of a script: asked not to be interrupted by
    Ctrl-C) stays ignored; SIGTERM is always handled (README, "Interruptions and resume")."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():  # handlers need the main thread
        yield stop
        return

    def handler(signum, frame):
        if stop.signum is not None:
            raise KeyboardInterrupt
        stop.signum = signum
        console.print("[bold yellow]stop requested:[/] finishing the epoch and saving a checkpoint (again: stop now)")

    signums: list[int] = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signums.append(signal.SIGINT)
    warning = _cluster_warning_signal()
    if warning is not None:
        signums.append(warning)
    previous = {s: signal.signal(s, handler) for s in signums}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
