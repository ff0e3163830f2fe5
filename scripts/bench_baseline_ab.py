"""Seconds per training epoch of a paper baseline: this checkout against another one (an A/B of two
commits), arms interleaved, each in its own process (so each imports its own code).

    git worktree add /tmp/old <commit>
    python scripts/bench_baseline_ab.py --old /tmp/old --baseline glnn_rk4 --lengths 10 40 70 100

For each Exp 2 training length (or the experiment's own setting when --lengths is not given): `--rounds`
rounds of [old, new] (or [new, old], alternating), each arm `bench.epoch_seconds` (fused path, best of
`--repeats` fits of `--epochs` epochs, one torch thread). Prints median wall and CPU seconds per epoch
and new ÷ old; `--reference` adds this checkout's reference path (`runtime.fused=false`); `--from-run RUN`
starts every fit from that run's last weights (an adaptive solver's cost grows as the field is trained).
Take the figures on an idle machine (the 1-minute load is printed beside them).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# the arm: run in a child process with the checkout's root first on sys.path
ARM = """
import json, sys
root, base, length, epochs, repeats, data, reference, run = sys.argv[1:9]
sys.path[:0] = [root, root + "/scripts"]
import torch
torch.set_num_threads(1)
import bench, liedfl_cli
assert liedfl_cli.__file__.startswith(root), liedfl_cli.__file__
if run != "-":  # start every fit from that run's last weights (a trained, stiffer field)
    from liedfl_cli import api
    weights = api.load_run(run, data_dir=data, checkpoint="last").model.state_dict()
    build = bench.build_model
    def build_model(*a, **k):
        model = build(*a, **k)
        model.load_state_dict(weights)
        return model
    bench.build_model = build_model
ov = list(bench.BASELINES[base])
if length != "-":
    ov = [o for o in ov if not o.startswith("dataset.train_steps")] + ["dataset.train_steps=" + length]
r = bench.epoch_seconds(ov, int(epochs), int(repeats), data, reference=reference == "1")
print(json.dumps(r))
"""


def arm(root: Path, args, length: str, reference: bool) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", ARM, str(root), args.baseline, length, str(args.epochs), str(args.repeats)]
        + [str(Path(args.data_dir).resolve()), "1" if reference else "0", args.from_run or "-"],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "PYTHONPATH": str(root)},
    )
    if out.returncode:
        sys.exit(f"error: the arm at {root} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="the other checkout (a git worktree of the older commit)")
    ap.add_argument("--baseline", default="glnn_rk4", help="a key of bench.BASELINES")
    ap.add_argument("--lengths", nargs="*", default=["-"], help="Exp 2 training lengths (default: the setting's)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--reference", action="store_true", help="also this checkout's reference path")
    ap.add_argument("--from-run", help="a run folder of this baseline: every fit starts from its last weights")
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    old = Path(args.old).resolve()
    if not (old / "liedfl_cli").is_dir():
        sys.exit(f"error: --old {old}: not a liedfl checkout (no liedfl_cli/)")
    rows = []
    print(f"load {os.getloadavg()[0]:.2f} at the start; {args.baseline}, {args.epochs} epochs x best of {args.repeats}")
    for length in args.lengths:
        runs: dict[str, list[dict]] = {"old": [], "new": []}
        for r in range(args.rounds):
            order = ("old", "new") if r % 2 == 0 else ("new", "old")
            for name in order:
                runs[name].append(arm(old if name == "old" else ROOT, args, length, False))
        med = {k: {m: statistics.median(x[m] for x in v) for m in ("fused", "cpu")} for k, v in runs.items()}
        row = {
            "length": length,
            "old_s": med["old"]["fused"],
            "new_s": med["new"]["fused"],
            "old_cpu_s": med["old"]["cpu"],
            "new_cpu_s": med["new"]["cpu"],
            "speedup_cpu": med["old"]["cpu"] / med["new"]["cpu"],
        }
        if args.reference:
            ref = arm(ROOT, args, length, True)
            row["reference_s"], row["reference_cpu_s"] = ref["reference"], ref["cpu_ref"]
        rows.append(row)
        extra = f", reference {row['reference_cpu_s']:.3f}" if args.reference else ""
        print(
            f"length {length}: old {row['old_cpu_s']:.3f} / new {row['new_cpu_s']:.3f} CPU s per epoch "
            f"({row['speedup_cpu']:.2f}x; wall {row['old_s']:.3f} / {row['new_s']:.3f}){extra}"
            f"  load {os.getloadavg()[0]:.2f}"
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {"baseline": args.baseline, "old": str(old), "rows": rows, "load_end": os.getloadavg()}, indent=2
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
