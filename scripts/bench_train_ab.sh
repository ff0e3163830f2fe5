#!/usr/bin/env bash
# CPU time of `liedfl train` before and after a change, alternately (old, new, old, new, ...), one thread:
#   bash scripts/bench_train_ab.sh <old commit> <repeats> [overrides...]    (prints "old|new i user sys wall")
# e.g. `bash scripts/bench_train_ab.sh 1d9c354 4 train.epochs=300` and `... 1d9c354 3 train.epochs=60
# runtime.fused=false` (docs/benchmarks.md, "The structure round, part 2"). Compare the user seconds.
set -euo pipefail
old_commit=$1 repeats=$2; shift 2
here=$(cd "$(dirname "$0")/.." && pwd)
old=$(mktemp -d)
git -C "$here" worktree add -q --detach "$old" "$old_commit"
trap 'git -C "$here" worktree remove --force "$old"' EXIT
for i in $(seq 1 "$repeats"); do
  for side in old new; do
    root=$here; [ "$side" = old ] && root=$old
    run=$(mktemp -d)
    (cd "$root" && /usr/bin/time -f "$side $i %U %S %e" env PYTHONPATH="$root" OMP_NUM_THREADS=1 python -m liedfl_cli train \
      rollout.enabled=false eval.plots=false ui.progress=false train.val_every=1000 \
      "paths.data_dir=$here/outputs/data" "hydra.run.dir=$run" "$@" > /dev/null 2> "$run.err" || cat "$run.err")
    tail -1 "$run.err"; rm -rf "$run" "$run.err"
  done
done
