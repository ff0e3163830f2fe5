"""Exp 3's cause, tested: does the learned MLP potential go wrong where the bodies leave the positions
it was trained on? (docs/results.md, "The cause, tested")

    python scripts/exp3_extrapolation.py RUN [RUN ...] [--json FILE]

For each trained Exp 3 run (`liedfl train experiment=exp3_manifold`, LieDFLNN with the paper's MLP
potential V(R, p)), along the TEST trajectories (the true poses over the whole rollout), the learned
translational acceleration the potential implies, a = -(1/m) dV/dp (m the learned mass: the data fix
L_d only up to a factor, the acceleration is free of it), against the truth, -g e3. Each sample is
binned by how far it lies from the training positions: d = |p - c| / r, c the centroid and r the
largest distance from it of the positions the model trained on (the train split's first
`dataset.train_steps` steps). d <= 1 is inside the training cloud's radius. The relative error
|a - a_true| / g per bin says whether the potential is right where it was trained and wrong beyond; the
same for the gravity torque per unit mass (left derivative of V along the body's rotation, against
-g rho x R^T e3), relative to g |rho|.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from liedfl_cli import api  # noqa: E402
from liedfl_cli.lie import Pose  # noqa: E402

BINS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, math.inf)


def learned_acceleration(model, R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """-(1/m) dV/dp of the model's potential at poses (N, B, 3, 3), (N, m, 3) -> (N, 3) (the SE(3) body)."""
    p = p.clone().requires_grad_(True)
    V = model.potential(Pose(R, p)).sum()
    (grad,) = torch.autograd.grad(V, p)
    m = float(model.physical_parameters()["m"][0])
    return -grad[:, 0] / m


def learned_torque_per_mass(model, R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """-(1/m) of the left derivative of the potential along R exp(hat(e)) at e = 0 (body frame) -> (N, 3):
    the gravity torque per unit mass, free of the overall factor of L_d as the acceleration is."""
    from liedfl_cli.lie import so3

    e = torch.zeros(R.shape[0], 3, dtype=R.dtype, requires_grad=True)
    R1 = R.clone()
    R1[:, 0] = R[:, 0] @ so3.exp(e)
    V = model.potential(Pose(R1, p)).sum()
    (grad,) = torch.autograd.grad(V, e)
    return -grad / float(model.physical_parameters()["m"][0])


def analyse(run_dir: Path) -> dict:
    run = api.load_run(run_dir, checkpoint="best")
    ds, model = run.dataset, run.model
    phys = ds.params["physics"]
    g = float(phys.get("g", 9.81))
    steps = int(run.config.dataset.train_steps)
    train_p = ds.p[ds.train_idx, : steps + 1, 0].reshape(-1, 3)
    c = train_p.mean(0)
    r = float(np.linalg.norm(train_p - c, axis=-1).max())
    R = torch.as_tensor(ds.R[ds.test_idx].reshape(-1, ds.n_bodies, 3, 3), dtype=torch.float64)
    p = torch.as_tensor(ds.p[ds.test_idx].reshape(-1, ds.n_se3, 3), dtype=torch.float64)
    a = learned_acceleration(model, R, p).detach().numpy()
    a_true = np.array([0.0, 0.0, -g])
    rel = np.linalg.norm(a - a_true, axis=-1) / g
    # the true gravity torque per unit mass in the body frame: -g rho x (R^T e3)
    rho = np.asarray(phys["rho"], dtype=float)
    up_body = R[:, 0].transpose(-1, -2).numpy() @ np.array([0.0, 0.0, 1.0])
    tau_true = -g * np.cross(rho, up_body)
    tau = learned_torque_per_mass(model, R, p).detach().numpy()
    rel_tau = np.linalg.norm(tau - tau_true, axis=-1) / (g * np.linalg.norm(rho))
    d = np.linalg.norm(p[:, 0].numpy() - c, axis=-1) / r
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (d > lo) & (d <= hi) if lo > 0 else d <= hi
        if sel.any():
            rows.append({"d_from": lo, "d_to": hi, "samples": int(sel.sum()), "rel_accel_error_median":
                         float(np.median(rel[sel])), "rel_accel_error_mean": float(rel[sel].mean()),
                         "rel_torque_error_median": float(np.median(rel_tau[sel]))})  # fmt: skip
    evaluation = {}  # the run's own evaluation (eval.csv): the rollout figures beside the diagnosis
    if (run_dir / "eval.csv").is_file():
        import csv

        with open(run_dir / "eval.csv") as f:
            for row in csv.DictReader(f):
                evaluation[row["model"]] = {k: float(row[k]) for k in ("rel_rot_error_mean", "position_error_mean",
                                            "train_seconds") if row.get(k) not in (None, "")}  # fmt: skip
    return {"run": str(run_dir), "seed": int(run.config.seed or 0), "train_radius": r, "max_d": float(d.max()),
            "bins": rows, "eval": evaluation}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = {"runs": [analyse(Path(r)) for r in args.runs]}
    for res in out["runs"]:
        print(f"{res['run']} (seed {res['seed']}): training radius {res['train_radius']:.3g}, test up to "
              f"{res['max_d']:.3g}x it")  # fmt: skip
        print("| distance / training radius | samples | median |a - a_true| / g | mean | median torque error |")
        print("|---|---|---|---|---|")
        for b in res["bins"]:
            print(f"| {b['d_from']:g}–{b['d_to']:g} | {b['samples']} | {b['rel_accel_error_median']:.3g} | "
                  f"{b['rel_accel_error_mean']:.3g} | {b['rel_torque_error_median']:.3g} |")  # fmt: skip
    if args.json:
        tmp = Path(args.json).with_name(f".{Path(args.json).name}.tmp{os.getpid()}")
        tmp.write_text(json.dumps(out, indent=1))
        os.replace(tmp, args.json)


if __name__ == "__main__":
    main()
