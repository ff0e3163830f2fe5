"""Speed against error beside MuJoCo: liedfl's articulated scheme and MuJoCo's integrators on the same
tree, error after a horizon against a fine-step reference, cost per trajectory per simulated second.

    python scripts/bench_mujoco.py [--tree branched5] [--joints ball] [--trajectories 8]
                                   [--horizons 1 5] [--batch 1 1000] [--json FILE] [--figure PNG]

The tree (`data.mujoco_chain.chain_dataset`: random links from `--seed`, a free root, gravity 9.81,
joint damping 0.05) is simulated by MuJoCo with RK4 at dt = 1e-4 from `--trajectories` random initial
states and sampled every h: that is the reference. Then, from the same initial states,
- liedfl's true-parameter articulated scheme (`models.true_scheme.true_model`: the tree's masses,
  centres of mass, inertias, damping and gravity as declared, joints as in the file) at h = 0.01 ...
  0.1, started from the reference's first two samples (a variational integrator starts from two
  poses; MuJoCo from a state), rolled out over the horizon;
- MuJoCo's RK4, Euler and implicitfast at dt = 1e-4 ... 5e-2 on the true MJCF, started from the
  reference's qpos/qvel.
Error: the mean over trajectories and bodies of the geodesic distance between the world attitudes and
the reference's at the horizon (rad), and the root position error (m). Cost: wall seconds of the
rollout (best of `--repeats`) per trajectory per simulated second; liedfl at batch 1 (the first
trajectory alone) and at `--batch` (the trajectories tiled), MuJoCo one trajectory at a time (its
Python `mj_step(nstep=...)` loop is C; MuJoCo batches by threads, which this 2-core machine does not
give it). One thread each (`torch.set_num_threads(1)`), in one process: ratios hold on a loaded
machine better than absolute times. The learned model is not in this script (it would add training:
docs/benchmarks.md gives its rollout cost, the same engine as the true scheme).

A failed liedfl rollout (Newton did not converge) is reported with its valid horizon; its error is
then NaN, never an average over the steps before the failure.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from machine_info import cpu_model  # noqa: E402

from liedfl_cli.data.mujoco_chain import TREES, chain_dataset, require_mujoco  # noqa: E402
from liedfl_cli.lie import Pose, so3  # noqa: E402
from liedfl_cli.models.true_scheme import true_model  # noqa: E402
from liedfl_cli.solvers.options import SolverOptions  # noqa: E402

FINE_DT = 1e-4
LIEDFL_H = (0.01, 0.02, 0.05, 0.1)
MUJOCO_DT = (1e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2, 5e-2, 0.1)  # (0.1: liedfl's largest step)
INTEGRATORS = ("RK4", "Euler", "implicitfast")


def geodesic(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """|log(Ra^T Rb)| (..., 3, 3) -> (...), rad: `so3.geodesic_distance` (through the log; an arccos of the
    trace would floor small errors at ~1e-8 rad)."""
    return so3.geodesic_distance(torch.as_tensor(Ra), torch.as_tensor(Rb)).numpy()


def reference(args, h: float, steps: int):
    """The MuJoCo reference sampled every h (a liedfl Dataset, world attitudes)."""
    return chain_dataset(
        parents=TREES.get(args.tree, args.tree),
        joints=[args.joints] * (len(TREES[args.tree]) - 1) if args.tree in TREES else None,
        root="free",
        gravity=9.81,
        joint_damping=0.05,
        n_trajectories=args.trajectories,
        steps=steps,
        h=h,
        dt=FINE_DT,
        seed=args.seed,
        speed=args.speed,
        test_fraction=0.0,
        rotations="world",
    )


def best_of(fn, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def liedfl_rows(args, horizon: float, truth_R: np.ndarray, truth_p: np.ndarray) -> list[dict]:
    rows = []
    for h in LIEDFL_H:
        steps = int(round(horizon / h))
        ds = reference(args, h, steps)
        model = true_model(ds)
        assert model is not None, "a MuJoCo tree declares its physics"
        model.requires_grad_(False)
        R = torch.as_tensor(ds.R, dtype=torch.float64)
        p = torch.as_tensor(ds.p, dtype=torch.float64)
        g0, g1 = Pose(R[:, 0], p[:, 0]), Pose(R[:, 1], p[:, 1])
        solver = SolverOptions()
        ro = model.rollout(g0, g1, steps, solver)
        conv = np.asarray(ro.converged) if getattr(ro, "converged", None) is not None else None
        ok = conv is None or bool(conv.all())
        Rl, pl = np.asarray(ro.pose.R[:, -1]), np.asarray(ro.pose.p[:, -1])
        err = float(geodesic(Rl, truth_R).mean()) if ok else math.nan
        perr = float(np.linalg.norm(pl[:, 0] - truth_p, axis=-1).mean()) if ok and pl.shape[1] else math.nan
        batches = sorted({1, *args.batch}) if horizon == args.horizons[0] else [1]  # (big batches: first horizon)
        for batch in batches:
            idx = np.arange(batch) % R.shape[0]
            a, b = Pose(R[idx, 0], p[idx, 0]), Pose(R[idx, 1], p[idx, 1])
            sec = best_of(functools.partial(model.rollout, a, b, steps, solver), args.repeats)
            rows.append(
                {
                    "engine": "liedfl",
                    "scheme": "true-parameter articulated DEL",
                    "step": h,
                    "horizon_s": horizon,
                    "batch": batch,
                    "rot_error_rad": err,
                    "root_pos_error_m": perr,
                    "converged": ok,
                    "ms_per_traj_per_sim_s": 1e3 * sec / (batch * horizon),
                    "us_per_traj_step": 1e6 * sec / (batch * steps),
                }
            )
            print(f"liedfl h={h} batch={batch}: {rows[-1]['rot_error_rad']:.3g} rad, "
                  f"{rows[-1]['ms_per_traj_per_sim_s']:.3g} ms per trajectory per simulated s", flush=True)  # fmt: skip
    return rows


def _mujoco_run(mujoco, model, data, qpos0, qvel0, n: int, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Every trajectory from (qpos0[i], qvel0[i]) over n steps: world attitudes (T, B, 3, 3) of the bodies
    `ids` and the root position (T, 3) at the end."""
    Rs, ps = [], []
    for i in range(qpos0.shape[0]):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos0[i], qvel0[i]
        mujoco.mj_step(model, data, nstep=n)
        mujoco.mj_forward(model, data)
        Rs.append(data.xmat[ids].reshape(-1, 3, 3).copy())
        ps.append(data.xpos[ids[0]].copy())
    return np.stack(Rs), np.stack(ps)


