"""Measure the run times the README and docs quote, as a user would see them, and regenerate their table.

    python scripts/run_times.py [--only main,smoke,...] [--articulated-epochs N] [--table-only]

Runs each command below exactly as the README gives it, in a fresh empty folder (so generating a
dataset is included), with the environment as it is (OMP_NUM_THREADS is recorded, not set), one after
the other, and records per command: the wall time, the exit code, the 1-minute load average before and
after (`os.getloadavg`), the CPU model and core count, the date, the commit and the torch version, into
docs/bench/run_times.json (one entry per command, the latest measurement; earlier ones kept under
"history"). Then it regenerates docs/run_times.md, the table the README points to. `--table-only`
regenerates the table from the record without running anything.

Commands (ids for --only):
  main         liedfl train                                   (the README's main job)
  smoke        liedfl train budget=smoke
  chain_data   python scripts/mujoco_chain.py --out chain.h5  (needs mujoco)
  articulated  liedfl train dataset=file dataset.path=chain.h5 model.kinetic=articulated
               (1000 epochs by default; --articulated-epochs N appends train.epochs=N and the record says so)
  tests        python -m pytest -m "not slow" -q -n 2 --dist worksteal   (in the repository; 2+ minutes idle,
               far more on a busy machine)
  arm_data, arm_train, arm_export   the commands of docs/tutorial_robot.md (steps 1, 3, 4), in one folder

`liedfl` is run from this checkout (the repository root is put first on PYTHONPATH). Run it in the
background on the machine you want figures for, e.g.
    nohup python scripts/run_times.py --only main,smoke,chain_data,articulated > run_times.log 2>&1 &
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RECORD = REPO / "docs" / "bench" / "run_times.json"
TABLE = REPO / "docs" / "run_times.md"
TESTS = 'python -m pytest -m "not slow" -q -n 2 --dist worksteal'
COMMANDS = {  # id: (command as the docs quote it, where it runs, what it is)
    "main": ("liedfl train", "fresh", "the main job: LieDFLNN on the default scene, 1000 epochs, rollout, eval, plots"),
    "smoke": ("liedfl train budget=smoke", "fresh", "any run at the CI budget (tiny data, 2 epochs)"),
    "chain_data": ("python scripts/mujoco_chain.py --out chain.h5", "chain", "simulate an articulated chain (MuJoCo)"),
    "articulated": (
        "liedfl train dataset=file dataset.path=chain.h5 model.kinetic=articulated",
        "chain",
        "the articulated model on that chain (1000 epochs by default)",
    ),
    "tests": (TESTS, "repo", "the fast test tier, as CI runs it"),
    "arm_data": (
        "python scripts/mujoco_chain.py --parents=-1,0,1,2 --joints hinge,hinge,universal,hinge --gravity 9.81 "
        "--h 0.01 --speed 1 --n-trajectories 32 --no-declare-joints --out arm.h5",
        "arm",
        "docs/tutorial_robot.md step 1: the recording",
    ),
    "arm_train": (
        "liedfl train dataset=file dataset.path=arm.h5 dataset.total_mass=9.593 train.epochs=300 "
        "paths.output_dir=arm_run",
        "arm",
        "docs/tutorial_robot.md step 3: identify the arm (300 epochs)",
    ),
    "arm_export": (
        "liedfl export run=arm_run format=mjcf out=arm.xml",
        "arm",
        "docs/tutorial_robot.md step 4: export to MuJoCo",
    ),
}


def machine() -> dict:
    """CPU model, cores, OS, Python and torch versions, OMP_NUM_THREADS as set (None: unset)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # (also when loaded by file path)
    from machine_info import cpu_model

    cpu = cpu_model(platform.processor() or "")
    try:
        import torch

        torch_version = torch.__version__
    except ImportError:
        torch_version = None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "torch": torch_version,
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
    }


def commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
        return out.stdout.strip() or None
    except OSError:
        return None


def child_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    env.setdefault("COLUMNS", "120")
    return env


def measure(key: str, command: str, cwd: Path, log: Path) -> dict:
    """Run `command` (bash) in `cwd`, output to `log`; wall time, exit code and load around it."""
    shell = command.replace("python scripts/", f"{shlex.quote(sys.executable)} {shlex.quote(str(REPO / 'scripts'))}/")
    shell = shell.replace("python -m pytest", f"{shlex.quote(sys.executable)} -m pytest")
    load_before = os.getloadavg()
    start = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(
            ["bash", "-c", shell], cwd=cwd, env=child_env(), stdout=f, stderr=subprocess.STDOUT
        ).returncode
    wall = time.perf_counter() - t0
    load_after = os.getloadavg()
    tail = log.read_text(errors="replace").strip().splitlines()[-3:]
    return {
        "command": command,
        "wall_s": round(wall, 1),
        "exit_code": rc,
        "load_1min_before": round(load_before[0], 2),
        "load_1min_after": round(load_after[0], 2),
        "load_5min_after": round(load_after[1], 2),
        "date": start,
        "commit": commit(),
        "machine": machine(),
        "output_tail": tail,
    }


