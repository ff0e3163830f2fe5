"""scripts/reproduce_paper.sh's jobs, its plan mode and its times.csv (scripts/paper_plan.py)."""

from __future__ import annotations

import copy
import csv
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "reproduce_paper.sh"
ALL = ["exp1_euler_vs_lie", "exp2_discrete_vs_continuous", "exp3_manifold", "exp4_mocap", "exp5_control"]


def _plan_module():
    if "paper_plan" in sys.modules:
        return sys.modules["paper_plan"]
    spec = importlib.util.spec_from_file_location("paper_plan", ROOT / "scripts" / "paper_plan.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["paper_plan"] = mod  # (its dataclass looks its module up there)
    spec.loader.exec_module(mod)
    return mod


# (experiment, extra overrides) -> (validated?, its jobs): `paper_plan.jobs` composes each job with
# Hydra (seconds per experiment), and its answer depends on the configs alone (not on ROOT or the
# environment); each experiment is composed (and validated, when asked) once per test process.
_JOBS: dict[tuple[str, tuple[str, ...]], tuple[bool, list]] = {}


def _composed_once(real):
    def jobs(experiments, extra, check=False):
        out = []
        for exp in experiments:  # `jobs` composes each experiment on its own, in order
            key = (exp, tuple(extra))
            hit = _JOBS.get(key)
            if hit is None or (check and not hit[0]):
                hit = _JOBS[key] = (check, real([exp], list(extra), check))
            out += copy.deepcopy(hit[1])  # copies: callers may change a job
        return out

    return jobs


@pytest.fixture(autouse=True)
def own_output_folder(tmp_path, monkeypatch):
    """`full` writes its runs under ROOT/outputs/paper_full and clears a job's folder before a fresh
    start: every test here gets a ROOT of its own, never the checkout's outputs. `jobs` composes
    each experiment once per process (`_composed_once`)."""
    plan = _plan_module()
    monkeypatch.setattr(plan, "jobs", _composed_once(plan.jobs))
    monkeypatch.setattr(plan, "ROOT", tmp_path)
    monkeypatch.setattr(plan, "FULL_DIR", tmp_path / "outputs" / "paper_full")
    # run_full sets LIEDFL_DATA_DIR when it is unset: here through monkeypatch, so no later test inherits it
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))


@pytest.fixture(scope="module")
def exp2_jobs():
    """Exp 2's jobs, composed and validated once for the tests of `full` (composition takes seconds)."""
    return _plan_module().jobs(["exp2_discrete_vs_continuous"], [], check=True)


@pytest.fixture
def cached_jobs(exp2_jobs, monkeypatch):
    """`paper_plan.jobs` answering Exp 2 from the cache (copies: callers may change a job)."""
    plan = _plan_module()
    real = plan.jobs

    def jobs(experiments, extra, check=False):
        if list(experiments) == ["exp2_discrete_vs_continuous"] and not extra:
            return [copy.deepcopy(j) for j in exp2_jobs]
        return real(experiments, extra, check)

    monkeypatch.setattr(plan, "jobs", jobs)
    return plan


def test_every_job_of_the_reproduction_composes_with_its_budget():
    """Every job the script launches (Exps 1-5, every baseline, the articulated Exp 4) composes and
    validates (as `liedfl train` checks it before the job starts), and a budget override reaches them."""
    plan = _plan_module()
    full = plan.jobs(ALL, [], check=True)
    smoke = plan.jobs(ALL[3:], ["budget=smoke"])
    assert [j.key for j in full][-3:] == [j.key for j in smoke] and len({j.key for j in full}) == len(full)
    per_exp = {e: [j for j in full if j.experiment == e] for e in ALL}
    assert {e: len(js) for e, js in per_exp.items()} == {ALL[0]: 6, ALL[1]: 16, ALL[2]: 4, ALL[3]: 2, ALL[4]: 1}
    assert {j.model.split()[0] for j in per_exp[ALL[1]]} == {
        "liedflnn",
        "glnn_rk4",
        "glnn_lie_midpoint",
        "glnn_lie_heun",
    }
    by_model = {m: [j for j in per_exp[ALL[1]] if j.model == m] for m in ("glnn_lie_midpoint", "glnn_lie_heun")}
    mid, heun = by_model["glnn_lie_midpoint"], by_model["glnn_lie_heun"]  # Midpoint trained as Lie-Heun
    assert [(j.epochs, j.batch, j.extra["window"]) for j in mid] == [(j.epochs, j.batch, "trajectory") for j in heun]
    assert {j.model for j in per_exp[ALL[3]]} == {"liedflnn (per_body)", "liedflnn (articulated)"}
    assert {j.model.split()[0] for j in per_exp[ALL[2]]} == {"liedflnn", "euclidean_dflnn", "neural_ode"}
    assert all(j.epochs == 2 for j in smoke)  # budget=smoke's epochs
    assert min(j.epochs for j in full) >= 500  # the paper's budgets


