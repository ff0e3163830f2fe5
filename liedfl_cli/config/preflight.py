"""Checks before a job runs (no data, nothing written) and the classification of the errors the
CLI reports as one line. Used by the CLI and by the Hydra callback (`status.LiedflCallback`)."""

from __future__ import annotations

import os
import re

# commands whose Hydra run dir is `${<key>}`, an existing directory named on the command line
DIR_ARGS = {
    "rollout": ("run", "run dir", "run directory", "a directory written by `liedfl train`"),
    "eval": ("run", "run dir", "run directory", "a directory written by `liedfl train`"),
    "resume": ("resume", "run dir", "run directory", "a directory written by `liedfl train`"),
    "report": ("sweep", "multirun dir", "multirun directory", "a directory written by `liedfl train -m`"),
}


def preflight(command: str, cfg) -> None:
    """Checks that need no data and write nothing: the directory argument and the schema. Raises
    ConfigError (called by the Hydra callback before the run folder exists, and when the job starts)."""
    from omegaconf import OmegaConf

    from ..errors import ConfigError
    from .schema import validate

    if command in DIR_ARGS and OmegaConf.is_missing(cfg, DIR_ARGS[command][0]):
        key, what, _, hint = DIR_ARGS[command]
        raise ConfigError(f"{key}=<{what}> is required ({hint})")
    validate(cfg, command)


def preflight_or_fail(command: str, cfg) -> None:
    """`preflight`, turning an error into one stderr line and a non-zero exit."""
    from ..display.ui import fail

    try:
        preflight(command, cfg)
    except BaseException as e:  # classified below; anything else goes on up
        known = classify(e)
        if known is None:
            raise
        fail(*known)


def classify(e: BaseException) -> tuple[str, int] | None:
    """(one-line message, exit code) of an error the CLI reports without a traceback; None for others."""
    from omegaconf.errors import OmegaConfBaseException

    from ..errors import LiedflError

    if isinstance(e, LiedflError):
        return str(e), int(getattr(e, "exit_code", 2))
    if isinstance(e, OSError) and not isinstance(e, BrokenPipeError):  # a full disk, a read-only folder, ...
        return os_error_line(e), 2
    if isinstance(e, FloatingPointError):
        return f"numerical failure: {e}", 2
    if isinstance(e, OmegaConfBaseException):  # e.g. a broken interpolation in an override file
        key = getattr(e, "full_key", None)
        text = str(e).strip()
        return f"config error: {text.splitlines()[0] if text else type(e).__name__}" + (
            f" (key {key})" if key else ""
        ), 2
    if isinstance(e, KeyboardInterrupt):  # KeyboardInterrupt("<how to resume>") adds its text to the line
        from ..files.signals import Terminated, interruption_message

        return interruption_message(e), e.exit_code if isinstance(e, Terminated) else 130
    if type(e).__name__ == "UncompletedJobError" and type(e).__module__.split(".")[0] == "submitit":
        # raised inside a submitit job by submitit's handler of the cluster's warning signal (the
        # job's time limit, hydra.launcher.timeout_min, or a preemption): the job records it and ends
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        why = lines[0].rstrip(".") if lines else "time limit or preemption"
        return (
            f"stopped by the cluster ({why}): `liedfl train resume=<job folder>` continues from its last checkpoint",
            2,
        )
    return None


# liedfl's temporary names: `.<name>.tmp<suffix>` (io_utils.atomic_path) and `<name>.h5.tmp<suffix>`
# (data.hdf5.save_dataset); the suffix is a process id, or host, process id and a random part
_TMP_NAME = re.compile(
    r"(?:(?<=/)|^)\.([^/\s'\"]+?)\.tmp(?:\d|[-_.])[A-Za-z0-9_.\-]*|([^/\s'\"]+?\.h5)\.tmp(?:\d|[-_.])[A-Za-z0-9_.\-]*"
)


def user_path(text: str) -> str:
    """`text` with liedfl's temporary file names replaced by the names of the files being written
    (an error while writing `.last.pt.tmp123` is about `last.pt`)."""
    return _TMP_NAME.sub(lambda m: m.group(1) or m.group(2), str(text))


def os_error_line(e: OSError) -> str:
    """One line for an OSError: the file it is about (the user's name, not a temporary one) and why;
    ENOSPC says that nothing half-written was kept (every file is written then renamed)."""
    import errno

    why = e.strerror or " ".join(str(a) for a in e.args) or type(e).__name__
    where = f"{user_path(os.fsdecode(e.filename))}: " if e.filename else ""
    line = user_path(f"{where}{why}")
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        line += " (no file was left half-written; free some space and run the command again)"
    return line
