"""Speed benchmark of the fused engine against the reference (unfused) paths, in one run.

    python scripts/bench.py --json FILE [--quick] [--threads N] [--no-compile] [--data-dir DIR]

Every figure is measured twice in the same process, once on the fused paths (`runtime.fused`,
the default) and once on the reference paths (`baseline_*` keys), alternately, each the best of a
few repeats, so a speed-up is a ratio taken under the same load. Keys:

  train_triplets_per_s          default `liedfl train` (free rigid body, batch 1024, SOAP)
  exp3_s_per_epoch              Exp 3 LieDFLNN (heavy body on SE(3), MLP potential 32x3)
  mocap_s_per_epoch             Exp 4 (mocap, SE(3) x SO(3)^22, SOAP, batch 63)
  mocap_articulated_s_per_epoch the same with model.kinetic=articulated (paper's DEL loss), marginal
                                seconds per epoch (the training set's one-off precomputation left out,
                                `*_setup_s`), beside mocap_per_body_marginal_s_per_epoch measured alike;
                                mocap_articulated_over_per_body their ratio
  mocap_articulated_newton_s_per_epoch  ... with train.loss=newton
  rollout_us_per_step_traj      {model: {batch: us}} for the free body with true parameters and
                                the SE(3) LieDFLNN with an MLP potential 64x3, batches 1/10/1000/10000
  learned_rollout_us_per_step_traj  {model: {batch: us}} for the learned models users roll out: an
                                SO(3) LieDFLNN with an MLP potential 10x2 and Rayleigh damping (the
                                peer's network size, `scripts/bench_peer.py`) and the SE(3) MLP 64x3
                                model above (the same figures as in rollout_us_per_step_traj)
  baseline_models               {baseline: {s_per_epoch_fused, s_per_epoch_reference, cpu_s_per_epoch_fused,
                                cpu_s_per_epoch_reference, batch, samples_per_epoch, paper_epochs, experiment}}:
                                one training epoch of each paper baseline (GLNN rk4 / lie_heun / lie_midpoint,
                                Euler and Euclidean DFLNN, Neural ODE) at its experiment's settings (Exp 2 at
                                its longest training length, 100 steps), fused (`runtime.fused`) and reference
                                paths alternately; paper_epochs x s_per_epoch projects a full-budget job
  articulated_rollout_us_per_step_traj  {model: {batch: {native, fused, reference, fused_chord, ...}}} for the
                                5-body MuJoCo tree's true-parameter scheme (free root, ball joints, per-DoF
                                damping, h 0.05) and the untrained 23-body Exp 4 articulated model (MLP
                                potential, nn + rayleigh_nonlinear forces, h 1/120), batches 1/1000, the
                                native step (`engines.native`, the default where it serves: the 5-body
                                tree), the fused articulated engine in torch (runtime.compile=false) and the
                                reference problem alternately; native_over_mujoco_rk4_substep; with
                                mujoco_rk4_dt1e-3_us_per_substep_tree5 (MuJoCo's RK4 on that tree's true
                                model, one trajectory at a time; --articulated-only runs these alone);
                                fused_chord / native_chord: with solver=chord (tol 1e-8, one Jacobian
                                per step), fused_over_fused_chord its speed-up; native_2_threads: the
                                native step with two torch threads (its rows split over them)
  articulated_training_tree5    {s_per_epoch_fused, s_per_epoch_reference, samples_per_epoch, start_s}: the
                                default articulated command on a 5-body branched MuJoCo tree (112
                                trajectories x 100 steps): seconds per epoch without the start, and the
                                seconds of the least-squares start (train.start=auto); cartwheel23_start_s:
                                the same start of the 23-body Exp 4 articulated model; cartwheel23_s_per_epoch_*:
                                its epochs (the paper's DEL loss, batch 63)
  compile_s                     first compilation of the Newton step (runtime.compile=true)
  compiled_rollout_us_per_step_traj  the free body with the compiled step, batches 1000/10000
  threads, load_avg             torch threads used; `os.getloadavg()` before and after
  threads_compare               (--compare-threads) default-train s/epoch and free-body rollout
                                us/step/trajectory with 1 and 2 threads
  speedup                       every baseline / fused ratio
  cpu_time                      the same figures in CPU time of this process (with one thread, what
                                the wall time would be on an idle machine when others share the cores)

--quick (< 3 minutes) runs fewer epochs and steps; datasets are generated (cached) on first use.
--baselines-only measures `baseline_models` alone (about 2 minutes on an idle machine).
--fast-tier also runs the README's test command (`python -m pytest -m "not slow" -q -n 2 --dist worksteal`,
with -p no:cacheprovider as in .ci/run) in a child process and adds
  fast_tier                     {wall_s, tests_passed, exit_code, load_avg_start, load_avg_end}
(271–281 s in one process on 2 idle cores, before it ran in two xdist workers; run it alone,
`--fast-tier-only`, so the tests and the timed figures do not share the cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# the README's test command runs the fast tier in two pytest-xdist workers (one per core), as .ci/run does
FAST_TIER_ARGS = ("-n", "2", "--dist", "worksteal")
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402
from machine_info import cpu_model  # noqa: E402

from liedfl_cli.cli import CONF_DIR  # noqa: E402
from liedfl_cli.commands.train import fit  # noqa: E402
from liedfl_cli.config.factory import build_model  # noqa: E402
from liedfl_cli.config.typed import typed  # noqa: E402
from liedfl_cli.data.scenes import dataset_steps, get_dataset  # noqa: E402
from liedfl_cli.lie import SE3, SO3, Pose, so3  # noqa: E402
from liedfl_cli.models.liedflnn.model import LieDFLNN  # noqa: E402
from liedfl_cli.models.true_scheme import physics_model  # noqa: E402
from liedfl_cli.solvers import compile as compile_cache  # noqa: E402
from liedfl_cli.solvers import runtime  # noqa: E402
from liedfl_cli.solvers.options import SolverOptions  # noqa: E402


def chord_options(**overrides) -> SolverOptions:
    """`solver=chord`'s settings as its config file writes them (conf/solver/chord.yaml), with `overrides`."""
    import yaml

    return SolverOptions(**{**yaml.safe_load((Path(CONF_DIR) / "solver" / "chord.yaml").read_text()), **overrides})


