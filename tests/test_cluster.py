"""Sweeps through submitit (the `cluster` extra: hydra-submitit-launcher), tested without a cluster.

`hydra/launcher=submitit_local` and liedfl's `liedfl_local` run each job in its own process through
the same submitit engine that `submitit_slurm` / `liedfl_slurm` use on SLURM: the per-job folders,
status.json, failures counted in the exit code and `liedfl report` over the sweep are the same code
paths. SLURM itself is not available here; `liedfl_slurm` is checked down to the sbatch script
submitit would submit (docs/cluster.md).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.commands import status

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("hydra_plugins.hydra_submitit_launcher") is None,
    reason='hydra-submitit-launcher is not installed: pip install -e ".[cluster]" (CI installs it, see .ci/run)',
)

FAST = ["ui.progress=false", "eval.plots=false", "rollout.reference=false"]


def liedfl(*args: str, cwd: Path, threads: str | None = "1", prelude: str = "") -> subprocess.CompletedProcess:
    """`liedfl *args` in a new process; `prelude`: Python run in it before `main()`."""
    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR", "OMP_NUM_THREADS")}
    env.update(MPLBACKEND="Agg", COLUMNS="200")
    if threads is not None:
        env["OMP_NUM_THREADS"] = threads
    cmd = [sys.executable, "-c", f"{prelude}from liedfl_cli.cli import main; main()", *args]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def _only_sweep(cwd: Path) -> Path:
    (sweep_dir,) = (cwd / "outputs" / "multirun").iterdir()
    return sweep_dir


def _status(job: Path) -> dict:
    return json.loads((job / "status.json").read_text())


# ----------------------------------------------------------------------------- the sweep
@pytest.fixture(scope="module")
def smoke_sweep(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """`liedfl train -m seed=0,1 budget=smoke hydra/launcher=submitit_local` (the plugin's own config)."""
    cwd = tmp_path_factory.mktemp("submitit")
    proc = liedfl("train", "-m", "seed=0,1", "budget=smoke", "hydra/launcher=submitit_local", *FAST, cwd=cwd)
    return proc, _only_sweep(cwd)


def test_submitit_local_runs_every_job_in_its_own_folder(smoke_sweep):
    proc, sweep_dir = smoke_sweep
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert f"all 2 jobs finished: {Path('outputs') / 'multirun' / sweep_dir.name}" in proc.stdout
    for job in ("0", "1"):
        st = _status(sweep_dir / job)
        assert st["status"] == "ok" and st["exit_code"] == 0, st
        assert (sweep_dir / job / "checkpoints" / "last.pt").is_file() and (sweep_dir / job / "eval.csv").is_file()
    assert [d.name for d in status.job_dirs(sweep_dir)] == ["0", "1"]  # (.submitit/ holds no job)
    # the jobs ran in submitit's processes: one result and one log per job under .submitit/
    assert len(list(sweep_dir.glob(".submitit/*/*_result.pkl"))) == 2
    logs = sorted(sweep_dir.glob(".submitit/*/*_log.out"))
    assert len(logs) == 2 and all("submitit INFO" in p.read_text() for p in logs)


def test_report_over_a_submitit_sweep_lists_both_runs(smoke_sweep, tmp_path, run_main):
    _, sweep_dir = smoke_sweep
    proc = run_main(
        "report", f"sweep={sweep_dir}", "plots=false", cwd=tmp_path
    )  # (in this process: test_report.py runs it as one)
    assert proc.returncode == 0, proc.stderr
    md = (sweep_dir / "report.md").read_text()
    assert "\n2 runs.\n" in md and "Failed runs" not in md
    rows = list(csv.DictReader((sweep_dir / "report.csv").read_text().splitlines()))
    assert len(rows) == 2, rows  # one row per run
    assert [(r["run"], r["seed"]) for r in rows] == [("0", "0"), ("1", "1")], rows
    assert all(r["setting"].startswith("budget=smoke") for r in rows), rows  # (the seed has its own column)


# ----------------------------------------------------------------------------- failures
@pytest.fixture(scope="module")
def failing_sweep(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """liedfl's `liedfl_local` (one thread per job through `setup`; OMP_NUM_THREADS unset here):
    job 0 fails validation, job 1 trains."""
    cwd = tmp_path_factory.mktemp("submitit_fail")
    args = ["train", "-m", "train.epochs=-1,2", "budget=smoke", "hydra/launcher=liedfl_local", *FAST]
    proc = liedfl(*args, cwd=cwd, threads=None)
    return proc, _only_sweep(cwd)


def test_a_failing_submitit_job_is_recorded_and_counted(failing_sweep):
    proc, sweep_dir = failing_sweep
    assert "Traceback" not in proc.stderr, proc.stderr
    assert _status(sweep_dir / "0") == {
        "status": "failed",
        "exit_code": 2,
        "error": "train.epochs=-1: must be an integer >= 0",
    }
    assert _status(sweep_dir / "1")["status"] == "ok"
    assert proc.returncode == 1  # the number of failed jobs
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    # the job printed its error into its submitit log; the launching process repeats it
    assert errors == [
        "error: [job 0] train.epochs=-1: must be an integer >= 0",
        f"error: 1 of 2 jobs failed: {Path('outputs') / 'multirun' / sweep_dir.name / '0'}",
    ]
    assert status.sweep_summary(sweep_dir)[:2] == (1, 2)


def test_liedfl_local_runs_one_thread_per_job(failing_sweep):
    """OMP_NUM_THREADS=1 comes from the launcher's `setup` lines, not from the caller's environment."""
    _, sweep_dir = failing_sweep
    assert _status(sweep_dir / "1")["threads"] == 1


def test_report_lists_the_failed_submitit_job(failing_sweep, tmp_path, run_main):
    _, sweep_dir = failing_sweep
    proc = run_main("report", f"sweep={sweep_dir}", "plots=false", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "failed runs (1)" in proc.stdout and "0: train.epochs=-1: must be an integer >= 0" in proc.stdout
    assert "1 runs, 1 failed." in (sweep_dir / "report.md").read_text()


def test_a_job_that_dies_outside_liedfl_is_one_line_and_a_nonzero_exit(tmp_path):
    """A job that never returns (here its shell set-up exits; on a cluster: killed, out of memory, out of
    time) makes submitit raise in the launching process: one line, the sweep summary, exit code >= 1."""
    # submitit waits 15 s (`Job._results_timeout_s`, for slow network file systems) for the result of a
    # job that has ended before it gives up; the local file system here needs no such grace
    proc = liedfl(
        "train", "-m", "seed=0", "budget=smoke", "hydra/launcher=liedfl_local", "hydra.launcher.setup=[exit 3]",
        *FAST, cwd=tmp_path, prelude="import submitit.core.core as c; c.Job._results_timeout_s = 0; ",
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: launcher: UncompletedJobError: "), lines
    assert "job logs: " in lines[0]


# ----------------------------------------------------------------------------- SLURM (no cluster here)
def _sbatch_script(tmp_path: Path, overrides: list[str], n_jobs: int = 3) -> str:
    """The sbatch script submitit would submit for a sweep of n_jobs under `liedfl_slurm`: the
    composed launcher config, instantiated as Hydra does, with submitit's executor built by the
    plugin's own `launch` (only the submission itself is replaced; a dummy `srun` on PATH stands in
    for SLURM, which submitit looks for)."""
    from unittest import mock

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 1\n")
    (bin_dir / "srun").chmod(0o755)
    with mock.patch.dict(os.environ, {"PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}):
        return _sbatch_text(tmp_path, overrides, n_jobs)


def _sbatch_text(tmp_path: Path, overrides: list[str], n_jobs: int) -> str:
    from unittest import mock

    import submitit
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.utils import instantiate
    from omegaconf import open_dict

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "train",
            [f"hydra.sweep.dir={tmp_path / 'sweep'}", "hydra/launcher=liedfl_slurm", *overrides],
            return_hydra_config=True,
        )
    with open_dict(cfg):
        cfg.hydra.job.config_name = "train"
    launcher = instantiate(cfg.hydra.launcher)
    launcher.setup(hydra_context=None, task_function=lambda c: None, config=cfg)
    seen = {}

    def map_array(executor, fn, *args):
        seen["executor"] = executor
        return []

    with mock.patch.object(submitit.AutoExecutor, "map_array", map_array):
        launcher.launch([[f"seed={i}"] for i in range(n_jobs)], initial_job_idx=0)
    slurm = seen["executor"]._executor
    slurm.parameters["map_count"] = n_jobs  # (set by submitit when it submits a job array)
    return slurm._make_submission_file_text("python -u -m submitit.core._submit FOLDER", "uid")


def test_liedfl_slurm_builds_the_sbatch_script_a_user_expects(tmp_path):
    text = _sbatch_script(tmp_path, [])
    lines = text.splitlines()
    for expected in (
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --time=720",
        "#SBATCH --mem=8GB",
        "#SBATCH --array=0-2%3",
        "#SBATCH --job-name=liedfl-train",
        "export OMP_NUM_THREADS=1",
        "export MKL_NUM_THREADS=1",
    ):
        assert expected in lines, (expected, text)
    assert not any(ln.startswith("#SBATCH --partition") for ln in lines)  # the cluster's default


def test_liedfl_slurm_settings_a_user_edits(tmp_path):
    text = _sbatch_script(
        tmp_path,
        [
            "hydra.launcher.partition=cpu",
            "hydra.launcher.timeout_min=2880",
            "hydra.launcher.cpus_per_task=4",
            "hydra.launcher.mem_gb=16",
            "hydra.launcher.array_parallelism=10",
            "hydra.launcher.account=proj42",
        ],
        n_jobs=40,
    )
    lines = text.splitlines()
    for expected in (
        "#SBATCH --partition=cpu",
        "#SBATCH --time=2880",
        "#SBATCH --cpus-per-task=4",
        "#SBATCH --mem=16GB",
        "#SBATCH --array=0-39%10",
        "#SBATCH --account=proj42",
        "export OMP_NUM_THREADS=4",  # threads follow the CPUs of the job
    ):
        assert expected in lines, (expected, text)


def test_launcher_configs_compose_and_name_the_plugin():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    for name, target in (("liedfl_local", "LocalLauncher"), ("liedfl_slurm", "SlurmLauncher")):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("train", [f"hydra/launcher={name}"], return_hydra_config=True)
        assert cfg.hydra.launcher._target_ == f"hydra_plugins.hydra_submitit_launcher.submitit_launcher.{target}"
        assert "export OMP_NUM_THREADS=1" in list(cfg.hydra.launcher.setup)


# ----------------------------------------------------------------------------- time limits
def test_submitits_stop_inside_a_job_is_a_recorded_failure():
    """submitit's handler of the warning signal raises UncompletedJobError in the job when training is
    not running (data generation, rollout): one line, and the job returns (its status records it)."""
    from submitit.core.utils import UncompletedJobError

    from liedfl_cli.config.preflight import classify

    message, code = classify(UncompletedJobError("Job not requeued because: timed-out too many times."))
    assert code == 2
    assert message == (
        "stopped by the cluster (Job not requeued because: timed-out too many times): "
        "`liedfl train resume=<job folder>` continues from its last checkpoint"
    )


@pytest.mark.slow
def test_a_job_at_its_time_limit_saves_a_checkpoint_and_resumes(tmp_path):
    """liedfl_local with timeout_min=1: submitit sends SIGUSR2 30 s before the limit; training stops
    after the epoch with a checkpoint, the job records it, and `liedfl train resume=<job>` finishes
    it (status ok: the report counts it). About a minute."""
    proc = liedfl(
        "train", "-m", "seed=0", "budget=smoke", "train.epochs=1000000", "hydra/launcher=liedfl_local",
        "hydra.launcher.timeout_min=1", *FAST, cwd=tmp_path,
    )  # fmt: skip
    sweep_dir = _only_sweep(tmp_path)
    st = _status(sweep_dir / "0")
    assert proc.returncode == 1 and st["status"] == "failed" and st["exit_code"] == 140, (st, proc.stderr)
    assert st["error"].startswith("SIGUSR2 (submitit: the job's time limit is near, or it is preempted): training")
    assert "checkpoint saved; resume with: liedfl train resume=" in st["error"]
    epoch = int(st["error"].split("after epoch ")[1].split("/")[0])
    done = liedfl("train", f"resume={sweep_dir / '0'}", f"epochs={epoch + 2}", "ui.progress=false", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert _status(sweep_dir / "0")["status"] == "ok"
    assert status.sweep_summary(sweep_dir)[:2] == (0, 1)


# ----------------------------------------------------------------------------- paper reproduction
@pytest.mark.slow
def test_reproduce_paper_farms_its_sweeps_out_through_a_launcher(tmp_path):
    """scripts/reproduce_paper.sh passes a launcher through to every sweep; its output feeds
    `liedfl report` and summarize_paper.py unchanged (Exp 3 only, smoke budget: about a minute)."""
    bin_dir = tmp_path / "bin"  # `liedfl` on PATH = this checkout (whatever is installed)
    bin_dir.mkdir()
    (bin_dir / "liedfl").write_text(
        f'#!/bin/sh\nexec {sys.executable} -c "from liedfl_cli.cli import main; main()" "$@"\n'
    )
    (bin_dir / "liedfl").chmod(0o755)
    root = Path(__file__).resolve().parent.parent
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR",)}
    env.update(
        PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}",
        PYTHONPATH=f"{root}{os.pathsep}{env.get('PYTHONPATH', '')}",
        OMP_NUM_THREADS="1",
        MPLBACKEND="Agg",
        LIEDFL_PAPER_DIR=str(tmp_path / "paper"),
        LIEDFL_DATA_DIR=str(tmp_path / "data"),
        LIEDFL_EXPERIMENTS="exp3_manifold",
        LIEDFL_SWEEPS_AT_ONCE="1",
    )
    proc = subprocess.run(
        ["bash", str(root / "scripts" / "reproduce_paper.sh"), "budget=smoke", "hydra/launcher=liedfl_local"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    sweep_dir = tmp_path / "paper" / "exp3_manifold"
    assert len(list(sweep_dir.glob(".submitit/*/*_result.pkl"))) == 3  # the jobs went through submitit
    assert "\n3 runs.\n" in (sweep_dir / "report.md").read_text()
    summary = (tmp_path / "paper" / "summary.md").read_text()
    assert "### Exp 3" in summary and all(m in summary for m in ("liedflnn", "euclidean_dflnn", "neural_ode"))


@pytest.mark.slow
def test_ctrl_c_during_a_local_submitit_sweep_is_one_line_and_counts_the_job(tmp_path):
    """Ctrl-C in a terminal: SIGINT to the launching process and to the local jobs (one process group).
    The launching process stops waiting with one line (exit 130). submitit's local controller passes
    the interrupt on to its job and kills it a second later, so the job records `interrupted` if it can
    (usually without the end-of-epoch checkpoint: the second SIGINT stops it at once) and counts as failed.
    submitit's controller's own KeyboardInterrupt traceback goes to .submitit/local_controller.err."""
    import signal
    import time

    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR")}
    env.update(OMP_NUM_THREADS="1", MPLBACKEND="Agg", COLUMNS="200")
    args = ["train", "-m", "seed=0", "budget=smoke", "train.epochs=1000000", "hydra/launcher=liedfl_local", *FAST]
    with open(tmp_path / "out.txt", "w") as out, open(tmp_path / "err.txt", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", "from liedfl_cli.cli import main; main()", *args],
            cwd=tmp_path,
            env=env,
            stdout=out,
            stderr=err,
            start_new_session=True,  # its own process group, as a terminal's foreground job
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # (SIGINT may be ignored here)
        )
        deadline = time.time() + 120
        while time.time() < deadline and not list(tmp_path.glob("outputs/multirun/*/0/train_metrics.csv")):
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=60) == 130
    job = _only_sweep(tmp_path) / "0"
    time.sleep(3)  # (the job is killed within about a second)
    text = (tmp_path / "err.txt").read_text()
    assert "Traceback" not in text
    assert "KeyboardInterrupt" in (job.parent / ".submitit" / "local_controller.err").read_text()
    assert [ln for ln in text.splitlines() if ln.strip()] == [
        f"error: interrupted: stopped waiting for the jobs of {Path('outputs') / 'multirun' / job.parent.name} (jobs"
        " that were not interrupted go on; `liedfl report sweep="
        f"{Path('outputs') / 'multirun' / job.parent.name}` lists them once they are done)"
    ]
    if (job / "status.json").is_file():  # (stopped at once, or at the end of an epoch the second signal did not cut)
        st = _status(job)
        assert st["status"] == "interrupted" and st["exit_code"] == 130, st
        assert st["error"] == "interrupted" or st["error"].startswith("SIGINT: training stopped after epoch"), st
    assert status.sweep_summary(job.parent)[:2] == (1, 1)
