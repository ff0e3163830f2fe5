"""Turn the report.csv files and times.csv of scripts/reproduce_paper.sh into the docs/results.md
sections (Exps 1-5) and the wall time of every experiment.

python scripts/summarize_paper.py outputs/paper > outputs/paper/summary.md
"""

import csv
import json
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
        r["kinetic"] = cfg["model"].get("kinetic", "")
        control = sweep / r["run"] / "control_eval.json"
        if control.is_file():  # Exp 5: the learned torque against the true one
            test = [c for c in json.loads(control.read_text()).get("rows", []) if c.get("split") == "test"]
            r["torque_error"] = test[0].get("rel_error_mean") if test else None
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
    e4 = rows(root / "exp4_mocap")
    if e4:
        print("### Exp 4: human cartwheels (CMU mocap, SE(3) x SO(3)^22, both recordings reproduced)\n")
        body = [
            [
                r["model"],
                r["kinetic"],
                r["epochs"],
                g(r["rel_rot_error_mean"]),
                g(r.get("position_error_mean")),
                r["newton_failures"],
                g(r["train_seconds"]),
            ]
            for r in e4
        ]
        header = ["model", "kinetic", "epochs", "rel. rot. error (mean)", "position error (mean)"]
        print(table(header + ["Newton failures", "train s"], body) + "\n")
        print("The paper's per-joint table: mocap_eval.md in each run folder.\n")
    e5 = rows(root / "exp5_control")
    if e5:
        print("### Exp 5: learning an unknown PD attitude control on SO(3)\n")
        body = [
            [r["model"], r["epochs"], g(r["rel_rot_error_mean"]), g(r.get("torque_error")), g(r["train_seconds"])]
            for r in e5
        ]
        header = ["model", "epochs", "rel. rot. error (mean)", "rel. torque error (test, mean)", "train s"]
        print(table(header, body) + "\n")
    times(root / "times.csv")


def times(path: Path):
    """Wall time per experiment from times.csv (one row per job, one per whole sweep)."""
    if not path.is_file():
        return
    with open(path) as f:
        rows_ = list(csv.DictReader(f))
    per: dict[str, dict] = defaultdict(lambda: {"jobs": 0, "job_s": 0.0, "sweep_s": None, "failed": 0})
    for r in rows_:
        e = per[r["experiment"]]
        if r["job"] == "(whole sweep)":
            e["sweep_s"] = float(r["seconds"])
            continue
        e["jobs"] += 1
        e["job_s"] += float(r["seconds"] or 0.0)
        e["failed"] += r["status"] != "ok"
    print("### Wall time of the reproduction (times.csv)\n")
    body = [
        [k, v["jobs"], v["failed"], g(v["job_s"] / 3600), g(v["sweep_s"] / 3600) if v["sweep_s"] is not None else "–"]
        for k, v in per.items()
    ]
    total = sum(v["sweep_s"] if v["sweep_s"] is not None else v["job_s"] for v in per.values())
    body.append(["**total**", sum(v["jobs"] for v in per.values()), "", "", f"**{g(total / 3600)}**"])
    print(table(["experiment", "jobs", "failed", "sum of job hours", "wall hours"], body) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/paper"))
