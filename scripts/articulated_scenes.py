"""The articulated acceptance table: MuJoCo scenes never used while developing, trained with the default
command, against constant velocity (and constant acceleration), with the joints inferred from the data.

    python scripts/articulated_scenes.py [--scenes all|name,name] [--out docs/bench/articulated_scenes.json]
        [--trajectories 128] [--steps 100] [--workdir outputs/scenes] [--label default] [-- key=value ...]

Each scene is simulated by MuJoCo (`liedfl_cli.data.mujoco_chain.chain_dataset`, seeds 9001+), written
WITHOUT its joints (so `model.joints=auto` must infer them), then trained with

    liedfl train dataset=file dataset.path=<scene>.h5 model.kinetic=articulated dataset.rollout_steps=50

plus whatever follows `--` (e.g. `train.epochs=400` for another budget). Recorded per scene: the eval's
one-step and 50-step rollout ratios to constant velocity, the constant-acceleration one-step ratio, Newton
failures, training seconds and the command's wall time, whether the inferred joints equal MuJoCo's, and
(when `liedfl export` exists) the MJCF replay ratio: the exported model, replayed by MuJoCo from the
engine's true initial states of the test trajectories, over 50 steps, mean geodesic error over constant
velocity's. Results are appended to the JSON (one record per scene and label) and printed as a table.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

SCENES: dict[str, dict] = {
    "chain3_ball": {"links": 3, "joint": "ball"},
    "tree5_ball": {"parents": [-1, 0, 0, 0, 1], "joints": ["free", "ball", "ball", "ball", "ball"]},
    "arm4_hinge_pinned_gravity": {
        "parents": [-1, 0, 1, 2],
        "joints": ["hinge", "hinge", "hinge", "hinge"],
        "gravity": 9.81,
        "h": 0.02,
        "speed": 2.0,
    },
    "tree7_hinge_ball": {
        "parents": [-1, 0, 1, 2, 0, 4, 5],
        "joints": ["free", "hinge", "ball", "hinge", "ball", "hinge", "ball"],
        "rotations": "parent",
    },
    "tree5_universal_weld": {
        "parents": [-1, 0, 0, 1, 2],
        "joints": ["free", "universal", "hinge", "weld", "ball"],
    },
    "tree4_pinned_universal_gravity": {
        "parents": [-1, 0, 0, 1],
        "joints": ["universal", "hinge", "ball", "hinge"],
        "gravity": 9.81,
        "h": 0.02,
        "speed": 2.0,
    },
    "chain4_heavy_root": {"parents": [-1, 0, 1, 2], "joints": ["free", "ball", "ball", "ball"], "heavy_root": True},
    "chain4_heavy_root_mm": {
        "parents": [-1, 0, 1, 2],
        "joints": ["free", "ball", "ball", "ball"],
        "heavy_root": True,
        "unit": "mm",
    },
}


def make_scene(name: str, path: Path, trajectories: int, steps: int, seed: int):
    from liedfl_cli.data.hdf5 import save_dataset
    from liedfl_cli.data.mujoco_chain import chain_dataset

    kw = {"h": 0.05, **SCENES[name]}
    ds = chain_dataset(n_trajectories=trajectories, steps=steps, seed=seed, declare_joints=False, **kw)
    save_dataset(ds, path)
    return ds


def read_eval(run: Path) -> dict:
    rows = {r["model"]: r for r in csv.DictReader((run / "eval.csv").open())}
    f = lambda r, k: float(r[k]) if r.get(k) not in (None, "") else None
    m, ca = rows["model"], rows.get("constant_acceleration", {})
    return {
        "one_step_vs_cv": f(m, "one_step_vs_cv"),
        "rollout50_vs_cv": f(m, "rollout_vs_cv"),
        "newton_failures": int(float(m["newton_failures"] or 0)),
        "train_seconds": f(m, "train_seconds"),
        "const_accel_one_step_vs_cv": f(ca, "one_step_vs_cv") if ca else None,
        "true_scheme_one_step_vs_cv": f(rows["true_scheme"], "one_step_vs_cv") if "true_scheme" in rows else None,
    }


def _dof_signs(ds, run: Path) -> list[tuple[tuple[int, int], float]]:
    """((qpos address, qvel address), +-1) of every hinge DoF of the engine's model: an inferred axis is
    defined up to its sign, so the engine's angle and rate are flipped where the run's axis is the
    opposite of MuJoCo's (the same motion in the exported model's convention)."""
    import mujoco

    src = mujoco.MjModel.from_xml_string(ds.params["mjcf"])
    learned = json.loads((run / "joints.json").read_text())["axes"]
    out = []
    for jid in range(src.njnt):
        if int(src.jnt_type[jid]) != 3:  # hinge
            continue
        name = mujoco.mj_id2name(src, mujoco.mjtObj.mjOBJ_JOINT, jid)  # j<b> or j<b>a / j<b>b (universal)
        b = int(name[1:].rstrip("ab"))
        row = 1 if name.endswith("b") else 0
        sgn = 1.0 if float(np.dot(src.jnt_axis[jid], learned[b][row])) >= 0 else -1.0
        out.append(((int(src.jnt_qposadr[jid]), int(src.jnt_dofadr[jid])), sgn))
    return out


def mjcf_replay(run: Path, ds, out: Path) -> float | None:
    """The exported model replayed by MuJoCo from the true initial states of the test trajectories:
    mean geodesic error over 50 steps / constant velocity's. None when export is not available."""
    from liedfl_cli.evaluation.metrics import geodesic_error
    from liedfl_cli.solvers.one_step import constant_velocity_rollout

    try:
        from liedfl_cli.files.mjcf import replay  # type: ignore[attr-defined]
    except ImportError:
        return None
    xml = out / "model.xml"
    r = subprocess.run(
        ["liedfl", "export", f"run={run}", "format=mjcf", f"out={xml}"],
        capture_output=True,
        text=True,
        cwd=out,
    )
    if r.returncode != 0:
        print(f"  export failed: {r.stderr.strip()[-300:]}")
        return None
    import torch

    from liedfl_cli.lie import Pose

    text = xml.read_text()
    signs = _dof_signs(ds, run)
    test = list(ds.test_idx)
    steps = min(50, ds.n_steps)
    errs, cvs = [], []
    truth = ds.pose(test)
    for j, i in enumerate(test):
        qpos, qvel = ds.extras["qpos"][i, 0].copy(), ds.extras["qvel"][i, 0].copy()
        for (qa, va), sgn in signs:
            qpos[qa] *= sgn
            qvel[va] *= sgn
        Rw, _ = replay(text, ds.tree, qpos, qvel, ds.h, steps)
        true_R = torch.as_tensor(ds.extras["body_R_world"][i, : steps + 1])
        errs.append(float(geodesic_error(torch.as_tensor(Rw), true_R).mean()))
        g0, g1 = truth.index((slice(j, j + 1), 0)), truth.index((slice(j, j + 1), 1))
        cv = constant_velocity_rollout(ds.group, g0, g1, steps)
        from liedfl_cli.lie.tree import forward_kinematics

        cvw = forward_kinematics(ds.tree, Pose(cv.R[0], cv.p[0]))
        cvs.append(float(geodesic_error(cvw.R, true_R).mean()))
    return float(np.mean(errs) / np.mean(cvs))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="all")
    ap.add_argument("--out", default=str(ROOT / "docs/bench/articulated_scenes.json"))
    ap.add_argument("--trajectories", type=int, default=128)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--workdir", default=str(ROOT / "outputs/scenes"))
    ap.add_argument("--label", default="default")
    a = ap.parse_args(argv)
    names = list(SCENES) if a.scenes == "all" else a.scenes.split(",")
    bad = [n for n in names if n not in SCENES]
    if bad:
        print(f"error: unknown scene(s) {bad}; choose from {list(SCENES)}", file=sys.stderr)
        return 2
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    out = Path(a.out)
    records = json.loads(out.read_text())["records"] if out.is_file() else []
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for k, name in enumerate(names):
        seed = 9001 + list(SCENES).index(name)
        path = work / f"{name}.h5"
        ds = make_scene(name, path, a.trajectories, a.steps, seed)
        run = work / f"run_{name}_{a.label}"
        cmd = [
            "liedfl",
            "train",
            "dataset=file",
            f"dataset.path={path}",
            "model.kinetic=articulated",
            "dataset.rollout_steps=50",
            "ui.progress=false",
            f"hydra.run.dir={run}",
            *extra,
        ]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=work, env=env)
        wall = time.perf_counter() - t0
        (work / f"{name}_{a.label}.log").write_text(r.stdout + r.stderr)
        if r.returncode != 0:
            print(f"{name}: train failed ({r.stderr.strip().splitlines()[-1:]})")
            continue
        rec = {"scene": name, "label": a.label, "seed": seed, "spec": SCENES[name], "extra": extra}
        rec.update(read_eval(run))
        rec["wall_seconds"] = wall
        joints = json.loads((run / "joints.json").read_text())
        truth = ds.params["physics"]["joints"]
        rec["joints_inferred"] = joints["kinds"]
        rec["joints_correct"] = list(joints["kinds"]) == list(truth)
        rec["mjcf_replay50_vs_cv"] = mjcf_replay(run, ds, work)
        rec["load"] = os.getloadavg()[0]
        rec["cpu"] = platform.processor() or platform.machine()
        records = [x for x in records if not (x["scene"] == name and x["label"] == a.label)] + [rec]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"records": records}, indent=1))
        print(
            f"[{k + 1}/{len(names)}] {name}: one step {rec['one_step_vs_cv']:.3f}x CV, 50 steps "
            f"{rec['rollout50_vs_cv']:.3f}x, Newton failures {rec['newton_failures']}, joints "
            f"{'ok' if rec['joints_correct'] else joints['kinds']}, train {rec['train_seconds']:.0f} s, "
            f"CA {rec['const_accel_one_step_vs_cv']:.2f}x, MJCF {rec['mjcf_replay50_vs_cv']}",
            flush=True,
        )
    print(table(records))
    return 0


def table(records: list[dict]) -> str:
    head = (
        "| scene | label | one step ÷ CV | 50 steps ÷ CV | Newton failures | joints inferred | train s | "
        "const. accel. one step ÷ CV | MJCF replay 50 ÷ CV |"
    )
    lines = [head, "|" + "---|" * 9]
    fmt = lambda x, p=3: "–" if x is None else f"{x:.{p}f}"
    for r in records:
        lines.append(
            f"| {r['scene']} | {r['label']} | {fmt(r['one_step_vs_cv'])} | {fmt(r['rollout50_vs_cv'])} | "
            f"{r['newton_failures']} | {'correct' if r['joints_correct'] else r['joints_inferred']} | "
            f"{fmt(r['train_seconds'], 0)} | {fmt(r['const_accel_one_step_vs_cv'], 2)} | "
            f"{fmt(r['mjcf_replay50_vs_cv'])} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
