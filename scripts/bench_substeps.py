"""Sub-steps and the fourth-order step against one second-order step per sample: error and cost.

Two scenes sampled the way the accuracy issue describes, from scipy's DOP853 at tolerance 1e-13 (an
integrator that shares nothing with liedfl's schemes): a damped heavy top pinned at a point (sample
step 0.02 s, 2 s) and a damped free rotor (0.05 s, 5 s). Metric: the rollout's relative error
mean_t ||R^_t - R_t||_F / ||R_t||_F over the 100 samples, geometric mean over the test trajectories.

For each step option (one step: s = 1 order 2; s = 2, 4 order 2; order 4 with s = 1, 2) the script
measures the true-parameter scheme and the learned model (trained from the training poses by the
start of `SubstepModel.initial_fit`: L-BFGS on the one-step DEL loss, then Levenberg-Marquardt on the
option's own residual, the one-step option included; its error is recorded, then the rollout refinement
`substeps.rollout_refinement` continues the same fit, and the error is recorded again), and the CPU time of
the test rollout (one thread, default Newton settings, best of 5 with the repeats of every model of the
scene interleaved, the batch of test trajectories, the internal-pose solve of the start included) as a
ratio to the one-step model's in the same run.

    OMP_NUM_THREADS=1 python scripts/bench_substeps.py --json docs/bench/substeps.json
    OMP_NUM_THREADS=1 python scripts/bench_substeps.py --seed 3 --no-speed --json docs/bench/substeps_seed3.json
    OMP_NUM_THREADS=1 python scripts/bench_substeps.py --warm-start --json docs/bench/substeps_warm_start.json
    OMP_NUM_THREADS=1 python scripts/bench_substeps.py --speed-only --json docs/bench/substeps_speed.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from machine_info import cpu_model  # scripts/machine_info.py (scripts/ is on the path of a script)

from liedfl_cli.data.physics import RigidBodySO3, simulate_so3
from liedfl_cli.lie import Pose, ProductGroup
from liedfl_cli.models.liedflnn import substeps as sb
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model
from liedfl_cli.solvers.options import SolverOptions

G = ProductGroup(0, 1)
J = [1.521, 1.362, 1.211]
SCENES = {
    "heavy_top": {
        "h": 0.02,
        "horizon": 2.0,
        "physics": {"J": J, "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81, "D": [0.1] * 3},
    },
    "free_rotor": {
        "h": 0.05,
        "horizon": 5.0,
        "physics": {"J": J, "m": 0.5, "rho": [0.0, 0.0, 0.0], "g": 0.0, "D": [0.05] * 3},
    },
}
OPTIONS = [(1, 2), (2, 2), (4, 2), (1, 4), (2, 4)]
SOLVER = SolverOptions(tol=1e-12, max_iter=20)
REPEATS = 5


def simulate(scene: dict, n_traj: int, seed: int) -> Pose:
    ph = scene["physics"]
    body = RigidBodySO3(J=np.diag(ph["J"]), m=ph["m"], rho=np.array(ph["rho"]), g=ph["g"], D=np.diag(ph["D"]))
    rng = np.random.default_rng(seed)
    w0 = rng.normal(size=(n_traj, 3))
    R0 = np.broadcast_to(np.eye(3), (n_traj, 3, 3)).copy()
    n = round(scene["horizon"] / scene["h"])
    sim = simulate_so3(body, R0, w0, scene["h"] * np.arange(n + 1), {"method": "DOP853", "rtol": 1e-13, "atol": 1e-14})
    R = torch.from_numpy(sim.R)[:, :, None]
    return Pose(R, R.new_zeros(n_traj, n + 1, 0, 3))


def rollout_seconds(model, truth: Pose) -> float:
    """Wall time of the rollout with the default Newton settings (what a user gets; tol 1e-5 on the step,
    whose quadratic convergence leaves ~1e-10): CPU seconds, the best of REPEATS, the first also warming
    the caches.
    The errors are measured on a separate rollout at tol 1e-12."""
    n = truth.R.shape[1] - 1
    secs = []
    for _ in range(REPEATS):
        t0 = time.process_time()  # CPU time of this (one-thread) process: steadier than wall time on a shared machine
        model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, SolverOptions())
        secs.append(time.process_time() - t0)
    return min(secs)


def rollout_seconds_once(model, truth: Pose) -> float:
    """CPU seconds of one rollout with the default Newton settings."""
    n = truth.R.shape[1] - 1
    t0 = time.process_time()
    model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, SolverOptions())
    return time.process_time() - t0


def rollout_error(model, truth: Pose) -> tuple[float, int]:
    """(geometric mean over trajectories of the mean relative error, Newton failures), at tol 1e-12."""
    n = truth.R.shape[1] - 1
    ro = model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, SOLVER)
    R, Rt = ro.pose.R[:, :, 0], truth.R[:, :, 0]
    rel = ((R - Rt).norm(dim=(-1, -2)) / Rt.norm(dim=(-1, -2))).mean(1)
    return float(torch.exp(torch.log(rel).mean())), ro.n_failed


def learned(scene: dict, train: Pose, s: int, order: int, rollout_fit: bool = True) -> tuple[object, float, str]:
    """The model of step option (s, order) fitted to the training poses: L-BFGS on the one-step DEL loss,
    then Levenberg-Marquardt on the option's own residual, then (`rollout_fit`) on its rollouts over short
    windows of the training poses (`SubstepModel.initial_fit`; for one step per sample the same stages on
    the one-step residual and rollouts, so every option gets the same fit)."""
    potential = ["uniform_gravity"] if scene["physics"]["g"] else []
    inner = LieDFLNN(G, scene["h"], potential=potential, forces=["rayleigh"], seed=0)
    wrapper = sb.SubstepModel(inner, s, order)  # (1, 2): the one-step residual itself
    samples = wrapper.training_set(train, train.R.shape[1] - 1)
    t0 = time.perf_counter()
    note = wrapper.initial_fit(samples, rollout_fit=rollout_fit) or ""
    return sb.with_substeps(inner, s, order), time.perf_counter() - t0, note


def refine(model, train: Pose, s: int, order: int) -> tuple[float, str]:
    """`learned(..., rollout_fit=False)`'s model taken on by the rollout refinement alone: (seconds, note)."""
    wrapper = model if isinstance(model, sb.SubstepModel) else sb.SubstepModel(model, s, order)
    t0 = time.perf_counter()
    note = sb.rollout_refinement(wrapper, train, train.R.shape[1] - 1) or ""
    return time.perf_counter() - t0, note


