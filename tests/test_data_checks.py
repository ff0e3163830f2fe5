"""Data checks at load and save: per-step rotation (warning above pi/2, error above 0.9 pi), float
precision of user files, the split group; interrupted and killed dataset writes."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from liedfl_cli.data import Dataset, DatasetError, load_dataset, save_dataset
from liedfl_cli.data.checks import ERROR_ANGLE, WARN_ANGLE, step_angles, step_rotation_summary
from liedfl_cli.errors import DataWarning
from liedfl_cli.files.io_utils import atomic_path, clean_orphans, write_text
from liedfl_cli.lie import so3


def _axis_angle(angle: float, axis=(0.3, -0.5, 0.8)) -> np.ndarray:
    u = torch.tensor(axis, dtype=torch.float64)
    return so3.exp(angle * u / u.norm()).numpy()


def _dataset(step: float, T=3, N=6, B=2, bad=None, big: float | None = None) -> Dataset:
    """T trajectories turning by `step` rad per step; `bad` = (traj, step, body) turns by `big` instead."""
    rng = np.random.default_rng(0)
    R = np.empty((T, N + 1, B, 3, 3))
    for i in range(T):
        for b in range(B):
            R[i, 0, b] = so3.random((), generator=torch.Generator().manual_seed(10 * i + b)).numpy()
            for k in range(N):
                a = big if bad == (i, k, b) else step
                W = _axis_angle(a, rng.standard_normal(3))
                R[i, k + 1, b] = R[i, k, b] @ W
    return Dataset(
        R=R,
        p=np.zeros((T, N + 1, 0, 3)),
        h=0.1,
        scene="custom",
        body_names=["upper", "lower"][:B],
        body_kinds=["so3"] * B,
        split={"train": np.arange(T - 1), "test": np.array([T - 1])},
    )


# ----------------------------------------------------------------------------- step angles
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.5, WARN_ANGLE, 2.5, ERROR_ANGLE, math.pi - 1e-6])
def test_step_angles_are_accurate_over_the_whole_range(angle):
    R0 = so3.random((), generator=torch.Generator().manual_seed(3)).numpy()
    R = np.stack([R0, R0 @ _axis_angle(angle)])[None, :, None]
    got = float(step_angles(R)[0, 0, 0])
    assert abs(got - angle) <= 1e-12 * max(1.0, angle) + 1e-15  # atan2 form: no sqrt(eps) loss at 0 or pi


def test_summary_reports_the_largest_step_and_where():
    ds = _dataset(0.2, bad=(1, 4, 1), big=2.0)
    s = step_rotation_summary(ds)
    assert s["where"] == {"trajectory": 1, "step": 4, "body": 1}
    assert abs(s["max_step_angle"] - 2.0) < 1e-12
    assert s["n_increments"] == 3 * 6 * 2 and s["n_over_half_pi"] == 1
    json.dumps(s)  # plain types (goes into a run's summary.json)


def test_well_sampled_data_load_silently(tmp_path):
    path = save_dataset(_dataset(0.3), tmp_path / "ok.h5")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_dataset(path)


def test_coarse_sampling_warns_with_the_figures_at_save_and_load(tmp_path):
    ds = _dataset(0.2, bad=(2, 3, 0), big=2.0)
    path = tmp_path / "coarse.h5"
    with pytest.warns(DataWarning) as rec:
        save_dataset(ds, path)
    with pytest.warns(DataWarning) as rec2:
        load_dataset(path)
    for r in (rec, rec2):
        msgs = [str(w.message) for w in r if issubclass(w.category, DataWarning)]
        assert len(msgs) == 1, msgs
        m = msgs[0]
        assert "\n" not in m and "2 rad" in m and "0.637 pi" in m
        assert "trajectory 2, step 3 -> 4, body 0 (upper)" in m and "1 of 36 increments exceed pi/2" in m
    assert str(path) in str(rec2[0].message)


def test_ambiguous_increments_are_an_error_at_save_and_at_load(tmp_path):
    ds = _dataset(0.2, bad=(0, 5, 1), big=3.0)
    path = tmp_path / "aliased.h5"
    with pytest.raises(DatasetError, match=r"aliased\.h5: dataset 'R' turns too far in one step.*3 rad") as e:
        save_dataset(ds, path)
    assert "trajectory 0, step 5 -> 6, body 1 (lower)" in str(e.value) and "ambiguous" in str(e.value)
    assert list(tmp_path.iterdir()) == []
    # the same data written by someone else: refused at load, naming the file
    with h5py.File(path, "w") as f:
        f.attrs["format_version"] = 1
        f.attrs["h"] = 0.1
        f.attrs["body_kinds"] = json.dumps(["so3", "so3"])
        f.create_dataset("R", data=ds.R)
        f.create_dataset("split/train", data=np.array([0, 1]))
        f.create_dataset("split/test", data=np.array([2]))
    with pytest.raises(DatasetError, match=str(path) + r": dataset 'R' turns too far"):
        load_dataset(path)


# ----------------------------------------------------------------------------- user files
def _user_file(path: Path, R, p=None, t=None, h=1 / 120, split=True, extras=None) -> Path:
    with h5py.File(path, "w") as f:
        f.attrs["format_version"] = 1
        f.attrs["h"] = h
        f.attrs["body_kinds"] = json.dumps(["so3"] * R.shape[2])
        f.create_dataset("R", data=R)
        if t is not None:
            f.create_dataset("t", data=t)
        if split:
            f.create_dataset("split/train", data=np.arange(R.shape[0] - 1))
            f.create_dataset("split/test", data=np.array([R.shape[0] - 1]))
        for k, v in (extras or {}).items():
            f.create_dataset(f"extras/{k}", data=v)
    return path


def test_float32_user_file_is_read_as_float64_including_a_long_float32_time_axis(tmp_path):
    """600 frames at 120 Hz stored in float32: t's rounding (~5e-7 s at t = 5 s) exceeds 1e-6 h, which
    used to be reported as an unevenly spaced time axis."""
    R = _dataset(0.01, T=3, N=599, B=1).R.astype(np.float32)
    t = (np.arange(600) / 120).astype(np.float32)
    omega = np.ones((3, 600, 1, 3), dtype=">f4")  # big-endian, as some writers store it
    path = _user_file(tmp_path / "mine.h5", R, t=t, extras={"omega": omega})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = load_dataset(path)
    assert ds.R.dtype == np.float64 and ds.p.dtype == np.float64 and ds.t.dtype == np.float64
    assert ds.extras["omega"].dtype == np.float32 and ds.extras["omega"].dtype.isnative
    torch.as_tensor(ds.extras["omega"])  # torch refuses big-endian arrays
    g = ds.pose("train")
    assert g.R.dtype == torch.float64


def test_float16_poses_are_a_clear_error(tmp_path):
    R = _dataset(0.1, T=2, N=3, B=1).R.astype(np.float16)
    path = _user_file(tmp_path / "half.h5", R)
    with pytest.raises(DatasetError, match=r"half\.h5: dataset 'R' is stored as float16.*float32 or float64"):
        load_dataset(path)


def test_a_file_without_split_fails_at_load_naming_the_file(tmp_path):
    path = _user_file(tmp_path / "nosplit.h5", _dataset(0.1, T=2, N=3, B=1).R, split=False)
    with pytest.raises(DatasetError, match=r"nosplit\.h5: group 'split' is missing"):
        load_dataset(path)
    ds = load_dataset(path, require_split=False)
    assert ds.split["train"].tolist() == [0, 1] and ds.split["test"].size == 0


def test_an_empty_train_split_fails_at_load(tmp_path):
    path = _user_file(tmp_path / "empty.h5", _dataset(0.1, T=2, N=3, B=1).R)
    with h5py.File(path, "r+") as f:
        del f["split/train"]
        f.create_dataset("split/train", data=np.zeros(0, dtype=np.int64))
    with pytest.raises(DatasetError, match=r"empty\.h5: dataset 'split/train' is empty"):
        load_dataset(path)


# ----------------------------------------------------------------------------- interrupted writes
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_orphaned_temporary_files_of_dead_writers_are_removed_at_the_next_write(tmp_path):
    from liedfl_cli.files.io_utils import host_id

    dead, alive, host = _dead_pid(), os.getppid(), host_id()
    orphan = tmp_path / f"scene-abc.h5.tmp.{host}.{dead}.0123abcd"
    orphan_small = tmp_path / f".eval.csv.tmp.{host}.{dead}.89abcdef"
    live = tmp_path / f"scene-abc.h5.tmp.{host}.{alive}.0123abcd"
    keep = tmp_path / "notes.tmp"  # no pid: not a liedfl temporary file
    user = tmp_path / f"notes.txt.tmp.{host}.{dead}.0123abcd"  # not named like liedfl's temporary files
    for p in (orphan, orphan_small, live, keep, user):
        p.write_bytes(b"half written")
    save_dataset(_dataset(0.1, T=2, N=3, B=1), tmp_path / "x.h5")
    assert not orphan.exists() and not orphan_small.exists()
    assert live.exists() and keep.exists() and user.exists()
    orphan.write_bytes(b"again")
    write_text(tmp_path / "y.txt", "atomic_path cleans too\n")
    assert not orphan.exists() and live.exists()
    assert clean_orphans(tmp_path) == []


_CHILD = textwrap.dedent(
    """
    import os, signal, sys
    import h5py
    from liedfl_cli.data.hdf5 import Dataset, save_dataset
    import numpy as np

    sig = getattr(signal, sys.argv[2])
    real = h5py.Group.create_dataset
    def create_dataset(self, *a, **k):  # the signal arrives while the file is being written
        os.kill(os.getpid(), sig)
        return real(self, *a, **k)
    h5py.Group.create_dataset = create_dataset
    R = np.broadcast_to(np.eye(3), (2, 4, 1, 3, 3)).copy()
    ds = Dataset(R=R, p=np.zeros((2, 4, 0, 3)), h=0.1, scene="x", body_names=["b"], body_kinds=["so3"],
                 split={"train": np.array([0]), "test": np.array([1])})
    try:
        save_dataset(ds, sys.argv[1])
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    print("not interrupted", file=sys.stderr)
    """
)


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM at their defaults, as from a terminal (a test run under
    `nohup` or as a background job of a script inherits SIGINT ignored, and Python then keeps it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.fixture
def sigint_raises():
    """This process's SIGINT raises KeyboardInterrupt (Python's default), even if it was started with SIGINT
    ignored; the previous disposition is restored afterwards."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_during_a_dataset_write_is_not_swallowed_and_leaves_no_temporary_file(tmp_path, sig):
    target = tmp_path / "data" / "x.h5"
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(target), sig], capture_output=True, text=True, timeout=120,
                          preexec_fn=_default_signals)  # fmt: skip
    if sig == "SIGINT":
        assert proc.returncode == 130 and proc.stderr.strip().splitlines()[-1] == "interrupted", proc.stderr
    else:
        assert proc.returncode == -signal.SIGTERM, (proc.returncode, proc.stderr)
    assert "Exception ignored" not in proc.stderr and "not interrupted" not in proc.stderr
    assert not [p for p in target.parent.iterdir() if ".tmp" in p.name]


