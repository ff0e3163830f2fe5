"""`liedfl report` over a small real sweep contains every run and writes its figures."""

import csv

import pytest


@pytest.fixture
def _liedfl(run_main):
    """_liedfl(args, cwd) -> CompletedProcess of `liedfl *args` run in-process (`run_main`; the sweep
    runs its jobs in this process too: Hydra's basic launcher)."""
    return lambda args, cwd: run_main(*args, cwd=cwd)


def test_report_over_small_sweep(tmp_path, _liedfl):
    r = _liedfl(
        ["train", "-m", "budget=smoke", "ui.progress=false", "eval.plots=false", "dataset.train_steps=4,8", "seed=0,1"],
        tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    sweeps = list((tmp_path / "outputs" / "multirun").iterdir())
    assert len(sweeps) == 1
    r = _liedfl(["report", f"sweep={sweeps[0]}"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    with open(sweeps[0] / "report.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4
    assert sorted(int(r["train_steps"]) for r in rows) == [4, 4, 8, 8]
    assert all(float(r["rel_rot_error_mean"]) > 0 and r["model"] == "liedflnn" for r in rows)
    for name in ("error_vs_training_length", "error_vs_time", "sphere_per_model", "error_vs_speed"):
        assert (sweeps[0] / "plots" / f"{name}.png").stat().st_size > 1000
    assert "4 runs" in (sweeps[0] / "report.md").read_text()


def test_report_rejects_missing_sweep(tmp_path, _liedfl):
    r = _liedfl(["report", f"sweep={tmp_path / 'nope'}"], tmp_path)
    assert r.returncode == 2
    assert "no such multirun directory" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "nope").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    r = _liedfl(["report", f"sweep={empty}"], tmp_path)
    assert r.returncode == 2 and "no finished runs" in r.stderr
