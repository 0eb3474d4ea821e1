#!/usr/bin/env bash
# The coded ensembles (arc-mlp-long-coded-xN.yaml, N = 2 or 3) from N shared_model.sh runs of
# arc-mlp-long-coded.yaml with seeds S, S+1, ... and the same fine-tuning recipe, without
# training again: their shared models join (join_members.py), as do their fine-tuned models
# per cable, and `dlo eval` scores each. Exactly what shared_model.sh OUT
# arc-mlp-long-coded-xN.yaml FINE S trains (each member is the network seed S+i gives alone).
# The entry in shared_model.json: spec arc-mlp-long-coded-xN.yaml, seed S, marked joined, the
# slowest member's seconds as it was run.
#   examples/real_cables/joined_model.sh OUT FINE S RUN_S RUN_S+1 [RUN_S+2]
set -euo pipefail
HERE=$(dirname "$0")
OUT=$1; FINE=$2; SEED=$3; shift 3
RUNS=("$@")
SPEC="$HERE/arc-mlp-long-coded-x${#RUNS[@]}.yaml"
[ -f "$SPEC" ] || { echo "error: no recipe $SPEC for ${#RUNS[@]} runs; give 2 or 3" >&2; exit 2; }
[ -f "$OUT/shared/train/summary.json" ] || python "$HERE/join_members.py" "$OUT/shared/train" \
  "${RUNS[@]/%//shared/train}" > /dev/null  # each run's folder + /shared/train
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/shared/eval-$c/summary.json" ] || dlo eval --checkpoint "$OUT/shared/train" \
    --data "${RUNS[0]}/data/$c" --out "$OUT/shared/eval-$c" --overwrite --json > /dev/null
  [ -f "$OUT/$c/train/summary.json" ] || python "$HERE/join_members.py" "$OUT/$c/train" \
    "${RUNS[@]/%//$c/train}" > /dev/null
  [ -f "$OUT/$c/eval/summary.json" ] || dlo eval --checkpoint "$OUT/$c/train" \
    --data "${RUNS[0]}/data/$c" --out "$OUT/$c/eval" --overwrite --json > /dev/null
done
python "$HERE/shared_model_entry.py" "$OUT" "$SPEC" "$FINE" "$SEED" --joined
