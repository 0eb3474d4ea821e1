#!/usr/bin/env bash
# A new cable from one recording, on each DEFORM cable left out: train a coded model on the other
# three, then `dlo adapt` from the left-out cable's first train recording: the pick among the
# trained cables' codes and their mean (no gradient), then the code alone and the whole model
# fine-tuned (200 steps each); `dlo eval` scores each on the left-out cable's eval split.
# Results: OUT/CABLE/..., gathered by adapt_report.py into examples/real_cables/adapt_leave_one_out.json.
#   DEFORM=/path/to/DEFORM/data_set examples/real_cables/adapt_leave_one_out.sh [OUT] [SPEC] [SEED]
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
OUT=${1:-runs/adapt_leave_one_out}
SPEC=${2:-examples/real_cables/arc-mlp-coded-small.yaml}
SEED=${3:-0}
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/data/$c/dataset.h5" ] || dlo import --source "$DEFORM/$c" --out "$OUT/data/$c" --json > /dev/null
done
for held_out in DLO1 DLO2 DLO3 DLO4; do
  run="$OUT/$held_out"
  cable="$OUT/data/$held_out"
  data=()
  for c in DLO1 DLO2 DLO3 DLO4; do [ "$c" = "$held_out" ] || data+=(--data "$OUT/data/$c"); done
  [ -f "$run/model/summary.json" ] || dlo train --spec "$SPEC" "${data[@]}" --seed "$SEED" \
    --out "$run/model" --overwrite --json > /dev/null
  dlo eval --checkpoint "$run/model" --data "$cable" --json > "$run/mean-eval.json"
  for how in pick code all; do
    tune=(); [ "$how" = pick ] || tune=(--fine-tune "$how")
    dlo adapt --checkpoint "$run/model" --data "$cable" "${tune[@]}" --out "$run/$how" --overwrite --json > "$run/$how.json"
    dlo eval --checkpoint "$run/$how" --data "$cable" --json > "$run/$how-eval.json"
  done
done
python examples/real_cables/adapt_report.py "$OUT" "$SPEC" "$SEED"
