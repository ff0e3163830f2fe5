"""Generate a liedfl dataset of a random articulated chain or tree simulated by MuJoCo (an independent
engine; code and file contents: liedfl_cli/data/mujoco_chain.py, docs/data_format.md "MuJoCo chains").

python scripts/mujoco_chain.py [--links 3] [--joint ball|hinge|universal|weld] [--rotations world|parent]
    [--root free|pinned] [--gravity 0] [--joint-damping 0.05 | --joint-damping 0,0.05,0.02:0.08,...]
    [--n-trajectories 128] [--steps 100] [--h 0.05] [--dt 1e-3] [--speed 5] [--seed 0]
    [--test-fraction 0.1] [--max-step-rotation 0.785] [--out chain.h5]
    [--tree chain3|chain5|branched5|branched7|binary7 | --parents 0,0,0,1] [--joints hinge,ball,universal,weld]
    [--heavy-root [--root-mass 4]] [--unit m|mm] [--no-declare-joints]

A tree: --tree NAME or --parents (one parent per non-root body, e.g. 0,0,0,1: a root with three branches;
a leading -1 for the root may be given, as --parents=-1,0,0,0,1). --joints: one joint per body (the
first "free" or a pinned root's joint) or one per non-root body (the root's from --root, pinned with
--joint), among ball, hinge, universal (two MJCF hinges in one body) and weld (no joint). --joint-damping:
one value for every non-root DoF, or one entry per body (the root's first, 0 for a free root), each a
value or per-DoF values joined by ':' (a universal joint's two). --heavy-root: a --root-mass kg root
(default 4) with 0.5-0.7 kg links; --unit mm: the same motion stored in millimetres; --no-declare-joints
leaves the file's 'joints' out (liedfl then infers them).

then `liedfl train dataset=file dataset.path=chain.h5 model.kinetic=articulated`.
Prints the tree (parents, joints, masses, joint offsets), the largest per-step rotation and the time taken.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from liedfl_cli.data import save_dataset
from liedfl_cli.data.mujoco_chain import TREE_JOINTS, TREES, UNITS, chain_dataset
from liedfl_cli.errors import ConfigError


def parse_parents(text: str) -> list[int]:
    """'0,0,0,1' or '-1,0,0,0,1' -> [-1, 0, 0, 0, 1]."""
    try:
        out = [int(x) for x in text.replace(" ", "").split(",") if x != ""]
    except ValueError:
        raise ConfigError(f"--parents {text!r}: comma-separated integers, e.g. 0,0,0,1") from None
    return out if out[:1] == [-1] else [-1] + out


def parse_damping(text: str) -> float | list:
    """'0.05' -> 0.05; '0,0.05,0.02:0.08' -> [0.0, 0.05, [0.02, 0.08]] (one entry per body)."""
    try:
        if "," not in text and ":" not in text:
            return float(text)
        return [[float(v) for v in e.split(":")] if ":" in e else float(e) for e in text.replace(" ", "").split(",")]
    except ValueError:
        raise ConfigError(f"--joint-damping {text!r}: a number or per-body values like 0,0.05,0.02:0.08") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--links", type=int, default=3, help="2..5 links of a serial chain (default 3)")
    ap.add_argument("--joint", choices=TREE_JOINTS, default="ball", help="every joint (a pinned root's too)")
    ap.add_argument("--rotations", choices=("world", "parent"), default="world")
    ap.add_argument("--root", choices=("free", "pinned"), default="free")
    ap.add_argument("--gravity", type=float, default=0.0, help="magnitude along -e3 (m/s^2), 0: none")
    ap.add_argument(
        "--joint-damping", default="0.05", help="MuJoCo per-DoF joint damping (N m s): one value or per body"
    )
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
    ap.add_argument("--tree", choices=sorted(TREES), default=None, help="a named tree (parents)")
    ap.add_argument("--parents", default=None, help="a tree: the parent of every non-root body, e.g. 0,0,0,1")
    ap.add_argument("--joints", default=None, help="comma-separated joints per body: free|ball|hinge|universal|weld")
    ap.add_argument("--heavy-root", action="store_true", help="a --root-mass kg root with light (0.5-0.7 kg) links")
    ap.add_argument("--root-mass", type=float, default=4.0, help="the heavy root's mass (kg)")
    ap.add_argument("--unit", choices=tuple(UNITS), default="m", help="length unit of the file")
    ap.add_argument("--no-declare-joints", action="store_true", help="leave the joints out of the file")
    ap.add_argument("--out", default="chain.h5")
    a = ap.parse_args(argv)
    start = time.perf_counter()
    try:
        if a.tree is not None and a.parents is not None:
            raise ConfigError("give --tree or --parents, not both")
        parents = parse_parents(a.parents) if a.parents is not None else a.tree
        ds = chain_dataset(
            links=a.links,
            joint=a.joint,
            rotations=a.rotations,
            root=a.root,
            gravity=a.gravity,
            joint_damping=parse_damping(a.joint_damping),
            n_trajectories=a.n_trajectories,
            steps=a.steps,
            h=a.h,
            dt=a.dt,
            seed=a.seed,
            speed=a.speed,
            test_fraction=a.test_fraction,
            max_step_rotation=a.max_step_rotation,
            parents=parents,
            joints=None if a.joints is None else [j for j in a.joints.replace(" ", "").split(",") if j],
            heavy_root=a.heavy_root,
            root_mass=a.root_mass,
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
    kinds = phys["joints"]
    print(
        f"{ds.group.name}: {ds.n_bodies} bodies, parents {list(ds.tree.parents)}, joints {kinds}"
        f"{'' if ds.tree.joints is not None else ' (not declared in the file)'}, rotations={a.rotations}, "
        f"g={phys['g']:g} {a.unit}/s^2, unit {a.unit}"
    )
    for b, body in enumerate(phys["bodies"]):
        off = np.round(ds.tree.offsets[b], 4).tolist()
        com = np.round(body["com"], 4).tolist()
        eig = np.round(np.linalg.eigvalsh(np.asarray(body["inertia"])), 5).tolist()
        print(
            f"  {body['name']}: parent {ds.tree.parents[b]:>2}, {kinds[b]}, mass {body['mass']:.3f} kg, offset {off}, "
            f"com {com}, principal inertia {eig}, damping per DoF {phys['dof_damping'][b]}"
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
        f"energy: mean {E[:, 0].mean():.4g} at t=0, mean change over a trajectory {np.mean(E[:, -1] - E[:, 0]):.3g} "
        f"(kg {a.unit}^2/s^2)"
    )
    print(
        f"{ds.n_trajectories} trajectories x {ds.n_steps} steps (train {len(ds.train_idx)}, test {len(ds.test_idx)}) "
        f"simulated in {seconds:.1f} s -> {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
