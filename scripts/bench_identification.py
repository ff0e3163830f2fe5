"""Identification (`liedfl_cli.models.articulated.identification.identify`: weighted least squares + Levenberg-Marquardt
in log-Cholesky parameters) against the least-squares start (`models.articulated.fit`) and against the
default first-order training (SOAP, lr 3e-3, DEL + regularity loss, batches of 1024, from the equal-mass
start) given the same wall time, on MuJoCo scenes (docs/identification.md).

    OMP_NUM_THREADS=1 python scripts/bench_identification.py [scene ...] [--out docs/bench/identification.json]

Each scene: 64 trajectories x 100 steps (seed 555), 56 to fit and 8 to test, the model built with the
declared joints; figures: seconds, the one-step teacher-forced rotation error over constant velocity's and
the 50-step rollout error over the constant-velocity rollout's on the test trajectories.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

from liedfl_cli.data.mujoco_chain import chain_dataset
from liedfl_cli.models.articulated import identification as idf
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedTriplets
from liedfl_cli.models.base import LossOptions

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from articulated_scenes import SCENES as ACCEPTANCE  # noqa: E402  (the acceptance scenes, beside this script)

# the acceptance scenes this benchmark uses, plus a heavy-root branched tree in millimetres
SCENES: dict[str, dict] = {
    **{k: ACCEPTANCE[k] for k in ("chain4_heavy_root", "chain4_heavy_root_mm", "tree5_ball")},
    "tree5_heavy_root_mm": {
        "parents": [-1, 0, 0, 0, 1],
        "joints": ["free", "ball", "ball", "ball", "ball"],
        "heavy_root": True,
        "unit": "mm",
    },
    **{
        k: ACCEPTANCE[k]
        for k in ("tree5_universal_weld", "arm4_hinge_pinned_gravity", "tree4_pinned_universal_gravity")
    },
}


def build(ds, kw):
    pot = ("uniform_gravity",) if kw.get("gravity") else ()
    g = ds.params["physics"]["g"] or 9.81
    return ArticulatedLieDFLNN(ds.tree, ds.h, potential=pot, forces=("rayleigh",), gravity=g)


def first_order(model, trip, seconds: float, seed: int = 0) -> tuple[int, float]:
    """The default epochs (SOAP lr 3e-3, DEL w 0.5 + regularity w 0.5 with 10 pairs, batches of 1024) until
    `seconds` have passed; returns (epochs, seconds)."""
    from liedfl_cli.commands.train import make_optimizer
    from liedfl_cli.config.typed import OptimizerConfig

    params = [p for p in model.parameters() if p.requires_grad]
    opt = make_optimizer(params, OptimizerConfig())
    opts = LossOptions()
    gen = torch.Generator().manual_seed(seed)
    t0, epochs = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        perm = torch.randperm(trip.n, generator=gen)
        for i in range(0, trip.n, 1024):
            batch = trip.batch(perm[i : i + 1024], gen, opts.reg_points)
            loss, _ = model.loss(batch, opts)
            opt.zero_grad()
            loss.backward()
            opt.step()
        epochs += 1
    return epochs, time.perf_counter() - t0


def ratios(model, test) -> tuple[float, float]:
    return idf.one_step_ratio(model, test), idf.rollout_ratio(model, test, 50)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--out", default=str(ROOT / "docs/bench/identification.json"))
    ap.add_argument("--iterations", type=int, default=60)
    a = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print(f"{'scene':32s} {'method':26s} {'seconds':>8s} {'one step/CV':>12s} {'50 steps/CV':>12s}", flush=True)
    for name in a.scenes:
        kw = {"h": 0.05, **SCENES[name]}
        ds = chain_dataset(n_trajectories=64, steps=100, seed=555, **kw)
        truth = ds.pose()
        train, test = truth.index(slice(0, 56)), truth.index(slice(56, 64))

        def row(method, seconds, model, extra=None, name=name, test=test):
            one, roll = ratios(model, test)
            rows.append(
                {
                    "scene": name,
                    "method": method,
                    "seconds": seconds,
                    "one_step_ratio": one,
                    "rollout50_ratio": roll,
                    **(extra or {}),
                }
            )
            print(f"{name:32s} {method:26s} {seconds:8.1f} {one:12.4f} {roll:12.4f}", flush=True)

        model = build(ds, kw)
        row("equal-mass start", 0.0, model)
        trip = ArticulatedTriplets(model, train, 100)
        t = time.perf_counter()
        res = idf.identify(model, trip, iterations=a.iterations, log=None)
        t_id = time.perf_counter() - t
        row("identify (LS + LM)", t_id, model, {"identification": res.as_dict()})
        from liedfl_cli.models.articulated.fit import least_squares_start

        model = build(ds, kw)
        trip = ArticulatedTriplets(model, train, 100)
        t = time.perf_counter()
        least_squares_start(model, trip, epsilon=10.0)
        row("least-squares start", time.perf_counter() - t, model)
        model = build(ds, kw)
        trip = ArticulatedTriplets(model, train, 100)
        epochs, secs = first_order(model, trip, t_id)
        row(f"first order ({epochs} epochs)", secs, model, {"epochs": epochs})
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.machine(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "omp": os.environ.get("OMP_NUM_THREADS"),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "trajectories": "64 x 100 steps, seed 555, 56 fit / 8 test",
    }
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
