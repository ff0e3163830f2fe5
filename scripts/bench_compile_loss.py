"""Compile time and per-step cost of the compiled training loss against eager, one process.

    python scripts/bench_compile_loss.py [--experiment exp4_mocap] [--steps 20] [--json FILE] [--data-dir DIR]
                                         [overrides...]

Builds the experiment's model (with the Hydra overrides given, e.g. `model.kinetic=articulated`) and one
training batch, compiles its loss as `runtime.compile=true` does (`torch.compile(dynamic=True)`: the fused
`increments_loss` of engines/training.py for LieDFLNN, `ArticulatedLieDFLNN.loss`'s DEL loss for the
articulated model), and prints the compile time and the CPU time of one forward + backward step, eager
and compiled (best of 3 x `--steps`). Figures: docs/benchmarks.md, "Compilation".
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from bench import config  # noqa: E402
from machine_info import cpu_model  # noqa: E402

from liedfl_cli.config.factory import build_model  # noqa: E402
from liedfl_cli.data.scenes import get_dataset  # noqa: E402
from liedfl_cli.files.io_utils import write_json  # noqa: E402
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN  # noqa: E402
from liedfl_cli.models.base import LossOptions  # noqa: E402
from liedfl_cli.models.liedflnn.engines import core as fused  # noqa: E402
from liedfl_cli.models.liedflnn.engines.training import increments_loss as fused_loss  # noqa: E402
from liedfl_cli.solvers import runtime  # noqa: E402
from liedfl_cli.solvers.execution import ExecutionPlan  # noqa: E402


def step_seconds(fn, model, batch, opts, steps: int) -> float:
    best = float("inf")
    for _ in range(3):
        t = time.process_time()
        for _ in range(steps):
            loss, _ = fn(model, batch, opts)
            loss.backward()
        best = min(best, (time.process_time() - t) / steps)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="exp4_mocap")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the experiment (model.kinetic=articulated)")
    args = ap.parse_args()
    runtime.configure(runtime.RuntimeOptions(threads=1, compile="false"))
    cfg = config([f"experiment={args.experiment}", *args.overrides], args.data_dir)
    ds, _ = get_dataset(cfg.dataset, args.data_dir)
    model = build_model(cfg, ds)
    tset = model.training_set(ds.pose(ds.train_idx), int(cfg.dataset.train_steps))
    batch_size = min(int(cfg.train.batch_size), tset.n)
    batch = tset.batch(torch.arange(batch_size), torch.Generator().manual_seed(0), 10)
    opts = LossOptions()
    load_start = os.getloadavg()[0]
    if isinstance(model, ArticulatedLieDFLNN):  # the model's own routing (`runtime.compile=true`)
        model.set_plan(ExecutionPlan(compile="true"))

        def eager_loss(m, b, o):
            return m._loss(b, o)

        def compiled(m, b, o):
            return m.loss(b, o)

    else:
        eager_loss = fused_loss
        fused.warm_caches(torch.float64, torch.device("cpu"), float(model.h))
        compiled = torch.compile(fused_loss, dynamic=True)
    t = time.perf_counter()
    compiled(model, batch, opts)[0].backward()
    compile_s = time.perf_counter() - t
    eager = step_seconds(eager_loss, model, batch, opts, args.steps)
    comp = step_seconds(compiled, model, batch, opts, args.steps)
    name = " ".join([args.experiment, *args.overrides])
    print(
        f"{name}: compile {compile_s:.1f} s; forward+backward CPU per step: eager {eager * 1e3:.2f} ms, "
        f"compiled {comp * 1e3:.2f} ms ({eager / comp:.2f}x)"
    )
    if args.json:
        out = {
            "job": name,
            "cpu": cpu_model(),
            "threads": 1,
            "batch": batch_size,
            "compile_s": compile_s,
            "eager_ms_per_step": eager * 1e3,
            "compiled_ms_per_step": comp * 1e3,
            "speedup": eager / comp,
            "inductor_cache_dir": os.environ.get("TORCHINDUCTOR_CACHE_DIR", "default (warm when compiled before)"),
            "load_1min_start": load_start,
            "load_1min_end": os.getloadavg()[0],
        }
        write_json(args.json, out)  # write then rename: a killed run never leaves half a record


if __name__ == "__main__":
    main()
