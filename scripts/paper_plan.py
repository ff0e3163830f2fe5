"""The jobs of scripts/reproduce_paper.sh: list them, time a few epochs of each, project the full run,
and record the wall time of every job of a finished sweep.

    python scripts/paper_plan.py plan [overrides...]       # table of every job, budget, projected time
    python scripts/paper_plan.py measure [overrides...]    # time train.epochs=3 of every job (minutes)
    python scripts/paper_plan.py full [--skip TEXT]... [--skip-measured] [--parallel N] [--stop-after DURATION]
                                      [--dry-run] [overrides...]
    python scripts/paper_plan.py full-table [records.json] # markdown: those jobs, their times and errors
                                                           # (default docs/bench/paper_full.json)
    python scripts/paper_plan.py compare OLD.json [NEW.json] # markdown: CPU s and errors of the jobs in both
    python scripts/paper_plan.py times <experiment> <sweep dir> <times.csv> [--sweep-seconds S]

The jobs are those reproduce_paper.sh launches for the experiments in LIEDFL_EXPERIMENTS: the
cartesian product of each experiment's `hydra.sweeper.params`, plus Exp 3 with the structured
potential. Overrides are the script's own (`budget=...`, `epoch_scale=...`); launcher settings
(hydra/launcher=..., hydra.*) do not change a job and are ignored here.

Projection of one job (docs/benchmarks.md, "Full paper reproduction: projection"): a run of
`train.epochs=E` at the job's settings gives the fixed cost (data, rollout, evaluation, plots:
job seconds - training seconds), the training seconds per epoch without validation and the seconds
of one validation pass; the full job = fixed + epochs x s/epoch + passes x s/pass, with the passes of
`train.val_every: auto`. Measurements live in docs/bench/paper_plan.json with the load at the time.

`full` runs the jobs (of LIEDFL_EXPERIMENTS, less those whose key holds a --skip text as whole words, so
`--skip dataset.train_steps=10` leaves `dataset.train_steps=100` alone) one after
the other at their full budget in outputs/paper_full/, and records each job's wall and CPU seconds,
exit code, load and run folder in docs/bench/paper_full.json as it finishes (a session too short for
the whole reproduction measures it piece by piece); `plan` then shows those jobs as measured.
`--parallel N` runs N jobs at a time (the longest projected first), each charged its own CPU seconds
(`wait4`); the run's own wall time is recorded under "runs": with every job in it, the whole paper's.
`--skip-measured` leaves out the jobs already recorded there (exit 0): how a later session goes on.
`--dry-run` lists the jobs that would run, in order, and runs nothing.

Jobs longer than a session run in pieces. `--stop-after 2.5h` (or `9000`, `150m`), or SIGTERM / Ctrl-C
to the runner, stops the run: no new job starts, and each running `liedfl train` gets SIGTERM, finishes
its epoch, saves `checkpoints/last.pt` and exits 143; its record says `interrupted` (with `epochs_done`)
and the runner exits 75. `full --skip-measured` then resumes those jobs first (`liedfl train
resume=<run>`, which ends with the same weights as an uninterrupted run), and the finished record sums
the wall and CPU seconds of its `pieces`. While a job runs its record says `running` with the runner's
host and pid: another runner leaves it alone, and if the runner died (a machine or session that ended
without the stop) the next `--skip-measured` resumes from the last checkpoint (written every minute)
and counts that piece under `lost_pieces`: its seconds are unknown, so the sums are lower bounds. A job
whose run folder a live `liedfl` command holds (`<run>/.lock`) is never cleared or resumed; a job
started afresh gets an empty folder.
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MEASUREMENTS = ROOT / "docs" / "bench" / "paper_plan.json"
FULL_RUNS = ROOT / "docs" / "bench" / "paper_full.json"
FULL_DIR = ROOT / "outputs" / "paper_full"
DEFAULT_EXPERIMENTS = "exp1_euler_vs_lie exp2_discrete_vs_continuous exp3_manifold exp4_mocap exp5_control"
EXTRA_JOBS = {"exp3_manifold": [("exp3_manifold_structured", ["model.potential=uniform_gravity"])]}
"""Single runs beyond the sweeps, by the experiment that triggers them: (folder, overrides)."""
TIMES_HEADER = ["experiment", "job", "overrides", "seconds", "exit_code", "status", "seconds_from"]
MEASURE_EPOCHS = 3
AUTO_VAL_PASSES = 20  # liedfl_cli/commands/validation.py: val_every auto = ceil(epochs / 20)
COMPILE_MIN_STEPS = 1.0e5  # liedfl_cli/solvers/runtime.py: compile auto for training above this


@dataclass
class Job:
    """One `liedfl train` job of the reproduction: its experiment, sweep folder (or run folder for a
    single run) and job overrides, and the budget its config composes to."""

    experiment: str
    folder: str
    overrides: list[str]
    model: str = ""
    epochs: int = 0
    batch: int = 0
    train_steps: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        return " ".join([f"experiment={self.experiment}", *self.overrides])


def job_overrides(args: list[str]) -> list[str]:
    """The script's arguments that change a job's config (launcher settings and --flags left out)."""
    return [a for a in args if not a.startswith(("hydra/", "hydra.", "--"))]


class _Composer:
    """Hydra's compose API over the train config, initialised once for many compositions."""

    def __enter__(self):
        from hydra import initialize_config_dir
        from hydra.core.global_hydra import GlobalHydra

        from liedfl_cli.cli import CONF_DIR
        from liedfl_cli.config import resolvers

        resolvers.register()
        GlobalHydra.instance().clear()
        self._ctx = initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3")
        self._ctx.__enter__()
        return self

    def __exit__(self, *exc):
        from hydra.core.global_hydra import GlobalHydra

        self._ctx.__exit__(*exc)
        GlobalHydra.instance().clear()

    def __call__(self, overrides: list[str], hydra_node: bool = False):
        from hydra import compose

        return compose(config_name="train", overrides=overrides, return_hydra_config=hydra_node)


def sweep_params(compose: _Composer, experiment: str, extra: list[str]) -> list[list[str]]:
    """Every job's overrides of `liedfl train -m experiment=<experiment>` (one empty list: one job)."""
    from omegaconf import OmegaConf

    cfg = compose([f"experiment={experiment}", *extra], hydra_node=True)
    params = OmegaConf.select(cfg, "hydra.sweeper.params") or {}
    axes = [[f"{k}={v.strip()}" for v in str(vals).split(",")] for k, vals in params.items()]
    return [list(p) for p in itertools.product(*axes)]


