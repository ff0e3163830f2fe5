#!/usr/bin/env bash
# Reproduce the paper's experiments 1-3 as config sweeps, report each sweep, and summarise them.
#
#   scripts/reproduce_paper.sh                         # paper budgets (days on 2 CPU cores)
#   scripts/reproduce_paper.sh budget=reduced epoch_scale=0.05   # what docs/results.md used
#
# Extra arguments are Hydra overrides passed to every sweep. Outputs: outputs/paper/<experiment>/
# (one run per job, report.md/.csv, plots/) and outputs/paper/summary.md (the results.md sections).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${LIEDFL_PAPER_DIR:-outputs/paper}
for exp in ${LIEDFL_EXPERIMENTS:-exp1_euler_vs_lie exp2_discrete_vs_continuous exp3_manifold}; do
  liedfl train -m "experiment=$exp" ui.progress=false "hydra.sweep.dir=$out/$exp" "$@"
  liedfl report "sweep=$out/$exp"
done
# Beyond the paper: Exp 3 with the structured potential (uniform_gravity) instead of the MLP
if [[ " ${LIEDFL_EXPERIMENTS:-exp3_manifold} " == *" exp3_manifold "* ]]; then
  liedfl train experiment=exp3_manifold model.potential=uniform_gravity ui.progress=false \
    "hydra.run.dir=$out/exp3_manifold_structured" "$@"
fi
python scripts/summarize_paper.py "$out" > "$out/summary.md"
echo "summary: $out/summary.md"
