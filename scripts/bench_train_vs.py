"""Default-train triplets/s of two checkouts in one process, interleaved: a ratio under the same load.

    python scripts/bench_train_vs.py --base /work/main [--new .] [--rounds 12] [--json FILE]

Both checkouts' `liedfl_cli` are imported into this process (each under its own snapshot of
`sys.modules`, swapped in before each of its calls, so hydra's `_target_` finds that checkout's
classes); each round runs `fit` of the default `liedfl train` (free rigid body, batch 1024, SOAP,
10 epochs, as `scripts/bench.py --quick` times it) once per checkout, alternately. Printed: the
best wall and CPU triplets/s of each, the median of the per-round new / base ratios (round 1, which
pays the lazy set-up of both, left out) and the final losses (with SOAP a last-bit difference in a
gradient changes them). On a shared machine the median CPU ratio is the figure to quote.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ours(name: str) -> bool:
    return name == "liedfl_cli" or name.startswith("liedfl_cli.")


def _use(snapshot: dict) -> None:
    for name in [n for n in sys.modules if _ours(n)]:
        del sys.modules[name]
    sys.modules.update(snapshot)


def _load(root: str) -> tuple[dict, dict]:
    """(snapshot of sys.modules for `root`'s liedfl_cli, its entry points)."""
    _use({})
    sys.path.insert(0, root)
    try:
        from liedfl_cli.cli import CONF_DIR
        from liedfl_cli.commands.train import fit
        from liedfl_cli.config.factory import build_model
        from liedfl_cli.data.scenes import get_dataset
        from liedfl_cli.solvers import runtime
    finally:
        sys.path.remove(root)
    snapshot = {n: m for n, m in sys.modules.items() if _ours(n)}
    # a checkout from before the callbacks (issue 35) prints unless told not to; fit is silent since
    quiet = {"show_progress": False, "log_epochs": False} if "log_epochs" in inspect.signature(fit).parameters else {}
    entry = {"conf": CONF_DIR, "fit": fit, "build": build_model, "data": get_dataset, "runtime": runtime}
    return snapshot, {**entry, "quiet": quiet}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="checkout to compare against (e.g. the main branch)")
    ap.add_argument("--new", default=str(ROOT))
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    ap.add_argument("--json", help="write the rounds and the ratios here")
    args = ap.parse_args()
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    trees = {"base": str(Path(args.base).resolve()), "new": str(Path(args.new).resolve())}
    loaded = {k: _load(root) for k, root in trees.items()}
    runs = {}
    for key, (snapshot, api) in loaded.items():
        _use(snapshot)
        rt = api["runtime"]  # RuntimeOptions: what both the typed and the mapping `configure` accept
        rt.configure(rt.RuntimeOptions(threads="auto", compile="false"))
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(api["conf"]), version_base="1.3"):
            paths = [f"paths.data_dir={args.data_dir}", "paths.output_dir=/tmp/liedfl-bench"]
            cfg = compose("train", overrides=paths)
        ds, _ = api["data"](cfg.dataset, args.data_dir)
        tcfg = OmegaConf.merge(cfg.train, {"epochs": args.epochs, "checkpoint_every": 10**9})
        runs[key] = (cfg, ds, ds.pose(ds.train_idx), tcfg)
    rounds: dict[str, list[dict]] = {k: [] for k in trees}
    for _ in range(args.rounds):
        for key, (snapshot, api) in loaded.items():
            _use(snapshot)
            cfg, ds, data, tcfg = runs[key]
            model = api["build"](cfg, ds)
            t, c = time.perf_counter(), time.process_time()
            out = api["fit"](model, data, tcfg, int(cfg.dataset.train_steps), **api["quiet"])
            wall, cpu = time.perf_counter() - t, time.process_time() - c
            n = out["n_samples"] * args.epochs
            rounds[key].append({"wall": n / wall, "cpu": n / cpu, "final_loss": out["history"][-1]["loss"],
                                "load_1min": os.getloadavg()[0]})  # fmt: skip
    best = {k: {q: max(r[q] for r in v) for q in ("wall", "cpu")} for k, v in rounds.items()}
    pairs = list(zip(rounds["base"], rounds["new"]))[1:] or list(zip(rounds["base"], rounds["new"]))
    median = {q: statistics.median(n[q] / b[q] for b, n in pairs) for q in ("wall", "cpu")}
    loads = [r["load_1min"] for r in rounds["new"]]
    finals = {k: v[-1]["final_loss"] for k, v in rounds.items()}
    for key in trees:
        print(f"{key:4s} best wall {best[key]['wall']:9.0f}  cpu {best[key]['cpu']:9.0f} triplets/s  "
              f"final loss {finals[key]:.16g}")  # fmt: skip
    print(f"new / base, median over rounds: cpu {median['cpu']:.2f}, wall {median['wall']:.2f} "
          f"(1-minute load {min(loads):.1f}-{max(loads):.1f})")  # fmt: skip
    if args.json:
        record = {"trees": trees, "rounds": rounds, "best": best, "median_ratio": median, "final_loss": finals}
        Path(args.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
