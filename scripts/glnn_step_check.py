"""Why a trained GLNN Lie-Midpoint model rolls out badly: solver or parameters?

    python scripts/glnn_step_check.py RUN [RUN ...]

For each trained GLNN run (Lie-Midpoint or Lie-Heun): from 4 random states, the rollout's midpoint
step (damped Newton to tolerance) against the training step (`train_newton_iters` Newton steps) and
against a Lie-Heun step with the same parameters (max |w' difference|); and the learned parameters
(J's diagonal over its first entry, the damping's diagonal). Figures: docs/baselines.md, "Known issues".
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from liedfl_cli import api
from liedfl_cli.lie import so3
from liedfl_cli.solvers.options import SolverOptions


def main() -> None:
    for run in sys.argv[1:]:
        m = api.load_run(run).model
        params = m._params()
        gen = torch.Generator().manual_seed(0)
        R = so3.exp(torch.randn(4, 3, generator=gen, dtype=torch.float64))
        w = torch.randn(4, 3, generator=gen, dtype=torch.float64)
        with torch.no_grad():
            _, w_heun = m.heun_step(R, w, params)
            _, w_train = m.midpoint_step_train(R, w, params)
        _, w_solve, _ = m.midpoint_step_solve(R, w, params, SolverOptions())
        J, D = params[0].diagonal(), params[2].diagonal()
        print(
            f"{run}: integrator {m.integrator}; |solve - train| {float((w_solve - w_train).abs().max()):.1e}, "
            f"|solve - heun| {float((w_solve - w_heun).abs().max()):.1e}; "
            f"J ratios {[round(float(x), 3) for x in J / J[0]]}, D diag {[round(float(x), 4) for x in D]}"
        )


if __name__ == "__main__":
    main()