def test_the_projection_follows_the_measurement_and_lists_what_is_unmeasured(tmp_path):
    plan = _plan_module()
    [job] = plan.jobs(["exp5_control"], [])
    # 3 epochs measured: 1.5 s training, 3 validation passes of 2 s, 37.5 s in all -> 30 s fixed
    rec = {"epochs": 3, "exit_code": 0, "job_seconds": 37.5, "train_seconds": 1.5, "val_s_per_pass": 2.0}
    rec.update(n_samples=400, load_1min=3.0, wall_seconds=40.0, cpu_seconds=20.0)  # half a core: load
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"jobs": {job.key: rec}}))
    passes = len(range(0, job.epochs, -(-job.epochs // 20)))
    expected = 30.0 + job.epochs * 0.5 + passes * 2.0
    assert plan.project(job, rec) == pytest.approx(expected)
    assert plan.project_cpu(job, rec) == pytest.approx(expected / 2)
    text = plan.plan_table(["exp5_control", "exp3_manifold"], [], path, tmp_path / "no_full_runs.json")
    assert f"| {expected:,.0f} | {expected / 2:,.0f} |" in text
    # exp3's jobs have no measurement: left out of the totals
    assert f"| **total** | **{expected / 3600:.2f}** | **{expected / 7200:.2f}** " in text
    assert "Not measured (left out of the totals): 4 job(s)" in text
    assert plan.project(job, {**rec, "exit_code": 1}) is None
    # the job run at its full budget: its measured seconds replace the projection in the totals
    full = tmp_path / "full.json"
    full.write_text(
        json.dumps({"jobs": {job.key: {"exit_code": 0, "wall_seconds": 90.0, "cpu_seconds": 80.0, "load_1min": 1.0}}})
    )
    text = plan.plan_table(["exp5_control"], [], path, full)
    assert "| 90 / 80 (1.0) |" in text and f"| **total** | **{90 / 3600:.2f}** | **{80 / 3600:.2f}** " in text
    assert "1 job(s) run at the full budget" in text
    assert "| ≥ " not in text and plan.ADAPTIVE_NOTE not in text  # no adaptive-solver job projected here
    # an adaptive-solver job's projection is a lower bound, and so is the total it enters
    node = next(j for j in plan.jobs(["exp3_manifold"], []) if j.model == "neural_ode")
    records = {node.key: {**rec, "epochs": 3}}
    (tmp_path / "node.json").write_text(json.dumps({"jobs": records}))
    text = plan.plan_table(["exp3_manifold"], [], tmp_path / "node.json", tmp_path / "none.json")
    assert "| ≥ " in text and "| **total** | **≥ " in text and plan.ADAPTIVE_NOTE in text
    full.write_text(
        json.dumps({"jobs": {job.key: {"exit_code": 1, "wall_seconds": 9.0, "cpu_seconds": 8.0, "load_1min": 1.0}}})
    )
    assert f"| **total** | **{expected / 3600:.2f}** |" in plan.plan_table(["exp5_control"], [], path, full)
    # the machine of the full runs: its factor over the projection scales the jobs not yet run
    records[job.key] = rec
    (tmp_path / "both.json").write_text(json.dumps({"jobs": records}))
    slow = {"exit_code": 0, "wall_seconds": 9.0, "cpu_seconds": 2.5 * expected / 2, "load_1min": 1.0}
    full.write_text(json.dumps({"jobs": {job.key: slow}}))
    text = plan.plan_table(["exp5_control", "exp3_manifold"], [], tmp_path / "both.json", full)
    rest = 2.5 * plan.project_cpu(node, records[node.key])  # (the one measured job not run)
    whole = slow["cpu_seconds"] + rest
    assert (
        "their 1 job(s) took a median 2.50x the projected CPU seconds (range 2.50-2.50x). At that factor the jobs "
        f"not yet run take ≥ {rest / 3600:.2f} CPU hours there, and the whole paper ≥ {whole / 3600:.2f} CPU hours"
    ) in text


def test_full_runs_every_job_not_skipped_and_records_it_as_it_finishes(tmp_path, monkeypatch, cached_jobs):
    plan = cached_jobs
    ran = []

    def fake(job, extra, work, epochs, **_):
        ran.append((job.key, epochs))
        return {"epochs": job.epochs, "wall_seconds": 5.0, "cpu_seconds": 4.0, "exit_code": 0, "load_1min": 0.5}

    monkeypatch.setattr(plan, "measure_one", fake)
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    path = tmp_path / "full.json"
    skip = [
        "baseline=glnn_rk4",
        "baseline=glnn_lie_midpoint",
        "baseline=glnn_lie_heun",
        "baseline=none dataset.train_steps=10",
    ]
    data = plan.run_full(["exp2_discrete_vs_continuous"], [], skip, path)
    assert [k for k, _ in ran] == [k for k in data["jobs"]] and all(e is None for _, e in ran)
    # whole words: skipping train_steps=10 leaves train_steps=100; "baseline=glnn_lie" would skip nothing
    assert [k.split("=")[-1] for k, _ in ran] == ["40", "70", "100"] and all("baseline=none" in k for k, _ in ran)
    assert not plan.holds_words("a baseline=glnn_lie_heun b", "baseline=glnn_lie") and not plan.holds_words("a", "")
    assert plan.holds_words("experiment=exp2 baseline=none x", "exp2 baseline=none")
    assert json.loads(path.read_text())["jobs"] == data["jobs"]
    assert all(r["run_dir"].startswith("outputs/paper_full/") for r in data["jobs"].values())
    bad = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full", "--skip"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "--skip needs a text" in bad.stderr


def test_plan_mode_of_the_script_runs_nothing(tmp_path):
    env = {**os.environ, "LIEDFL_EXPERIMENTS": "exp5_control", "LIEDFL_PAPER_DIR": str(tmp_path / "paper")}
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    env["PYTHON"] = sys.executable
    proc = subprocess.run(
        ["bash", str(SCRIPT), "--plan", "budget=smoke", "hydra/launcher=joblib"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("PROJECTION") and "| exp5_control | – | liedflnn (per_body) | 8 | 2 |" in proc.stdout
    assert not (tmp_path / "paper").exists()
    bad = subprocess.run(["bash", str(SCRIPT), "--plans"], env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--plans" in bad.stderr


def _job(folder: Path, overrides: list[str], status: dict | None):
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (folder / ".hydra" / "config.yaml").write_text("{}\n")
    if status is not None:
        (folder / "status.json").write_text(json.dumps(status))


def test_times_csv_has_a_row_per_job_and_replaces_a_rerun(tmp_path):
    plan = _plan_module()
    sweep = tmp_path / "exp2"
    _job(sweep / "0", ["baseline=none", "dataset.train_steps=10"], {"status": "ok", "exit_code": 0, "seconds": 12.5})
    _job(sweep / "1", ["baseline=glnn_rk4"], {"status": "failed", "exit_code": 1, "error": "x"})
    _job(sweep / "2", ["baseline=glnn_lie_heun"], None)  # never finished
    times = tmp_path / "times.csv"
    assert plan.record_times("exp2", sweep, times, sweep_seconds=40.0) == 3
    assert plan.record_times("exp5", sweep / "0", times) == 1  # a single run folder
    assert plan.record_times("exp2", sweep, times, sweep_seconds=41.0) == 3  # rerun: replaced, not appended
    with open(times) as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == plan.TIMES_HEADER
    exp2 = {r["job"]: r for r in rows if r["experiment"] == "exp2"}
    assert set(exp2) == {"0", "1", "2", "(whole sweep)"} and len(rows) == 5
    assert exp2["0"]["overrides"] == "baseline=none dataset.train_steps=10" and float(exp2["0"]["seconds"]) == 12.5
    assert exp2["1"]["exit_code"] == "1" and exp2["1"]["seconds_from"] == "file times" and exp2["1"]["seconds"]
    assert exp2["2"]["status"] == "unfinished" and exp2["2"]["seconds"] == ""
    assert float(exp2["(whole sweep)"]["seconds"]) == 41.0
    assert [r["job"] for r in rows if r["experiment"] == "exp5"] == ["0"]


@pytest.mark.slow
def test_a_tiny_reproduction_times_every_job(tmp_path):
    """The whole script on Exp 5 at budget=smoke: a times.csv row per job and the summary's sections."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "liedfl").write_text(
        f'#!/bin/sh\nexec {sys.executable} -c "from liedfl_cli.cli import main; main()" "$@"\n'
    )
    (bin_dir / "liedfl").chmod(0o755)
    env = {**os.environ, "LIEDFL_EXPERIMENTS": "exp5_control", "LIEDFL_PAPER_DIR": str(tmp_path / "paper")}
    env.update(
        PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}",
        PYTHONPATH=f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}",
        PYTHON=sys.executable,
        LIEDFL_DATA_DIR=str(tmp_path / "data"),
        OMP_NUM_THREADS="1",
        MPLBACKEND="Agg",
    )
    proc = subprocess.run(
        ["bash", str(SCRIPT), "budget=smoke", "eval.plots=false"], env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    with open(tmp_path / "paper" / "times.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["job"] for r in rows] == ["0", "(whole sweep)"] and rows[0]["status"] == "ok"
    assert float(rows[0]["seconds"]) <= float(rows[1]["seconds"]) + 1
    summary = (tmp_path / "paper" / "summary.md").read_text()
    assert "### Exp 5" in summary and "### Wall time of the reproduction" in summary


def test_full_table_joins_the_times_with_each_runs_test_errors(tmp_path):
    plan = _plan_module()
    run = tmp_path / "run"
    run.mkdir()
    evals = [
        {"model": "model", "rel_rot_error_mean": 0.0304, "rel_rot_error_final": 0.072, "rollout_vs_cv": 0.0212},
        {"model": "true_scheme", "rel_rot_error_mean": 0.0401},
    ]
    evals[0].update(newton_failures=0, checkpoint_epoch=950)
    (run / "summary.json").write_text(json.dumps({"eval": evals}))
    rec = {"epochs": 1000, "wall_seconds": 1848.0, "cpu_seconds": 42.0, "load_1min": 2.2, "load_1min_end": 2.9}
    gone = {**rec, "run_dir": str(tmp_path / "deleted")}
    path = tmp_path / "full.json"
    jobs = {"experiment=exp2 x": {**rec, "run_dir": str(run), "paused_seconds": 1806.0}, "experiment=exp5": gone}
    path.write_text(json.dumps({"jobs": jobs}))
    text = plan.full_table(path)
    assert (
        "| exp2 x | 1000 | 1,848 (1,806 paused) | 42 | 2.2 → 2.9 | 0.0304 / 0.072 | – | 0.0212 | 0.0401 | 0 | 950 |"
        in text
    )
    assert "| exp5 | 1000 | 1,848 | 42 | 2.2 → 2.9 | – | – | – | – | – | – |" in text
    jobs["experiment=exp5"]["exit_code"] = -15  # (killed before it trained: no result, not a 1-s job)
    path.write_text(json.dumps({"jobs": jobs}))
    assert "| exp5 | 1000 | 1,848 (failed: exit -15) | 42 |" in plan.full_table(path)
    # the command prints it from any records file (an archived one), and names a missing one
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full-table", str(path)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0 and "| exp5 | 1000 | 1,848 (failed: exit -15) | 42 |" in done.stdout
    missing = tmp_path / "none.json"
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full-table", str(missing)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and done.stderr.strip() == f"paper_plan.py full-table: {missing}: no such file"


def test_full_keeps_each_runs_test_errors_in_its_record(tmp_path, monkeypatch):
    """Output folders do not outlive the machine: the record keeps the errors, and the table reads them
    even once the run folder is gone."""
    plan = _plan_module()
    evals = [{"model": "model", "rel_rot_error_mean": 0.25, "rel_rot_error_final": 0.5, "loss": 3.0}]

    def fake(job, extra, work, epochs, **_):
        run = work / job.folder.replace("/", "_")
        run.mkdir(parents=True)
        (run / "summary.json").write_text(json.dumps({"eval": evals}))
        return {"epochs": job.epochs, "wall_seconds": 5.0, "cpu_seconds": 4.0, "exit_code": 0, "load_1min": 0.5}

    monkeypatch.setattr(plan, "measure_one", fake)
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    path = tmp_path / "full.json"
    data = plan.run_full(["exp5_control"], [], [], path)
    (rec,) = data["jobs"].values()
    assert rec["eval"] == [{"model": "model", "rel_rot_error_mean": 0.25, "rel_rot_error_final": 0.5}]
    assert set(rec["provenance"]) == {"commit", "cpu", "torch"}  # (ROOT is tmp_path here: no commit)
    shutil.rmtree(tmp_path / "outputs")
    assert "| 0.25 / 0.5 |" in plan.full_table(path)


def test_full_in_parallel_runs_jobs_side_by_side_longest_first_and_records_the_whole(
    tmp_path, monkeypatch, cached_jobs
):
    plan = cached_jobs
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setattr(plan, "MEASUREMENTS", tmp_path / "plan.json")
    keys = [j.key for j in plan.jobs(["exp2_discrete_vs_continuous"], []) if "baseline=none" in j.key]
    # projections from measurements: the longest training length is the longest job
    measured = {k: {"exit_code": 0, "epochs": 3, "wall_seconds": 1.0, "cpu_seconds": 1.0} for k in keys}
    for i, k in enumerate(keys):
        measured[k].update(job_seconds=1.0 + i, train_seconds=0.3 * (i + 1), val_s_per_pass=0.0, n_samples=10)
    (tmp_path / "plan.json").write_text(json.dumps({"jobs": measured}))
    running, most, started = [0], [0], []
    lock = threading.Lock()
    both = threading.Barrier(2, timeout=30)

    def fake(job, extra, work, epochs, **_):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
            started.append(job.key)
        if len(started) <= 2:
            both.wait()  # the first two are running at the same time
        with lock:
            running[0] -= 1
        return {"epochs": job.epochs, "wall_seconds": 5.0, "cpu_seconds": 4.0, "exit_code": 0, "load_1min": 0.5}

    monkeypatch.setattr(plan, "measure_one", fake)
    path = tmp_path / "full.json"
    skip = ["baseline=glnn_rk4", "baseline=glnn_lie_midpoint", "baseline=glnn_lie_heun"]
    data = plan.run_full(["exp2_discrete_vs_continuous"], [], skip, path, parallel=2)
    assert most[0] == 2 and sorted(data["jobs"]) == sorted(keys)
    # the longest projected job is submitted first; with two workers it starts in the first pair (which
    # of the two threads gets the runner's lock first is the scheduler's choice)
    assert [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip, 2, False, path)][0] == keys[-1]
    assert keys[-1] in started[:2]
    assert all(r["parallel"] == 2 for r in data["jobs"].values())
    (whole,) = data["runs"]
    assert whole["parallel"] == 2 and sorted(whole["jobs"]) == sorted(keys) and whole["wall_seconds"] >= 0
    assert f"| {whole['started']} | 4 | 2 | " in plan.full_table(path)
    bad = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full", "--parallel", "0"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "--parallel needs a number of jobs >= 1, got '0'" in bad.stderr


def test_a_jobs_cpu_seconds_are_its_own(tmp_path):
    """run_child charges the child its own CPU time (wait4), whatever else this process ran."""
    plan = _plan_module()
    burn = "import time\nwhile time.process_time() < 0.3: pass\nprint('done')"
    done, wall, cpu = plan.run_child([sys.executable, "-c", burn])
    assert done.returncode == 0 and done.stdout.strip() == "done"
    assert cpu >= 0.3 and wall > 0
    failed, _, _ = plan.run_child([sys.executable, "-c", "import sys; sys.exit('no such thing')"])
    assert failed.returncode == 1 and "no such thing" in failed.stderr


def test_full_with_overrides_records_them_in_the_key_and_keeps_the_full_budget_records(tmp_path, monkeypatch):
    """`full budget=smoke` (a quick try) must not overwrite a full-budget job's record."""
    plan = _plan_module()
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setattr(
        plan,
        "measure_one",
        lambda job, extra, work, epochs, **_: {"wall_seconds": 1.0, "cpu_seconds": 1.0, "exit_code": 0},
    )
    path = tmp_path / "full.json"
    full = {"wall_seconds": 99.0, "cpu_seconds": 98.0, "exit_code": 0}
    path.write_text(json.dumps({"jobs": {"experiment=exp5_control": full}}))
    data = plan.run_full(["exp5_control"], ["budget=smoke"], [], path)
    assert data["jobs"]["experiment=exp5_control"] == full
    assert data["jobs"]["experiment=exp5_control budget=smoke"]["wall_seconds"] == 1.0


def test_skip_measured_leaves_out_recorded_jobs_and_dry_run_runs_nothing(tmp_path, monkeypatch, cached_jobs):
    plan = cached_jobs
    full = tmp_path / "full.json"
    monkeypatch.setattr(plan, "FULL_RUNS", full)
    keys = [j.key for j in plan.jobs(["exp2_discrete_vs_continuous"], []) if "baseline=none" in j.key]
    done = {keys[0]: {"exit_code": 0}, keys[1]: {"exit_code": 1}}  # a failed job is not measured
    done[keys[2] + " budget=smoke"] = {"exit_code": 0}  # nor is a try with other overrides
    full.write_text(json.dumps({"jobs": done}))
    skip = ["baseline=glnn_rk4", "baseline=glnn_lie_midpoint", "baseline=glnn_lie_heun"]
    got = [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip, 1, skip_measured=True)]
    assert got == keys[1:]
    assert [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip)] == keys
    env = {**os.environ, "LIEDFL_EXPERIMENTS": "exp5_control", "LIEDFL_DATA_DIR": str(tmp_path / "data")}
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full", "--dry-run", "--parallel", "2"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["experiment=exp5_control (2000 epochs)", "1 job(s), 2 at a time"]
    assert not (tmp_path / "data").exists()


# ----------------------------------------------------------------------------- pieces: stop and resume
def _interruptible(plan, ran: list, epochs_done: int = 7, block: bool = True):
    """A `measure_one` stand-in: a fresh job trains until `full` asks it to stop, then leaves what
    `liedfl train` leaves after SIGTERM (a checkpoint, metrics up to its epoch, exit 143); a resumed
    one, or any with block=False, finishes (exit 0)."""

    def fake(job, extra, work, epochs, resume=False, stop=None):
        run = work / job.folder.replace("/", "_")
        ran.append((job.key, resume))
        assert resume == (run / "checkpoints" / "last.pt").is_file()  # (a fresh start: a cleared folder)
        if resume or not block:
            return {"epochs": job.epochs, "wall_seconds": 3.0, "cpu_seconds": 2.0, "exit_code": 0, "load_1min": 0.5}
        (run / "checkpoints").mkdir(parents=True)
        (run / "checkpoints" / "last.pt").write_bytes(b"")
        rows = "\n".join(f"{e},0.5" for e in range(1, epochs_done + 1))
        (run / "train_metrics.csv").write_text("epoch,loss\n" + rows + "\n")
        assert stop is not None
        for _ in range(3000):  # (until --stop-after asks)
            if stop.requested:
                break
            threading.Event().wait(0.01)
        assert stop.requested, "the stop never came"
        return {"epochs": job.epochs, "wall_seconds": 5.0, "cpu_seconds": 4.0, "exit_code": 143, "load_1min": 0.5}

    return fake


def test_a_stopped_full_run_records_its_jobs_as_interrupted_and_the_next_one_resumes_them(
    tmp_path, monkeypatch, cached_jobs, capsys
):
    plan = cached_jobs
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    ran: list = []
    monkeypatch.setattr(plan, "measure_one", _interruptible(plan, ran))
    path = tmp_path / "full.json"
    skip = ["baseline=glnn_rk4", "baseline=glnn_lie_midpoint", "baseline=glnn_lie_heun"]
    keys = [j.key for j in plan.jobs(["exp2_discrete_vs_continuous"], []) if "baseline=none" in j.key]
    # stale folders of an earlier run: a fresh start must not leave their checkpoints
    stale = [plan.FULL_DIR / f"exp2_discrete_vs_continuous_{i}" / "checkpoints" / "best.pt" for i in range(4)]
    for old in stale:
        old.parent.mkdir(parents=True)
        old.write_bytes(b"old")

    data = plan.run_full(["exp2_discrete_vs_continuous"], [], skip, path, parallel=2, stop_after=1.5)
    assert data["stopped"] == "--stop-after 1.5 s"
    said = capsys.readouterr().out
    assert "stopped (--stop-after 1.5 s): 2 job(s) interrupted with a checkpoint, 4 job(s) left to finish" in said
    assert sum(old.exists() for old in stale) == 2  # the two started, of four
    first = [k for k, _ in ran]
    assert len(first) == 2 and not any(r for _, r in ran)  # two at a time; none started after the stop
    recs = json.loads(path.read_text())["jobs"]
    assert sorted(recs) == sorted(first)
    for rec in recs.values():
        assert rec["status"] == "interrupted" and rec["epochs_done"] == 7 and rec["exit_code"] == 143
    (whole,) = json.loads(path.read_text())["runs"]
    assert whole["stopped"] == "--stop-after 1.5 s" and sorted(whole["interrupted"]) == sorted(first)
    table = plan.full_table(path)
    assert "| 5 (interrupted after epoch 7) | 4 |" in table and "(stopped: --stop-after 1.5 s) |" in table
    # the interrupted jobs first (by what they have left), then the others
    order = [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip, 1, True, path)]
    assert sorted(order[:2]) == sorted(first) and sorted(order) == sorted(keys)

    ran.clear()
    monkeypatch.setattr(plan, "measure_one", _interruptible(plan, ran, block=False))
    data = plan.run_full(["exp2_discrete_vs_continuous"], [], skip, path, parallel=1, skip_measured=True)
    assert "stopped" not in data and not any(old.exists() for old in stale)
    assert [k for k, r in ran if r] == order[:2]  # resumed first, then the two never started, afresh
    assert [k for k, r in ran if not r] == order[2:]
    for key in first:
        rec = data["jobs"][key]
        assert rec["exit_code"] == 0 and "status" not in rec
        assert [p["exit_code"] for p in rec["pieces"]] == [143, 0]
        assert rec["wall_seconds"] == 8.0 and rec["cpu_seconds"] == 6.0 and "lost_pieces" not in rec
        assert "(2 pieces)" in plan.full_table(path)


def test_a_job_left_running_by_a_dead_runner_resumes_with_its_piece_counted_lost(tmp_path, monkeypatch):
    plan = _plan_module()
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    ran: list = []
    monkeypatch.setattr(plan, "measure_one", _interruptible(plan, ran))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = {**plan.runner_id(), "pid": int(gone.stdout.strip())}
    run = plan.FULL_DIR / "exp5_control_0"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"")
    path = tmp_path / "full.json"
    piece = {"wall_seconds": 10.0, "cpu_seconds": 9.0, "exit_code": 143}
    rec = {"status": "running", "runner": dead, "run_dir": "outputs/paper_full/exp5_control_0", "pieces": [piece]}
    path.write_text(json.dumps({"jobs": {"experiment=exp5_control": rec}}))
    assert plan.resumable(rec) and not plan.runner_alive(dead)
    # while its runner lives, another runner leaves the job alone
    alive = {**rec, "runner": plan.runner_id()}
    path.write_text(json.dumps({"jobs": {"experiment=exp5_control": alive}}))
    assert plan.full_jobs(["exp5_control"], [], [], 1, True, path) == [] and not plan.resumable(alive)
    (run / "train_metrics.csv").write_text("epoch,loss\n1,0.5\n2,0.4\n")
    alive.update(started="2026-11-27 21:51 UTC", wall_seconds=10.0, cpu_seconds=9.0, epochs=2000)
    path.write_text(json.dumps({"jobs": {"experiment=exp5_control": alive}}))
    assert "| exp5_control | 2000 | 10 (running since 2026-11-27 21:51 UTC, at epoch 2) | 9 |" in plan.full_table(path)
    path.write_text(json.dumps({"jobs": {"experiment=exp5_control": rec}}))
    data = plan.run_full(["exp5_control"], [], [], path, skip_measured=True)
    assert ran == [("experiment=exp5_control", True)]
    out = data["jobs"]["experiment=exp5_control"]
    assert out["exit_code"] == 0 and out["lost_pieces"] == 1 and out["wall_seconds"] == 13.0
    assert "(2 pieces; ≥: 1 lost)" in plan.full_table(path)


def test_stop_after_reads_durations_and_refuses_others():
    plan = _plan_module()
    assert [plan.parse_duration(t) for t in ("90", "90s", "1.5m", "2.5h")] == [90.0, 90.0, 90.0, 9000.0]
    for bad in ("", "h", "-1h", "0", "soon", "nan"):
        with pytest.raises(ValueError):
            plan.parse_duration(bad)
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "full", "--stop-after", "soon"],
        capture_output=True,
        text=True,
    )
    assert (
        proc.returncode == 2
        and "--stop-after needs a duration > 0 (9000, 9000s, 150m, 2.5h), got 'soon'" in proc.stderr
    )


