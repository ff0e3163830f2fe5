"""Measure the empirical convergence orders of the true-parameter scheme (docs/results.md) and of its
sub-step and fourth-order options (docs/substeps.md).

    OMP_NUM_THREADS=1 python scripts/consistency_orders.py [--steps] [--json docs/bench/orders.json]

Default: the DEL residual's order and the rollout error's order of the paper's scheme on SO(3) and
SE(3) against scipy's DOP853 (rtol 1e-13). --steps: the rollout order of every step option (s = 1, 2, 4
sub-steps of order 2; order 4 with s = 1, 2) on SO(3) and SE(3) against DOP853 and on a reduced tree
(free root, hinge, universal, ball, weld; gravity and per-DoF damping) against the same scheme 8
order-4 sub-steps finer, with the wall time of each rollout (one thread).
"""

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers live there
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from consistency import residual_order, rollout_order

OPTIONS = [(1, 2), (2, 2), (4, 2), (1, 4), (2, 4)]


def paper_scheme() -> None:
    print("| group | quantity | h | value | fitted order |")
    print("|---|---|---|---|---|")
    for kind in ("so3", "se3"):
        r = residual_order(kind)
        print(
            f"| {kind.upper()} | max DEL residual (t <= 0.8) | {', '.join(map(str, r['h']))} | "
            f"{', '.join(f'{v:.3e}' for v in r['max_residual'])} | {r['order']:.3f} |"
        )
        o = rollout_order(kind)
        print(
            f"| {kind.upper()} | rollout error at t = 2 | {', '.join(map(str, o['h']))} | "
            f"{', '.join(f'{v:.3e}' for v in o['final_error'])} | {o['order']:.3f} |"
        )
        print(f"| {kind.upper()} | max orthogonality drift over those rollouts | | {o['max_orth_drift']:.1e} | |")


def tree_orders() -> list[dict]:
    from liedfl_cli.models.liedflnn import substeps as sb
    from tests.test_articulated_joints import learned_like, mixed_tree, smooth_motion

    tree = mixed_tree("world")
    out = []
    hs = (0.04, 0.02, 0.01)  # at 0.08 the order-4 start has no solution on one trajectory (docs/substeps.md)
    T = 0.4
    for s, order in OPTIONS:
        errs, secs = [], []
        for h in hs:
            q = smooth_motion(tree, 2, 1, h, seed=6)
            q0, q1 = q.index((slice(None), 0)), q.index((slice(None), 1))
            torch.manual_seed(1)  # learned_like draws the damping per DoF from the global generator
            base = learned_like(tree, h)
            steps = round(T / h)
            ref = sb.SubstepModel(base, 8, 4).rollout(q0, q1, steps)
            t0 = time.perf_counter()
            ro = sb.with_substeps(base, s, order).rollout(q0, q1, steps)
            secs.append(time.perf_counter() - t0)
            errs.append(float((ro.pose.R[:, -1] - ref.pose.R[:, -1]).norm(dim=(-1, -2)).max()))
        slope = float(np.polyfit(np.log(hs), np.log(errs), 1)[0])
        out.append(
            {"substeps": s, "scheme_order": order, "h": list(hs), "error": errs, "seconds": secs, "fitted_order": slope}
        )
    return out


def step_options() -> dict:
    rec: dict = {}
    for kind in ("so3", "se3", "se3_rotational_damping"):
        rows = []
        for s, order in OPTIONS if kind != "se3_rotational_damping" else [(1, 4)]:
            hs = (0.08, 0.04, 0.02) if kind.startswith("se3") else (0.08, 0.04, 0.02, 0.01)
            t0 = time.perf_counter()
            o = rollout_order(kind, hs=hs, final_time=2.0, substeps=s, order=order)
            fitted = o.pop("order")
            rows.append(
                {"substeps": s, "scheme_order": order, **o, "error": o["final_error"], "fitted_order": fitted}
                | {"seconds_all_h": time.perf_counter() - t0}
            )
        rec[kind] = rows
    rec["tree"] = tree_orders()
    return rec


def tree_only() -> None:
    for r in tree_orders():
        print(r["substeps"], r["scheme_order"], [f"{e:.2e}" for e in r["error"]], f"{r['fitted_order']:.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", action="store_true", help="the orders of every sub-step option")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--tree", action="store_true", help="the tree's orders only (printed)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.tree:
        tree_only()
        return
    if not args.steps:
        paper_scheme()
        return
    rec = {"command": "OMP_NUM_THREADS=1 python scripts/consistency_orders.py --steps --json docs/bench/orders.json"}
    rec["load_before"] = os.getloadavg()[0]
    rec.update(step_options())
    rec["load_after"] = os.getloadavg()[0]
    print("| system | substeps | order | h | error at the end | fitted order |")
    print("|---|---|---|---|---|---|")
    for kind in ("so3", "se3", "se3_rotational_damping", "tree"):
        for r in rec[kind]:
            print(
                f"| {kind} | {r['substeps']} | {r['scheme_order']} | {', '.join(map(str, r['h']))} | "
                f"{', '.join(f'{e:.2e}' for e in r['error'])} | {r['fitted_order']:.2f} |"
            )
    assert all(math.isfinite(r["fitted_order"]) for k in ("so3", "se3", "tree") for r in rec[k])
    print("(se3_rotational_damping: SE(3) with damping on the rotation only; tree: against 8 order-4 sub-steps)")
    if args.json:
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(rec, indent=1))
        tmp.replace(args.json)


if __name__ == "__main__":
    main()
