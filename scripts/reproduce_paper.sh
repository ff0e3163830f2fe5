#!/usr/bin/env bash
# Reproduce the paper's experiments 1-3 as config sweeps, report each sweep, and summarise them.
#
#   scripts/reproduce_paper.sh                         # paper budgets (days on 2 CPU cores)
#   scripts/reproduce_paper.sh budget=reduced epoch_scale=0.05   # what docs/results.md used
#   scripts/reproduce_paper.sh hydra/launcher=joblib hydra.launcher.n_jobs=2   # jobs in parallel processes
#   scripts/reproduce_paper.sh hydra/launcher=liedfl_slurm hydra.launcher.partition=cpu \
#       hydra.launcher.timeout_min=2880           # every job a SLURM task (docs/cluster.md)
#
# Extra arguments are Hydra overrides passed to every sweep, a launcher (hydra/launcher=...) and its
# settings (hydra.launcher.*) included. With a SLURM launcher the three sweeps are submitted at once
# (each waits for its jobs in the background, its console output in outputs/paper/<experiment>.log);
# otherwise they run one after the other (LIEDFL_SWEEPS_AT_ONCE=1 or 0 overrides this).
# Outputs, whichever launcher: outputs/paper/<experiment>/ (one run per job, report.md/.csv, plots/)
# and outputs/paper/summary.md (the results.md sections).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${LIEDFL_PAPER_DIR:-outputs/paper}
experiments=${LIEDFL_EXPERIMENTS:-exp1_euler_vs_lie exp2_discrete_vs_continuous exp3_manifold}
at_once=0
for arg in "$@"; do
  case "$arg" in hydra/launcher=*slurm*) at_once=1 ;; esac
done
at_once=${LIEDFL_SWEEPS_AT_ONCE:-$at_once}

sweep() {  # a sweep finishes even when some jobs fail (exit code = number of failed jobs)
  local exp=$1
  shift
  liedfl train -m "experiment=$exp" ui.progress=false "hydra.sweep.dir=$out/$exp" "$@"
}

failed=0
if [ "$at_once" = 1 ]; then
  mkdir -p "$out"
  pids=()
  for exp in $experiments; do
    sweep "$exp" "$@" >"$out/$exp.log" 2>&1 &
    pids+=($!)
    echo "sweep $exp: submitted (console output in $out/$exp.log)"
  done
  for pid in "${pids[@]}"; do
    wait "$pid" || failed=1
  done
  for exp in $experiments; do  # report every sweep, failed jobs included
    liedfl report "sweep=$out/$exp"
  done
else
  for exp in $experiments; do
    sweep "$exp" "$@" || failed=1
    liedfl report "sweep=$out/$exp"  # every sweep, failed jobs included
  done
fi
# Beyond the paper: Exp 3 with the structured potential (uniform_gravity) instead of the MLP
if [[ " $experiments " == *" exp3_manifold "* ]]; then
  liedfl train experiment=exp3_manifold model.potential=uniform_gravity ui.progress=false \
    "hydra.run.dir=$out/exp3_manifold_structured" "$@" || failed=1
fi
python scripts/summarize_paper.py "$out" > "$out/summary.md"
echo "summary: $out/summary.md"
if [ "$failed" -ne 0 ]; then
  echo "some sweep jobs failed: see the 'Failed runs' section of each report.md" >&2
  exit 1
fi
