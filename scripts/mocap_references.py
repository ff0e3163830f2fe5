"""The zero-parameter references on the cartwheel recordings (Exp 4): one-step errors of constant
velocity, constant acceleration and constant velocity with Euclidean positions, teacher-forced from the
true poses over every sample of both recordings (`evaluation.mocap.one_step_errors`, the metrics of the
paper's table), the ratios of the last two to constant velocity, and the ground-truth discrepancy between the
two recordings. No training: the bar a model must clear.

`OMP_NUM_THREADS=1 python scripts/mocap_references.py [--out docs/bench/mocap_references_<date>.json]`
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=ROOT / "docs" / "bench" / f"mocap_references_{datetime.now():%Y-%m-%d}.json"
    )
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    a = ap.parse_args()
    from hydra import compose, initialize_config_dir

    from liedfl_cli.cli import CONF_DIR  # (registers the config's resolvers)
    from liedfl_cli.config.typed import typed
    from liedfl_cli.data.mocap import moving_joints
    from liedfl_cli.data.scenes import get_dataset
    from liedfl_cli.evaluation.mocap import (
        ONE_STEP_REFERENCES,
        _asf_per_unit,
        discrepancy,
        one_step_errors,
        sequence_errors,
    )

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=exp4_mocap"])
    ds, path = get_dataset(typed(cfg, "train").dataset, a.data_dir)
    spec = importlib.util.spec_from_file_location("paper_bands", ROOT / "scripts" / "paper_bands.py")
    assert spec is not None and spec.loader is not None
    bands = importlib.util.module_from_spec(spec)
    sys.modules["paper_bands"] = bands
    spec.loader.exec_module(bands)
    joints = moving_joints(ds)
    asf = _asf_per_unit(ds)
    out = one_step_errors(None, ds.R, ds.p, None, joints=joints, group=ds.group)
    assert out is not None
    names = [str(n) for n in (ds.params or {}).get("recordings", [])] or [
        f"recording {i}" for i in range(ds.R.shape[0])
    ]
    rec: dict = {
        "command": "OMP_NUM_THREADS=1 python scripts/mocap_references.py",
        "measured": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": bands.machine(),
        "dataset": str(path.name),
        "samples_per_recording": int(ds.R.shape[1]),
        "root_pos_unit": "CMU ASF units",
        "errors": {},
        "over_constant_velocity": {},
    }
    for who in ONE_STEP_REFERENCES:
        rec["errors"][who] = {
            k: [float(v * (asf if k == "root_pos" else 1.0)) for v in np.asarray(out[who][k])] for k in out[who]
        }
    for who in ONE_STEP_REFERENCES[1:]:
        rec["over_constant_velocity"][who] = {
            k: [float(x / y) for x, y in zip(out[who][k], out["const_velocity"][k])] for k in out[who]
        }
    rec["recordings"] = names
    # rollouts over the whole recordings: constant velocity and its Euclidean variant from the true first
    # pair, constant acceleration from the first three poses (one more than a model's rollout gets)
    import torch

    from liedfl_cli.lie import Pose
    from liedfl_cli.solvers import one_step as ref

    truth = Pose(torch.as_tensor(ds.R), torch.as_tensor(ds.p))
    g = [truth.index((slice(None), k)) for k in range(3)]
    S = int(ds.R.shape[1]) - 1
    rollouts = {
        "const_velocity": ref.constant_velocity_rollout(ds.group, g[0], g[1], S),
        "const_acceleration": ref.constant_acceleration_rollout(g[0], g[1], g[2], S),
        "euclid_velocity": ref.euclidean_velocity_rollout(g[0], g[1], S),
    }
    rec["rollout_errors"] = {}
    for who, ro in rollouts.items():
        e = sequence_errors(ro.R.numpy(), ro.p.numpy(), ds.R, ds.p, joints=joints)
        rec["rollout_errors"][who] = {
            k: [float(v * (asf if k == "root_pos" else 1.0)) for v in np.asarray(e[k])]
            for k in ("root_rot", "joint_rot", "joint_rot_all", "root_pos")
        }
    disc = discrepancy(ds)
    if disc is not None:  # the ground-truth discrepancy between the recordings (the paper's last row)
        rec["discrepancy"] = {
            k: float(disc[k]) * (asf if k == "root_pos" else 1.0)
            for k in ("root_rot", "joint_rot", "joint_rot_all", "root_pos")
        }
    a.out.write_text(json.dumps(rec, indent=1) + "\n")
    print(json.dumps({k: rec[k] for k in ("errors", "over_constant_velocity")}, indent=1))


if __name__ == "__main__":
    main()
