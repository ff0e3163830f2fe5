"""One process per run folder: `<run>/.lock`.

Every command that writes into a run folder (`liedfl train`, `train resume=<run>`, `rollout run=<run>`,
`eval run=<run>`) holds the folder's lock while it runs. The lock is a file created atomically
(a complete file hard-linked to `.lock`, which fails when the name exists; `O_CREAT|O_EXCL` where the
file system has no hard links), both atomic on NFS, unlike `flock`. It holds JSON: host (`io_utils.host_id`),
pid, the process's start time and boot id (a pid reused after the holder died is not mistaken for it),
when it was taken, the command and a random token.

A second process on the folder stops with one line naming the folder and the holder. A lock of this
host whose process is gone (or whose pid now belongs to another process) is stale: it is taken over
under a short-lived `.lock.takeover` file created the same way, after reading the lock again, so two
processes that both found it stale cannot both take it. A lock of another host is never judged by its
pid (that pid means nothing here): the process refuses and says how to remove it; the environment
variable `LIEDFL_RUN_LOCK=break` takes it over regardless, for a job known to be gone.

The lock is released (its file removed, if it still holds this process's token) when the command ends:
normally, on an error, on SIGINT/SIGTERM (which the CLI turns into exceptions), and at interpreter exit.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import secrets
import socket
import time
from datetime import datetime, timezone
from pathlib import Path

from ..errors import LiedflError
from .io_utils import host_id, pid_alive, temporary_name

LOCK_FILE = ".lock"
TAKEOVER_FILE = ".lock.takeover"
BREAK_ENV = "LIEDFL_RUN_LOCK"  # =break: take over another host's lock (that job is known to be gone)


class RunLocked(LiedflError):
    """The run folder is locked by another process."""


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def process_start(pid: int) -> str:
    """The start time of process `pid` in clock ticks since boot (/proc/<pid>/stat field 22); '' where
    unknown (not Linux, or no such process)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    # the command name (field 2) is in parentheses and may hold spaces: fields after its last ')'
    fields = stat[stat.rfind(")") + 2 :].split()
    return fields[19] if len(fields) > 19 else ""


def _record(command: str) -> dict:
    return {
        "host": host_id(),
        "hostname": socket.gethostname(),
        "pid": os.getpid(),
        "start": process_start(os.getpid()),
        "boot": _boot_id(),
        "since": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": command,
        "token": secrets.token_hex(8),
    }


def holder_alive(holder: dict) -> bool | None:
    """True/False for a holder of this host (its pid exists and is still the same process); None for a
    holder of another host, whose liveness cannot be judged from here."""
    if holder.get("host") != host_id():
        return None
    if holder.get("boot") and _boot_id() and holder.get("boot") != _boot_id():
        return False  # this host rebooted since
    try:
        pid = int(holder.get("pid", -1))
    except (TypeError, ValueError):
        return False
    if not pid_alive(pid):
        return False
    start = process_start(pid)
    return not (holder.get("start") and start and start != holder.get("start"))  # a reused pid: not the holder


def describe(holder: dict) -> str:
    """'host <h>, pid <p>, since <time> (<command>)'."""
    what = f" ({holder['command']})" if holder.get("command") else ""
    host = holder.get("hostname") or holder.get("host")
    return f"host {host}, pid {holder.get('pid')}, since {holder.get('since')}{what}"


def _read(path: Path) -> tuple[dict | None, tuple | None]:
    """(the lock's record, its identity (inode, mtime, bytes)); (None, None) when there is no lock;
    ({}, identity) when the file is not a lock record (damaged)."""
    try:
        st = path.stat()
        raw = path.read_bytes()
    except FileNotFoundError:
        return None, None
    except OSError:
        return {}, None
    try:
        obj = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        obj = {}
    return (obj if isinstance(obj, dict) else {}), (st.st_ino, st.st_mtime_ns, raw)


def _create(path: Path, record: dict) -> bool:
    """Create `path` holding `record`, atomically and only if it does not exist: a complete temporary
    file hard-linked to the name (link fails if the name exists, also on NFS); O_CREAT|O_EXCL where the
    file system has no hard links. False when the name exists."""
    data = (json.dumps(record) + "\n").encode()
    tmp = temporary_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
            return True
        except FileExistsError:
            # NFS may report a link that was made (its first reply lost) as existing: two names = ours
            return os.stat(tmp).st_nlink == 2
        except OSError:  # no hard links here
            pass
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    return True


