#!/usr/bin/env bash
# Speed before and after a change, in one session: `scripts/bench.py --quick --no-compile` of an old checkout and
# of this tree alternately (old, new, old, new), one process and one thread each.
#   bash scripts/bench_before_after.sh <old commit> <out dir>     (writes <out>/{old,new}_{1,2}.json and .log)
# docs/benchmarks.md "The structure round (issue 35)" was measured this way with <old commit> = 46b1b77.
set -euo pipefail
old_commit=$1 out=$2
here=$(cd "$(dirname "$0")/.." && pwd)
old=$(mktemp -d)
git -C "$here" worktree add -q --detach "$old" "$old_commit"
trap 'git -C "$here" worktree remove --force "$old"' EXIT
mkdir -p "$out"
for i in 1 2; do
  for side in old new; do
    root=$here; [ "$side" = old ] && root=$old
    (cd "$root" && PYTHONPATH=$root OMP_NUM_THREADS=1 python scripts/bench.py --quick --no-compile \
      --data-dir "$here/outputs/data" --json "$out/${side}_$i.json" > "$out/${side}_$i.log" 2>&1)
  done
done
