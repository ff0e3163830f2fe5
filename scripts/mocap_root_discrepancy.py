"""Why our Exp 4 root-rotation discrepancy (1.535 rad) is not the paper's 0.373: every definition tried.

python scripts/mocap_root_discrepancy.py [--out outputs/mocap_root_discrepancy.md]

The "ground-truth discrepancy" of the paper's Exp 4 table is the mean over frames of the distance
between recording 49_06 and recording 49_07. Our import reproduces the paper's joint (0.413 over the
18 moving joints vs 0.416) and root position (6.645 vs 6.624 ASF units) discrepancies, but the root
rotation gives 1.535 rad vs 0.373. This script recomputes the root-rotation discrepancy under

  1. all 72 Euler conventions: which file column is about which axis (6) x the order in which the
     three elementary rotations are composed (6) x the matrix or its transpose (2);
  2. with and without the converter's T-pose first frame;
  3. 120 / 60 / 30 / 15 Hz (every 1st / 2nd / 4th / 8th frame);
  4. Savitzky-Golay smoothing windows (raw; 15/4; 51/6, the import's; 101/6);
  5. the y-up -> z-up world turn (a fixed left factor: no effect on a distance between recordings);
  6. heading removal (the yaw about the vertical taken out of every frame) and rotations relative to
     each recording's first frame (R_0^T R_k and R_k R_0^T);
  7. the best constant alignment of one recording to the other (left Q R_k or right R_k Q, chordal
     optimum);
  8. six distances: geodesic angle, chordal (Frobenius norm of R1 - R2), relative (the same over the
     norm of R2), quaternion 1 - abs(q1.q2), norm of log R1 - log R2, wrapped Euler-angle difference;
  9. mean, RMS and median over frames;
 10. a time shift of one recording against the other (the only change that reaches the paper's value,
     at about 90 frames, and it breaks the joint and position discrepancies).

It prints (and writes to --out) one table per item. No training; takes seconds.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
import torch

from liedfl_cli.data.bvh import axis_rotation, read_bvh
from liedfl_cli.data.mocap import CMU_BODY_JOINTS, Z_UP
from liedfl_cli.data.smoothing import savgol_rotations
from liedfl_cli.lie import so3

ROOT = Path(__file__).resolve().parents[1]
FILES = (ROOT / "data" / "cmu_mocap" / "49_06.bvh", ROOT / "data" / "cmu_mocap" / "49_07.bvh")
PAPER = {"root_rot": 0.373, "joint_rot": 0.416, "root_pos": 6.624}


# ----------------------------------------------------------------------------- distances
def geodesic(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return so3.geodesic_distance(torch.from_numpy(A), torch.from_numpy(B)).numpy()


def quaternion(R: np.ndarray) -> np.ndarray:
    return so3.to_quaternion(torch.from_numpy(np.ascontiguousarray(R))).numpy()


def euler_zyx(R: np.ndarray) -> np.ndarray:
    """Intrinsic Z-Y-X angles (rad) of R = Rz Ry Rx."""
    y = np.arcsin(np.clip(-R[..., 2, 0], -1, 1))
    z = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    x = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return np.stack([z, y, x], -1)


DISTANCES = {
    "geodesic angle of R1^T R2 (rad)": geodesic,
    "chordal: Frobenius norm of R1 - R2": lambda A, B: np.linalg.norm(A - B, axis=(-1, -2)),
    "relative: Frobenius norm of R1 - R2 over that of R2": lambda A, B: (
        np.linalg.norm(A - B, axis=(-1, -2)) / np.sqrt(3.0)
    ),
    "quaternion: 1 - abs(q1.q2)": lambda A, B: 1.0 - np.abs((quaternion(A) * quaternion(B)).sum(-1)),
    "norm of log R1 - log R2 (rad)": lambda A, B: np.linalg.norm(
        so3.log(torch.from_numpy(A)).numpy() - so3.log(torch.from_numpy(B)).numpy(), axis=-1
    ),
    "wrapped ZYX Euler difference (rad)": lambda A, B: np.linalg.norm(
        np.angle(np.exp(1j * (euler_zyx(A) - euler_zyx(B)))), axis=-1
    ),
}


# ----------------------------------------------------------------------------- data
class Recording:
    def __init__(self, path: Path):
        self.bvh = read_bvh(path)
        self.root = self.bvh.joint_index("Hips")
        self.angles = self.bvh.euler_angles(self.root)  # (F, 3) degrees, file columns Z Y X
        self.order = self.bvh.rotation_order(self.root)
        Rw, pw = self.bvh.world_poses()
        self.R_world, self.p = Rw[:, self.root], pw[:, self.root]
        self.joints = self.bvh.local_rotations([self.bvh.joint_index(n) for n in CMU_BODY_JOINTS])

    def root_rotations(self, axes: str | None = None, compose: tuple[int, ...] | None = None, transpose=False):
        """Root rotation from the file's three columns read as rotations about `axes` (default the declared
        ones), composed in the column order `compose` (default 0, 1, 2 = the BVH convention)."""
        axes = axes or self.order
        compose = compose or (0, 1, 2)
        R = np.broadcast_to(np.eye(3), self.angles.shape[:1] + (3, 3)).copy()
        for c in compose:
            R = R @ axis_rotation(axes[c], np.deg2rad(self.angles[:, c]))
        return np.swapaxes(R, -1, -2) if transpose else R


def common(a: np.ndarray, b: np.ndarray, skip: int = 1, sub: int = 1):
    a, b = a[skip::sub], b[skip::sub]
    n = min(len(a), len(b))
    return a[:n], b[:n]


def heading_free(R: np.ndarray) -> np.ndarray:
    """Remove the rotation about the vertical (y in BVH) that turns the root's z axis into its heading."""
    f = R[..., :, 2]  # the root's z axis in the world
    psi = np.arctan2(f[..., 0], f[..., 2])  # heading about y
    return np.swapaxes(axis_rotation("Y", psi), -1, -2) @ R