def interleaved_seconds(models: list, truth: Pose) -> list[float]:
    """`rollout_seconds` of every model, the repeats interleaved (model 1, 2, ..., then again) so that a
    change of the machine's load weighs on all alike: CPU seconds, the best of REPEATS each."""
    n = truth.R.shape[1] - 1
    best = [math.inf] * len(models)
    for _ in range(REPEATS):
        for i, model in enumerate(models):
            t0 = time.process_time()
            model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, SolverOptions())
            best[i] = min(best[i], time.process_time() - t0)
    return best


COST_OPTIONS = [(1, 2, 1), (2, 2, 1), (4, 2, 1), (8, 2, 1), (1, 4, 1), (2, 4, 1), (1, 2, 2), (1, 2, 4), (1, 2, 8)]


def speed_against_error(n_traj: int = 32) -> list[dict]:
    """The heavy top with the true parameters, sampled at 0.02 s to 5 s: the rotation error after 1 s
    and 5 s (mean over trajectories of ||R^ - R||_F) and the rollout's CPU time per trajectory per
    simulated second, for sub-steps s = 1..8 of order 2, order 4 with s = 1, 2, and the one-step scheme
    at the sample step divided by 2, 4, 8 (its own, finer data; the same total time)."""
    base = dict(SCENES["heavy_top"], horizon=5.0)
    rows, runs = [], []
    for s, order, refine in COST_OPTIONS:
        scene = dict(base, h=base["h"] / refine)
        truth = simulate(scene, n_traj, 3)
        model = sb.with_substeps(physics_model(G, scene["h"], scene["physics"]), s, order)
        n = truth.R.shape[1] - 1
        ro = model.rollout(truth.index((slice(None), 0)), truth.index((slice(None), 1)), n, SOLVER)
        runs.append((model, truth))
        err = (ro.pose.R[:, :, 0] - truth.R[:, :, 0]).norm(dim=(-1, -2)).mean(0)
        i1, i5 = round(1.0 / scene["h"]), round(5.0 / scene["h"])
        rows.append(
            {
                "substeps": s,
                "order": order,
                "h": scene["h"],
                "solves_per_second": s * (1 if order == 2 else 3) / scene["h"],
                "error_1s": float(err[i1]),
                "error_5s": float(err[i5]),
                "newton_failures": ro.n_failed,
            }
        )
    # the repeats interleaved over the options (`interleaved_seconds`): a change of load weighs on all alike
    best = [math.inf] * len(runs)
    for _ in range(REPEATS):
        for i, (model, truth) in enumerate(runs):
            best[i] = min(best[i], rollout_seconds_once(model, truth))
    for r, sec in zip(rows, best):
        r["ms_per_trajectory_second"] = 1e3 * sec / n_traj / base["horizon"]
        print(
            f"h {r['h']:.4f} s={r['substeps']} order={r['order']}: error 1 s {r['error_1s']:.2e}, "
            f"5 s {r['error_5s']:.2e}, {r['ms_per_trajectory_second']:.3f} ms per trajectory-second",
            flush=True,
        )
    return rows