def test_sigterm_to_the_runner_stops_a_real_job_with_a_checkpoint_and_the_next_run_finishes_it(tmp_path, monkeypatch):
    """End to end with `liedfl train`: SIGTERM to the runner reaches the job, which checkpoints and
    exits 143; `--skip-measured` resumes it (`liedfl train resume=`) to the end of its epochs."""
    plan = _plan_module()
    monkeypatch.setenv("LIEDFL_DATA_DIR", str(tmp_path / "data"))
    extra = ["budget=smoke", "train.epochs=300", "eval.plots=false", "runtime.threads=1"]
    path = tmp_path / "full.json"
    metrics = plan.FULL_DIR / "exp5_control_0" / "train_metrics.csv"

    def signal_when_training() -> None:
        for _ in range(6000):
            if metrics.is_file() and len(metrics.read_text().splitlines()) > 2:
                os.kill(os.getpid(), signal.SIGTERM)
                return
            threading.Event().wait(0.01)

    watcher = threading.Thread(target=signal_when_training, daemon=True)
    watcher.start()
    before = signal.getsignal(signal.SIGTERM)
    data = plan.run_full(["exp5_control"], extra, [], path)
    watcher.join(timeout=5)
    assert signal.getsignal(signal.SIGTERM) == before  # (the runner's handler is gone again)
    key = "experiment=exp5_control " + " ".join(extra)
    rec = data["jobs"][key]
    assert data["stopped"] == "SIGTERM", rec
    assert rec["status"] == "interrupted" and rec["exit_code"] == 143, rec
    assert 1 <= rec["epochs_done"] < 300
    data = plan.run_full(["exp5_control"], extra, [], path, skip_measured=True)
    rec = data["jobs"][key]
    assert rec["exit_code"] == 0 and [p["exit_code"] for p in rec["pieces"]] == [143, 0], rec
    epochs = [int(r["epoch"]) for r in csv.DictReader(metrics.open())]
    assert epochs == list(range(1, 301))  # every epoch once: the second piece went on from the first
    assert rec["eval"] and rec["cpu_seconds"] == pytest.approx(sum(p["cpu_seconds"] for p in rec["pieces"]))


