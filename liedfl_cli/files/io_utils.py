"""Atomic file writing: every output is written to a temporary name and renamed into place."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import secrets
import signal
import socket
import threading
import time
from pathlib import Path

# liedfl's temporary names carry the writer's host, pid and a random token, so that writers on several
# machines sharing one file system (a cluster's NFS home) never share a name and the clean-up can tell
# whose file it is: `.<name>.tmp.<host>.<pid>.<token>` (atomic_path) and
# `<stem>.h5.tmp.<host>.<pid>.<token>` (save_dataset).
_TMP = re.compile(r"(?:\..+|.+\.h5)\.tmp\.(?P<host>[A-Za-z0-9_-]+)\.(?P<pid>\d+)\.(?P<token>[0-9a-f]{8})")
_LEGACY_TMP = re.compile(r"(?:\..+|.+\.h5)\.tmp(\d+)")  # liedfl before 0.x: no host in the name
# Another host's temporary file (or a legacy one, whose host is unknown) is removed only when untouched
# for this long: its writer's liveness cannot be judged from here, and a write takes seconds to minutes
# (a writer's file changes as it writes), so a day-old one is a leftover of a killed node, not a write.
FOREIGN_TMP_MAX_AGE = 86400.0


def host_id() -> str:
    """This machine's name as written into temporary names and locks: the host name with characters
    other than letters, digits, `-` and `_` replaced by `_`, plus `-ns<inode>` of the PID namespace
    where Linux tells it (two containers with one host name but their own PIDs differ by it)."""
    name = re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname() or "localhost")[:64] or "localhost"
    ns = _pid_namespace()
    return f"{name}-ns{ns}" if ns else name


def _pid_namespace() -> str:
    try:
        link = os.readlink("/proc/self/ns/pid")  # 'pid:[4026531836]'
    except OSError:
        return ""
    m = re.search(r"\d+", link)
    return m.group(0) if m else ""


def temporary_name(path: str | os.PathLike, hidden: bool = True) -> Path:
    """A temporary name next to `path`, unique across hosts and processes:
    `.<name>.tmp.<host>.<pid>.<token>` (hidden) or `<name>.tmp.<host>.<pid>.<token>`."""
    path = Path(path)
    tag = f"tmp.{host_id()}.{os.getpid()}.{secrets.token_hex(4)}"
    return path.with_name(f".{path.name}.{tag}" if hidden else f"{path.name}.{tag}")


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


def _orphan(p: Path, me: str) -> bool:
    """Whether `p` is a liedfl temporary file whose writer is gone: one of this host whose process no
    longer exists, or (another host's, or a legacy name without a host) untouched for a day."""
    m = _TMP.fullmatch(p.name)
    if m is not None and m.group("host") == me:
        pid = int(m.group("pid"))
        return pid != os.getpid() and not pid_alive(pid)
    if m is None and _LEGACY_TMP.fullmatch(p.name) is None:
        return False
    try:
        return time.time() - p.lstat().st_mtime > FOREIGN_TMP_MAX_AGE
    except OSError:
        return False


def clean_orphans(folder) -> list[Path]:
    """Remove liedfl's temporary files in `folder` left by writers that are gone (killed between writing
    the temporary file and renaming it): liveness is judged only for writers of this host (the host in
    the name); another host's file, whose writer may be writing right now, is kept unless untouched
    for `FOREIGN_TMP_MAX_AGE`. Files not named like liedfl's temporary files are kept. Returns the
    removed paths."""
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    me = host_id()
    for p in entries:
        if not _orphan(p, me):
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
    tmp = temporary_name(path)
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
