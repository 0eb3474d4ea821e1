#!/usr/bin/env bash
# The two-network coded ensemble (arc-mlp-long-coded-x2.yaml) from two shared_model.sh runs
# of arc-mlp-long-coded.yaml with seeds S and S+1 and the same fine-tuning recipe, without
# training again: their shared models join (join_members.py), as do their fine-tuned models
# per cable, and `dlo eval` scores each. Exactly what shared_model.sh OUT
# arc-mlp-long-coded-x2.yaml FINE S trains (each member is the network seed S+i gives alone).
# The entry in shared_model.json: spec arc-mlp-long-coded-x2.yaml, seed S, the slower
# member's seconds (both train at once, one per core).
#   examples/real_cables/joined_model.sh RUN_S RUN_S+1 OUT FINE S
set -euo pipefail
HERE=$(dirname "$0")
A=$1; B=$2; OUT=$3; FINE=$4; SEED=$5
[ -f "$OUT/shared/train/summary.json" ] || python "$HERE/join_members.py" "$OUT/shared/train" \
  "$A/shared/train" "$B/shared/train" > /dev/null
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/shared/eval-$c/summary.json" ] || dlo eval --checkpoint "$OUT/shared/train" \
    --data "$A/data/$c" --out "$OUT/shared/eval-$c" --overwrite --json > /dev/null
  [ -f "$OUT/$c/train/summary.json" ] || python "$HERE/join_members.py" "$OUT/$c/train" \
    "$A/$c/train" "$B/$c/train" > /dev/null
  [ -f "$OUT/$c/eval/summary.json" ] || dlo eval --checkpoint "$OUT/$c/train" \
    --data "$A/data/$c" --out "$OUT/$c/eval" --overwrite --json > /dev/null
done
python "$HERE/shared_model_entry.py" "$OUT" "$HERE/arc-mlp-long-coded-x2.yaml" "$FINE" "$SEED" --joined
