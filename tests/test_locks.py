"""One process per run folder (liedfl_cli/files/locks.py) and temporary names that are safe on a file system
shared by several hosts (liedfl_cli/files/io_utils.py): issue 18, items 2 and 3."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from liedfl_cli.data.hdf5 import Dataset, load_dataset, save_dataset
from liedfl_cli.files import locks
from liedfl_cli.files.io_utils import clean_orphans, host_id, temporary_name


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _write_lock(folder: Path, **fields) -> dict:
    """A lock record as another process would have written it (default: this host, the live parent)."""
    pid = os.getppid()
    record = {"host": host_id(), "hostname": "here", "pid": pid, "start": locks.process_start(pid),
              "boot": locks._boot_id(), "since": "2026-01-01T00:00:00+00:00", "command": "train",
              "token": "f" * 16}  # fmt: skip
    record.update(fields)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / locks.LOCK_FILE).write_text(json.dumps(record))
    return record


def _lock(folder: Path) -> dict:
    return json.loads((folder / locks.LOCK_FILE).read_text())


@pytest.fixture(autouse=True)
def _no_break(monkeypatch):
    monkeypatch.delenv(locks.BREAK_ENV, raising=False)
    yield
    locks.release_all()


# ----------------------------------------------------------------------------- the lock itself
def test_a_lock_is_taken_released_and_reentrant(tmp_path):
    lock = locks.acquire(tmp_path, "eval")
    held = _lock(tmp_path)
    assert held["pid"] == os.getpid() and held["host"] == host_id() and held["command"] == "eval"
    assert locks.acquire(tmp_path, "eval") is lock  # the same process again: counted
    lock.release()
    assert (tmp_path / ".lock").exists()
    lock.release()
    assert not (tmp_path / ".lock").exists()
    assert not [p for p in tmp_path.iterdir()]  # no temporary file left either


def test_a_live_holder_of_this_host_refuses_with_one_line_naming_it(tmp_path):
    record = _write_lock(tmp_path / "run")
    with pytest.raises(locks.RunLocked) as e:
        locks.acquire(tmp_path / "run", "train")
    line = str(e.value)
    assert "\n" not in line and str(tmp_path / "run") in line and f"pid {record['pid']}" in line
    assert "since 2026-01-01" in line
    assert _lock(tmp_path / "run") == record  # untouched


@pytest.mark.parametrize("how", ["dead-pid", "reused-pid", "other-boot", "garbled"])
def test_a_stale_lock_of_this_host_is_taken_over(tmp_path, how):
    fields = {
        "dead-pid": {"pid": _dead_pid()},
        "reused-pid": {"start": "1"},  # the pid lives, but it is another process than the one that locked
        "other-boot": {"boot": "another-boot-id"},
    }.get(how, {})
    if how == "garbled":
        tmp_path.joinpath(".lock").write_text("{not json")
    else:
        _write_lock(tmp_path, **fields)
    locks.acquire(tmp_path, "train")
    assert _lock(tmp_path)["pid"] == os.getpid()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lock"]


def test_a_lock_of_another_host_is_never_judged_by_its_pid(tmp_path, monkeypatch):
    record = _write_lock(tmp_path, host="othernode", hostname="othernode.cluster", pid=_dead_pid())
    with pytest.raises(locks.RunLocked) as e:
        locks.acquire(tmp_path, "train")
    line = str(e.value)
    assert "another machine" in line and "othernode.cluster" in line and f"{locks.BREAK_ENV}=break" in line
    assert _lock(tmp_path) == record
    monkeypatch.setenv(locks.BREAK_ENV, "break")  # the user knows that job is gone
    locks.acquire(tmp_path, "train")
    assert _lock(tmp_path)["pid"] == os.getpid()


_RECOVER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from liedfl_cli.files import locks
    go = Path(sys.argv[2])
    while not go.exists():
        time.sleep(0.001)
    try:
        locks.acquire(sys.argv[1], "train")
    except locks.RunLocked:
        print("refused")
    else:
        print("won")
        time.sleep(1.5)  # hold it while the others try
    """
)


