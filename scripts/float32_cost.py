"""What `runtime.dtype=float32` costs in accuracy: float32 against float64 rollouts on the default
free-body scene.

    python scripts/float32_cost.py [--steps 2000] [--data-dir outputs/data] [--json FILE]

The free rigid body of `liedfl train` (conf/dataset/free_rigid_body.yaml, every setting as there but
`steps` = `rollout_steps` = --steps, default 2000), its 10 test trajectories rolled out over all steps
from their true first pair by the true-parameter scheme: a LieDFLNN holding the scene's J_d and D, so
the rollout code of every trained LieDFLNN (fused Newton step) without a training error in the way.
Three variants, on the CPU:

  float64         the default (runtime.dtype=float64)
  float32_before  float32 re-orthonormalising only the increment W_k (what float32 did before poses
                  were projected too: `lie.tolerances.PROJECT_POSES[float32] = False`)
  float32         runtime.dtype=float32: every composed pose is re-orthonormalised as well

Per variant: `drift` max ||R^T R - I||_F over trajectories and steps; `rel_err_mean` /
`rel_err_final` the rollout error against the ground truth (||R^-R||_F / ||R||_F, mean over
trajectories and steps / at the last step: eval.csv's rel_rot_error_mean / _final) and their relative
differences to float64 (`*_rel_diff`); `max_diff_to_float64` the largest ||R^ - R^_64||_F;
`newton_failures`; `s_per_step` (wall time, this machine, not a benchmark).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402
from hydra.core.global_hydra import GlobalHydra  # noqa: E402

from liedfl_cli.cli import CONF_DIR  # noqa: E402
from liedfl_cli.data.scenes import get_dataset  # noqa: E402
from liedfl_cli.evaluation.metrics import orthogonality_drift, relative_rotation_error  # noqa: E402
from liedfl_cli.lie import tolerances  # noqa: E402
from liedfl_cli.models.true_scheme import true_model  # noqa: E402
from liedfl_cli.solvers.options import SolverOptions  # noqa: E402


@contextlib.contextmanager
def pose_projection(on: bool):
    """Switch the float32 pose projection (for the `float32_before` variant)."""
    before = tolerances.PROJECT_POSES[torch.float32]
    tolerances.PROJECT_POSES[torch.float32] = on
    try:
        yield
    finally:
        tolerances.PROJECT_POSES[torch.float32] = before


def dataset(steps: int, data_dir: str):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", [f"dataset.steps={steps}", f"dataset.rollout_steps={steps}"])
    return get_dataset(cfg.dataset, data_dir)[0]


def measure(steps: int, data_dir: str) -> dict:
    ds = dataset(steps, data_dir)
    idx = ds.test_idx
    truth = ds.pose(idx)  # float64, the reference of every variant
    out: dict = {
        "scene": ds.scene,
        "trajectories": len(idx),
        "steps": steps,
        "h": ds.h,
        "model": "true-parameter scheme (LieDFLNN, fused rollout)",
    }
    preds = {}
    for name, dtype, project in (
        ("float64", torch.float64, False),
        ("float32_before", torch.float32, False),
        ("float32", torch.float32, True),
    ):
        model = true_model(ds).to(dtype=dtype)
        model.eval()
        g = truth.to(dtype=dtype)
        g0, g1 = g.index((slice(None), 0)), g.index((slice(None), 1))
        with pose_projection(project):
            t0 = time.perf_counter()
            ro = model.rollout(g0, g1, steps, SolverOptions())
            seconds = time.perf_counter() - t0
        R = ro.pose.R.to(torch.float64)
        preds[name] = R
        err = relative_rotation_error(R, truth.R).amax(-1)  # (T, S+1): the worst body (one here)
        out[name] = {
            "drift": float(orthogonality_drift(R).max()),
            "rel_err_mean": float(err.mean()),
            "rel_err_final": float(err[:, -1].mean()),
            "newton_failures": ro.n_failed,
            "s_per_step": seconds / max(steps - 1, 1),
        }
    ref = out["float64"]
    for name in ("float32_before", "float32"):
        r = out[name]
        r["rel_err_mean_rel_diff"] = abs(r["rel_err_mean"] - ref["rel_err_mean"]) / ref["rel_err_mean"]
        r["rel_err_final_rel_diff"] = abs(r["rel_err_final"] - ref["rel_err_final"]) / ref["rel_err_final"]
        r["max_diff_to_float64"] = float(torch.linalg.matrix_norm(preds[name] - preds["float64"]).max())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--data-dir", default=str(ROOT / "outputs" / "data"))
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args()
    torch.set_num_threads(1)
    result = measure(args.steps, args.data_dir)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
