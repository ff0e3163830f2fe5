"""Default-train triplets/s of two checkouts, interleaved, as a ratio under the same load.

    python scripts/bench_train_vs.py --base /work/main [--new .] [--rounds 4] [--json FILE]

Each round runs `fit` of the default `liedfl train` (free rigid body, batch 1024, SOAP; 10 epochs,
best of 4 in one process, as `scripts/bench.py --quick` times it) in a fresh process per checkout,
the two alternating, and prints wall and CPU triplets/s with the 1-minute load. The ratio of the
CPU rates (best of the rounds) is the figure to quote on a shared machine; the final losses show
whether the two runs trained alike (with SOAP a last-bit difference changes them).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def worker(root: str, data_dir: str, epochs: int, repeats: int) -> None:
    sys.path.insert(0, root)
    from omegaconf import OmegaConf

    from liedfl_cli.commands.train import fit
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.data.scenes import get_dataset
    from liedfl_cli.solvers import runtime

    sys.argv = [sys.argv[0]]
    import scripts.bench as bench

    runtime.configure({"threads": "auto", "compile": "false"})
    cfg = bench.config([], data_dir)
    ds, _ = get_dataset(cfg.dataset, data_dir)
    data = ds.pose(ds.train_idx)
    tcfg = OmegaConf.merge(cfg.train, {"epochs": epochs, "checkpoint_every": 10**9})
    wall = cpu = float("inf")
    out: dict = {}
    for _ in range(repeats):
        model = build_model(cfg, ds)
        t, c = time.perf_counter(), time.process_time()
        out = fit(model, data, tcfg, int(cfg.dataset.train_steps), show_progress=False, log_epochs=False)
        wall = min(wall, (time.perf_counter() - t) / epochs)
        cpu = min(cpu, (time.process_time() - c) / epochs)
    n = out["n_samples"]
    print(json.dumps({"wall": n / wall, "cpu": n / cpu, "final_loss": out["history"][-1]["loss"]}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="checkout to compare against (e.g. the main branch)")
    ap.add_argument("--new", default=str(Path(__file__).resolve().parents[1]))
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--data-dir", default=str(Path(__file__).resolve().parents[1] / "outputs" / "data"))
    ap.add_argument("--json", help="write the rounds and the ratios here")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.data_dir, args.epochs, args.repeats)
        return
    trees = {"base": str(Path(args.base).resolve()), "new": str(Path(args.new).resolve())}
    rounds: dict[str, list[dict]] = {k: [] for k in trees}
    for _ in range(args.rounds):
        for key, root in trees.items():
            cmd = [sys.executable, __file__, "--base", args.base, "--worker", root, "--data-dir", args.data_dir,
                   "--epochs", str(args.epochs), "--repeats", str(args.repeats)]  # fmt: skip
            done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": root})
            lines = [x for x in done.stdout.splitlines() if x.startswith("{")]
            if done.returncode or not lines:
                sys.exit(f"{root}: the benchmark failed:\n{done.stderr[-2000:]}")
            row = {**json.loads(lines[-1]), "load_1min": os.getloadavg()[0]}
            rounds[key].append(row)
            print(f"{key:5s} wall {row['wall']:10.0f}  cpu {row['cpu']:10.0f} triplets/s  "
                  f"load {row['load_1min']:.1f}  final loss {row['final_loss']:.16g}", flush=True)  # fmt: skip
    best = {k: {q: max(r[q] for r in v) for q in ("wall", "cpu")} for k, v in rounds.items()}
    ratios = {q: best["new"][q] / best["base"][q] for q in ("wall", "cpu")}
    print(
        f"best: base {best['base']}, new {best['new']}; new / base: wall {ratios['wall']:.2f}, cpu {ratios['cpu']:.2f}"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"trees": trees, "rounds": rounds, "best": best, "ratio": ratios}, indent=1)
        )


if __name__ == "__main__":
    main()
