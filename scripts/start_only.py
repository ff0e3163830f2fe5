"""The least-squares start alone on the MuJoCo scenes of scripts/articulated_scenes.py: the one-step
error over constant velocity of the geometric start and of the start (docs/identification.md).

    python scripts/start_only.py [scene ...]
"""

import sys
import time
from pathlib import Path

import torch

from liedfl_cli.data.mujoco_chain import chain_dataset
from liedfl_cli.evaluation.metrics import geodesic_error
from liedfl_cli.models.articulated.fit import least_squares_start
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedTriplets
from liedfl_cli.solvers.one_step import constant_velocity_one_step, one_step_predictions
from liedfl_cli.solvers.options import SolverOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
import articulated_scenes as A  # the scene list, beside this script

torch.set_num_threads(1)


def ratio(model, truth):
    pred, conv = one_step_predictions(model, truth, SolverOptions())
    cv = constant_velocity_one_step(model.G, truth)
    tgt = truth.index((slice(None), slice(2, None)))
    return float(geodesic_error(pred.R, tgt.R).mean() / geodesic_error(cv.R, tgt.R).mean())


for name, spec in [(n, A.SCENES[n]) for n in (sys.argv[1:] or A.SCENES)]:
    kw = {"h": 0.05, **spec}
    ds = chain_dataset(n_trajectories=64, steps=100, seed=555, **kw)
    truth = ds.pose()
    tr, te = truth.index(slice(0, 56)), truth.index(slice(56, 64))
    pot = ("uniform_gravity",) if kw.get("gravity") else ()
    model = ArticulatedLieDFLNN(
        ds.tree, ds.h, potential=pot, forces=("rayleigh",), gravity=ds.params["physics"]["g"] or 9.81
    )
    b = ratio(model, te)
    t = time.time()
    rep = least_squares_start(model, ArticulatedTriplets(model, tr, 100), epsilon=10.0)
    print(f"{name:32s} start {b:.3f} -> LS {ratio(model, te):.4f} ({time.time() - t:.1f}s) {rep.line()}", flush=True)
