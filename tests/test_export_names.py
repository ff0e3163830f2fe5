"""`export=csv|npz` keeps the recording's trajectory names and time stamps (issue 38): the import records
them per trajectory (also per piece of `chunk_steps`), the export writes them back; a dataset without
them keeps the index and its own `t`. (End to end, with a rollout: tests/test_rollout_export.py.)"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from own_data import H, write_csv

from helpers import main_in_process
from liedfl_cli.commands.export import sample_times, trajectory_labels
from liedfl_cli.data.hdf5 import load_dataset


def test_the_import_records_names_and_first_stamps_per_piece(tmp_path):
    write_csv(tmp_path / "log.csv", n_traj=2, n_samples=21, rotation="wxyz", t0=100.0)
    code, trace = main_in_process(
        "data", "dataset=import", "dataset.path=log.csv", "dataset.rotation=wxyz", "dataset.chunk_steps=9",
        "ui.progress=false", cwd=tmp_path,
    )  # fmt: skip
    assert code == 0, trace
    (cached,) = (tmp_path / "outputs" / "data").glob("import-*.h5")
    ds = load_dataset(cached)
    assert ds.params["trajectory_names"] == ["take0", "take0", "take1", "take1"]
    assert np.allclose(ds.params["trajectory_start_s"], [100.0, 100.0 + 10 * H] * 2, rtol=0, atol=1e-9)
    traj = np.array([3, 0])
    assert trajectory_labels(ds, traj) == ["take1", "take0"]
    t = sample_times(ds, traj, ds.h, 4)
    assert np.allclose(t, [100.0 + 10 * H + H * np.arange(4), 100.0 + H * np.arange(4)], rtol=0, atol=1e-9)


def test_without_names_the_index_and_the_datasets_own_t():
    ds = SimpleNamespace(params={}, n_trajectories=3, t=2.0 + 0.1 * np.arange(6))
    traj = np.array([2, 1])
    assert trajectory_labels(ds, traj) is None
    assert np.allclose(sample_times(ds, traj, 0.1, 4), np.tile(2.0 + 0.1 * np.arange(4), (2, 1)))
    stale = SimpleNamespace(params={"trajectory_names": ["a"], "trajectory_start_s": [1.0]}, n_trajectories=3, t=None)
    assert trajectory_labels(stale, traj) is None  # names that do not match the trajectories are not used
    assert np.allclose(sample_times(stale, traj, 0.5, 3), [[0.0, 0.5, 1.0]] * 2)
