"""SIGTERM in every phase of a command, and the phase a command is in.

SLURM sends SIGTERM on `scancel` and at a job's time limit. Python's default would end the process at
once, silently, leaving whatever the interrupted phase had made (an empty run folder, an empty
`rollouts/<name>/`). While a CLI job runs (`terminate_as_exception`), SIGTERM raises `Terminated`
instead, a KeyboardInterrupt: it goes through the same clean-up as Ctrl-C (folders a phase created
removed, `status.json` written, locks released) and ends with one line and exit code 143. The training
loop installs its own handler while it trains (finish the epoch, checkpoint; `train.graceful_stop`).
A SIGINT the process inherited ignored (`nohup`, a background job of a script) stays ignored.

`set_phase` records what the command is doing (data generation, training, rollout, evaluation,
report) for the error line and `status.json`.
"""

from __future__ import annotations

import contextlib
import signal
import threading

_phase: dict[str, str | None] = {"name": None, "hint": None}


class Terminated(KeyboardInterrupt):
    """SIGTERM (or another terminating signal) received while a CLI job runs."""

    def __init__(self, signum: int):
        super().__init__()
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum)


def set_phase(name: str | None, hint: str | None = None) -> None:
    """The command is now in phase `name` ("data generation", "training", "rollout", "evaluation",
    "report"); `hint`: what the user can do if it is interrupted there (e.g. how to resume)."""
    _phase.update(name=name, hint=hint)


def phase() -> str | None:
    return _phase["name"]


def phase_hint() -> str | None:
    return _phase["hint"]


def interruption_message(e: BaseException) -> str:
    """The one line of an interruption: `SIGTERM: interrupted during rollout (<hint>)`, or for Ctrl-C
    `interrupted` with the exception's own text (e.g. how to resume)."""
    detail = " ".join(str(a) for a in e.args if str(a).strip())
    if isinstance(e, Terminated):
        text = f"{signal.Signals(e.signum).name}: interrupted"
        if phase():
            text += f" during {phase()}"
        if phase_hint():
            text += f"; {phase_hint()}"
        return text
    return "interrupted: " + detail if detail else "interrupted"


@contextlib.contextmanager
def terminate_as_exception():
    """While the block runs, SIGTERM raises `Terminated` (in the main thread; elsewhere nothing
    changes). A second SIGTERM while the first unwinds is ignored, so that the clean-up completes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum, frame):
        if fired:  # already unwinding: let the clean-up finish
            return
        fired.append(signum)
        raise Terminated(signum)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main interpreter
        yield
        return
    set_phase(None)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        set_phase(None)


__all__ = ["Terminated", "set_phase", "phase", "phase_hint", "interruption_message", "terminate_as_exception"]