def mujoco_rows(args, horizon: float, ref, truth_R: np.ndarray, truth_p: np.ndarray) -> list[dict]:
    mujoco = require_mujoco()
    xml = ref.params["mjcf"]
    qpos0, qvel0 = ref.extras["qpos"][:, 0], ref.extras["qvel"][:, 0]
    unit = float(ref.params.get("length_unit_m", 1.0))
    rows = []
    for name in INTEGRATORS:
        for dt in MUJOCO_DT:
            model = mujoco.MjModel.from_xml_string(xml)
            model.opt.timestep = dt
            model.opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{name.upper()}")
            data = mujoco.MjData(model)
            n = int(round(horizon / dt))
            # liedfl's body order (the file's body_names are the MJCF's link names; MuJoCo numbers depth first)
            ids = [int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b)) for b in ref.body_names]
            Rm, pm = _mujoco_run(mujoco, model, data, qpos0, qvel0, n, ids)
            finite = np.isfinite(Rm).all()
            sec = best_of(functools.partial(_mujoco_run, mujoco, model, data, qpos0, qvel0, n, ids), args.repeats)
            rows.append(
                {
                    "engine": "mujoco",
                    "scheme": name,
                    "step": dt,
                    "horizon_s": horizon,
                    "batch": 1,
                    "rot_error_rad": float(geodesic(Rm, truth_R).mean()) if finite else math.nan,
                    "root_pos_error_m": float(np.linalg.norm(pm - truth_p * unit, axis=-1).mean()) / unit
                    if finite
                    else math.nan,
                    "converged": bool(finite),
                    "ms_per_traj_per_sim_s": 1e3 * sec / (qpos0.shape[0] * horizon),
                    "us_per_traj_step": 1e6 * sec / (qpos0.shape[0] * n),
                }
            )
            print(f"mujoco {name} dt={dt}: {rows[-1]['rot_error_rad']:.3g} rad, "
                  f"{rows[-1]['ms_per_traj_per_sim_s']:.3g} ms per trajectory per simulated s", flush=True)  # fmt: skip
    return rows


