"""Exception types of liedfl.

Every error that reaches a user carries a one-line message that names the file (or config key),
the offending field and, where there is one, the first offending index.
"""

from __future__ import annotations


class LiedflError(Exception):
    """Base class of all liedfl errors."""


class DatasetError(LiedflError, ValueError):
    """A dataset file (or in-memory dataset) is missing, malformed or violates the data format."""


class CheckpointError(LiedflError, ValueError):
    """A checkpoint is missing, malformed or does not match the current configuration."""


class ConfigError(LiedflError, ValueError):
    """A configuration value is missing, of the wrong type or out of range."""


class InputError(LiedflError, ValueError):
    """An argument of the Python API (`liedfl_cli.api`) has the wrong type, dtype, shape or group."""


class SimulationError(LiedflError, RuntimeError):
    """Ground-truth integration failed (solver failure or too much drift off SO(3))."""


class LiedflWarning(UserWarning):
    """Base class of liedfl's warnings (the CLI prints them as one `warning: ...` line)."""


class DataWarning(LiedflWarning):
    """A dataset is usable but suspicious (rotations projected onto SO(3), coarse sampling, ...)."""


__all__ = [
    "LiedflError",
    "DatasetError",
    "CheckpointError",
    "ConfigError",
    "InputError",
    "SimulationError",
    "LiedflWarning",
    "DataWarning",
]
