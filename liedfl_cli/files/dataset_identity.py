"""The identity of a run's dataset file: its SHA-256, recorded in the checkpoint at train time
(`dataset_sha256`) and compared when the run is rolled out, evaluated or resumed. A file replaced or
edited since training is refused with one line (`accept_changed_dataset=true` accepts it, with a
warning): the run would otherwise be evaluated against data it never saw."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from ..errors import ConfigError, DatasetError

OVERRIDE_KEY = "accept_changed_dataset"

_CACHE: dict[tuple[str, int, int], str] = {}


def file_sha256(path) -> str:
    """SHA-256 of the file's bytes, computed once per (path, size, modification time) in a process."""
    path = Path(path).resolve()
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _CACHE[key] = h.hexdigest()
    return _CACHE[key]


def accept_option(value) -> bool:
    """The value of a command's `accept_changed_dataset` (None: absent, false); ConfigError unless a boolean."""
    if value is None:
        return False
    if not isinstance(value, bool):
        raise ConfigError(f"{OVERRIDE_KEY}={value!r}: must be true or false")
    return value


def check_unchanged(ckpt, recorded, path, accept: bool = False) -> None:
    """DatasetError when the file at `path` is not the one `ckpt` recorded (`recorded`: its SHA-256;
    None for runs written before it was recorded: nothing to compare)."""
    if not recorded:
        return
    now = file_sha256(path)
    if now == recorded:
        return
    message = (
        f"{path}: the dataset file changed since {ckpt} was trained on it (sha256 {str(recorded)[:12]}... "
        f"recorded, {now[:12]}... now)"
    )
    if accept:
        import warnings

        from ..errors import DataWarning

        warnings.warn(f"{message}; used anyway ({OVERRIDE_KEY}=true)", DataWarning, stacklevel=2)
        return
    raise DatasetError(f"{message}; restore the file, or give {OVERRIDE_KEY}=true to use it anyway")


def absolute(path: str) -> str:
    """A user's path made absolute against the current directory (`~` expanded)."""
    return os.path.abspath(os.path.expanduser(path))