def test_full_leaves_a_job_alone_whose_folder_a_live_command_holds(tmp_path, monkeypatch):
    """A job a `liedfl` command still writes (another runner's, started by hand): never cleared."""
    from liedfl_cli.files import locks

    plan = _plan_module()
    ran: list = []
    monkeypatch.setattr(plan, "measure_one", _interruptible(plan, ran, block=False))
    run = plan.FULL_DIR / "exp5_control_0"
    run.mkdir(parents=True)
    (run / "train.log").write_text("theirs")
    path = tmp_path / "full.json"
    with locks.run_lock(run, "train"):
        assert "pid" in (plan.folder_held(run) or "")
        data = plan.run_full(["exp5_control"], [], [], path)
    assert ran == [] and (run / "train.log").read_text() == "theirs" and not data.get("jobs")
    assert plan.folder_held(run) is None
    plan.run_full(["exp5_control"], [], [], path)
    assert ran == [("experiment=exp5_control", False)] and not (run / "train.log").exists()


def test_interrupted_jobs_come_first_also_when_shorter(tmp_path, monkeypatch, cached_jobs):
    """What was started gets finished: an interrupted job before longer fresh ones, with --parallel too."""
    plan = cached_jobs
    monkeypatch.setattr(plan, "MEASUREMENTS", tmp_path / "plan.json")
    keys = [j.key for j in plan.jobs(["exp2_discrete_vs_continuous"], []) if "baseline=none" in j.key]
    measured = {k: {"exit_code": 0, "epochs": 3, "wall_seconds": 1.0, "cpu_seconds": 1.0} for k in keys}
    for i, k in enumerate(keys):  # the longest training length is the longest job
        measured[k].update(job_seconds=1.0 + i, train_seconds=0.3 * (i + 1), val_s_per_pass=0.0, n_samples=10)
    (tmp_path / "plan.json").write_text(json.dumps({"jobs": measured}))
    run = plan.FULL_DIR / "exp2_discrete_vs_continuous_0"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"")
    stopped = {"exit_code": 143, "wall_seconds": 1.0, "cpu_seconds": 1.0, "run_dir": str(run.relative_to(tmp_path))}
    path = tmp_path / "full.json"
    path.write_text(json.dumps({"jobs": {keys[0]: stopped}}))
    skip = ["baseline=glnn_rk4", "baseline=glnn_lie_midpoint", "baseline=glnn_lie_heun"]
    order = [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip, 2, True, path)]
    assert order == [keys[0], *reversed(keys[1:])]
    fresh = [j.key for j in plan.full_jobs(["exp2_discrete_vs_continuous"], [], skip, 2, False, path)]
    assert fresh == list(reversed(keys))  # (without --skip-measured nothing is resumed: longest first)