PHYS = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0]}
BATCHES = (1, 10, 1000, 10000)
CPU_US: list[float] = []  # CPU time of each `rollout_us` call, in call order


def config(overrides: list[str], data_dir: str):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        paths = [f"paths.data_dir={data_dir}", "paths.output_dir=/tmp/liedfl-bench"]
        return compose("train", overrides=[*overrides, *paths])


def epoch_seconds(overrides: list[str], epochs: int, repeats: int, data_dir: str, reference: bool = True) -> dict:
    """Seconds per epoch of `fit` (best of `repeats`), fused and reference (`reference=False`: fused
    only, the reference figures NaN), and the sample count."""
    run = typed(config(overrides, data_dir), "train")  # as `liedfl train` converts it, once
    ds, _ = get_dataset(run.dataset, data_dir)
    data = ds.pose(ds.train_idx)
    tcfg = dataclasses.replace(run.train, epochs=epochs, checkpoint_every=10**9)
    best = {True: float("inf"), False: float("inf") if reference else float("nan")}
    cpu = {True: float("inf"), False: float("inf") if reference else float("nan")}
    n = 0
    for _ in range(repeats):
        for fused in (True, False) if reference else (True,):
            with runtime.using(fused=fused):
                model = build_model(run, ds)
                t, c = time.perf_counter(), time.process_time()
                steps = dataset_steps(run.dataset, ds, "train_steps")  # a file's null: all its steps
                out = fit(model, data, tcfg, steps)
                best[fused] = min(best[fused], (time.perf_counter() - t) / epochs)
                cpu[fused] = min(cpu[fused], (time.process_time() - c) / epochs)
                n = out["n_samples"]
    return {"fused": best[True], "reference": best[False], "n_samples": n, "cpu": cpu[True], "cpu_ref": cpu[False]}


