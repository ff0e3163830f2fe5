"""End to end through the `liedfl` command (cwd = a temporary directory), plus `run_train` called
in-process on a composed config. Everything runs on the smoke budget. The commands run `main()` in
this process (the first train in the module fixture, the rest through `run_main`: the same code without
a new interpreter per call); `--help` and an unknown command run the installed command as a process,
and so do test_tutorial.py (`liedfl data`, `train`, `export` to the end) and test_packaging.py (the
wheel's train); test_signals_phases.py and test_hostile.py run rollout and eval as processes."""

from __future__ import annotations

import csv
import math
import shutil
import subprocess
from pathlib import Path

import h5py
import pytest
from omegaconf import OmegaConf

from helpers import compose_config, main_in_process, run_cli

FAST = ["budget=smoke", "ui.progress=false"]
PLOTS = ["error_vs_step", "drift_vs_step", "sphere", "predicted_vs_true"]


def liedfl(*args: str, cwd: Path, ok: bool = True) -> subprocess.CompletedProcess:
    return run_cli(*args, cwd=cwd, ok=ok)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """`liedfl train budget=smoke ui.progress=false` in a fresh directory -> its run dir.

    In this process (`main()`, the entry point's code, with `cli_env()`'s variables): a new interpreter
    costs ~3.5 s of imports. The installed `liedfl train` runs to the end as a process in
    test_tutorial.py (exit 0, no traceback, the files the page names) and as the built wheel in
    test_packaging.py; `--help` and an unknown command below go through the installed command."""
    cwd = tmp_path_factory.mktemp("train_cli")
    with pytest.MonkeyPatch.context() as mp:
        for key in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR"):
            mp.delenv(key, raising=False)
        for key, value in (("MPLBACKEND", "Agg"), ("COLUMNS", "200")):
            mp.setenv(key, value)
        code, traceback = main_in_process("train", *FAST, cwd=cwd)
    assert code == 0 and not traceback, traceback
    runs = sorted((cwd / "outputs" / "runs").iterdir())
    assert len(runs) == 1, runs
    return runs[0]