class RunLock:
    """A held lock of one run folder (`acquire`); `release()` removes it if it is still ours."""

    def __init__(self, folder: Path, record: dict):
        self.folder, self.record = folder, record
        self.path = folder / LOCK_FILE
        self.count = 1

    def release(self) -> None:
        self.count -= 1
        if self.count > 0:
            return
        _held.pop(str(self.folder), None)
        holder, _ = _read(self.path)
        if holder and holder.get("token") == self.record["token"]:
            with contextlib.suppress(OSError):
                self.path.unlink()


_held: dict[str, RunLock] = {}


def _takeover(folder: Path, seen: tuple, record: dict) -> bool:
    """Replace the lock whose identity is `seen` by `record`, under `.lock.takeover`; False when the
    lock changed in between (someone else took it) or another takeover is under way."""
    guard = folder / TAKEOVER_FILE
    if not _create(guard, record):
        g, _ = _read(guard)
        if g is not None and holder_alive(g) is False:  # a takeover whose process died in it (very rare)
            with contextlib.suppress(OSError):
                guard.unlink()
        time.sleep(0.05)
        return False
    try:
        _, now = _read(folder / LOCK_FILE)
        if now != seen:
            return False
        fresh = temporary_name(folder / LOCK_FILE)
        fresh.write_text(json.dumps(record) + "\n")
        os.replace(fresh, folder / LOCK_FILE)
        return True
    finally:
        with contextlib.suppress(OSError):
            guard.unlink()


def acquire(folder, command: str, override: str | None = None) -> RunLock:
    """Take the lock of run folder `folder` for `command` (the same process again: counted, not
    refused). `override="break"` (default: the environment's LIEDFL_RUN_LOCK) takes over a lock of another
    host (the user knows that job is gone). Raises RunLocked with one line naming the folder and the holder."""
    if override is None:
        override = os.environ.get(BREAK_ENV) or None
    folder = Path(os.path.abspath(folder))
    key = str(folder)
    if key in _held:
        _held[key].count += 1
        return _held[key]
    path = folder / LOCK_FILE
    record = _record(command)
    for attempt in range(200):
        if _create(path, record):
            break
        holder, seen = _read(path)
        if holder is None:  # released in between: try again
            continue
        mine = next((lk for lk in _held.values() if holder and holder.get("token") == lk.record["token"]), None)
        if mine is not None:  # this process's lock, reached by another spelling of the path
            mine.count += 1
            return mine
        if seen is None:
            raise RunLocked(f"{path}: cannot read the lock of run folder {folder}")
        if not holder and attempt < 20:  # being written (O_EXCL fallback): give it a moment
            time.sleep(0.05)
            continue
        alive = holder_alive(holder) if holder else False
        if alive is None and override == "break":
            alive = False
        if alive:
            raise RunLocked(f"run folder {folder} is in use by another liedfl process ({describe(holder)})")
        if alive is None:
            raise RunLocked(
                f"run folder {folder} is locked by a liedfl process on another machine ({describe(holder)}); if that"
                f" job is gone, rerun with {BREAK_ENV}=break (or remove {path})"
            )
        if _takeover(folder, seen, record):
            break
    else:
        raise RunLocked(f"run folder {folder}: could not take its lock {path} (it keeps changing)")
    lock = RunLock(folder, record)
    _held[key] = lock
    return lock


@contextlib.contextmanager
def run_lock(folder, command: str, override: str | None = None):
    """`acquire` for the block; released when it ends, however it ends."""
    lock = acquire(folder, command, override)
    try:
        yield lock
    finally:
        lock.release()


def release_folder(folder) -> None:
    """Release this process's lock of `folder` however often it was taken (nothing if not held)."""
    lock = _held.get(str(Path(os.path.abspath(folder))))
    if lock is not None:
        lock.count = 1
        lock.release()


def release_all() -> None:
    """Release every lock this process holds (at interpreter exit)."""
    for lock in list(_held.values()):
        lock.count = 1
        lock.release()


atexit.register(release_all)

__all__ = [
    "RunLocked",
    "RunLock",
    "acquire",
    "run_lock",
    "release_folder",
    "release_all",
    "holder_alive",
    "describe",
    "LOCK_FILE",
]