def test_two_recoverers_of_one_stale_lock_cannot_both_win(tmp_path):
    run, go = tmp_path / "run", tmp_path / "go"
    _write_lock(run, pid=_dead_pid())
    procs = [
        subprocess.Popen([sys.executable, "-c", _RECOVER, str(run), str(go)], stdout=subprocess.PIPE, text=True)
        for _ in range(4)
    ]
    time.sleep(1.0)  # (all of them imported and waiting)
    go.touch()
    outs = [p.communicate(timeout=60)[0].strip() for p in procs]
    assert sorted(outs) == ["refused", "refused", "refused", "won"], outs
    assert not (run / ".lock").exists()  # the winner released it when it exited


# ----------------------------------------------------------------------------- through the CLI
_HOLD = "import sys, time\nfrom liedfl_cli.files import locks\nlocks.acquire(sys.argv[1], 'train')\nprint('held', flush=True)\ntime.sleep(60)\n"  # noqa: E501


@pytest.fixture
def holder(tmp_path):
    """A process that holds the lock of `tmp_path / 'run'` (a first liedfl on the folder)."""
    run = tmp_path / "run"
    run.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    yield run, proc
    proc.kill()
    proc.wait()


def _main(args, monkeypatch, capfd) -> tuple[int, str]:
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.cli import main

    capfd.readouterr()
    monkeypatch.setattr(sys, "argv", ["liedfl", *args])
    try:
        main()
        code = 0
    except SystemExit as e:
        code = int(e.code or 0)
    finally:
        GlobalHydra.instance().clear()
    return code, capfd.readouterr().err


@pytest.mark.parametrize(
    "args",
    [
        ("eval", "run={run}", "ui.progress=false"),
        ("rollout", "run={run}", "ui.progress=false"),
        ("train", "resume={run}", "ui.progress=false"),
        ("train", "budget=smoke", "ui.progress=false", "hydra.run.dir={run}"),
    ],
    ids=["eval", "rollout", "resume", "train-same-dir"],
)
def test_a_second_process_on_a_run_folder_is_refused_and_the_first_goes_on(holder, args, monkeypatch, capfd, tmp_path):
    run, proc = holder
    monkeypatch.chdir(tmp_path)
    before = _lock(run)
    code, err = _main([a.format(run=run) for a in args], monkeypatch, capfd)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("error: run folder ") and str(run.absolute()) in lines[0]
    assert f"pid {proc.pid}" in lines[0] and "in use" in lines[0]
    assert proc.poll() is None and _lock(run) == before  # the first process and its lock: untouched
    assert sorted(p.name for p in run.iterdir()) == [".lock"]  # (train: no .hydra/ written over the first's)


def test_the_lock_is_released_after_a_failed_command(tmp_path, monkeypatch, capfd):
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.chdir(tmp_path)
    code, err = _main(["eval", f"run={run}", "ui.progress=false"], monkeypatch, capfd)
    assert code == 2 and "checkpoint" in err
    assert list(run.iterdir()) == []


# ----------------------------------------------------------------------------- temporary files
def _dataset(T: int = 3) -> Dataset:
    R = np.broadcast_to(np.eye(3), (T, 5, 1, 3, 3)).copy()
    return Dataset(R=R, p=np.zeros((T, 5, 0, 3)), h=0.1, scene="x", body_names=["b"], body_kinds=["so3"],
                   split={"train": np.array([0, 1]), "test": np.array([2])})  # fmt: skip


def test_temporary_names_carry_host_pid_and_a_random_token(tmp_path, monkeypatch):
    monkeypatch.setattr("socket.gethostname", lambda: "node-7.cluster.local")
    a, b = temporary_name(tmp_path / "x.csv"), temporary_name(tmp_path / "x.csv")
    assert a != b and a.name.startswith(".x.csv.tmp.node-7_cluster_local") and f".{os.getpid()}." in a.name