def warm_start_effect(sizes=(16, 32)) -> list[dict]:
    """The order-4 cycle's warm start before/after (`substeps.PREDICTOR_DEGREE` < 0: the last increment
    scaled to the sub-step, the previous start; else the extrapolation of the same sub-step's last cycles),
    true parameters, the two scenes' test trajectories: Newton iterations per sub-step at the default
    tolerance and at 1e-12 (the solver's counts), the largest pose difference between the two at 1e-12,
    and the rollout's CPU time (default settings) against the one-step scheme's, the repeats interleaved.
    16 trajectories roll out in row layout, 32 in column layout (each scheme on its own best path)."""
    rows = []
    degree = sb.PREDICTOR_DEGREE
    for name, scene in SCENES.items():
        for T in sizes:
            test = simulate(scene, T, 2)
            n = test.R.shape[1] - 1
            start = test.index((slice(None), 0)), test.index((slice(None), 1))
            one = physics_model(G, scene["h"], scene["physics"])
            four = sb.SubstepModel(physics_model(G, scene["h"], scene["physics"]), 1, 4)
            row: dict = {"scene": name, "trajectories": T}
            poses = {}
            for label, deg in (("before", -1), ("after", degree)):
                sb.PREDICTOR_DEGREE = deg
                tight, default = four.rollout(*start, n, SOLVER), four.rollout(*start, n, SolverOptions())
                poses[label] = tight.pose.R
                solves = tight.iterations.numel() * 3
                row[f"iterations_per_substep_{label}"] = float(default.iterations.sum()) / solves
                row[f"iterations_per_substep_tol_1e-12_{label}"] = float(tight.iterations.sum()) / solves
                row[f"newton_failures_{label}"] = tight.n_failed + default.n_failed
                one_s, four_s = interleaved_seconds([one, four], test)
                row[f"cpu_one_step_{label}"], row[f"cpu_order_4_{label}"] = one_s, four_s
                row[f"cost_ratio_{label}"] = four_s / one_s
            sb.PREDICTOR_DEGREE = degree
            row["max_pose_difference_tol_1e-12"] = float((poses["after"] - poses["before"]).abs().max())
            row["one_step_iterations_per_step"] = float(
                one.rollout(*start, n, SolverOptions()).iterations.double().mean()
            )
            rows.append(row)
            its = [row[f"iterations_per_substep{t}_{x}"] for t in ("", "_tol_1e-12") for x in ("before", "after")]
            print(
                f"{name} T={T}: iterations/sub-step {its[0]:.2f} -> {its[1]:.2f} (tol 1e-12: {its[2]:.2f} -> "
                f"{its[3]:.2f}); CPU / one step {row['cost_ratio_before']:.2f} -> {row['cost_ratio_after']:.2f}; "
                f"max |dR| {row['max_pose_difference_tol_1e-12']:.1e}",
                flush=True,
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", type=int, default=16, help="training trajectories per scene")
    ap.add_argument("--test", type=int, default=16, help="test trajectories per scene")
    ap.add_argument("--seed", type=int, default=1, help="seed of the training trajectories (test: seed + 1)")
    ap.add_argument("--no-speed", action="store_true", help="skip the speed-against-error table")
    ap.add_argument("--speed-only", action="store_true", help="only the speed-against-error table")
    ap.add_argument("--warm-start", action="store_true", help="only the order-4 warm start before/after")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    for flag, key, measure in (
        ("speed_only", "speed_against_error", speed_against_error),
        ("warm_start", "rows", warm_start_effect),
    ):
        if getattr(args, flag):  # a part alone: its own record
            rec = {
                "command": f"OMP_NUM_THREADS=1 python scripts/bench_substeps.py --{flag.replace('_', '-')}"
                + (f" --json {args.json}" if args.json else ""),
                "cpu": cpu_model(),
                "load_before": os.getloadavg()[0],
                "threads": 1,
            }
            rec[key] = measure()
            rec["load_after"] = os.getloadavg()[0]
            if args.json:
                args.json.write_text(json.dumps(rec, indent=1))
            return
    command = "OMP_NUM_THREADS=1 python scripts/bench_substeps.py"
    command += (f" --seed {args.seed}" if args.seed != 1 else "") + (" --no-speed" if args.no_speed else "")
    record: dict = {
        "command": command + (f" --json {args.json}" if args.json else ""),
        "seed_train": args.seed,
        "seed_test": args.seed + 1,
        "cpu": cpu_model(),
        "load_before": os.getloadavg()[0],
        "threads": 1,
        "scenes": {},
    }
    for name, scene in SCENES.items():
        train, test = simulate(scene, args.train, args.seed), simulate(scene, args.test, args.seed + 1)
        rows, models = [], []
        for s, order in OPTIONS:
            true_model = sb.with_substeps(physics_model(G, scene["h"], scene["physics"]), s, order)
            true_err, true_fail = rollout_error(true_model, test)
            model, fit_sec, note = learned(scene, train, s, order, rollout_fit=False)
            residual_err, fail0 = rollout_error(model, test)
            refine_sec, refine_note = refine(model, train, s, order)
            err, fail = rollout_error(model, test)
            models += [model, true_model]
            rows.append(
                {
                    "substeps": s,
                    "order": order,
                    "solves_per_step": s * (1 if order == 2 else 3),
                    "true_error": true_err,
                    "learned_error_residual_fit": residual_err,
                    "learned_error": err,
                    "fit_seconds_residual": fit_sec,
                    "fit_seconds_rollout": refine_sec,
                    "fit_seconds": fit_sec + refine_sec,
                    "newton_failures": fail0 + fail + true_fail,
                    "fit": "; ".join(x for x in (note, refine_note) if x),
                    "J_learned": model.physical_parameters()["J_d"].diagonal(dim1=-2, dim2=-1).tolist(),
                }
            )
            print(
                f"{name} s={s} order={order}: true {true_err:.3e}  learned {residual_err:.3e} (residual fit) "
                f"{err:.3e} (+ rollout fit)  fit {fit_sec:.1f} + {refine_sec:.1f} s",
                flush=True,
            )
        secs = interleaved_seconds(models, test)
        for r, sec, true_sec in zip(rows, secs[0::2], secs[1::2]):
            r["learned_seconds"], r["true_seconds"] = sec, true_sec
        base = rows[0]
        for r in rows:
            r["learned_error_vs_one_step"] = r["learned_error"] / base["learned_error"]
            r["residual_fit_error_vs_one_step"] = r["learned_error_residual_fit"] / base["learned_error_residual_fit"]
            r["learned_error_vs_one_step_residual_fit"] = r["learned_error"] / base["learned_error_residual_fit"]
            r["rollout_cost_vs_one_step"] = r["learned_seconds"] / base["learned_seconds"]
            r["true_rollout_cost_vs_one_step"] = r["true_seconds"] / base["true_seconds"]
        record["scenes"][name] = {
            "h": scene["h"],
            "horizon_s": scene["horizon"],
            "train": args.train,
            "test": args.test,
            "rows": rows,
        }
    record["speed_against_error"] = [] if args.no_speed else speed_against_error()
    record["load_after"] = os.getloadavg()[0]
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(record, indent=1))
        tmp.replace(args.json)
    for name, sc in record["scenes"].items():
        print(f"\n{name} (h {sc['h']} s, {sc['horizon_s']} s)")
        print(
            "| substeps | order | solves/step | true scheme | learned (residual fit) | learned (+ rollout fit) "
            "| learned / one step | rollout cost / one step |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for r in sc["rows"]:
            print(
                f"| {r['substeps']} | {r['order']} | {r['solves_per_step']} | {r['true_error']:.2e} "
                f"| {r['learned_error_residual_fit']:.2e} | {r['learned_error']:.2e} "
                f"| {r['learned_error_vs_one_step']:.3f} | {r['rollout_cost_vs_one_step']:.2f} |"
            )
    print("\nheavy top, true parameters, sampled at 0.02 s (rows with h < 0.02: the one-step scheme on finer data)")
    print("| h (s) | substeps | order | solves per s | error after 1 s | after 5 s | ms per trajectory-second |")
    print("|---|---|---|---|---|---|---|")
    for r in record["speed_against_error"]:
        print(
            f"| {r['h']:g} | {r['substeps']} | {r['order']} | {r['solves_per_second']:.0f} | {r['error_1s']:.2e} "
            f"| {r['error_5s']:.2e} | {r['ms_per_trajectory_second']:.3f} |"
        )
    assert all(math.isfinite(r["learned_error"]) for sc in record["scenes"].values() for r in sc["rows"])


if __name__ == "__main__":
    main()