BASELINES = {  # the paper's settings: experiment file and, for Exp 2, its longest training length
    "glnn_rk4": ["experiment=exp2_discrete_vs_continuous", "baseline=glnn_rk4", "dataset.train_steps=100"],
    "glnn_lie_heun": ["experiment=exp2_discrete_vs_continuous", "baseline=glnn_lie_heun", "dataset.train_steps=100"],
    "glnn_lie_midpoint": [
        "experiment=exp2_discrete_vs_continuous",
        "baseline=glnn_lie_midpoint",
        "dataset.train_steps=100",
    ],
    "euler_dflnn": ["experiment=exp1_euler_vs_lie", "baseline=euler_dflnn"],
    "euclidean_dflnn": ["experiment=exp3_manifold", "baseline=euclidean_dflnn"],
    "neural_ode": ["experiment=exp3_manifold", "baseline=neural_ode"],
}


def write_figures(out: dict, path: str, t_all: float, log) -> None:
    """Close the record (load at the end, total seconds) and write it as JSON to `path`."""
    out["load_avg_end"] = list(os.getloadavg())
    out["load_avg"] = out["load_avg_start"][0]
    out["seconds"] = time.perf_counter() - t_all
    Path(path).write_text(json.dumps(out, indent=2) + "\n")
    log(f"wrote {path}")


def fast_tier(log) -> dict:
    """Wall time of the README's test command (the fast tier), run from the repository root in a
    child process: {wall_s, tests_passed, exit_code, load_avg_start, load_avg_end}."""
    import re
    import subprocess

    start = list(os.getloadavg())
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-m", "not slow", "-q", "-p", "no:cacheprovider", *FAST_TIER_ARGS],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    passed = re.search(r"(\d+) passed", tail)
    out = {
        "wall_s": wall,
        "tests_passed": int(passed.group(1)) if passed else None,
        "exit_code": proc.returncode,
        "summary": tail,
        "load_avg_start": start,
        "load_avg_end": list(os.getloadavg()),
    }
    log(f"fast tier: {wall:.0f} s wall, {tail}")
    return out


def baseline_models(data_dir: str, quick: bool, log) -> dict:
    """`baseline_models`: seconds per training epoch of every paper baseline, fused and reference."""
    out = {}
    for name, overrides in BASELINES.items():
        cfg = config(overrides, data_dir)
        r = epoch_seconds(overrides, 1 if quick else 2, 2 if quick else 3, data_dir)
        out[name] = {
            "s_per_epoch_fused": r["fused"],
            "s_per_epoch_reference": r["reference"],
            "cpu_s_per_epoch_fused": r["cpu"],
            "cpu_s_per_epoch_reference": r["cpu_ref"],
            "batch": min(int(cfg.train.batch_size), int(r["n_samples"])),
            "samples_per_epoch": r["n_samples"],
            "paper_epochs": int(cfg.train.epochs),
            "experiment": " ".join(overrides),
        }
        log(f"baseline {name}: {r['fused']:.3f} s/epoch (reference {r['reference']:.3f})")
    return out


def start(G, n: int, h: float, seed: int = 0) -> tuple[Pose, Pose]:
    gen = torch.Generator().manual_seed(seed)
    g0 = Pose(
        so3.exp(torch.randn(n, G.n_bodies, 3, generator=gen, dtype=torch.float64)),
        torch.randn(n, G.n_se3, 3, generator=gen, dtype=torch.float64),
    )
    return g0, G.retract(g0, h * torch.randn(n, G.dim, generator=gen, dtype=torch.float64))


def rollout_models():
    free = physics_model(SO3, 0.1, {**PHYS, "g": 0.0, "D": [0.05] * 3})
    torch.manual_seed(0)
    se3 = LieDFLNN(SE3, 0.05, potential="mlp", forces=["rayleigh"], mlp_width=64, mlp_depth=3)
    se3.requires_grad_(False)
    return {"free_body_true": (free, SO3, 0.1), "se3_mlp": (se3, SE3, 0.05)}


def learned_so3_model():
    """The SO(3) LieDFLNN of `scripts/bench_peer.py`: MLP potential 10 x 2, Rayleigh damping, h = 0.05."""
    torch.manual_seed(0)
    so3_mlp = LieDFLNN(SO3, 0.05, potential="mlp", forces=["rayleigh"], mlp_width=10, mlp_depth=2)
    so3_mlp.requires_grad_(False)
    return so3_mlp, SO3, 0.05


