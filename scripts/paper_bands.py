"""Bands over seeds for the headline figures of docs/results.md that take a few minutes a run.

`OMP_NUM_THREADS=1 python scripts/paper_bands.py [--seeds 0 1 2] [--out docs/bench/bands_<date>.json] [--only KEY]`;
`python scripts/paper_bands.py --table --out <record>` prints the record's bands as markdown.

Runs each job of JOBS (the paper's experiment file and full budget; `seed=<s>` changes the training seed,
the dataset stays the experiment's) once per seed, one at a time, in outputs/paper_bands/, and writes
after every run the record: the machine (CPU model from /proc/cpuinfo, cores, threads, torch version,
commit, load before and after each run), each run's wall and CPU seconds and the kept eval rows
(`paper_plan.EVAL_KEYS`: errors, valid horizons, both sides of every reference ratio), and per job the
band (min / median / max over seeds) of the learned model's mean relative rotation error. Same code,
seed, CPU model and thread count repeat a run exactly; another CPU or thread count need not (SOAP's
rounding sends training down another, equally good path).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JOBS = {
    "exp2 LieDFLNN length 10": ["experiment=exp2_discrete_vs_continuous", "baseline=none", "dataset.train_steps=10"],
    "exp2 LieDFLNN length 100": ["experiment=exp2_discrete_vs_continuous", "baseline=none", "dataset.train_steps=100"],
    "exp5 control": ["experiment=exp5_control"],
    "exp2 Lie-Heun length 10": [
        "experiment=exp2_discrete_vs_continuous",
        "baseline=glnn_lie_heun",
        "dataset.train_steps=10",
    ],
    "exp2 Lie-Heun length 100": [
        "experiment=exp2_discrete_vs_continuous",
        "baseline=glnn_lie_heun",
        "dataset.train_steps=100",
    ],
    "exp2 GLNN-RK4 length 10": [
        "experiment=exp2_discrete_vs_continuous",
        "baseline=glnn_rk4",
        "dataset.train_steps=10",
    ],
    "exp2 GLNN-RK4 length 100": [  # the other half of Exp 2's claim (issue 36: ten minutes of one core a run)
        "experiment=exp2_discrete_vs_continuous",
        "baseline=glnn_rk4",
        "dataset.train_steps=100",
    ],
    # Exp 1's headline (Euler angles 25x worse at the fastest start): 7 / 19 minutes of one core a run
    "exp1 LieDFLNN omega 1.0": [
        "experiment=exp1_euler_vs_lie",
        "baseline=none",
        "dataset.initial.omega_scale=1.0",
    ],
    "exp1 Euler DFLNN omega 1.0": [
        "experiment=exp1_euler_vs_lie",
        "baseline=euler_dflnn",
        "dataset.initial.omega_scale=1.0",
    ],
    # Exp 4 at the full 10,000 epochs: about an hour of one core a run (per body), 1.5 (articulated)
    "exp4 per body": ["experiment=exp4_mocap", "model.kinetic=per_body"],
    "exp4 articulated": ["experiment=exp4_mocap", "model.kinetic=articulated"],
}
"""The banded jobs: those whose full budget takes minutes of one core ("The whole paper in one run"), then
Exp 1's headline and Exp 4 (an hour or more a run: LONG)."""
LONG = ("exp4 per body", "exp4 articulated")
"""Run only when named by --only (a plain run leaves out their 6-9 CPU hours)."""