def figure(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    horizons = sorted({r["horizon_s"] for r in rows})
    fig, axes = plt.subplots(1, len(horizons), figsize=(6.2 * len(horizons), 4.6), squeeze=False)
    styles = {("liedfl", 1): ("o-", "C0"), ("mujoco", "RK4"): ("s--", "C1"), ("mujoco", "Euler"): ("^--", "C2"),
              ("mujoco", "implicitfast"): ("v--", "C3")}  # fmt: skip
    for ax, H in zip(axes[0], horizons):
        every = [r for r in rows if r["horizon_s"] == H and math.isfinite(r["rot_error_rad"])]
        sub = [r for r in every if r["rot_error_rad"] > 0]  # (the reference itself, restarted: 0 on a log axis)
        for batch in sorted({r["batch"] for r in sub if r["engine"] == "liedfl"}):
            pts = sorted((r for r in sub if r["engine"] == "liedfl" and r["batch"] == batch), key=lambda r: r["step"])
            mark, col = ("o-", "C0") if batch == 1 else ("o:", "C4")
            label = f"liedfl true scheme, batch {batch} (h {pts[0]['step']:g}–{pts[-1]['step']:g} s)"
            ax.plot([r["ms_per_traj_per_sim_s"] for r in pts], [r["rot_error_rad"] for r in pts], mark, color=col,
                    label=label)  # fmt: skip
        for name in INTEGRATORS:
            pts = sorted((r for r in sub if r["engine"] == "mujoco" and r["scheme"] == name), key=lambda r: r["step"])
            if pts:
                mark, col = styles[("mujoco", name)]
                ax.plot([r["ms_per_traj_per_sim_s"] for r in pts], [r["rot_error_rad"] for r in pts], mark,
                        color=col, label=f"MuJoCo {name} (dt {pts[0]['step']:g}–{pts[-1]['step']:g} s)")  # fmt: skip
        floor = [r["rot_error_rad"] for r in every if r["engine"] == "mujoco" and r["step"] == FINE_DT]
        if floor and floor[0] > 0:  # the reference's own integrator restarted: below it the comparison cannot see
            ax.axhline(
                floor[0], color="0.5", lw=0.8, ls=":", label=f"floor: the reference restarted ({floor[0]:.1g} rad)"
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cost per trajectory per simulated second (ms, wall, one thread)")
        ax.set_ylabel(f"attitude error after {H:g} s (rad, mean over bodies)")
        ax.set_title(f"{title}: horizon {H:g} s")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=120)
    os.replace(tmp, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default="branched5", help=f"one of {list(TREES)}")
    ap.add_argument("--joints", default="ball", help="joint of every non-root body (ball, hinge, universal)")
    ap.add_argument("--trajectories", type=int, default=8)
    ap.add_argument("--horizons", type=float, nargs="+", default=[1.0])
    ap.add_argument("--batch", type=int, nargs="+", default=[1000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed", type=float, default=2.0, help="initial angular speed scale (rad/s)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--figure", default=None)
    ap.add_argument("--figure-from", default=None, help="only draw --figure from this JSON record")
    args = ap.parse_args()
    if args.figure_from:
        rec = json.loads(Path(args.figure_from).read_text())
        figure(rec["rows"], Path(args.figure), f"{rec['setup']['tree']} tree, {rec['setup']['joints']} joints")
        return
    torch.set_num_threads(1)
    out = {
        "machine": {
            "cpu": cpu_model(),
            "cores": os.cpu_count(),
            "load_start": os.getloadavg(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "mujoco": require_mujoco().__version__,
            "threads": 1,
        },  # fmt: skip
        "setup": {k: getattr(args, k) for k in ("tree", "joints", "trajectories", "seed", "speed", "repeats")},
        "reference": f"MuJoCo RK4 at dt={FINE_DT:g}",
        "rows": [],
    }
    for H in args.horizons:
        fine = reference(args, 0.01, int(round(H / 0.01)))
        truth_R, truth_p = fine.R[:, -1], fine.p[:, -1, 0]
        out["rows"] += liedfl_rows(args, H, truth_R, truth_p)
        out["rows"] += mujoco_rows(args, H, fine, truth_R, truth_p)
    out["machine"]["load_end"] = os.getloadavg()
    if args.json:
        tmp = Path(args.json).with_name(f".{Path(args.json).name}.tmp{os.getpid()}")
        tmp.write_text(json.dumps(out, indent=1))
        os.replace(tmp, args.json)
    if args.figure:
        figure(out["rows"], Path(args.figure), f"{args.tree} tree, {args.joints} joints")
    print(json.dumps(out["machine"]))


if __name__ == "__main__":
    main()