def rollout_us(model, G, h, n: int, budget: float, repeats: int, **settings) -> float:
    """Microseconds per step per trajectory (best of `repeats`) of a rollout of about `budget` s;
    the CPU time of the same rollouts goes to `CPU_US`. `fused=`: the model's path (fixed per model:
    `with_path`); `compile=`: the twin's plan; `solver=`: the rollouts' `SolverOptions` (default the CLI's)."""
    g0, g1 = start(G, n, h)
    opts = settings.pop("solver", None)
    model = model.with_path("fused" if settings.pop("fused", model.path == "fused") else "reference")
    if "compile" in settings:  # this twin's plan (the model's own stays as it is)
        model.set_plan(dataclasses.replace(model.plan, compile=settings.pop("compile")))
    assert not settings, f"unknown settings {settings}"
    t = time.perf_counter()
    model.rollout(g0, g1, 4, opts)
    per_step = (time.perf_counter() - t) / 3
    steps = int(min(500, max(6, budget / max(per_step, 1e-6))))
    best = best_cpu = float("inf")
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        model.rollout(g0, g1, steps, opts)
        best = min(best, (time.perf_counter() - t) / (steps - 1))
        best_cpu = min(best_cpu, (time.process_time() - c) / (steps - 1))
    CPU_US.append(best_cpu / n * 1e6)
    return best / n * 1e6


def articulated_models(data_dir: str) -> dict:
    """The articulated model's rollout subjects: the true-parameter scheme of a 5-body branched MuJoCo
    tree (free root, ball joints, h 0.05) and the untrained 23-body Exp 4 articulated model (the
    cartwheel skeleton, h 1/120): name -> (model, group, h). Random start poses are valid for both
    (ball joints: any relative rotation)."""
    from liedfl_cli.data.mujoco_chain import chain_dataset
    from liedfl_cli.models.true_scheme import true_model

    ds5 = chain_dataset(parents="branched5", n_trajectories=2, steps=3, h=0.05, gravity=9.81, test_fraction=0.0)
    tree5 = true_model(ds5)
    assert tree5 is not None
    cfg = config(["experiment=exp4_mocap", "model.kinetic=articulated"], data_dir)
    run = typed(cfg, "train")
    assert run.dataset is not None
    ds23, _ = get_dataset(run.dataset, data_dir)
    torch.manual_seed(0)
    tree23 = build_model(run, ds23)
    out = {}
    for name, model, ds in (("tree5_true", tree5, ds5), ("cartwheel23_articulated", tree23, ds23)):
        model.requires_grad_(False)
        out[name] = (model, ds.group, ds.h)
    return out


def mujoco_rk4_us_per_substep(ds, dt: float = 1e-3, steps: int = 1000, repeats: int = 3) -> float | None:
    """MuJoCo's RK4 on the TRUE model of an articulated MuJoCo dataset (its MJCF), one trajectory at a
    time from its recorded initial states: best-of-`repeats` microseconds per substep of dt (the done-when
    of issue 34: a liedfl step at batch 1,000 should cost no more per trajectory than one of these).
    None without MuJoCo (the test extra)."""
    try:
        import mujoco
    except ImportError:
        return None
    model = mujoco.MjModel.from_xml_string(ds.params["mjcf"])
    model.opt.timestep = dt
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    data = mujoco.MjData(model)
    qpos0, qvel0 = ds.extras["qpos"][:, 0], ds.extras["qvel"][:, 0]
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for i in range(qpos0.shape[0]):
            mujoco.mj_resetData(model, data)
            data.qpos[:], data.qvel[:] = qpos0[i], qvel0[i]
            mujoco.mj_step(model, data, nstep=steps)
        best = min(best, (time.perf_counter() - t) / (qpos0.shape[0] * steps))
    return best * 1e6


