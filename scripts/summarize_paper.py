"""Turn the report.csv files of scripts/reproduce_paper.sh into the docs/results.md sections.

python scripts/summarize_paper.py outputs/paper > outputs/paper/summary.md
"""

import csv
import sys
from collections import defaultdict
from pathlib import Path

import yaml


def rows(sweep: Path):
    path = sweep / "report.csv"
    if not path.is_file():
        return []
    with open(path) as f:
        out = list(csv.DictReader(f))
    for r in out:  # recover swept settings (scale, epochs) from each run's config
        cfg = yaml.safe_load((sweep / r["run"] / ".hydra" / "config.yaml").read_text())
        r["omega_scale"] = cfg["dataset"].get("initial", {}).get("omega_scale")
        r["epochs"] = cfg["train"]["epochs"]
    return out


def g(x, nd=3):
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "–"
    return f"{v:.{nd}e}" if v and (abs(v) < 1e-2 or abs(v) >= 1e4) else f"{v:.{nd}g}"


def table(header, body):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(map(str, b)) + " |" for b in body]
    return "\n".join(lines)


def main(root: Path):
    e1 = rows(root / "exp1_euler_vs_lie")
    if e1:
        print("### Exp 1: rotation matrices vs Euler angles (heavy body on SO(3))\n")
        body = [
            [
                r["model"],
                r["omega_scale"],
                r["epochs"],
                g(r["rel_rot_error_mean"]),
                g(r["rel_rot_error_final"]),
                g(r["geodesic_error_mean"]),
                r["newton_failures"],
                g(r["train_seconds"]),
            ]
            for r in sorted(e1, key=lambda r: (r["model"], float(r["omega_scale"] or 0)))
        ]
        print(
            table(
                [
                    "model",
                    "omega0 scale",
                    "epochs",
                    "rel. rot. error (mean)",
                    "(final)",
                    "geodesic (rad)",
                    "Newton failures",
                    "train s",
                ],
                body,
            )
            + "\n"
        )
    e2 = rows(root / "exp2_discrete_vs_continuous")
    if e2:
        print("### Exp 2: discrete vs continuous (free rigid body, 10 test trajectories x 500 steps)\n")
        err, tim = defaultdict(dict), defaultdict(dict)
        lengths = sorted({int(r["train_steps"]) for r in e2})
        for r in e2:
            err[r["model"]][int(r["train_steps"])] = g(r["rel_rot_error_mean"])
            tim[r["model"]][int(r["train_steps"])] = g(r["train_seconds"])
        print(
            table(
                ["model"] + [f"error, length {n}" for n in lengths] + [f"train s, length {n}" for n in lengths],
                [
                    [m] + [err[m].get(n, "–") for n in lengths] + [tim[m].get(n, "–") for n in lengths]
                    for m in sorted(err)
                ],
            )
            + "\n"
        )
    e3 = rows(root / "exp3_manifold")
    extra = root / "exp3_manifold_structured"
    if (extra / "eval.csv").is_file():  # the structured model, beyond the paper
        with open(extra / "eval.csv") as f:
            r = next(csv.DictReader(f))
        cfg = yaml.safe_load((extra / ".hydra" / "config.yaml").read_text())
        r["model"] = "liedflnn, potential uniform_gravity (beyond the paper)"
        r["epochs"] = cfg["train"]["epochs"]
        e3.append(r)
    if e3:
        print("### Exp 3: staying on the manifold (heavy rigid body on SE(3), 200-step rollout)\n")
        body = [
            [
                r["model"],
                r["epochs"],
                g(r["rel_rot_error_mean"]),
                g(r.get("position_error_mean")),
                g(r["max_orth_drift"]),
                g(r["max_det_drift"]),
                r["newton_failures"],
                g(r["train_seconds"]),
            ]
            for r in e3
        ]
        print(
            table(
                [
                    "model",
                    "epochs",
                    "rel. rot. error (mean)",
                    "position error (mean)",
                    "max ‖RᵀR − I‖_F",
                    "max abs(det R − 1)",
                    "Newton failures",
                    "train s",
                ],
                body,
            )
            + "\n"
        )


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/paper"))
