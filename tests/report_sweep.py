"""A synthetic sweep for `liedfl report` (run folders with the files the report reads, no training):
`points` model/setting combinations x `seeds` runs, spread over decades of speed and error, some
with a standard deviation wider than the mean (the case a log-axis error bar must survive)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

MODELS = ("liedflnn", "euclidean_dflnn", "neural_ode", "glnn_rk4")


def fake_sweep(root: Path, points: int = 16, seeds: int = 3, seed: int = 0, cv=None) -> Path:
    """Write the sweep under `root / 'sweep'` and return it. Run k = (model k % 4, train_steps
    setting k // 4); the error and the speeds are drawn log-uniformly, the seeds scattered around them.
    cv: constant velocity's rel_rot_error_mean, one value for every run or a function of the run's
    number (None: no constant-velocity row)."""
    rng = np.random.default_rng(seed)
    sweep = root / "sweep"
    job = 0
    for k in range(points):
        model = MODELS[k % len(MODELS)]
        steps = 16 * 2 ** (k // len(MODELS))
        err, train_s, roll_s = 10 ** rng.uniform(-3, 0.5), 10 ** rng.uniform(0, 3), 10 ** rng.uniform(-5, -2)
        wide = k % 5 == 0  # seeds that disagree by more than their mean
        for s in range(seeds):
            run = sweep / str(job)
            (run / ".hydra").mkdir(parents=True)
            jitter = (0.05, 0.1, 2.85)[s % 3] if wide else rng.uniform(0.8, 1.25)  # wide: std > mean
            cfg = {"seed": s, "model": {"name": model}, "dataset": {"name": "heavy_se3", "train_steps": steps}}
            (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(cfg))
            overrides = [f"model={model}", f"dataset.train_steps={steps}", f"seed={s}"]
            (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
            e = err * jitter
            header = "model,rel_rot_error_mean,geodesic_error_mean,rollout_s_per_step,rollout_trajectories"
            row = f"model,{e},{2 * e},{roll_s * 10 * rng.uniform(0.9, 1.1)},10"
            if cv is not None:
                row += f"\nconstant_velocity,{cv(job) if callable(cv) else cv},,,"
            (run / "eval.csv").write_text(f"{header}\n{row}\n")
            timings = {"train_seconds": train_s * rng.uniform(0.9, 1.1), "seconds_per_epoch": 0.1, "parameters": 15}
            (run / "summary.json").write_text(json.dumps({"timings": timings}))
            job += 1
    return sweep