def articulated_training(data_dir: str, quick: bool, log) -> dict:
    """The default articulated command's training on a 5-body branched MuJoCo tree (ball joints, per-DoF
    damping, 100 train trajectories x 100 steps, h 0.05; `liedfl train dataset=file dataset.path=<tree>
    model.kinetic=articulated`): seconds per epoch (fused and reference, fit's epochs without the start)
    and the seconds of its start, the prediction-weighted least-squares fit (`train.start=auto`)."""
    from liedfl_cli.data.hdf5 import save_dataset
    from liedfl_cli.data.mujoco_chain import chain_dataset

    path = Path(data_dir) / "bench_tree5_branched.h5"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        ds = chain_dataset(parents="branched5", n_trajectories=112, steps=100, h=0.05, gravity=9.81, seed=9002)
        save_dataset(ds, path)
    overrides = ["dataset=file", f"dataset.path={path}", "model.kinetic=articulated"]
    epochs = 2 if quick else 5
    no_start = epoch_seconds([*overrides, "train.start=none"], epochs, 1 if quick else 2, data_dir)
    run = typed(config(overrides, data_dir), "train")
    ds, _ = get_dataset(run.dataset, data_dir)
    data = ds.pose(ds.train_idx)
    tcfg = dataclasses.replace(run.train, epochs=0, checkpoint_every=10**9)
    starts = []
    for _ in range(1 if quick else 2):
        model = build_model(run, ds)
        steps = dataset_steps(run.dataset, ds, "train_steps")  # a file's null: all its steps
        starts.append(fit(model, data, tcfg, steps)["start_seconds"])
    out = {
        "s_per_epoch_fused": no_start["fused"],
        "s_per_epoch_reference": no_start["reference"],
        "samples_per_epoch": no_start["n_samples"],
        "start_s": min(starts),
    }
    # the same start on the 23-body Exp 4 articulated model (278 parameters, the cartwheels' 938 triplets)
    run = typed(config(["experiment=exp4_mocap", "model.kinetic=articulated"], data_dir), "train")
    assert run.dataset is not None
    ds, _ = get_dataset(run.dataset, data_dir)
    torch.manual_seed(0)
    model = build_model(run, ds)
    tcfg = dataclasses.replace(run.train, epochs=0, checkpoint_every=10**9)
    steps = dataset_steps(run.dataset, ds, "train_steps")
    fitted = fit(model, ds.pose(ds.train_idx), tcfg, steps)
    out["cartwheel23_start_s"] = fitted["start_seconds"]
    e23 = epoch_seconds(
        ["experiment=exp4_mocap", "model.kinetic=articulated", "train.start=none"], 2 if quick else 5, 1, data_dir
    )
    out["cartwheel23_s_per_epoch_fused"], out["cartwheel23_s_per_epoch_reference"] = e23["fused"], e23["reference"]
    log(
        f"articulated training (5-body tree): {out['s_per_epoch_fused']:.3f} s/epoch "
        f"(reference {out['s_per_epoch_reference']:.3f}), least-squares start {out['start_s']:.2f} s "
        f"(23-body Exp 4 model: {out['cartwheel23_start_s']:.1f} s, {out['cartwheel23_s_per_epoch_fused']:.3f} s/epoch)"
    )
    return out


def articulated_rollouts(data_dir: str, quick: bool, log) -> dict:
    """Articulated rollout us per step per trajectory at batch 1 and 1,000 on the fused engine
    (`models.articulated.engines.fused`) and the reference problem, alternately in this process (issue 34
    items 1 and 3), and MuJoCo's RK4 per substep of the 5-body tree's true model in the same run."""
    from liedfl_cli.data.mujoco_chain import chain_dataset
    from liedfl_cli.models.articulated.engines import native

    budget, repeats = (0.3, 1) if quick else (1.0, 2)
    figures: dict = {}
    for name, (model, G, h) in articulated_models(data_dir).items():
        figures[name] = {}
        serves = native.applies(model) is None and native.available()
        for n in (1, 1000):
            row = {}
            # native: the default (runtime.compile auto) where the native step serves the model; fused and
            # fused_chord: the torch engine (runtime.compile=false); reference: the reference problem
            for path in ("native", "native_chord", "fused", "reference", "fused_chord"):
                if path.startswith("native") and not serves:
                    continue
                opts = chord_options() if path.endswith("chord") else None
                eager = {} if path in ("native", "native_chord", "reference") else {"compile": "false"}
                row[path] = rollout_us(model, G, h, n, budget, repeats, fused=path != "reference", solver=opts, **eager)
            row["reference_over_fused"] = row["reference"] / row["fused"]
            row["fused_over_fused_chord"] = row["fused"] / row["fused_chord"]
            if "native" in row:
                row["fused_over_native"] = row["fused"] / row["native"]
                before = torch.get_num_threads()
                try:  # the native step splits its rows over runtime.threads
                    torch.set_num_threads(2)
                    row["native_2_threads"] = rollout_us(model, G, h, n, budget, repeats)
                finally:
                    torch.set_num_threads(before)
            figures[name][str(n)] = row
            log(
                f"articulated rollout {name} batch {n}: "
                + (f"{row['native']:.1f} us/step/traj native, " if "native" in row else "")
                + f"{row['fused']:.1f} fused, "
                f"{row['reference']:.1f} reference ({row['reference_over_fused']:.2f}x), "
                f"{row['fused_chord']:.1f} fused with solver=chord ({row['fused_over_fused_chord']:.2f}x)"
            )
    ds5 = chain_dataset(parents="branched5", n_trajectories=8, steps=3, h=0.05, gravity=9.81, test_fraction=0.0)
    rk4 = mujoco_rk4_us_per_substep(ds5, repeats=2 if quick else 3)
    figures["mujoco_rk4_dt1e-3_us_per_substep_tree5"] = rk4
    if rk4 is not None:
        log(f"MuJoCo RK4 (dt 1e-3) on the 5-body tree's true model: {rk4:.1f} us per substep")
        for row in figures["tree5_true"].values():
            if "native" in row:
                row["native_over_mujoco_rk4_substep"] = row["native"] / rk4
    return figures