@pytest.mark.parametrize(
    "argv",
    [
        ["full", "--help"],
        ["full", "-h", "--parallel", "2"],
        ["plan", "--help"],
        ["--help"],
    ],
)
def test_help_prints_the_usage_and_runs_nothing(argv, monkeypatch, capsys):
    plan = _plan_module()
    ran: list[str] = []
    for name in ("run_full", "measure", "plan_table", "full_table", "record_times"):
        monkeypatch.setattr(plan, name, lambda *a, _n=name, **k: ran.append(_n))
    assert plan.main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: paper_plan.py") and "--skip-measured" in out
    assert ran == []


@pytest.mark.parametrize(
    ("argv", "bad"),
    [
        (["full", "--skip-measure"], "--skip-measure"),  # a misspelling would have started every job afresh
        (["full", "--parallel", "2", "--stop_after", "1h"], "--stop_after"),
        (["full", "--skip", "exp1", "-n", "2"], "-n"),
        (["plan", "--dry-run"], "--dry-run"),  # full's option, not plan's
        (["times", "exp5_control", "s", "t.csv", "--seconds", "3"], "--seconds"),
    ],
)
def test_an_unknown_option_is_refused_before_anything_runs(argv, bad, monkeypatch, capsys):
    plan = _plan_module()
    ran: list[str] = []
    for name in ("run_full", "measure", "plan_table", "full_table", "record_times"):
        monkeypatch.setattr(plan, name, lambda *a, _n=name, **k: ran.append(_n))
    assert plan.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"unknown option {bad!r}" in err[0] and "nothing was run" in err[0]
    assert ran == []


