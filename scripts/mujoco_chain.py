"""Generate a liedfl dataset of a random articulated chain simulated by MuJoCo (an independent engine;
code and file contents: liedfl_cli/data/mujoco_chain.py, docs/data_format.md "MuJoCo chains").

python scripts/mujoco_chain.py [--links 3] [--joint ball|hinge] [--rotations world|parent]
    [--root free|pinned] [--gravity 0] [--joint-damping 0.05] [--n-trajectories 128] [--steps 100]
    [--h 0.05] [--dt 1e-3] [--speed 5] [--seed 0] [--test-fraction 0.1] [--out chain.h5]
    [--parents -1,0,0,0,1 --joints free,ball,hinge,universal,weld] [--heavy-root] [--unit m|mm]
    [--no-declare-joints]

--parents/--joints make a tree (any parents, every joint type; a pinned root's joint is joints[0]);
--heavy-root a 4 kg root with 0.5-0.7 kg links; --unit mm the same motion in millimetres;
--no-declare-joints leaves the file's 'joints' out (liedfl then infers them).

then `liedfl train dataset=file dataset.path=chain.h5 model.kinetic=articulated`.
Prints the chain (masses, joint offsets), the largest per-step rotation and the time taken.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from liedfl_cli.data import save_dataset
from liedfl_cli.data.mujoco_chain import chain_dataset
from liedfl_cli.errors import ConfigError


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--links", type=int, default=3, help="2..5 links (default 3)")
    ap.add_argument("--joint", choices=("ball", "hinge"), default="ball")
    ap.add_argument("--rotations", choices=("world", "parent"), default="world")
    ap.add_argument("--root", choices=("free", "pinned"), default="free")
    ap.add_argument("--gravity", type=float, default=0.0, help="magnitude along -e3 (m/s^2), 0: none")
    ap.add_argument("--joint-damping", type=float, default=0.05, help="MuJoCo per-DOF joint damping (N m s)")
    ap.add_argument("--n-trajectories", type=int, default=128)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--h", type=float, default=0.05, help="sample step (s), a multiple of --dt")
    ap.add_argument("--dt", type=float, default=1e-3, help="MuJoCo's RK4 step (s)")
    ap.add_argument(
        "--speed", type=float, default=5.0, help="initial kinetic energy as every link spinning at this rate (rad/s)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-fraction", type=float, default=0.1)
    ap.add_argument("--max-step-rotation", type=float, default=math.pi / 4, help="refuse data above this (rad)")
    ap.add_argument("--parents", default=None, help="a tree: comma-separated parent indices, -1 first")
    ap.add_argument("--joints", default=None, help="comma-separated joint per body: free|ball|hinge|universal|weld")
    ap.add_argument("--heavy-root", action="store_true", help="a 4 kg root with light (0.5-0.7 kg) links")
    ap.add_argument("--unit", choices=("m", "mm"), default="m", help="length unit of the file")
    ap.add_argument("--no-declare-joints", action="store_true", help="leave the joints out of the file")
    ap.add_argument("--out", default="chain.h5")
    a = ap.parse_args(argv)
    start = time.perf_counter()
    try:
        ds = chain_dataset(
            links=a.links,
            joint=a.joint,
            rotations=a.rotations,
            root=a.root,
            gravity=a.gravity,
            joint_damping=a.joint_damping,
            n_trajectories=a.n_trajectories,
            steps=a.steps,
            h=a.h,
            dt=a.dt,
            seed=a.seed,
            speed=a.speed,
            test_fraction=a.test_fraction,
            max_step_rotation=a.max_step_rotation,
            parents=None if a.parents is None else [int(x) for x in a.parents.split(",")],
            joints=None if a.joints is None else a.joints.split(","),
            heavy_root=a.heavy_root,
            unit=a.unit,
            declare_joints=not a.no_declare_joints,
        )
    except (ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    seconds = time.perf_counter() - start
    path = save_dataset(ds, a.out)
    phys = ds.params["physics"]
    assert ds.tree is not None
    print(
        f"{ds.group.name}: {ds.n_bodies} bodies, joints {list(ds.tree.joint_kinds)}, rotations={a.rotations}, "
        f"g={a.gravity}, unit {a.unit}"
    )
    for b, body in enumerate(phys["bodies"]):
        off = np.round(ds.tree.offsets[b], 4).tolist()
        com = np.round(body["com"], 4).tolist()
        eig = np.round(np.linalg.eigvalsh(np.asarray(body["inertia"])), 5).tolist()
        print(
            f"  {body['name']}: parent {ds.tree.parents[b]:>2}, mass {body['mass']:.3f} kg, offset {off}, com {com}, "
            f"principal inertia {eig}"
        )
    r = ds.params["step_rotation"]
    print(
        f"largest per-step rotation: {r['coordinates']:.3f} rad (coordinates), {r['world']:.3f} rad (world attitudes) "
        f"at (trajectory, step, body) {tuple(r['where'])}; pi/2 = {math.pi / 2:.3f}"
    )
    print(
        f"damping stiffness h * lambda_max(M^-1 D) = {ds.params['simulation']['h_lambda_max_damping']:.3f} "
        "(largest over the initial states; liedfl's rollouts warn above 2)"
    )
    E = ds.extras["energy"]
    print(
        f"energy: mean {E[:, 0].mean():.4g} J at t=0, mean change over a trajectory {np.mean(E[:, -1] - E[:, 0]):.3g} J"
    )
    print(
        f"{ds.n_trajectories} trajectories x {ds.n_steps} steps (train {len(ds.train_idx)}, test {len(ds.test_idx)}) "
        f"simulated in {seconds:.1f} s -> {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