def compare_threads(data_dir: str, quick: bool) -> dict:
    """Default-train seconds per epoch and free-body rollout us/step/trajectory with 1 and 2 torch
    threads, alternately in this process (fused paths)."""
    before = torch.get_num_threads()
    model, G, h = rollout_models()["free_body_true"]
    out: dict = {}
    try:
        for threads in (1, 2, 1, 2):
            torch.set_num_threads(threads)
            key = str(threads)
            r = epoch_seconds([], 5 if quick else 20, 1, data_dir)
            figures = {"train_s_per_epoch": r["fused"]}
            for n in (10, 1000, 10000):
                figures[f"rollout_us_{n}"] = rollout_us(model, G, h, n, 0.3, 2, fused=True)
            old = out.get(key)
            out[key] = figures if old is None else {k: min(v, old[k]) for k, v in figures.items()}
    finally:
        torch.set_num_threads(before)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", required=True, help="write the figures here")
    ap.add_argument("--quick", action="store_true", help="fewer epochs and steps (< 3 minutes)")
    ap.add_argument("--threads", default="auto", help="runtime.threads (auto = the engine's default)")
    ap.add_argument("--no-compile", action="store_true", help="skip the compilation figures")
    ap.add_argument("--compare-threads", action="store_true", help="also time 1 against 2 threads (fused paths)")
    ap.add_argument("--baselines-only", action="store_true", help="only the baseline_models figures")
    ap.add_argument("--articulated-only", action="store_true", help="only the articulated rollout figures")
    ap.add_argument("--fast-tier", action="store_true", help="also time the fast tier of the tests")
    ap.add_argument("--fast-tier-only", action="store_true", help="only time the fast tier of the tests")
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    args = ap.parse_args()
    threads = args.threads if args.threads == "auto" else int(args.threads)
    runtime.configure(runtime.RuntimeOptions(threads=threads, compile="false"))
    q = args.quick
    out: dict = {
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "quick": q,
        "load_avg_start": list(os.getloadavg()),
    }
    t_all = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_all:6.1f} s] {msg}", flush=True)

    if args.fast_tier_only or args.baselines_only or args.articulated_only:
        if args.articulated_only:
            out["articulated_rollout_us_per_step_traj"] = articulated_rollouts(args.data_dir, q, log)
            out["articulated_training_tree5"] = articulated_training(args.data_dir, q, log)
        if args.baselines_only:
            out["baseline_models"] = baseline_models(args.data_dir, q, log)
        if args.fast_tier_only:
            out["fast_tier"] = fast_tier(log)
        write_figures(out, args.json, t_all, log)
        return

    # training
    r = epoch_seconds([], 10 if q else 50, 2 if q else 3, args.data_dir)
    out["train_triplets_per_s"] = r["n_samples"] / r["fused"]
    out["baseline_train_triplets_per_s"] = r["n_samples"] / r["reference"]
    out["train_s_per_epoch"], out["baseline_train_s_per_epoch"] = r["fused"], r["reference"]
    cpu: dict = {"train_s_per_epoch": r["cpu"], "baseline_train_s_per_epoch": r["cpu_ref"]}
    ref_rate = out["baseline_train_triplets_per_s"]
    log(f"default train: {out['train_triplets_per_s']:.0f} triplets/s (reference {ref_rate:.0f})")
    r = epoch_seconds(["experiment=exp3_manifold", "baseline=none"], 2 if q else 5, 1 if q else 2, args.data_dir)
    out["exp3_s_per_epoch"], out["baseline_exp3_s_per_epoch"] = r["fused"], r["reference"]
    cpu["exp3_s_per_epoch"], cpu["baseline_exp3_s_per_epoch"] = r["cpu"], r["cpu_ref"]
    log(f"exp3: {r['fused']:.3f} s/epoch (reference {r['reference']:.3f})")
    r = epoch_seconds(["experiment=exp4_mocap"], 1 if q else 3, 1, args.data_dir)
    out["mocap_s_per_epoch"], out["baseline_mocap_s_per_epoch"] = r["fused"], r["reference"]
    cpu["mocap_s_per_epoch"], cpu["baseline_mocap_s_per_epoch"] = r["cpu"], r["cpu_ref"]
    log(f"mocap: {r['fused']:.3f} s/epoch (reference {r['reference']:.3f})")
    # the articulated model (model.kinetic=articulated) at the same Exp 4 settings, with the paper's DEL loss
    # and with train.loss=newton, against the per-body model: marginal seconds per epoch (the training set's
    # one-off precomputation, FK and its Jacobian for the articulated model, left out), all in this process
    E = 3 if q else 6
    marginal = {}
    for key, extra in (
        ("mocap_per_body_marginal_s_per_epoch", []),
        ("mocap_articulated_s_per_epoch", ["model.kinetic=articulated"]),
        ("mocap_articulated_newton_s_per_epoch", ["model.kinetic=articulated", "train.loss=newton"]),
    ):
        one = epoch_seconds(["experiment=exp4_mocap", *extra], 1, 2, args.data_dir, False)
        many = epoch_seconds(["experiment=exp4_mocap", *extra], E, 1, args.data_dir, False)
        marginal[key] = (many["fused"] * E - one["fused"]) / (E - 1)
        out[key], cpu[key] = marginal[key], (many["cpu"] * E - one["cpu"]) / (E - 1)
        out[key.replace("s_per_epoch", "setup_s")] = one["fused"] - marginal[key]
        log(f"{key}: {marginal[key]:.3f} s/epoch (+ {one['fused'] - marginal[key]:.2f} s set-up)")
    per_body = marginal["mocap_per_body_marginal_s_per_epoch"]
    out["mocap_articulated_over_per_body"] = marginal["mocap_articulated_s_per_epoch"] / per_body
    out["mocap_articulated_newton_over_per_body"] = marginal["mocap_articulated_newton_s_per_epoch"] / per_body
    log(
        f"articulated / per-body epoch: {out['mocap_articulated_over_per_body']:.2f} (del), "
        f"{out['mocap_articulated_newton_over_per_body']:.2f} (newton)"
    )

    out["baseline_models"] = baseline_models(args.data_dir, q, log)
    out["articulated_rollout_us_per_step_traj"] = articulated_rollouts(args.data_dir, q, log)
    out["articulated_training_tree5"] = articulated_training(args.data_dir, q, log)

    # rollouts
    budget, repeats = (0.3, 2) if q else (1.0, 3)
    fused: dict = {}
    ref: dict = {}
    cpu_fused: dict = {}
    cpu_ref: dict = {}
    for name, (model, G, h) in rollout_models().items():
        fused[name], ref[name], cpu_fused[name], cpu_ref[name] = {}, {}, {}, {}
        for n in BATCHES:
            fused[name][str(n)] = rollout_us(model, G, h, n, budget, repeats, fused=True)
            cpu_fused[name][str(n)] = CPU_US[-1]
            ref[name][str(n)] = rollout_us(model, G, h, n, budget, repeats, fused=False)
            cpu_ref[name][str(n)] = CPU_US[-1]
            log(f"rollout {name} batch {n}: {fused[name][str(n)]:.2f} us/step/traj (reference {ref[name][str(n)]:.2f})")
    # the learned SO(3) model of the peer comparison; the SE(3) MLP 64x3 figures are those above
    learned, learned_ref = {"se3_mlp_64x3": fused["se3_mlp"]}, {"se3_mlp_64x3": ref["se3_mlp"]}
    model, G, h = learned_so3_model()
    learned["so3_mlp_10x2"], learned_ref["so3_mlp_10x2"] = {}, {}
    cpu_learned: dict = {"se3_mlp_64x3": cpu_fused["se3_mlp"], "so3_mlp_10x2": {}}
    cpu_learned_ref: dict = {"se3_mlp_64x3": cpu_ref["se3_mlp"], "so3_mlp_10x2": {}}
    for n in BATCHES:
        learned["so3_mlp_10x2"][str(n)] = rollout_us(model, G, h, n, budget, repeats, fused=True)
        cpu_learned["so3_mlp_10x2"][str(n)] = CPU_US[-1]
        learned_ref["so3_mlp_10x2"][str(n)] = rollout_us(model, G, h, n, budget, repeats, fused=False)
        cpu_learned_ref["so3_mlp_10x2"][str(n)] = CPU_US[-1]
        log(
            f"rollout so3_mlp_10x2 batch {n}: {learned['so3_mlp_10x2'][str(n)]:.2f} us/step/traj "
            f"(reference {learned_ref['so3_mlp_10x2'][str(n)]:.2f})"
        )
    out["learned_rollout_us_per_step_traj"], out["baseline_learned_rollout_us_per_step_traj"] = learned, learned_ref
    out["rollout_us_per_step_traj"], out["baseline_rollout_us_per_step_traj"] = fused, ref
    cpu["rollout_us_per_step_traj"], cpu["baseline_rollout_us_per_step_traj"] = cpu_fused, cpu_ref
    cpu["learned_rollout_us_per_step_traj"] = cpu_learned
    cpu["baseline_learned_rollout_us_per_step_traj"] = cpu_learned_ref
    out["cpu_time"] = cpu

    # compilation
    if not args.no_compile and compile_cache.compiler_available():
        model, G, h = rollout_models()["free_body_true"]
        g0, g1 = start(G, 8, h)
        t = time.perf_counter()
        model = model.with_path(model.path)
        model.set_plan(dataclasses.replace(model.plan, compile="true"))
        model.rollout(g0, g1, 3)
        out["compile_s"] = time.perf_counter() - t
        out["compiled_rollout_us_per_step_traj"] = {
            str(n): rollout_us(model, G, h, n, budget, repeats, compile="true") for n in (1000, 10000)
        }
        log(f"compile {out['compile_s']:.1f} s; compiled free body {out['compiled_rollout_us_per_step_traj']}")
    else:
        out["compile_s"] = None

    if args.compare_threads:
        out["threads_compare"] = compare_threads(args.data_dir, q)
        log(f"threads: {out['threads_compare']}")

    speed = {
        "train": out["train_triplets_per_s"] / out["baseline_train_triplets_per_s"],
        "exp3": out["baseline_exp3_s_per_epoch"] / out["exp3_s_per_epoch"],
        "mocap": out["baseline_mocap_s_per_epoch"] / out["mocap_s_per_epoch"],
    }
    for name in fused:
        for n in fused[name]:
            speed[f"rollout_{name}_{n}"] = ref[name][n] / fused[name][n]
    for n in BATCHES:
        speed[f"learned_rollout_so3_mlp_10x2_{n}"] = (
            learned_ref["so3_mlp_10x2"][str(n)] / learned["so3_mlp_10x2"][str(n)]
        )
    for name, b in out["baseline_models"].items():
        speed[f"baseline_{name}"] = b["s_per_epoch_reference"] / b["s_per_epoch_fused"]
    out["speedup"] = speed
    if args.fast_tier:  # after the timed figures, so that the tests do not share the cores with them
        out["fast_tier"] = fast_tier(log)
    write_figures(out, args.json, t_all, log)


if __name__ == "__main__":
    main()