def load_record() -> dict:
    if RECORD.is_file():
        return json.loads(RECORD.read_text())
    return {"entries": {}}


def save_record(record: dict) -> None:
    RECORD.parent.mkdir(parents=True, exist_ok=True)
    tmp = RECORD.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    tmp.replace(RECORD)


def add(record: dict, key: str, entry: dict) -> None:
    old = record["entries"].get(key)
    if old is not None:
        entry.setdefault("history", [])
        entry["history"] = [*old.pop("history", []), old][-5:]
    record["entries"][key] = entry


def _minutes(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min ({s:.0f} s)"


def _row(e: dict) -> str:
    m = e.get("machine", {})
    return (
        f"| `{e['command']}` | {_minutes(e['wall_s'])} | {e['exit_code']} | "
        f"{e['load_1min_before']} → {e['load_1min_after']} | "
        f"{m.get('cpu', '?')}, {m.get('usable_cores', '?')} cores | "
        f"{m.get('OMP_NUM_THREADS') or 'unset'} | {e['date']} | {e.get('note', '')} |"
    )


def write_table(record: dict) -> str:
    """docs/run_times.md from the record: one row per command, its machine and load beside it."""
    order = [k for k in COMMANDS if k in record["entries"]] + [k for k in record["entries"] if k not in COMMANDS]
    lines = [
        "# Run times as a user sees them",
        "",
        "Generated by `python scripts/run_times.py` (`--table-only` rebuilds this page from the record,",
        "[docs/bench/run_times.json](bench/run_times.json)); do not edit by hand. Each command was run as the README",
        "gives it, in a fresh empty folder (dataset generation included), its output sent to a log file (not a",
        "terminal), with OMP_NUM_THREADS as shown (unset:",
        "torch's default, one thread per core), one command at a time, on a machine that other jobs were also",
        "using: the load beside each time is the 1-minute load average (`os.getloadavg`) before and after the",
        "command; on a 2-core machine a load of 2 means both cores already busy. Installing (pip) is not included.",
        "",
        "| command | wall time | exit | load before → after | machine | OMP_NUM_THREADS | date | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key in order:
        latest = record["entries"][key]
        for e in [*latest.get("history", []), latest]:  # every measurement kept, oldest first
            lines.append(_row(e))
    lines += [
        "",
        "The same commands elsewhere, for scale: the main job took 23.4 s wall on an idle 2-core machine",
        "(2026-11-25) and 60 s on a 2-core machine at load 2–4 (issue 38); the articulated command took 901 s",
        "there (also issue 38, with output to a file). Expect times between these on a 2-core machine, longer",
        "under heavier load. A command that failed (exit ≠ 0) is listed with its time to failure; `output_tail`",
        "in the record says why. The date is the command's start.",
        "",
    ]
    text = "\n".join(lines)
    TABLE.write_text(text)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default="main,smoke,chain_data,articulated", help="comma-separated ids (see above)")
    ap.add_argument("--articulated-epochs", type=int, default=None, help="append train.epochs=N (recorded)")
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folders (printed)")
    args = ap.parse_args(argv)
    record = load_record()
    if not args.table_only:
        keys = [k.strip() for k in args.only.split(",") if k.strip()]
        unknown = [k for k in keys if k not in COMMANDS]
        if unknown:
            ap.error(f"unknown ids {unknown}; choose among {list(COMMANDS)}")
        work = Path(tempfile.mkdtemp(prefix="liedfl_run_times_"))
        chain = work / "chain"
        chain.mkdir()
        for key in keys:
            command, where, what = COMMANDS[key]
            note = what
            if key == "articulated" and args.articulated_epochs is not None:
                command += f" train.epochs={args.articulated_epochs}"
                note += f"; measured at {args.articulated_epochs} epochs, not the README's 1000"
            needs = {
                "articulated": chain / "chain.h5",
                "arm_train": work / "arm" / "arm.h5",
                "arm_export": work / "arm" / "arm_run",
            }
            if key in needs and not needs[key].exists():
                print(f"{key}: needs {needs[key].name} (run the step before it in the same call); skipped", flush=True)
                continue
            cwd = {"fresh": work / key, "chain": chain, "repo": REPO, "arm": work / "arm"}[where]
            cwd.mkdir(exist_ok=True)
            print(f"{key}: {command} (in {cwd}) ...", flush=True)
            entry = measure(key, command, cwd, work / f"{key}.log")
            entry["note"] = note
            print(f"{key}: {entry['wall_s']} s, exit {entry['exit_code']}, load {entry['load_1min_before']} -> "
                  f"{entry['load_1min_after']}", flush=True)  # fmt: skip
            add(record, key, entry)
            save_record(record)  # after each command: a long run that dies keeps what it measured
            write_table(record)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"kept {work}")
    print(write_table(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
