"""Atomic file writing: every output is written to a temporary name and renamed into place."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import signal
import threading
from pathlib import Path

# liedfl's temporary names: `.<name>.tmp<pid>` (atomic_path) and `<stem>.h5.tmp<pid>` (save_dataset)
_TMP = re.compile(r"(?:\..+|.+\.h5)\.tmp(\d+)")


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (on this machine)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def clean_orphans(folder) -> list[Path]:
    """Remove liedfl's temporary files (`.<name>.tmp<pid>`, `<stem>.h5.tmp<pid>`) in `folder` left by
    processes that no longer exist (a writer killed between writing its temporary file and renaming
    it). Files of live processes, and files not named like that, are kept. Returns the removed paths."""
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    me = os.getpid()
    for p in entries:
        m = _TMP.fullmatch(p.name)
        if not m or int(m.group(1)) == me or pid_alive(int(m.group(1))):
            continue
        try:
            if p.is_file() or p.is_symlink():
                p.unlink()
                removed.append(p)
        except OSError:
            pass
    return removed


@contextlib.contextmanager
def deferred_signals(signums=(signal.SIGINT, signal.SIGTERM)):
    """Hold SIGINT/SIGTERM while the block runs (a file being written and renamed), then deliver them
    to the handlers that were installed before. A Ctrl-C in the middle of an HDF5 or torch write
    would otherwise be raised inside library code (and may be swallowed as "Exception ignored").
    Only the main thread can install handlers; elsewhere the block runs unprotected. A signal whose
    disposition is SIG_IGN (e.g. SIGINT inherited ignored under `nohup`) is left ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield []
        return
    received: list[int] = []

    def hold(signum, frame):
        received.append(signum)

    old = {}
    try:
        for s in signums:
            if signal.getsignal(s) is not signal.SIG_IGN:
                old[s] = signal.signal(s, hold)
        yield received
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        for s in dict.fromkeys(received):
            signal.raise_signal(s)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path next to `path`; rename it onto `path` only if the block succeeds.

    SIGINT/SIGTERM are held until the file is in place (or the temporary file removed) and then
    delivered; temporary files of dead processes in the same folder are removed first."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_orphans(path.parent)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with deferred_signals():
        try:
            yield tmp
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def write_json(path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, default=_jsonable) + "\n")


def _jsonable(x):
    if hasattr(x, "tolist"):
        return x.tolist()
    return str(x)


def write_csv(path, rows: list[dict]) -> None:
    """Rows of dicts (union of keys as header, in first-seen order)."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        if v != v:
            return "nan"
        return f"{v:.3e}" if (abs(v) < 1e-2 or abs(v) >= 1e4) and v != 0 else f"{v:.4g}"
    return str(v)


def markdown_table(rows: list[dict], columns: list[str] | None = None) -> str:
    cols = columns or [k for r in rows for k in r if k][:None]
    cols = list(dict.fromkeys(cols))
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(lines) + "\n"