def test_another_hosts_temporary_file_is_never_removed_and_both_writers_end_with_a_valid_cache(tmp_path, monkeypatch):
    """The issue's reproducer: node A writes the data cache; meanwhile node B writes the same cache and
    cleans the folder. A's writer pid does not exist on B (here: a dead pid). Before the fix B removed A's
    temporary file and A failed with `No such file or directory`."""
    target = tmp_path / "data" / "scene-abc.h5"
    dead = _dead_pid()
    real_pid, real_create = os.getpid, h5py.Group.create_dataset
    seen: dict[str, list[str]] = {}

    def create_dataset(self, *a, **k):
        if not seen:  # A is writing its temporary file: B runs now
            seen["during"] = sorted(p.name for p in target.parent.iterdir())
            monkeypatch.setattr("socket.gethostname", lambda: "nodeB")
            monkeypatch.setattr(os, "getpid", real_pid)
            save_dataset(_dataset(), target)
            seen["after_b"] = sorted(p.name for p in target.parent.iterdir())
            monkeypatch.setattr("socket.gethostname", lambda: "nodeA")
            monkeypatch.setattr(os, "getpid", lambda: dead)
        return real_create(self, *a, **k)

    monkeypatch.setattr("socket.gethostname", lambda: "nodeA")
    monkeypatch.setattr(os, "getpid", lambda: dead)  # A's pid, not visible on B
    monkeypatch.setattr(h5py.Group, "create_dataset", create_dataset)
    save_dataset(_dataset(), target)  # A: completes although B wrote and cleaned in between
    monkeypatch.setattr(os, "getpid", real_pid)
    (a_tmp,) = seen["during"]
    assert a_tmp.startswith("scene-abc.h5.tmp.nodeA") and a_tmp in seen["after_b"]  # B kept A's file
    assert sorted(p.name for p in target.parent.iterdir()) == ["scene-abc.h5"]
    assert load_dataset(target).n_trajectories == 3


def test_the_clean_up_judges_only_this_hosts_writers(tmp_path, monkeypatch):
    monkeypatch.setattr("socket.gethostname", lambda: "nodeA")
    me, dead = host_id(), _dead_pid()
    mine_dead = tmp_path / f".eval.csv.tmp.{me}.{dead}.0123abcd"
    theirs_dead = tmp_path / f".eval.csv.tmp.nodeB.{dead}.0123abcd"  # that pid means nothing here
    theirs_old = tmp_path / f"s.h5.tmp.nodeB.{dead}.89abcdef"
    legacy_new, legacy_old = tmp_path / f".a.csv.tmp{dead}", tmp_path / f".b.csv.tmp{dead}"
    for p in (mine_dead, theirs_dead, theirs_old, legacy_new, legacy_old):
        p.write_text("half")
    old = time.time() - 2 * 86400
    for p in (theirs_old, legacy_old):
        os.utime(p, (old, old))
    removed = {p.name for p in clean_orphans(tmp_path)}
    assert removed == {mine_dead.name, theirs_old.name, legacy_old.name}
    assert theirs_dead.exists() and legacy_new.exists()


def test_a_signal_still_leaves_no_temporary_file(tmp_path):
    """A Ctrl-C during a dataset write, with the new temporary names: the file is completed, then the
    interrupt; nothing else is left."""
    code = textwrap.dedent(
        f"""
        import os, signal, h5py, numpy as np
        from liedfl_cli.data.hdf5 import Dataset, save_dataset
        real = h5py.Group.create_dataset
        def create(self, *a, **k):
            os.kill(os.getpid(), signal.SIGINT)
            return real(self, *a, **k)
        h5py.Group.create_dataset = create
        R = np.broadcast_to(np.eye(3), (2, 4, 1, 3, 3)).copy()
        ds = Dataset(R=R, p=np.zeros((2, 4, 0, 3)), h=0.1, scene="x", body_names=["b"], body_kinds=["so3"],
                     split={{"train": np.array([0]), "test": np.array([1])}})
        try:
            save_dataset(ds, {str(tmp_path / "x.h5")!r})
        except KeyboardInterrupt:
            raise SystemExit(130)
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], timeout=120,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    assert proc.returncode == 130
    assert [p.name for p in tmp_path.iterdir()] == ["x.h5"]  # held until the file was in place; no temporary
