"""A new recording rolled out whole and exported in the import's layout (issue 21, item 3): the README's
commands (import, train, `liedfl rollout ... dataset=import ... export=csv`), the exported quaternions
against the rollout's rotations, the exported file imported again, and the rollout's split options."""

from __future__ import annotations

import csv
import json

import h5py
import numpy as np
import pytest
import torch
from own_data import H, write_csv

from helpers import main_in_process
from liedfl_cli.data.hdf5 import load_dataset
from liedfl_cli.lie import so3

FAST = ["budget=smoke", "ui.progress=false", "runtime.threads=1"]
IMPORT = ["dataset=import", "dataset.path=log.csv", "dataset.rotation=xyzw"]  # the README's commands
WXYZ = [3, 0, 1, 2]  # the export follows the import's convention: q0..q3 = x, y, z, w


@pytest.fixture(scope="module")
def trained_on_two_recordings(tmp_path_factory):
    """(cwd, run dir): a CSV with two recordings imported and trained on (tiny budget)."""
    cwd = tmp_path_factory.mktemp("export")
    write_csv(cwd / "log.csv", n_traj=2, n_samples=21, rotation="xyzw")
    code, trace = main_in_process("train", *IMPORT, *FAST, "dataset.n_test=1", "eval.plots=false", cwd=cwd)
    assert code == 0, trace
    (run,) = (cwd / "outputs" / "runs").iterdir()
    return cwd, run


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_both_recordings_rolled_out_exported_as_csv_and_imported_again(trained_on_two_recordings, run_main):
    cwd, run = trained_on_two_recordings
    ds_run = load_dataset(cwd / json.loads((run / "summary.json").read_text())["dataset_path"])
    assert len(ds_run.test_idx) == 1  # the run's own rollout covers its test split only
    out = run_main(
        "rollout",
        f"run={run}",
        *IMPORT,
        "export=csv",
        "ui.progress=false",
        "runtime.threads=1",
        "eval.plots=false",
        cwd=cwd,
        ok=True,
    ).stdout
    assert "split=all" in out and "re-import: liedfl data dataset=import" in out
    (folder,) = (run / "rollouts").iterdir()
    with h5py.File(folder / "rollout.h5", "r") as f:
        traj = f["traj_index"][:]
        R = f["model/R"][:]
        p = f["model/p"][:]
    assert traj.tolist() == [0, 1]  # both recordings, not the 1 test trajectory
    assert json.loads((folder / "source.json").read_text())["split"] == "all"
    rows = _rows(folder / "predictions.csv")
    assert list(rows[0]) == ["trajectory", "t", "q0", "q1", "q2", "q3", "x", "y", "z"]
    T, S1 = R.shape[:2]
    assert len(rows) == T * S1
    ids = np.array([r["trajectory"] for r in rows]).reshape(T, S1)  # the recording's names (issue 38)
    t = np.array([float(r["t"]) for r in rows]).reshape(T, S1)
    q = np.array([[float(r[f"q{k}"]) for k in WXYZ] for r in rows]).reshape(T, S1, 1, 4)  # (w, x, y, z)
    xyz = np.array([[float(r[c]) for c in "xyz"] for r in rows]).reshape(T, S1, 1, 3)
    assert (ids == np.array([f"take{i}" for i in traj])[:, None]).all()
    assert np.allclose(t, 100.0 + H * np.arange(S1)[None], rtol=0, atol=1e-12 * 100)  # its own time stamps
    assert (q[..., 0] >= 0).all()  # the sign convention: w >= 0
    back = so3.from_quaternion(torch.from_numpy(q)).numpy()
    assert np.abs(back - R).max() <= 1e-12 * np.abs(R).max()
    assert np.abs(xyz - p).max() <= 1e-12 * np.abs(p).max()
    # the exported file is a recording again: imported, it holds the predictions
    again = run_main(
        "data",
        "dataset=import",
        f"dataset.path={folder / 'predictions.csv'}",
        "dataset.rotation=xyzw",
        cwd=cwd,
        ok=True,
    ).stdout
    assert "2 trajectories x 20 steps on SE(3)" in again
    (cached,) = [
        c
        for c in (cwd / "outputs" / "data").glob("import-*.h5")
        if c.stat().st_mtime >= (folder / "predictions.csv").stat().st_mtime
    ]
    ds = load_dataset(cached)
    assert np.abs(ds.R - R).max() <= 1e-12 and np.abs(ds.p - p).max() <= 1e-12 * np.abs(p).max()
    # and `liedfl eval` evaluates the rollout over the same trajectories
    run_main("eval", f"run={run}", f"rollout={folder}", "ui.progress=false", "eval.plots=false", cwd=cwd, ok=True)
    assert (folder / "eval.csv").is_file()


def test_rollout_split_options_and_npz_export(trained_on_two_recordings, run_main):
    cwd, run = trained_on_two_recordings
    before = set((run / "rollouts").iterdir()) if (run / "rollouts").exists() else set()
    # a rollout trains nothing: dataset.test_fraction=1.0 and dataset.n_test=T are accepted (every trajectory);
    # a new file of 3 recordings: all 3, although the smoke-trained run caps its own rollouts at 2
    write_csv(cwd / "new.csv", n_traj=3, n_samples=21, rotation="xyzw")
    new_file = ["dataset=import", "dataset.path=new.csv", "dataset.rotation=xyzw"]
    for args in ([*IMPORT, "dataset.test_fraction=1.0", "split=test"], [*new_file, "dataset.n_test=3"]):
        run_main(
            "rollout", f"run={run}", *args, "export=npz", "ui.progress=false", "eval.plots=false", cwd=cwd, ok=True
        )
    new = sorted(set((run / "rollouts").iterdir()) - before)
    assert len(new) == 2
    for folder, want in zip(new, ([0, 1], [0, 1, 2])):
        z = np.load(folder / "predictions.npz")
        with h5py.File(folder / "rollout.h5", "r") as f:
            R, traj = f["model/R"][:], f["traj_index"][:]
        assert traj.tolist() == z["trajectory"].tolist() == want
        assert z["q"].shape == (*R.shape[:3], 4) and z["p"].shape == (*R.shape[:3], 3)
        back = so3.from_quaternion(torch.from_numpy(z["q"][..., WXYZ])).numpy()
        assert np.abs(back - R).max() <= 1e-12
    # the run's own data: test by default; split=train / all on request (recorded for `liedfl eval`)
    run_main(
        "rollout", f"run={run}", "split=train", "steps=5", "ui.progress=false", "eval.plots=false", cwd=cwd, ok=True
    )
    (folder,) = sorted(set((run / "rollouts").iterdir()) - before - set(new))
    assert folder.name.endswith("_train_steps5")
    with h5py.File(folder / "rollout.h5", "r") as f:
        ds_run = load_dataset(cwd / json.loads((run / "summary.json").read_text())["dataset_path"])
        assert f["traj_index"][:].tolist() == ds_run.train_idx.tolist()
    assert json.loads((folder / "source.json").read_text())["split"] == "train"
    run_main("eval", f"run={run}", f"rollout={folder}", "ui.progress=false", "eval.plots=false", cwd=cwd, ok=True)
    bad = run_main("rollout", f"run={run}", "split=some", cwd=cwd)
    assert bad.returncode == 2 and "split='some'" in bad.stderr and "Traceback" not in bad.stderr
    bad = run_main("rollout", f"run={run}", "export=xls", cwd=cwd)
    assert bad.returncode == 2 and "export='xls'" in bad.stderr and "Traceback" not in bad.stderr
