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
failed=0
for exp in ${LIEDFL_EXPERIMENTS:-exp1_euler_vs_lie exp2_discrete_vs_continuous exp3_manifold}; do
  # a sweep finishes even when some jobs fail (exit code = number of failed jobs); report them all
  liedfl train -m "experiment=$exp" ui.progress=false "hydra.sweep.dir=$out/$exp" "$@" || failed=1
  liedfl report "sweep=$out/$exp"
done
python scripts/summarize_paper.py "$out" > "$out/summary.md"
echo "summary: $out/summary.md"
if [ "$failed" -ne 0 ]; then
  echo "some sweep jobs failed: see the 'Failed runs' section of each report.md" >&2
  exit 1
fi