def test_option_values_and_negative_numbers_are_not_taken_for_options():
    plan = _plan_module()
    assert plan.unknown_option(["full", "--skip", "--odd-text", "--parallel", "2", "--dry-run"]) is None
    assert plan.unknown_option(["full", "train.lr=-1e-3", "seed=-1"]) is None
    assert plan.unknown_option(["times", "exp5_control", "s", "t.csv", "--sweep-seconds", "-1"]) is None
    assert plan.unknown_option(["full", "--dry-run", "--skip-measured", "--bogus"]) == "--bogus"


def test_a_job_in_pieces_sums_its_seconds_so_its_fixed_seconds_stay_the_job_less_its_training():
    plan = _plan_module()
    # first piece: 100 s of job, 90 of them training, stopped; the resumed run's summary counts the
    # training of both pieces (90 + 40) but its status.json only its own 50 s
    first = {"wall_seconds": 103.0, "cpu_seconds": 100.0, "job_seconds": 100.0, "exit_code": 143, "epochs": 20}
    last = {"wall_seconds": 52.0, "cpu_seconds": 50.0, "exit_code": 0, "epochs": 20, "job_seconds": 50.0}
    last.update(train_seconds=130.0, val_s_per_pass=0.0)
    out = plan.merge_pieces(first, {**last, **plan.rates(last)})
    assert out["job_seconds"] == 150.0 and out["wall_seconds"] == 155.0 and out["cpu_seconds"] == 150.0
    assert out["fixed_seconds"] == pytest.approx(20.0) and out["fit_s_per_epoch"] == pytest.approx(130.0 / 20)
    # a piece recorded before job_seconds were kept counts with its wall seconds
    older = {k: v for k, v in first.items() if k != "job_seconds"}
    out = plan.merge_pieces(older, {**last, **plan.rates(last)})
    assert out["job_seconds"] == 153.0 and out["fixed_seconds"] == pytest.approx(23.0)
    # a failed piece has no timings of its own: nothing to recompute
    failed = {"wall_seconds": 5.0, "cpu_seconds": 4.0, "exit_code": 1, "epochs": 20}
    assert "fixed_seconds" not in plan.merge_pieces(first, failed)