def test_train_writes_the_run_directory(trained):
    run = trained
    for rel in [
        ".hydra/config.yaml",
        "checkpoints/last.pt",
        "train_metrics.csv",
        "rollout.h5",
        "eval.csv",
        "eval.md",
        "components.json",
        *(f"plots/{p}.png" for p in PLOTS),
    ]:
        f = run / rel
        assert f.is_file() and f.stat().st_size > 0, f"missing or empty: {rel}"
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    assert cfg.train.epochs == 2 and cfg.ui.progress is False
    with open(run / "train_metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and all(math.isfinite(float(r["loss"])) for r in rows)
    with open(run / "eval.csv") as f:
        models = [r["model"] for r in csv.DictReader(f)]
    assert models[0] == "model"
    # the dataset went to ./outputs/data (LIEDFL_DATA_DIR unset)
    assert len(list((run.parents[2] / "outputs" / "data").glob("*.h5"))) == 1
    assert not [p for p in run.rglob("*") if ".tmp" in p.name]


def test_rollout_writes_a_new_folder(trained, run_main):
    """`liedfl rollout` writes <run>/rollouts/<name>/ (rollout.h5 and its evaluation) each time and leaves
    the run's own rollout.h5 and evaluation byte for byte as they were."""
    run = trained
    own = {name: (run / name).read_bytes() for name in ("rollout.h5", "eval.csv", "eval.md", "eval_curves.json")}
    with h5py.File(run / "rollout.h5") as f:
        assert int(f.attrs["steps"]) != 15
    args = ("rollout", f"run={run}", "steps=15", "ui.progress=false", "eval.plots=false")
    for _ in range(2):  # in this process (test_signals_phases.py rolls out in a process)
        run_main(*args, cwd=run.parents[2], ok=True)
    new = sorted(d for d in (run / "rollouts").iterdir() if "_steps15" in d.name)
    assert len(new) == 2 and all(d.name.endswith(("_steps15", "_steps15_2")) for d in new), new
    for d in new:
        with h5py.File(d / "rollout.h5") as f:
            assert int(f.attrs["steps"]) == 15
            assert f["model/R"].shape[1] == 16
        with open(d / "eval.csv") as f:
            rows = list(csv.DictReader(f))
        assert rows[0]["model"] == "model" and int(rows[0]["rollout_steps"]) == 15
        assert "steps 0..15" in (d / "eval.md").read_text()
    assert {name: (run / name).read_bytes() for name in own} == own
    assert not [p for p in run.rglob("*") if ".tmp" in p.name]


def test_a_failed_rollout_leaves_no_folder(trained, monkeypatch):
    """`liedfl rollout` removes its new folder when anything fails after creating it."""
    from liedfl_cli.commands import rollout as rollout_mod

    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    before = sorted(p.name for p in (trained / "rollouts").iterdir()) if (trained / "rollouts").exists() else None
    cfg = compose_config("rollout", [f"run={trained}", "steps=9", "ui.progress=false"])
    monkeypatch.setattr(rollout_mod, "rollout_and_save", broken)
    with pytest.raises(KeyboardInterrupt):
        rollout_mod.run_rollout(cfg)
    after = sorted(p.name for p in (trained / "rollouts").iterdir()) if (trained / "rollouts").exists() else None
    assert after == before


def test_eval_rewrites_eval_csv(trained, tmp_path, run_main):
    run = trained
    (run / "eval.csv").write_text("stale\n")
    run_main("eval", f"run={run}", "ui.progress=false", "eval.plots=false", cwd=tmp_path, ok=True)  # another cwd
    with open(run / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and rows[0]["model"] == "model" and math.isfinite(float(rows[0]["rel_rot_error_mean"]))
    assert list(tmp_path.iterdir()) == []  # the recorded dataset was found; nothing regenerated here


def test_eval_of_another_rollout_writes_next_to_it(trained, tmp_path, run_main):
    """`liedfl eval run=<run> rollout=<file or folder>` evaluates that file and writes next to it only."""
    run = trained

    def liedfl(*args: str, cwd: Path, ok: bool = True) -> subprocess.CompletedProcess:
        return run_main(*args, cwd=cwd, ok=ok)

    liedfl("rollout", f"run={run}", "steps=12", "ui.progress=false", "eval.plots=false", cwd=tmp_path)
    folder = next(d for d in (run / "rollouts").iterdir() if d.name.endswith("_steps12"))
    (folder / "eval.csv").unlink()
    own = (run / "eval.csv").read_bytes()
    liedfl("eval", f"run={run}", f"rollout={folder}", "ui.progress=false", "eval.plots=false", cwd=tmp_path)
    with open(folder / "eval.csv") as f:
        assert int(next(csv.DictReader(f))["rollout_steps"]) == 12
    assert (run / "eval.csv").read_bytes() == own
    proc = liedfl("eval", f"run={run}", f"rollout={folder / 'nope.h5'}", "ui.progress=false", cwd=tmp_path, ok=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert [line for line in proc.stderr.splitlines() if line.strip()] == [
        f"error: rollout={folder / 'nope.h5'}: no such rollout file"
    ]


def test_eval_refuses_a_rollout_that_does_not_match_the_dataset(trained, tmp_path, run_main):
    """Issue 11: a rollout.h5 with one predicted trajectory for two test trajectories is a one-line error
    naming the file and field (exit 2), and the run's evaluation stays as it was."""
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    with h5py.File(run / "rollout.h5", "r+") as f:
        assert len(f["traj_index"]) == 2
        for k in ("R", "p"):
            a = f[f"model/{k}"][:1]
            del f[f"model/{k}"]
            f[f"model/{k}"] = a
    before = (run / "eval.csv").read_bytes()
    proc = run_main("eval", f"run={run}", "ui.progress=false", cwd=tmp_path)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"error: {run / 'rollout.h5'}: dataset 'model/R' holds 1 trajectories"), lines[0]
    assert (run / "eval.csv").read_bytes() == before


def test_data_writes_one_dataset(tmp_path, run_main):
    """In this process (`run_main`); test_hostile.py's `ctrl-c-during-dataset-write` runs `liedfl data` as one."""
    from liedfl_cli.data.hdf5 import load_dataset

    run_main("data", "dataset=heavy_se3", *FAST, cwd=tmp_path, ok=True)
    files = [p for p in (tmp_path / "outputs").rglob("*") if p.is_file()]
    assert len(files) == 1 and files[0].parent == tmp_path / "outputs" / "data", files
    assert files[0].suffix == ".h5" and files[0].name.startswith("heavy_se3-")
    ds = load_dataset(files[0])
    assert ds.n_se3 == 1 and ds.n_trajectories == 6


def test_multirun_makes_one_run_dir_per_job(tmp_path, run_main):
    """Hydra's basic launcher in this process (`run_main`); test_cluster.py's sweeps go through processes."""
    run_main("train", "-m", *FAST, "eval.plots=false", "seed=0,1", cwd=tmp_path, ok=True)
    sweeps = list((tmp_path / "outputs" / "multirun").iterdir())
    assert len(sweeps) == 1
    jobs = sorted(p for p in sweeps[0].iterdir() if p.is_dir())
    assert [p.name for p in jobs] == ["0", "1"]
    seeds = []
    for job in jobs:
        assert (job / "checkpoints" / "last.pt").is_file() and (job / "eval.csv").is_file()
        assert not (job / "plots").exists()
        seeds.append(OmegaConf.load(job / ".hydra" / "config.yaml").seed)
    assert seeds == [0, 1]
    assert not (tmp_path / "outputs" / "runs").exists()


def test_help_and_unknown_command(tmp_path):
    proc = liedfl("--help", cwd=tmp_path)
    assert "train" in proc.stdout and "rollout" in proc.stdout
    proc = liedfl("nonsense", cwd=tmp_path, ok=False)
    assert proc.returncode == 2
    assert "nonsense" in proc.stderr and "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_run_train_in_process(tmp_path):
    from liedfl_cli.commands.train import run_train
    from liedfl_cli.config.runs import load_run
    from liedfl_cli.config.schema import validate

    cfg = compose_config(
        "train",
        [
            *FAST,
            "eval.plots=false",
            f"paths.output_dir={tmp_path / 'run'}",
            f"paths.data_dir={tmp_path / 'data'}",
        ],
    )
    validate(cfg)
    summary = run_train(cfg)
    run = tmp_path / "run"
    assert summary["run_dir"] == str(run)
    assert Path(summary["dataset_path"]).parent == tmp_path / "data"
    assert math.isfinite(summary["final_loss"])
    assert summary["timings"]["epochs"] == 2 and summary["timings"]["parameters"] > 0
    assert summary["rollout"]["model"]["n_failed"] >= 0
    assert [r["model"] for r in summary["eval"]][0] == "model"
    for rel in ("checkpoints/last.pt", "rollout.h5", "eval.csv", "eval.md", "summary.json", "train_metrics.csv"):
        assert (run / rel).is_file(), rel
    assert not (run / "plots").exists()
    run_cfg, model, dataset, run_dir = load_run(run)
    assert run_cfg.train.epochs == 2 and dataset.n_trajectories == 6