def test_atomic_path_holds_a_signal_until_the_file_is_in_place(tmp_path, sigint_raises):
    target = tmp_path / "a.txt"
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        Path(tmp).write_text("complete\n")
        os.kill(os.getpid(), signal.SIGINT)  # held: the rename still happens, then the interrupt
    assert target.read_text() == "complete\n"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_the_cli_shows_the_coarse_sampling_warning_on_one_line(tmp_path, run_main):
    """`liedfl data` on a cached file with one increment of 0.6 pi: exit 0, one `warning:` line."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.cli import CONF_DIR
    from liedfl_cli.data.scenes import get_dataset

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="data", overrides=["budget=smoke"])
    GlobalHydra.instance().clear()
    _, path = get_dataset(cfg.dataset, tmp_path / "outputs" / "data")
    with h5py.File(path, "r+") as f:
        R = f["R"][...]
        W = _axis_angle(0.6 * math.pi, (0.0, 0.0, 1.0))
        R[2, 7:, 0] = (R[2, 6, 0] @ W @ R[2, 7, 0].T) @ R[2, 7:, 0]
        f["R"][...] = R
    proc = run_main("data", "budget=smoke", "ui.progress=false", cwd=tmp_path)  # in-process: the message is tested
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning: "), proc.stderr
    assert path.name in lines[0] and "0.600 pi" in lines[0] and "trajectory 2, step 6 -> 7, body 0" in lines[0]
