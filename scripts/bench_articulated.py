"""Exp 4 epoch, articulated against per-body model, interleaved in one process (issue 20's <= 2x target).

    python scripts/bench_articulated.py [--epochs 3] [--repeats 4] [--library-soap] [--json FILE]

`bench.py --quick` times each model once, and on a VM whose speed wanders by +-50 % within minutes
one run each says little about a ratio. Here each model trains `epochs` epochs from the same seed,
`repeats` times, in a random interleaved order. The medians of seconds per epoch and their ratio are
printed (and written to FILE). `--library-soap` makes `FusedSOAP` take pytorch_optimizer's own
per-tensor step (what every Exp 4 step did before round 6), for an A/B of the optimiser step. The
Exp 4 data are generated under --data-dir on first use (outputs/data, as `bench.py`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import random
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench import ROOT, build_model, config, fit, get_dataset, runtime, typed

from liedfl_cli.commands import fused_optim

KINETIC = ("per_body", "articulated")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=3, help="epochs per timed run")
    ap.add_argument("--repeats", type=int, default=4, help="timed runs per model")
    ap.add_argument("--library-soap", action="store_true", help="pytorch_optimizer's per-tensor SOAP step")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    args = ap.parse_args()
    runtime.configure(runtime.RuntimeOptions(threads=1, compile="false"))
    if args.library_soap:
        fused_optim.FusedSOAP._list_group = lambda self: None  # type: ignore[method-assign]
    setups = {}
    for kin in KINETIC:
        run = typed(config(["experiment=exp4_mocap", f"model.kinetic={kin}"], args.data_dir), "train")
        ds, _ = get_dataset(run.dataset, args.data_dir)
        setups[kin] = (run, ds, ds.pose(ds.train_idx))
    load_start = os.getloadavg()[0]
    order = [kin for kin in KINETIC for _ in range(args.repeats)]
    random.Random(0).shuffle(order)
    seconds: dict[str, list[float]] = {kin: [] for kin in KINETIC}
    for kin in order:
        run, ds, data = setups[kin]
        torch.manual_seed(0)
        model = build_model(run, ds)
        tcfg = dataclasses.replace(run.train, epochs=args.epochs, checkpoint_every=10**9)
        t = time.perf_counter()
        fit(model, data, tcfg, int(run.dataset.train_steps))
        seconds[kin].append((time.perf_counter() - t) / args.epochs)
    med = {kin: statistics.median(v) for kin, v in seconds.items()}
    out = {
        "mocap_s_per_epoch": med["per_body"],
        "mocap_articulated_s_per_epoch": med["articulated"],
        "mocap_articulated_over_per_body": med["articulated"] / med["per_body"],
        "runs": seconds,
        "epochs": args.epochs,
        "library_soap": args.library_soap,
        "load_avg_start": load_start,
        "load_avg_end": os.getloadavg()[0],
    }
    for kin in KINETIC:
        print(f"{kin:12s} median {med[kin]:.3f} s/epoch  runs {[round(x, 3) for x in seconds[kin]]}")
    print(f"articulated / per_body: {out['mocap_articulated_over_per_body']:.2f}x (load {load_start:.2f})")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
