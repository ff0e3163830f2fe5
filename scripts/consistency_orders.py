"""Measure the empirical convergence orders of the true-parameter scheme (docs/results.md).

python scripts/consistency_orders.py
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers live there
from consistency import residual_order, rollout_order


def main():
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


if __name__ == "__main__":
    main()
