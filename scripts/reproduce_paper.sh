#!/usr/bin/env bash
# Reproduce the paper's experiments 1-5 as config sweeps, time every job, report each sweep, and
# summarise them.
#
#   scripts/reproduce_paper.sh                         # paper budgets (projection: docs/benchmarks.md)
#   scripts/reproduce_paper.sh --plan                  # every job, its budget and projected time; runs nothing
#   scripts/reproduce_paper.sh --plan --measure        # first time train.epochs=3 of every job (minutes)
#   scripts/reproduce_paper.sh budget=reduced epoch_scale=0.05   # what docs/results.md used
#   scripts/reproduce_paper.sh hydra/launcher=joblib hydra.launcher.n_jobs=2   # jobs in parallel processes
#   scripts/reproduce_paper.sh hydra/launcher=liedfl_slurm hydra.launcher.partition=cpu \
#       hydra.launcher.timeout_min=2880           # every job a SLURM task (docs/cluster.md)
#
# Jobs (scripts/paper_plan.py lists them): Exp 1 (6), Exp 2 (16: LieDFLNN and the three GLNN
# baselines at 4 training lengths), Exp 3 (3, plus the structured potential beyond the paper),
# Exp 4 (2: the paper's per-body model and model.kinetic=articulated), Exp 5 (1).
# Extra arguments are Hydra overrides passed to every sweep, a launcher (hydra/launcher=...) and its
# settings (hydra.launcher.*) included. With a SLURM launcher the sweeps are submitted at once
# (each waits for its jobs in the background, its console output in outputs/paper/<experiment>.log);
# otherwise they run one after the other (LIEDFL_SWEEPS_AT_ONCE=1 or 0 overrides this).
# LIEDFL_EXPERIMENTS picks experiments; LIEDFL_PLAN=1 is --plan.
# Outputs, whichever launcher: outputs/paper/<experiment>/ (one run per job, report.md/.csv, plots/),
# outputs/paper/times.csv (experiment, job, overrides, seconds, exit code of every job, and each
# sweep's wall time) and outputs/paper/summary.md (the results.md sections and the times).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${LIEDFL_PAPER_DIR:-outputs/paper}
experiments=${LIEDFL_EXPERIMENTS:-exp1_euler_vs_lie exp2_discrete_vs_continuous exp3_manifold exp4_mocap exp5_control}
export LIEDFL_EXPERIMENTS=$experiments
python=${PYTHON:-python}
plan=${LIEDFL_PLAN:-0}
measure=0
args=()
for arg in "$@"; do
  case "$arg" in
    --plan) plan=1 ;;
    --measure) measure=1 ;;
    --*) echo "reproduce_paper.sh: unknown option $arg (--plan, --measure)" >&2; exit 2 ;;
    *) args+=("$arg") ;;
  esac
done
if [ "$plan" = 1 ]; then
  if [ "$measure" = 1 ]; then
    exec nice -n 10 "$python" scripts/paper_plan.py measure ${args[@]+"${args[@]}"}
  fi
  exec "$python" scripts/paper_plan.py plan ${args[@]+"${args[@]}"}
fi
set -- ${args[@]+"${args[@]}"}
at_once=0
for arg in "$@"; do
  case "$arg" in hydra/launcher=*slurm*) at_once=1 ;; esac
done
at_once=${LIEDFL_SWEEPS_AT_ONCE:-$at_once}
mkdir -p "$out"

sweep() {  # a sweep finishes even when some jobs fail (exit code = number of failed jobs)
  local exp=$1
  shift
  liedfl train -m "experiment=$exp" ui.progress=false "hydra.sweep.dir=$out/$exp" "$@"
}

timed_sweep() {  # the sweep, then its wall time in $out/<exp>.seconds
  local exp=$1 start=$SECONDS rc=0
  sweep "$@" || rc=$?
  echo $((SECONDS - start)) >"$out/$exp.seconds"
  return $rc
}

times() {  # every job's time and exit code into times.csv (the experiment's earlier rows replaced)
  local exp=$1 folder=$2 sweep_s=()
  [ -f "$out/$exp.seconds" ] && sweep_s=(--sweep-seconds "$(cat "$out/$exp.seconds")")
  "$python" scripts/paper_plan.py times "$exp" "$folder" "$out/times.csv" ${sweep_s[@]+"${sweep_s[@]}"}
}

failed=0
if [ "$at_once" = 1 ]; then
  pids=()
  for exp in $experiments; do
    timed_sweep "$exp" "$@" >"$out/$exp.log" 2>&1 &
    pids+=($!)
    echo "sweep $exp: submitted (console output in $out/$exp.log)"
  done
  for pid in "${pids[@]}"; do
    wait "$pid" || failed=1
  done
  for exp in $experiments; do  # report every sweep, failed jobs included
    times "$exp" "$out/$exp"
    liedfl report "sweep=$out/$exp"
  done
else
  for exp in $experiments; do
    timed_sweep "$exp" "$@" || failed=1
    times "$exp" "$out/$exp"
    liedfl report "sweep=$out/$exp"  # every sweep, failed jobs included
  done
fi
# Beyond the paper: Exp 3 with the structured potential (uniform_gravity) instead of the MLP
if [[ " $experiments " == *" exp3_manifold "* ]]; then
  extra=exp3_manifold_structured
  start=$SECONDS
  liedfl train experiment=exp3_manifold model.potential=uniform_gravity ui.progress=false \
    "hydra.run.dir=$out/$extra" "$@" || failed=1
  echo $((SECONDS - start)) >"$out/$extra.seconds"
  times "$extra" "$out/$extra"
fi
"$python" scripts/summarize_paper.py "$out" >"$out/summary.md.tmp"
mv "$out/summary.md.tmp" "$out/summary.md"
echo "summary: $out/summary.md; job times: $out/times.csv"
if [ "$failed" -ne 0 ]; then
  echo "some sweep jobs failed: see the 'Failed runs' section of each report.md" >&2
  exit 1
fi
