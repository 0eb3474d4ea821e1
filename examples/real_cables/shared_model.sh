#!/usr/bin/env bash
# One model for all four DEFORM cables, with `dlo` alone: train it on all four at once
# (`dlo train --data A --data B ...`), score it on each cable's eval split (`dlo eval`), then
# fine-tune a copy per cable (`dlo train --init-from`) and score that. Results:
# OUT/shared/{train,eval-CABLE}, OUT/CABLE/{train,eval}; gathered into
# examples/real_cables/shared_model.json (one entry per spec, fine-tuning spec and seed).
#   DEFORM=/path/to/DEFORM/data_set examples/real_cables/shared_model.sh [OUT] [SPEC] [FINE] [SEED]
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
HERE=$(dirname "$0")
OUT=${1:-runs/shared_model}
SPEC=${2:-$HERE/arc-mlp-long.yaml}
FINE=${3:-$HERE/fine_tune_long.yaml}
SEED=${4:-0}
data=()
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/data/$c/dataset.h5" ] || dlo import --source "$DEFORM/$c" --out "$OUT/data/$c" --json > /dev/null
  data+=(--data "$OUT/data/$c")
done
[ -f "$OUT/shared/train/summary.json" ] || dlo train --spec "$SPEC" "${data[@]}" --seed "$SEED" \
  --out "$OUT/shared/train" --overwrite --json > /dev/null
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/shared/eval-$c/summary.json" ] || dlo eval --checkpoint "$OUT/shared/train" \
    --data "$OUT/data/$c" --out "$OUT/shared/eval-$c" --overwrite --json > /dev/null
  [ -f "$OUT/$c/train/summary.json" ] || dlo train --spec "$FINE" --init-from "$OUT/shared/train" \
    --data "$OUT/data/$c" --seed "$SEED" --out "$OUT/$c/train" --overwrite --json > /dev/null
  [ -f "$OUT/$c/eval/summary.json" ] || dlo eval --checkpoint "$OUT/$c/train" \
    --data "$OUT/data/$c" --out "$OUT/$c/eval" --overwrite --json > /dev/null
done
python "$HERE/shared_model_entry.py" "$OUT" "$SPEC" "$FINE" "$SEED"