def _plan():
    spec = importlib.util.spec_from_file_location("paper_plan", ROOT / "scripts" / "paper_plan.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["paper_plan"] = mod
    spec.loader.exec_module(mod)
    return mod


def machine() -> dict:
    """CPU model, cores, threads, torch, commit: what a figure's record names beside it."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # (also when loaded by file path)
    from machine_info import cpu_model

    cpu = cpu_model("?")
    import torch

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return {
        "cpu_model": cpu,
        "cores": os.cpu_count(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "commit": commit.stdout.strip() or None,
        "load_1min_start": os.getloadavg()[0],
    }


def band(values: list[float]) -> dict | None:
    v = sorted(x for x in values if x is not None)
    return {"min": v[0], "median": statistics.median(v), "max": v[-1], "n": len(v)} if v else None


def table(path: Path) -> str:
    """Markdown: per job of the record, the learned model's mean relative rotation error per seed, its band,
    the rollout and one-step ratios to the best zero-parameter reference (same samples), and the CPU seconds."""
    rec = json.loads(path.read_text())
    lines = [
        "| job | seeds | mean rel. rotation error per seed | band (min – max) | rollout ÷ best reference | "
        "one step ÷ best reference | beats every reference | CPU s per run |",
        "|---|---|---|---|---|---|---|---|",
    ]
    fmt = lambda x: "–" if x is None else f"{x:.3g}"
    for key, job in rec["jobs"].items():
        runs = {s: r for s, r in job["runs"].items() if r.get("exit_code") == 0}
        rows = {s: next((e for e in r.get("eval", []) if e.get("model") == "model"), {}) for s, r in runs.items()}
        errs = [rows[s].get("rel_rot_error_mean") for s in runs]
        b = band(errs)

        def span(k: str, rows: dict = rows) -> str:
            v = [r[k] for r in rows.values() if r.get(k) is not None]
            return f"{fmt(min(v))} – {fmt(max(v))}" if v else "–"

        beats = {rows[s].get("beats_references") for s in runs}
        cpu = [r["cpu_seconds"] for r in runs.values()]
        lines.append(
            f"| {key} | {', '.join(runs)} | {' / '.join(fmt(e) for e in errs)} "
            f"| {fmt(b['min']) + ' – ' + fmt(b['max']) if b else '–'} | {span('rollout_vs_best')} "
            f"| {span('one_step_vs_best')} | {' / '.join(str(x) for x in sorted(beats, key=str))} "
            f"| {fmt(min(cpu)) + ' – ' + fmt(max(cpu)) if cpu else '–'} |"
        )
    m = rec.get("machine", {})
    lines.append("")
    lines.append(
        f"Machine: {m.get('cpu_model')}, {m.get('cores')} cores, OMP_NUM_THREADS={m.get('omp_num_threads')}, "
        f"torch {m.get('torch')}, commit {m.get('commit')}."
    )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "bench" / f"bands_{datetime.now():%Y-%m-%d}.json")
    ap.add_argument("--only", nargs="*", default=None, help="job keys of JOBS (default: all but LONG)")
    ap.add_argument("--table", action="store_true", help="print the record's bands as markdown, run nothing")
    a = ap.parse_args()
    if a.table:
        print(table(a.out))
        return
    plan = _plan()
    rec = json.loads(a.out.read_text()) if a.out.is_file() else {"jobs": {}}
    rec["machine"] = machine()
    rec["command"] = "OMP_NUM_THREADS=1 python scripts/paper_bands.py " + " ".join(sys.argv[1:])
    work = ROOT / "outputs" / "paper_bands"
    for key, overrides in JOBS.items():
        if (a.only and key not in a.only) or (not a.only and key in LONG):
            continue
        job = rec["jobs"].setdefault(key, {"overrides": overrides, "runs": {}})
        for seed in a.seeds:
            if str(seed) in job["runs"] and job["runs"][str(seed)].get("exit_code") == 0:
                continue
            run = work / f"{key.replace(' ', '_')}_seed{seed}"
            cmd = [sys.executable, "-m", "liedfl_cli", "train", *overrides, f"seed={seed}", "ui.progress=false"]
            cmd += [f"hydra.run.dir={run}"]
            load = os.getloadavg()[0]
            t0, c0 = time.perf_counter(), os.times()
            proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
            c1 = os.times()
            r = {
                "exit_code": proc.returncode,
                "wall_seconds": round(time.perf_counter() - t0, 2),
                "cpu_seconds": round(
                    (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system), 2
                ),
                "load_1min": load,
                "load_1min_end": os.getloadavg()[0],
                "measured": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            }
            if proc.returncode == 0:
                r["eval"] = plan.eval_rows(run)
            else:
                r["error"] = (proc.stderr.strip().splitlines() or ["?"])[-1][:300]
            job["runs"][str(seed)] = r
            errs = [
                e.get("rel_rot_error_mean")
                for x in job["runs"].values()
                for e in x.get("eval", [])
                if e.get("model") == "model"
            ]
            job["band_rel_rot_error_mean"] = band(errs)
            a.out.parent.mkdir(parents=True, exist_ok=True)
            tmp = a.out.with_suffix(".tmp")  # write then rename: a killed run never leaves half a record
            tmp.write_text(json.dumps(rec, indent=1, default=str) + "\n")
            tmp.replace(a.out)
            print(
                f"{key} seed {seed}: exit {proc.returncode}, {r['wall_seconds']} s, "
                f"band {job['band_rel_rot_error_mean']}",
                flush=True,
            )


if __name__ == "__main__":
    main()