def best_alignment(A: np.ndarray, B: np.ndarray, side: str) -> np.ndarray:
    """A aligned to B by one constant rotation Q (chordal optimum): Q A_k (left) or A_k Q (right)."""
    M = (B @ np.swapaxes(A, -1, -2)).sum(0) if side == "left" else (np.swapaxes(A, -1, -2) @ B).sum(0)
    Q = so3.project(torch.from_numpy(M)).numpy()
    return Q @ A if side == "left" else A @ Q


def table(title: str, rows: list[tuple], header: tuple[str, ...]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(x if isinstance(x, str) else f"{x:.3f}" for x in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("outputs/mocap_root_discrepancy.md"))
    args = ap.parse_args()
    r1, r2 = (Recording(f) for f in FILES)
    out = []
    mean_geo = lambda A, B: float(geodesic(A, B).mean())

    # 0. our import (z-up, T-pose frame skipped, 120 Hz, root world rotation) and the other two numbers
    A, B = common(r1.R_world, r2.R_world)
    base = mean_geo(A, B)
    J1, J2 = common(r1.joints, r2.joints)
    dj = geodesic(J1, J2)
    moving = dj.max(0) > 1e-9
    p1, p2 = common(r1.p, r2.p)
    pos = float(np.linalg.norm((p1 - p1[:1]) - (p2 - p2[:1]), axis=-1).mean())
    out.append(
        table(
            "Our import against the paper (mean over the 471 common frames)",
            [
                ("root rotation (rad)", base, PAPER["root_rot"]),
                (f"joint rotation, {int(moving.sum())} moving joints (rad)", float(dj[:, moving].mean()), 0.416),
                ("joint rotation, all 22 joints (rad)", float(dj.mean()), 0.416),
                ("root position from each start (ASF units)", pos, PAPER["root_pos"]),
            ],
            ("quantity", "ours", "paper"),
        )
    )

    # 1. 72 Euler conventions
    vals = []
    for axes in itertools.permutations("ZYX"):
        for order in itertools.permutations(range(3)):
            for tr in (False, True):
                a, b = common(r1.root_rotations("".join(axes), order, tr), r2.root_rotations("".join(axes), order, tr))
                vals.append(("".join(axes), order, tr, mean_geo(a, b)))
    v = np.array([x[-1] for x in vals])
    best = vals[int(np.argmin(v))]
    declared = next(x[-1] for x in vals if x[0] == r1.order and x[1] == (0, 1, 2) and not x[2])
    out.append(
        table(
            "1. 72 Euler conventions (column axes x composition order x transpose), root rotation (rad)",
            [
                ("the file's own convention (local, before the world turn)", declared),
                ("minimum over the 72", float(v.min())),
                ("median over the 72", float(np.median(v))),
                ("maximum over the 72", float(v.max())),
                (f"minimum at axes {best[0]}, order {best[1]}, transpose {best[2]}", best[3]),
            ],
            ("convention", "mean geodesic"),
        )
    )

    # 2-5. frames, rates, smoothing, world turn
    rows = [
        ("skip the T-pose frame (ours)", mean_geo(*common(r1.R_world, r2.R_world, skip=1))),
        ("keep the T-pose frame", mean_geo(*common(r1.R_world, r2.R_world, skip=0))),
    ]
    rows += [(f"{120 // s} Hz", mean_geo(*common(r1.R_world, r2.R_world, sub=s))) for s in (2, 4, 8)]
    for w, o in ((15, 4), (51, 6), (101, 6)):
        a, b = (savgol_rotations(R[1:], w, o) for R in (r1.R_world, r2.R_world))
        rows.append((f"Savitzky-Golay window {w}, order {o}", mean_geo(*common(a, b, skip=0))))
    rows.append(("y-up -> z-up world turn (ours)", mean_geo(*common(Z_UP @ r1.R_world, Z_UP @ r2.R_world))))
    out.append(
        table("2-5. Frames, rates, smoothing, world frame: root rotation (rad)", rows, ("variant", "mean geodesic"))
    )

    # 6-7. heading, relative to the start, constant alignment
    A, B = common(r1.R_world, r2.R_world)
    rows = [
        ("heading (yaw about the vertical) removed", mean_geo(heading_free(A), heading_free(B))),
        ("relative to each start, R_0^T R_k", mean_geo(np.swapaxes(A[:1], -1, -2) @ A, np.swapaxes(B[:1], -1, -2) @ B)),
        ("relative to each start, R_k R_0^T", mean_geo(A @ np.swapaxes(A[:1], -1, -2), B @ np.swapaxes(B[:1], -1, -2))),
        ("best constant left alignment Q R_k", mean_geo(best_alignment(A, B, "left"), B)),
        ("best constant right alignment R_k Q", mean_geo(best_alignment(A, B, "right"), B)),
    ]
    out.append(
        table(
            "6-7. Heading, start frame, best constant alignment: root rotation (rad)",
            rows,
            ("variant", "mean geodesic"),
        )
    )

    # 8-9. distances and statistics
    rows = []
    for name, d in DISTANCES.items():
        x = d(A, B)
        rows.append((name, float(x.mean()), float(np.sqrt((x**2).mean())), float(np.median(x))))
    out.append(table("8-9. Six distances, three statistics over frames", rows, ("distance", "mean", "RMS", "median")))

    # 10. time shift
    shifts = range(-150, 151)
    res = []
    for s in shifts:
        a, b = (r1.R_world[1 + s :], r2.R_world[1:]) if s >= 0 else (r1.R_world[1:], r2.R_world[1 - s :])
        n = min(len(a), len(b))
        res.append(mean_geo(a[:n], b[:n]))
    k = int(np.argmin(res))
    s = list(shifts)[k]

    def at_shift(s: int) -> tuple[float, float, float]:
        sl1 = slice(1 + max(s, 0), None)
        sl2 = slice(1 + max(-s, 0), None)
        n = min(len(r1.R_world[sl1]), len(r2.R_world[sl2]))
        root = mean_geo(r1.R_world[sl1][:n], r2.R_world[sl2][:n])
        jd = geodesic(r1.joints[sl1][:n], r2.joints[sl2][:n])[:, moving].mean()
        q1, q2 = r1.p[sl1][:n], r2.p[sl2][:n]
        ps = float(np.linalg.norm((q1 - q1[:1]) - (q2 - q2[:1]), axis=-1).mean())
        return root, float(jd), ps

    rows = [(f"shift {t} frames", *at_shift(t)) for t in (0, s)]
    rows.append(("paper", PAPER["root_rot"], PAPER["joint_rot"], PAPER["root_pos"]))
    out.append(
        table(
            f"10. Time shift of 49_06 against 49_07 (best root shift {s} frames = {s / 120:.2f} s)",
            rows,
            ("alignment", "root rot (rad)", "joint rot, moving (rad)", "root pos (ASF)"),
        )
    )
    text = "\n".join(out)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)


if __name__ == "__main__":
    main()