def jobs(experiments: list[str], extra: list[str], check: bool = False) -> list[Job]:
    """Every job reproduce_paper.sh launches for `experiments`, in its order, with composed budgets
    (a config that does not compose raises; with `check`, also one that does not validate as
    `liedfl train` validates it, e.g. an unknown key)."""
    from liedfl_cli.config.schema import validate
    from liedfl_cli.config.typed import typed

    out = []
    with _Composer() as compose:
        for exp in experiments:
            for i, ov in enumerate(sweep_params(compose, exp, extra)):
                out.append(Job(exp, f"{exp}/{i}", ov))
            for folder, ov in EXTRA_JOBS.get(exp, []):
                out.append(Job(exp, folder, ov))
        for job in out:
            cfg = compose([f"experiment={job.experiment}", *job.overrides, *extra])
            if check:
                validate(cfg, "train")
            run = typed(cfg, "train")  # the job's settings, typed once
            assert run.train is not None and run.dataset is not None, "a train config"
            model = run.model or {}
            kinetic = model.get("kinetic")
            if (
                kinetic == "auto"
            ):  # articulated only for data with a tree: no paper scene but Exp 4, which pins per_body
                kinetic = "per_body"
            job.model = str(model.get("name")) + (f" ({kinetic})" if kinetic is not None else "")
            job.epochs, job.batch = int(run.train.epochs), int(run.train.batch_size)
            job.train_steps = int(run.dataset.train_steps or 0)
            job.extra = {"window": model.get("window")}
    return out


def experiments_from_env() -> list[str]:
    return os.environ.get("LIEDFL_EXPERIMENTS", DEFAULT_EXPERIMENTS).split()


# ----------------------------------------------------------------------------- measurement
def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def _write_json(path: Path, obj) -> None:  # write then rename: never a half-written file
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1) + "\n")
    tmp.replace(path)


RESUMABLE_EXITS = (130, 143)
"""Exit codes of a `liedfl train` stopped by SIGINT / SIGTERM: it finished its epoch, saved
`checkpoints/last.pt` and can be resumed (README, "Interruptions and resume")."""
STOPPED_EXIT = 75  # (EX_TEMPFAIL) `full` stopped with jobs left to resume: run it again with --skip-measured


class Stop:
    """A request to stop `full`: no new job starts, and each running one gets SIGTERM, so it
    finishes its epoch, saves its checkpoint and exits 143 (a piece the next `full --skip-measured`
    resumes). Raised by the --stop-after deadline or by the runner's own SIGTERM / SIGINT."""

    def __init__(self) -> None:
        self.reason: str | None = None
        self._lock = threading.Lock()
        self._children: set[subprocess.Popen] = set()

    @property
    def requested(self) -> bool:
        return self.reason is not None

    def request(self, reason: str) -> None:
        with self._lock:
            if self.reason is not None:
                return
            self.reason = reason
            children = list(self._children)
        for child in children:
            _terminate(child)

    def add(self, child: subprocess.Popen) -> None:
        with self._lock:
            self._children.add(child)
            late = self.reason is not None
        if late:  # (the request came while it was starting)
            _terminate(child)

    def discard(self, child: subprocess.Popen) -> None:
        with self._lock:
            self._children.discard(child)


def _terminate(child: subprocess.Popen) -> None:
    # os.kill, not Popen.send_signal: that one polls, which could reap the child before run_child's
    # wait4 has read its CPU seconds
    with contextlib.suppress(ProcessLookupError):  # (already gone)
        os.kill(child.pid, signal.SIGTERM)


def parse_duration(text: str) -> float:
    """'9000', '9000s', '150m', '2.5h' -> seconds (> 0); ValueError otherwise."""
    units = {"s": 1.0, "m": 60.0, "h": 3600.0}
    unit = units.get(text[-1:].lower()) if text else None
    number = text[:-1] if unit is not None else text
    seconds = float(number) * (unit or 1.0)  # (ValueError for anything else)
    if not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(text)
    return seconds


def runner_id() -> dict:
    """This runner, as a `running` record names it: the fields of a run-folder lock's holder (host,
    pid, the process's start time), so `runner_alive` is the locks' own test."""
    from liedfl_cli.files import locks
    from liedfl_cli.files.io_utils import host_id

    return {"host": host_id(), "pid": os.getpid(), "start": locks.process_start(os.getpid())}


def provenance() -> dict:
    """What a job's seconds depend on besides the job, taken as it starts: `commit` (ROOT's git HEAD,
    short, with `+changes` when liedfl_cli/ or scripts/ differ from it; None outside a checkout),
    `cpu` (the model name /proc/cpuinfo gives, else `platform.processor()`), `torch` (its version).
    One VM ran 2-4x faster on some days than on others (docs/benchmarks.md) and records of one job
    from different code differ by as much, so each record names both."""
    import importlib.metadata
    import platform

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "--short", "HEAD")
    if commit and git("status", "--porcelain", "--", "liedfl_cli", "scripts"):
        commit += "+changes"
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # (also when loaded by file path)
    from machine_info import cpu_model

    cpu = cpu_model(platform.processor() or platform.machine())
    try:
        torch_version: str | None = importlib.metadata.version("torch")
    except importlib.metadata.PackageNotFoundError:
        torch_version = None
    return {"commit": commit, "cpu": cpu, "torch": torch_version}


def runner_alive(runner) -> bool:
    """Whether the runner a `running` record names still runs: `locks.holder_alive` (a reused pid is
    not the runner; another host's runner counts as gone, its folder's `.lock` still guards the job)."""
    from liedfl_cli.files import locks

    return isinstance(runner, dict) and locks.holder_alive(runner) is True


def last_epoch(run: Path) -> int | None:
    """The last epoch `train_metrics.csv` of a run folder records (None: no such row)."""
    path = run / "train_metrics.csv"
    if not path.is_file():
        return None
    rows = path.read_text().strip().splitlines()
    if len(rows) < 2:
        return None
    head, last = rows[0].split(","), rows[-1].split(",")
    try:
        return int(float(last[head.index("epoch")]))
    except (ValueError, IndexError):
        return None


def resumable(rec: dict | None) -> bool:
    """Whether a `full` record is a job to resume rather than to start: stopped by a signal (exit
    130 / 143) or left `running` by a runner that is gone, with the run's checkpoint still there."""
    if not rec or not rec.get("run_dir"):
        return False
    stopped = rec.get("exit_code") in RESUMABLE_EXITS
    orphaned = rec.get("status") == "running" and not runner_alive(rec.get("runner"))
    return (stopped or orphaned) and (ROOT / rec["run_dir"] / "checkpoints" / "last.pt").is_file()