def test_provenance_names_the_commit_with_its_changes_the_cpu_and_torch(tmp_path, monkeypatch):
    import torch

    plan = _plan_module()
    assert plan.provenance()["commit"] is None  # (ROOT is tmp_path: not a checkout)
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (tmp_path / "liedfl_cli").mkdir()
    (tmp_path / "liedfl_cli" / "a.py").write_text("x = 1\n")
    (tmp_path / "notes.md").write_text("a\n")
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "c"], check=True)
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    got = plan.provenance()
    assert got["commit"] == head and got["torch"] == torch.__version__ and got["cpu"]
    (tmp_path / "notes.md").write_text("b\n")  # (not code: the commit still says what ran)
    assert plan.provenance()["commit"] == head
    (tmp_path / "liedfl_cli" / "a.py").write_text("x = 2\n")
    assert plan.provenance()["commit"] == head + "+changes"


def test_compare_lines_up_the_jobs_finished_in_both_files(tmp_path):
    plan = _plan_module()

    def rec(cpu: float, err: float, **more) -> dict:
        row = {"model": "model", "rel_rot_error_mean": err, "rollout_vs_cv": err / 2, "newton_failures": 0}
        return {"exit_code": 0, "cpu_seconds": cpu, "eval": [row], **more}

    old, new = tmp_path / "old.json", tmp_path / "new.json"
    old_jobs = {"experiment=a": rec(400.0, 0.1), "experiment=b": rec(100.0, 0.2), "experiment=gone": rec(5.0, 0.3)}
    new_jobs = {"experiment=a": rec(100.0, 0.12), "experiment=b": rec(50.0, 0.2)}
    new_jobs["experiment=c"] = rec(9.0, 0.4)
    new_jobs["experiment=gone"] = {"status": "running", "cpu_seconds": 1.0}  # (not finished: not compared)
    new_jobs["experiment=untimed"] = {"exit_code": 0, "wall_seconds": 3.0, "eval": None}  # (no CPU s: left out)
    old.write_text(json.dumps({"jobs": old_jobs}))
    new.write_text(json.dumps({"jobs": new_jobs}))
    text = plan.compare_table(old, new)
    assert "| a | 400 | 100 | 4.00 | 0.1 → 0.12 | – → – | 0.05 → 0.06 | 0 → 0 |" in text
    assert "| b | 100 | 50 | 2.00 | 0.2 → 0.2 |" in text
    assert "| **total (2 jobs)** | **500** | **150** | **3.33** |" in text
    assert "Finished only in the old file: gone" in text and "Finished only in the new file: c" in text
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "paper_plan.py"), "compare", str(old), str(tmp_path / "no.json")],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "no.json: no such file" in done.stderr
