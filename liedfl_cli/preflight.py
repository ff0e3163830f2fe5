"""Checks before a job runs (no data, nothing written) and the classification of the errors the
CLI reports as one line. Used by the CLI and by the Hydra callback (`status.LiedflCallback`)."""

from __future__ import annotations

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

    from .errors import ConfigError
    from .schema import validate

    if command in DIR_ARGS and OmegaConf.is_missing(cfg, DIR_ARGS[command][0]):
        key, what, _, hint = DIR_ARGS[command]
        raise ConfigError(f"{key}=<{what}> is required ({hint})")
    validate(cfg, command)


def preflight_or_fail(command: str, cfg) -> None:
    """`preflight`, turning an error into one stderr line and a non-zero exit."""
    from .ui import fail

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

    from .errors import LiedflError

    if isinstance(e, LiedflError):
        return str(e), int(getattr(e, "exit_code", 2))
    if isinstance(e, FloatingPointError):
        return f"numerical failure: {e}", 2
    if isinstance(e, OmegaConfBaseException):  # e.g. a broken interpolation in an override file
        key = getattr(e, "full_key", None)
        text = str(e).strip()
        return f"config error: {text.splitlines()[0] if text else type(e).__name__}" + (
            f" (key {key})" if key else ""
        ), 2
    if isinstance(e, KeyboardInterrupt):  # KeyboardInterrupt("<how to resume>") adds its text to the line
        from .signals import Terminated, interruption_message

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