def folder_held(run: Path) -> str | None:
    """Who holds a run folder's lock (`liedfl_cli.files.locks`: a `liedfl` command of this host that
    still runs, or one of another host), or None. `full` never clears or resumes a folder in use."""
    from liedfl_cli.files import locks

    try:
        holder = json.loads((run / locks.LOCK_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(holder, dict) or locks.holder_alive(holder) is False:
        return None
    return locks.describe(holder)


PIECE_KEYS = (
    "provenance",
    "wall_seconds",
    "cpu_seconds",
    "job_seconds",
    "exit_code",
    "load_1min",
    "load_1min_end",
    "measured",
    "epochs_done",
)


def pieces_of(prev: dict | None) -> list[dict]:
    """The pieces a record holds: its `pieces`, or the record itself as one piece (a job stopped once)."""
    if not prev:
        return []
    if "pieces" in prev:
        return [dict(p) for p in prev["pieces"]]
    return [{k: prev[k] for k in PIECE_KEYS if k in prev}] if "wall_seconds" in prev else []


def merge_pieces(prev: dict | None, rec: dict) -> dict:
    """The record of a job run in pieces: `rec` (the latest piece) with wall and CPU seconds summed
    over every piece and each piece under `pieces`. A piece lost with its runner (a `running` record)
    counts as lost: its seconds are unknown, so the sums are lower bounds (`lost_pieces`)."""
    if prev is None:
        return rec
    pieces = pieces_of(prev)
    lost = int(prev.get("lost_pieces", 0)) + (1 if prev.get("status") == "running" else 0)
    pieces.append({k: rec[k] for k in PIECE_KEYS if k in rec})
    out = {**rec, "pieces": pieces}
    out["wall_seconds"] = round(sum(float(p["wall_seconds"]) for p in pieces), 3)
    out["cpu_seconds"] = round(sum(float(p["cpu_seconds"]) for p in pieces), 3)
    if "job_seconds" in rec and "train_seconds" in rec:
        # the run's train_seconds count every piece (the trainer carries them across a resume) but its
        # status.json's seconds only the last: the job's seconds are summed too, so that fixed_seconds
        # stays the job less its training. (A piece recorded without them, before 2026-11-28, counts
        # with its wall seconds, which hold them.)
        out["job_seconds"] = round(sum(float(p.get("job_seconds", p["wall_seconds"])) for p in pieces), 3)
        out.update(rates(out))
    if lost:
        out["lost_pieces"] = lost
    return out


def measure_one(
    job: Job,
    extra: list[str],
    work: Path,
    epochs: int | None = MEASURE_EPOCHS,
    resume: bool = False,
    stop: Stop | None = None,
) -> dict:
    """Run `job` with train.epochs=`epochs` (None: its full budget; its other settings unchanged) in
    `work`; its timings. resume: continue the interrupted run in its folder from `checkpoints/last.pt`
    (`liedfl train resume=<run>`, the run's own config) instead of starting it. stop: asks the job to
    stop early (see `Stop`)."""
    run = work / job.folder.replace("/", "_")
    if resume:
        cmd = [sys.executable, "-m", "liedfl_cli", "train", f"resume={run}", "ui.progress=false"]
    else:
        cmd = [sys.executable, "-m", "liedfl_cli", "train", f"experiment={job.experiment}", *job.overrides, *extra]
        cmd += [*([f"train.epochs={epochs}"] if epochs is not None else [])]
        cmd += ["ui.progress=false", f"hydra.run.dir={run}"]
    load = os.getloadavg()[0]
    proc, wall, cpu = run_child(cmd, stop)
    rec = {"epochs": epochs if epochs is not None else job.epochs, "wall_seconds": round(wall, 3)}
    rec.update(cpu_seconds=round(cpu, 3), exit_code=proc.returncode, load_1min=load)
    if proc.returncode != 0:
        rec["error"] = (proc.stderr.strip().splitlines() or ["?"])[-1][:300]
        return rec
    summary = _read_json(run / "summary.json")
    status = _read_json(run / "status.json")
    t = summary.get("timings", {})
    val_s = float(t.get("val_seconds", 0.0) or 0.0)
    rec.update(
        job_seconds=float(status.get("seconds", wall)),
        # validation excluded (train.py); the model's start (`train.start`, a one-off fit) counts as fixed:
        # in a run of a few epochs it would otherwise pass for their training time
        train_seconds=round(float(t.get("train_seconds", 0.0)) - float(t.get("start_seconds", 0.0) or 0.0), 3),
        val_s_per_pass=val_s / val_passes(rec["epochs"]) if val_s else 0.0,
        n_samples=int(t.get("n_samples", 0)),
    )
    return {**rec, **rates(rec)}


def run_child(cmd: list[str], stop: Stop | None = None) -> tuple[subprocess.CompletedProcess, float, float]:
    """Run cmd in ROOT -> (its completed process with stdout and stderr, wall seconds, CPU seconds of
    the child and its descendants). The CPU seconds come from the child's own `wait4` record, so jobs
    run side by side (`full --parallel`) are each charged their own. stop: the child is registered
    with it while it runs, so that a stop request reaches it (SIGTERM)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        child = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=err, text=True)
        if stop is not None:
            stop.add(child)
        try:
            _, status, usage = os.wait4(child.pid, 0)
        except BaseException:  # (an exception in the runner itself: the job goes too, and is reaped)
            child.kill()
            child.wait()
            raise
        finally:
            if stop is not None:
                stop.discard(child)
        wall = time.perf_counter() - t0
        child.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        done = subprocess.CompletedProcess(cmd, child.returncode, out.read(), err.read())
    return done, wall, usage.ru_utime + usage.ru_stime


def val_passes(epochs: int) -> int:
    """Validation passes of a run of `epochs` under `train.val_every: auto` (every k-th epoch)."""
    return len(range(0, epochs, max(1, math.ceil(epochs / AUTO_VAL_PASSES))))


def rates(rec: dict) -> dict:
    """From a measurement's raw times: training s/epoch (validation excluded) and the fixed seconds
    (the job's seconds less training and validation: data, model building, rollout, evaluation, plots)."""
    val = rec["val_s_per_pass"] * val_passes(rec["epochs"])
    return {
        "fit_s_per_epoch": rec["train_seconds"] / rec["epochs"],
        "fixed_seconds": round(rec["job_seconds"] - rec["train_seconds"] - val, 3),
    }


def measure(experiments: list[str], extra: list[str], path: Path = MEASUREMENTS) -> dict:
    """Time every job for a few epochs (fresh data folder: data generation counts once per dataset,
    as in the real run) and merge the records into `path` under each job's key."""
    data: dict = {}
    with tempfile.TemporaryDirectory(prefix="paper_plan_") as tmp:
        os.environ["LIEDFL_DATA_DIR"] = str(Path(tmp) / "data")
        for job in jobs(experiments, extra, check=True):
            source = provenance()
            rec = measure_one(job, extra, Path(tmp))
            rec["measured"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
            rec["provenance"] = source
            print(f"{job.key}: {rec.get('fit_s_per_epoch', rec.get('error'))}", flush=True)
            data = _read_json(path)  # (re-read: other measurements may have landed meanwhile)
            data.setdefault("jobs", {})[job.key] = rec
            data["machine"] = f"{os.cpu_count()} CPU cores, nice -n 10, shared; load in each record (1-min average)"
            _write_json(path, data)
    return data


def holds_words(key: str, text: str) -> bool:
    """Whether `text`'s space-separated words occur in `key` as a run of whole words (`experiment=` may
    be left out, as in the tables)."""
    words, part = (s.replace("experiment=", "").split() for s in (key, text))
    return bool(part) and any(words[i : i + len(part)] == part for i in range(len(words) - len(part) + 1))


def full_jobs(
    experiments: list[str],
    extra: list[str],
    skip: list[str],
    parallel: int = 1,
    skip_measured: bool = False,
    path: Path | None = None,
) -> list[Job]:
    """The jobs `run_full` runs, in the order it starts them: those not skipped and not held by another
    runner (a `running` record of a live one); with skip_measured, not those recorded at the full budget
    with exit 0 in `path` (FULL_RUNS), and the interrupted ones (`resumable`) first, so that what was
    started gets finished. With parallel > 1 the longest projected first within each part
    (docs/bench/paper_plan.json; an interrupted job by what it has left; unmeasured ones last)."""
    recorded = _read_json(path or FULL_RUNS).get("jobs", {})
    done = {k for k, r in recorded.items() if r.get("exit_code") == 0}
    held = {k for k, r in recorded.items() if r.get("status") == "running" and runner_alive(r.get("runner"))}
    todo = [
        job
        for job in jobs(experiments, extra, check=True)
        if not any(holds_words(job.key, t) for t in skip)
        and not (skip_measured and " ".join([job.key, *extra]) in done)
        and " ".join([job.key, *extra]) not in held
    ]

    def left(job: Job) -> float:  # the fraction of its epochs a job has still to train
        rec = recorded.get(" ".join([job.key, *extra]))
        if not (skip_measured and resumable(rec)):
            return 1.0
        assert rec is not None
        done_epochs = rec.get("epochs_done") or last_epoch(ROOT / rec["run_dir"]) or 0
        return max(0.0, 1.0 - done_epochs / max(job.epochs, 1))

    if parallel > 1:
        records = _read_json(MEASUREMENTS).get("jobs", {})
        todo.sort(key=lambda job: -(project_cpu(job, records.get(job.key)) or 0.0) * left(job))
    if skip_measured:  # (stable: the interrupted jobs first, so what was started gets finished)
        todo.sort(key=lambda job: not resumable(recorded.get(" ".join([job.key, *extra]))))
    return todo


def run_full(
    experiments: list[str],
    extra: list[str],
    skip: list[str],
    path: Path = FULL_RUNS,
    parallel: int = 1,
    skip_measured: bool = False,
    stop_after: float | None = None,
) -> dict:
    """Run every job not skipped at its full budget in FULL_DIR and merge each record (timings, load
    at start and end, run folder, test errors) into `path` as the job finishes; then record the run as
    a whole under "runs" (wall seconds, jobs, `parallel`). parallel = N > 1: N jobs at a time (one torch
    thread each), the longest projected first (docs/bench/paper_plan.json), which shortens the whole.

    Pieces: with skip_measured, a job stopped earlier (`resumable`) continues from its checkpoint
    (`liedfl train resume=`) and its record sums the pieces' seconds. stop_after (seconds) or the
    runner's own SIGTERM / SIGINT stops the run (`Stop`): no new job starts and the running ones
    checkpoint and are recorded as interrupted. A job's record reads `running` while it runs."""
    os.environ.setdefault("LIEDFL_DATA_DIR", str(FULL_DIR / "data"))
    todo = full_jobs(experiments, extra, skip, parallel, skip_measured, path)
    lock = threading.Lock()
    stop = Stop()
    started, t0 = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), time.perf_counter()
    ran: list[str] = []  # (started here)
    interrupted: list[str] = []  # (stopped with a checkpoint)
    finished: list[str] = []  # (exit 0)

    def write(key: str, rec: dict) -> None:  # (under `lock`)
        data = _read_json(path)  # (re-read: another process may have recorded meanwhile)
        # overrides (budget=smoke, ...) make another job: its own key, never a full-budget record's
        data.setdefault("jobs", {})[key] = rec
        data["machine"] = f"{os.cpu_count()} CPU cores, shared; load at the start and end of each job (1-min average)"
        _write_json(path, data)

    def one(job: Job) -> None:
        key = " ".join([job.key, *extra])
        run = FULL_DIR / job.folder.replace("/", "_")
        with lock:
            if stop.requested:
                return
            holder = folder_held(run)
            if holder is not None:
                print(f"{job.key}: skipped, its folder {run} is in use by {holder}", flush=True)
                return
            prev = _read_json(path).get("jobs", {}).get(key)
            resume = skip_measured and resumable(prev)
            if not resume:
                prev = None
                if run.exists():  # (a fresh start: nothing of an earlier run of this job may stay)
                    shutil.rmtree(run)
            at = f" from epoch {(prev or {}).get('epochs_done') or last_epoch(run)}" if resume else ""
            print(f"{job.key}: {job.epochs} epochs{' (resumed' + at + ')' if resume else ''} ...", flush=True)
            mark: dict = {
                "status": "running",
                "runner": runner_id(),
                "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            }
            mark.update(epochs=job.epochs, run_dir=str(run.relative_to(ROOT)), pieces=pieces_of(prev))
            if mark["pieces"]:  # (the seconds of the pieces before this one)
                mark.update(
                    {k: round(sum(float(p[k]) for p in mark["pieces"]), 3) for k in ("wall_seconds", "cpu_seconds")}
                )
            write(key, mark)
            ran.append(key)
        source = provenance()  # (the code the job imports as it starts)
        rec = measure_one(job, extra, FULL_DIR, epochs=None, resume=resume, stop=stop)
        rec.update(
            provenance=source,
            load_1min_end=os.getloadavg()[0],
            run_dir=str(run.relative_to(ROOT)),
            measured=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            eval=eval_rows(run),
            parallel=parallel,
        )
        if rec["exit_code"] in RESUMABLE_EXITS and (run / "checkpoints" / "last.pt").is_file():
            rec.update(status="interrupted", epochs_done=last_epoch(run))
        rec = merge_pieces(prev, rec)
        with lock:
            state = f", interrupted after epoch {rec['epochs_done']}" if rec.get("status") == "interrupted" else ""
            print(
                f"{job.key}: {rec['wall_seconds']:.0f} s wall, {rec['cpu_seconds']:.0f} s CPU, exit {rec['exit_code']}"
                + (f" ({len(rec['pieces'])} pieces)" if len(rec.get("pieces", [])) > 1 else "")
                + state,
                flush=True,
            )
            if state:
                interrupted.append(key)
            if rec["exit_code"] == 0:
                finished.append(key)
            write(key, rec)

    timer = threading.Timer(stop_after, stop.request, args=(f"--stop-after {stop_after:g} s",)) if stop_after else None
    with _stop_on_signals(stop):
        if timer is not None:
            timer.daemon = True
            timer.start()
        try:
            with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
                for _ in pool.map(one, todo):  # (re-raises a job's exception here)
                    pass
        finally:
            if timer is not None:
                timer.cancel()
    data = _read_json(path)
    if ran:
        whole = {
            "started": started,
            "wall_seconds": round(time.perf_counter() - t0, 3),
            "parallel": parallel,
            "jobs": ran,
            "load_1min_end": os.getloadavg()[0],
        }
        if stop.requested:
            whole.update(stopped=stop.reason, interrupted=interrupted)
        data.setdefault("runs", []).append(whole)
        _write_json(path, data)
    if stop.requested:
        left = len(todo) - len(finished)
        print(
            f"stopped ({stop.reason}): {len(interrupted)} job(s) interrupted with a checkpoint, {left} job(s) left "
            "to finish; "
            "the same command with --skip-measured goes on from there",
            flush=True,
        )
        data["stopped"] = stop.reason  # (for the caller; not written)
    return data


class _stop_on_signals:
    """While `full` runs in the main thread: SIGTERM, and SIGINT unless it is ignored (nohup), ask
    `stop` to stop (the jobs checkpoint) instead of ending the runner with its jobs orphaned."""

    def __init__(self, stop: Stop) -> None:
        self.stop = stop
        self.saved: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                old = signal.getsignal(sig)
                if sig == signal.SIGINT and old == signal.SIG_IGN:
                    continue
                self.saved[sig] = old
                signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.stop.request(signal.Signals(signum).name)
        self.__exit__()  # (a second signal acts as it would have: SIGINT raises, SIGTERM ends the runner)

    def __exit__(self, *exc):
        for sig, old in self.saved.items():
            signal.signal(sig, old)
        self.saved = {}


EVAL_KEYS = (
    "model",
    "rel_rot_error_mean",
    "rel_rot_error_final",
    "geodesic_error_mean",
    "position_error_mean",
    "rollout_vs_cv",
    "cv_geodesic_error_same_horizon",
    "rollout_vs_best",
    "one_step_vs_cv",
    "one_step_vs_best",
    "best_reference",
    "beats_references",
    "valid_horizon_min",
    "valid_horizon_mean",
    "failed_trajectories",
    "error_steps",
    "newton_failures",
    "checkpoint_epoch",
)
"""What a record keeps of each eval row: the errors, the valid horizon they cover, and both sides of every
ratio to a reference (`cv_geodesic_error_same_horizon`: constant velocity over the model's valid samples)."""


def same_horizon_ratio(ev: dict) -> str:
    """The rollout ÷ constant velocity cell of a record's model row: the ratio when both sides cover the
    same steps (records with `cv_geodesic_error_same_horizon`, or a rollout without a Newton failure),
    else "not comparable" (older records divided a rollout cut at its first failure by constant velocity
    over all steps)."""
    if not ev or ev.get("rollout_vs_cv") is None:
        return "–"
    same = ev.get("cv_geodesic_error_same_horizon") is not None or not ev.get("newton_failures")
    return _fmt(ev["rollout_vs_cv"]) if same else "not comparable (different horizons)"


def horizon_note(ev: dict) -> str:
    """ " (valid to step k of n)" after an error of a rollout that failed within the error span."""
    lo, n = ev.get("valid_horizon_min"), ev.get("error_steps")
    if lo is None:
        return " (valid horizon not recorded)" if ev.get("newton_failures") else ""
    return f" (valid to step {lo} of {n})" if n is not None and lo < n else ""


def eval_rows(run: Path) -> list[dict]:
    """The test-error rows of a finished run (`summary.json`'s eval, the keys of EVAL_KEYS), kept in the
    record because output folders do not outlive the machine; [] where the run wrote none."""
    return [{k: e[k] for k in EVAL_KEYS if k in e} for e in _read_json(run / "summary.json").get("eval", [])]


def _fmt(x, spec: str = ".3g") -> str:
    return "–" if x is None else format(x, spec)


def full_table(path: Path = FULL_RUNS) -> str:
    """Markdown: every job run at its full budget (`full`), its times and load, and the learned model's
    test errors kept in the record (older records: read from the run folder; "–" where it is gone)."""
    lines = [
        "| job | epochs | wall s | CPU s | load start → end | mean / final rel. rotation error "
        "| mean position error | rollout ÷ const. velocity | true scheme (mean rotation) | Newton failures "
        "| checkpoint epoch |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, rec in _read_json(path).get("jobs", {}).items():
        kept = rec.get("eval") or (eval_rows(ROOT / rec["run_dir"]) if rec.get("run_dir") else [])
        rows = {e.get("model"): e for e in kept}
        ev, true = rows.get("model", {}), rows.get("true_scheme", {})
        err = f"{_fmt(ev.get('rel_rot_error_mean'))} / {_fmt(ev.get('rel_rot_error_final'))}" if ev else "–"
        err += horizon_note(ev) if ev else ""
        notes = [f"{rec['paused_seconds']:,.0f} paused"] if rec.get("paused_seconds") else []
        if len(rec.get("pieces", [])) > 1 or rec.get("lost_pieces"):
            notes.append(f"{len(rec['pieces'])} pieces")
        if rec.get("lost_pieces"):  # (their seconds are unknown: the sums are lower bounds)
            notes.append(f"≥: {rec['lost_pieces']} lost")
        if rec.get("status") == "interrupted":
            notes.append(f"interrupted after epoch {rec.get('epochs_done')}")
        elif rec.get("exit_code") not in (0, None) and rec.get("status") != "running":
            notes.append(f"failed: exit {rec['exit_code']}")  # (no result; --skip-measured runs it again)
        elif rec.get("status") == "running":
            at = last_epoch(ROOT / rec["run_dir"]) if rec.get("run_dir") else None
            notes.append(f"running since {rec.get('started')}" + (f", at epoch {at}" if at else ""))
        wall = _fmt(rec.get("wall_seconds"), ",.0f") + (f" ({'; '.join(notes)})" if notes else "")
        lines.append(
            f"| {key.replace('experiment=', '')} | {rec.get('epochs')} | {wall} "
            f"| {_fmt(rec.get('cpu_seconds'), ',.0f')} "
            f"| {_fmt(rec.get('load_1min'), '.1f')} → {_fmt(rec.get('load_1min_end'), '.1f')} | {err} "
            f"| {_fmt(ev.get('position_error_mean'))} | {same_horizon_ratio(ev)} "
            f"| {_fmt(true.get('rel_rot_error_mean'))} "
            f"| {ev.get('newton_failures', '–')} | {ev.get('checkpoint_epoch', '–')} |"
        )
    runs = _read_json(path).get("runs", [])
    if runs:  # each `full` invocation as a whole: with every job in one of them, the paper's wall time
        lines += ["", "| run started | jobs | at a time | wall s |", "|---|---|---|---|"]
        lines += [
            f"| {r['started']} | {len(r['jobs'])} | {r['parallel']} | {r['wall_seconds']:,.0f}"
            + (f" (stopped: {r['stopped']})" if r.get("stopped") else "")
            + " |"
            for r in runs
        ]
    return "\n".join(lines)


def compare_table(old_path: Path, new_path: Path = FULL_RUNS) -> str:
    """Markdown: each job finished (exit 0, with CPU seconds) in both records files, its CPU seconds in
    each and their ratio, and in each the learned model's mean relative rotation error, mean position
    error (where the job has one), rollout error over constant velocity's and Newton failures; a total
    over those jobs. Jobs finished in only one file are listed after the table. For runs of one
    reproduction on other code or another machine: each record's `provenance` says which."""
    olds, news = (
        {
            k: r
            for k, r in _read_json(p).get("jobs", {}).items()
            if r.get("exit_code") == 0 and "status" not in r and r.get("cpu_seconds")  # (older records: no CPU s)
        }
        for p in (old_path, new_path)
    )

    def model_row(rec: dict) -> dict:
        return next((e for e in rec.get("eval") or [] if e.get("model") == "model"), {})

    lines = [
        f"| job | CPU s ({old_path.name}) | CPU s ({new_path.name}) | old ÷ new | mean rel. rotation error, old → new "
        "| mean position error, old → new | rollout ÷ const. velocity, old → new | Newton failures, old → new |",
        "|---|---|---|---|---|---|---|---|",
    ]
    both = [k for k in news if k in olds]
    for key in both:
        o, n = olds[key], news[key]
        eo, en = model_row(o), model_row(n)
        lines.append(
            f"| {key.replace('experiment=', '')} | {o['cpu_seconds']:,.0f} | {n['cpu_seconds']:,.0f} "
            f"| {o['cpu_seconds'] / n['cpu_seconds']:.2f} "
            f"| {_fmt(eo.get('rel_rot_error_mean'))} → {_fmt(en.get('rel_rot_error_mean'))} "
            f"| {_fmt(eo.get('position_error_mean'))} → {_fmt(en.get('position_error_mean'))} "
            f"| {same_horizon_ratio(eo)} → {same_horizon_ratio(en)} "
            f"| {eo.get('newton_failures', '–')} → {en.get('newton_failures', '–')} |"
        )
    if both:
        cpu_o, cpu_n = (sum(float(d[k]["cpu_seconds"]) for k in both) for d in (olds, news))
        lines.append(
            f"| **total ({len(both)} jobs)** | **{cpu_o:,.0f}** | **{cpu_n:,.0f}** | **{cpu_o / cpu_n:.2f}** | | | | |"
        )
    for name, only in (("old", [k for k in olds if k not in news]), ("new", [k for k in news if k not in olds])):
        if only:
            lines += ["", f"Finished only in the {name} file: " + "; ".join(k.replace("experiment=", "") for k in only)]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- projection
def project(job: Job, rec: dict | None) -> float | None:
    """Projected wall seconds of the full job at the load of its measurement (None: not measured or
    it failed)."""
    if not rec or rec.get("exit_code") != 0:
        return None
    r = rates(rec)
    return r["fixed_seconds"] + job.epochs * r["fit_s_per_epoch"] + val_passes(job.epochs) * rec["val_s_per_pass"]


def project_cpu(job: Job, rec: dict | None) -> float | None:
    """The projection scaled by the measurement's CPU seconds / wall seconds: what the job would take
    on a core of its own (one torch thread per job), i.e. on an idle machine. None without CPU times."""
    sec = project(job, rec)
    if sec is None or not rec or not rec.get("cpu_seconds") or not rec.get("wall_seconds"):
        return None
    return sec * min(1.0, rec["cpu_seconds"] / rec["wall_seconds"])


def _h(seconds: float) -> str:
    return f"{seconds / 3600:.2f}"


ADAPTIVE = ("neural_ode", "glnn_rk4")
"""Models integrated by an adaptive solver (dopri5): their epochs slow down as training stiffens the
learned field, so a projection from the first epochs is a lower bound."""
ADAPTIVE_MARK = "≥ "
ADAPTIVE_NOTE = (
    "≥: a lower bound. Neural ODE and GLNN-RK4 integrate with adaptive dopri5, whose step count grows as "
    "training stiffens the learned field: Exp 3's Neural ODE took 0.21 s per epoch at the start and 2.47 "
    "by epoch 700 (2026-11-27, docs/benchmarks.md), 12x its projection."
)


def plan_table(experiments: list[str], extra: list[str], path: Path = MEASUREMENTS, full_path: Path = FULL_RUNS) -> str:
    """Markdown: every job, its budget, measured s/epoch and projected time; totals per experiment.
    Two projections: wall time at the load of the measurement, and CPU time (about an idle core).
    A job run at its full budget (`full`, recorded in `full_path`) counts with its measured times."""
    records = _read_json(path).get("jobs", {})
    full_runs = {k: r for k, r in _read_json(full_path).get("jobs", {}).items() if r.get("exit_code") == 0}
    lines = [
        "| experiment | job | model | train length | epochs | batch | optimiser steps | s/epoch (measured) "
        "| projected s at that load | projected CPU s (≈ idle core) | load at measurement "
        "| full run: wall s / CPU s (load) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    n_full, any_lower = 0, False
    factors: list[float] = []  # full-budget CPU seconds / projected CPU seconds, per job run both ways
    run_cpu = unrun_cpu = 0.0
    unrun_adaptive = False
    totals: dict[str, list[float]] = {}
    missing: list[str] = []
    for job in jobs(experiments, extra):
        rec = records.get(job.key)
        sec, cpu = project(job, rec), project_cpu(job, rec)
        steps = "–"
        if rec and rec.get("n_samples"):
            n = math.ceil(rec["n_samples"] / job.batch)
            steps = f"{job.epochs * n:,}" + (" (compiles)" if job.epochs * n >= COMPILE_MIN_STEPS else "")
        measured = "–"
        frec = full_runs.get(job.key)
        if frec is None and cpu is not None:
            unrun_cpu += cpu
            unrun_adaptive = unrun_adaptive or job.model in ADAPTIVE
        if frec is not None:  # measured at the full budget: replaces the projection in the totals
            n_full += 1
            run_cpu += float(frec["cpu_seconds"])
            if cpu:  # (how much slower the full run's machine was than the projection's)
                factors.append(float(frec["cpu_seconds"]) / cpu)
            measured = f"{frec['wall_seconds']:,.0f} / {frec['cpu_seconds']:,.0f} ({frec['load_1min']:.1f})"
            sec, cpu = float(frec["wall_seconds"]), float(frec["cpu_seconds"])
        if sec is None:
            missing.append(job.key)
        t = totals.setdefault(job.experiment, [0.0, 0.0])
        t[0] += sec or 0.0
        t[1] += cpu if cpu is not None else (sec or 0.0)
        per_epoch = f"{rates(rec)['fit_s_per_epoch']:.3g}" if rec and sec is not None else "not measured"
        lower = ADAPTIVE_MARK if job.model in ADAPTIVE and frec is None and sec is not None else ""
        any_lower = any_lower or bool(lower)
        projected = f"{lower}{sec:,.0f}" if sec is not None else "–"
        projected_cpu = f"{lower}{cpu:,.0f}" if cpu is not None else "–"
        load = f"{rec['load_1min']:.1f}" if rec else "–"
        lines.append(
            f"| {job.experiment} | {' '.join(job.overrides) or '–'} | {job.model} | {job.train_steps} | {job.epochs} "
            f"| {job.batch} | {steps} | {per_epoch} | {projected} | {projected_cpu} | {load} | {measured} |"
        )
    lines += ["", "| experiment | projected hours at the measured load | projected CPU hours (≈ idle, one core) |"]
    lines.append("|---|---|---|")
    lines += [f"| {e} | {_h(w)} | {_h(c)} |" for e, (w, c) in totals.items()]
    wall, cpu = sum(t[0] for t in totals.values()), sum(t[1] for t in totals.values())
    lo = ADAPTIVE_MARK if any_lower else ""
    lines.append(
        f"| **total** | **{lo}{_h(wall)}** | **{lo}{_h(cpu)}** (two jobs at a time on 2 cores: ≥ {_h(cpu / 2)}) |"
    )
    if n_full:
        lines += ["", f"{n_full} job(s) run at the full budget count with their measured wall and CPU seconds."]
    if factors and unrun_cpu:
        f = statistics.median(factors)
        lo = ADAPTIVE_MARK if unrun_adaptive else ""
        whole = run_cpu + f * unrun_cpu
        lines += [
            "",
            f"On the machine of the full-budget runs, their {len(factors)} job(s) took a median {f:.2f}x the "
            f"projected CPU seconds (range {min(factors):.2f}-{max(factors):.2f}x). At that factor the jobs not "
            f"yet run take {lo}{_h(f * unrun_cpu)} CPU hours there, and the whole paper {lo}{_h(whole)} CPU hours "
            f"({lo}{_h(whole / 2)} h on two cores).",
        ]
    if missing:
        lines += ["", f"Not measured (left out of the totals): {len(missing)} job(s): {'; '.join(missing)}"]
    lines += ["", "(A job measured without CPU times counts with its wall projection in the CPU column.)"]
    if any_lower:
        lines += ["", ADAPTIVE_NOTE]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- times.csv
def job_times(experiment: str, sweep: Path) -> list[dict]:
    """One row per job folder of `sweep` (or the single run folder `sweep`): its overrides, its
    seconds (status.json's; for a failed job, the time from its config to its status file) and exit."""
    from liedfl_cli.commands.status import job_dirs, read_status

    folders = job_dirs(sweep) or ([sweep] if (sweep / ".hydra").is_dir() else [])
    rows = []
    for d in folders:
        st = read_status(d) or {"status": "unfinished", "exit_code": ""}
        ov_file = d / ".hydra" / "overrides.yaml"
        ov = ov_file.read_text().splitlines() if ov_file.is_file() else []
        overrides = " ".join(line[2:] for line in ov if line.startswith("- "))
        seconds, src = st.get("seconds"), "status.json"
        if seconds is None and (d / "status.json").is_file() and (d / ".hydra" / "config.yaml").is_file():
            seconds = (d / "status.json").stat().st_mtime - (d / ".hydra" / "config.yaml").stat().st_mtime
            src = "file times"
        rows.append(
            {
                "experiment": experiment,
                "job": d.name if d != sweep else sweep.name,
                "overrides": overrides,
                "seconds": "" if seconds is None else f"{float(seconds):.1f}",
                "exit_code": st.get("exit_code", ""),
                "status": st.get("status", ""),
                "seconds_from": src if seconds is not None else "",
            }
        )
    return rows


def record_times(experiment: str, sweep: Path, times_csv: Path, sweep_seconds: float | None = None) -> int:
    """Replace `experiment`'s rows of times.csv by those of `sweep` (+ the sweep's wall time); the
    number of job rows written."""
    old = []
    if times_csv.is_file():
        with open(times_csv) as f:
            old = [r for r in csv.DictReader(f) if r.get("experiment") != experiment]
    new = job_times(experiment, sweep)
    if sweep_seconds is not None:
        new.append(
            {
                "experiment": experiment,
                "job": "(whole sweep)",
                "overrides": "",
                "seconds": f"{sweep_seconds:.1f}",
                "exit_code": "",
                "status": "",
                "seconds_from": "script clock",
            }
        )
    times_csv.parent.mkdir(parents=True, exist_ok=True)
    tmp = times_csv.with_name(times_csv.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=TIMES_HEADER)
        w.writeheader()
        w.writerows(old + new)
    tmp.replace(times_csv)
    return len(new) - (sweep_seconds is not None)


USAGE = (
    "usage: paper_plan.py plan|measure [overrides...] "
    "| full [--skip TEXT]... [--skip-measured] [--parallel N] [--stop-after DURATION] [--dry-run] "
    "[overrides...] "
    "| times <experiment> <sweep> <times.csv> [--sweep-seconds S] | full-table [records.json] "
    "| compare OLD.json [NEW.json]"
)
# the options each command takes; any other `-x` / `--x` is refused before anything runs, because
# `full` without `--skip-measured` starts every job afresh (removing its folder): a misspelt
# `--skip-measure` or a `--help` must never do that
OPTIONS = {
    "plan": (),
    "measure": (),
    "full": ("--skip", "--skip-measured", "--parallel", "--stop-after", "--dry-run"),
    "times": ("--sweep-seconds",),
    "full-table": (),
    "compare": (),
}


def unknown_option(argv: list[str]) -> str | None:
    """The first argument of `argv` (command first) that looks like an option (`-x`, `--x`) and is not
    one its command takes; None if there is none. A value after `--skip` / `--parallel` /
    `--stop-after` / `--sweep-seconds` is not an option, whatever it starts with."""
    known, takes_value = OPTIONS.get(argv[0], ()), ("--skip", "--parallel", "--stop-after", "--sweep-seconds")
    i = 1
    while i < len(argv):
        a = argv[i]
        if a.startswith("-") and not _is_number(a):
            if a not in known:
                return a
            i += 2 if a in takes_value else 1
            continue
        i += 1
    return None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def main(argv: list[str]) -> int:
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print((__doc__ or "").strip())
        return 0
    if not argv or argv[0] not in OPTIONS:
        print(USAGE, file=sys.stderr)
        return 2
    bad = unknown_option(argv)
    if bad is not None:
        print(
            f"paper_plan.py {argv[0]}: unknown option {bad!r} (options: {', '.join(OPTIONS[argv[0]]) or 'none'});"
            " nothing was run",
            file=sys.stderr,
        )
        return 2
    if argv[0] == "compare":
        sys.path.insert(0, str(ROOT))
        files = [Path(a) for a in argv[1:]]
        if len(files) not in (1, 2):
            print("usage: paper_plan.py compare OLD.json [NEW.json]", file=sys.stderr)
            return 2
        for f in files:
            if not f.is_file():
                print(f"paper_plan.py compare: {f}: no such file", file=sys.stderr)
                return 2
        print(compare_table(*files))
        return 0
    if argv[0] == "full-table":
        sys.path.insert(0, str(ROOT))
        if len(argv) > 2:
            print("usage: paper_plan.py full-table [records.json]", file=sys.stderr)
            return 2
        records = Path(argv[1]) if len(argv) == 2 else FULL_RUNS
        if not records.is_file():
            print(f"paper_plan.py full-table: {records}: no such file", file=sys.stderr)
            return 2
        print(full_table(records))
        return 0
    sys.path.insert(0, str(ROOT))
    if argv[0] == "times":
        if len(argv) not in (4, 6):
            print("usage: paper_plan.py times <experiment> <sweep> <times.csv> [--sweep-seconds S]", file=sys.stderr)
            return 2
        seconds = float(argv[5]) if len(argv) == 6 else None
        n = record_times(argv[1], Path(argv[2]), Path(argv[3]), seconds)
        print(f"{argv[3]}: {n} job(s) of {argv[1]}")
        return 0
    if argv[0] == "full":
        args, skip = list(argv[1:]), []
        while "--skip" in args:
            i = args.index("--skip")
            if i + 1 >= len(args):
                print("paper_plan.py full: --skip needs a text", file=sys.stderr)
                return 2
            skip.append(args[i + 1])
            del args[i : i + 2]
        parallel = 1
        if "--parallel" in args:
            i = args.index("--parallel")
            value = args[i + 1] if i + 1 < len(args) else ""
            if not value.isdigit() or int(value) < 1:
                print(f"paper_plan.py full: --parallel needs a number of jobs >= 1, got {value!r}", file=sys.stderr)
                return 2
            parallel = int(value)
            del args[i : i + 2]
        stop_after = None
        if "--stop-after" in args:
            i = args.index("--stop-after")
            value = args[i + 1] if i + 1 < len(args) else ""
            try:
                stop_after = parse_duration(value)
            except ValueError:
                print(
                    f"paper_plan.py full: --stop-after needs a duration > 0 (9000, 9000s, 150m, 2.5h), got {value!r}",
                    file=sys.stderr,
                )
                return 2
            del args[i : i + 2]
        dry, measured = "--dry-run" in args, "--skip-measured" in args
        args = [a for a in args if a not in ("--dry-run", "--skip-measured")]
        if dry:  # what would run, in order, and nothing else
            extra = job_overrides(args)
            todo = full_jobs(experiments_from_env(), extra, skip, parallel, measured)
            recorded = _read_json(FULL_RUNS).get("jobs", {})
            for job in todo:
                rec = recorded.get(" ".join([job.key, *extra]))
                at = (rec or {}).get("epochs_done") or (last_epoch(ROOT / rec["run_dir"]) if rec else None)
                more = f", resumed from epoch {at}" if measured and resumable(rec) else ""
                print(f"{job.key} ({job.epochs} epochs{more})")
            print(f"{len(todo)} job(s), {parallel} at a time")
            return 0
        data = run_full(
            experiments_from_env(),
            job_overrides(args),
            skip,
            parallel=parallel,
            skip_measured=measured,
            stop_after=stop_after,
        )
        return STOPPED_EXIT if data.get("stopped") else 0
    extra = job_overrides(argv[1:])
    if argv[0] == "measure":
        measure(experiments_from_env(), extra)
    print("PROJECTION from a few measured epochs per job (not a measured full run):\n")
    print(plan_table(experiments_from_env(), extra))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
