#!/usr/bin/env bash
# Issue 17's acceptance figures on MuJoCo chains never used while developing (docs/results.md,
# "Articulated bodies"): generate each chain, train the articulated model and the paper's per-body model
# for 400 epochs with everything else at its default, roll out 50 steps, and print the eval rows
# (one-step and 50-step errors against constant velocity, Newton failures).
#   bash scripts/articulated_chains.sh [OUT_DIR]      (about 10 minutes per chain on 2 cores)
set -euo pipefail
out=${1:-outputs/articulated_chains}
mkdir -p "$out"
chain() {  # name, generator options...
  local name=$1; shift
  python scripts/mujoco_chain.py --out "$out/$name.h5" "$@"
  for kinetic in articulated per_body; do
    liedfl train dataset=file dataset.path="$out/$name.h5" model.kinetic=$kinetic train.epochs=400 \
      rollout.steps=50 ui.progress=false runtime.threads=1 hydra.run.dir="$out/${name}_$kinetic"
    python - "$out/${name}_$kinetic/eval.csv" <<'PY'
import csv, sys
for r in csv.DictReader(open(sys.argv[1])):
    print(f"{sys.argv[1]}: {r['model']:18s} one-step/CV {float(r['one_step_vs_cv']):.4f}  "
          f"50-step/CV {float(r['rollout_vs_cv']):.4f}  Newton failures {r['newton_failures'] or '-'}")
PY
  done
}
chain c5world --links 5 --rotations world --seed 2026
chain c3parent_grav --links 3 --rotations parent --seed 4242 --gravity 9.81
