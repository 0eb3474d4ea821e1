#!/usr/bin/env bash
# Fine-tuning curve on a cable the model never saw: each leave-one-out model
# (leave_one_out.sh's OUT/CABLE/train) fine-tuned on the first 1, 2, 4 and all of the left-out
# cable's train recordings (FINE, default fine_tune.yaml; fine_tune_code.yaml learns the code
# alone of a model with cable codes), then scored on its eval split (`dlo eval`).
# Results: OUT/CABLE/fine-N/{train,eval}, gathered into examples/real_cables/NAME.json
# (NAME default fine_tune_curve).
#   DEFORM=/path/to/DEFORM/data_set [FINE=...] [NAME=...] examples/real_cables/fine_tune_curve.sh [OUT]
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
OUT=${1:-runs/leave_one_out}
HERE=$(dirname "$0")
CABLES=${CABLES:-DLO1 DLO2 DLO3 DLO4}
COUNTS=${COUNTS:-1 2 4 all}
FINE=${FINE:-$HERE/fine_tune.yaml}
NAME=${NAME:-fine_tune_curve}
for c in $CABLES; do
  [ -f "$OUT/$c/train/summary.json" ] || { echo "run leave_one_out.sh $OUT first ($c)" >&2; exit 2; }
  for n in $COUNTS; do
    data="$OUT/data/$c-first-$n" run="$OUT/$c/fine-$n"
    if [ ! -f "$data/dataset.h5" ]; then  # the first n train recordings, every eval one
      src=$(mktemp -d); mkdir "$src/train"; ln -s "$(realpath "$DEFORM/$c/eval")" "$src/eval"
      recordings=$(ls "$DEFORM/$c/train" | sort -n)
      [ "$n" = all ] || recordings=$(echo "$recordings" | head -n "$n")
      for f in $recordings; do ln -s "$(realpath "$DEFORM/$c/train/$f")" "$src/train/$f"; done
      dlo import --source "$src" --out "$data" --json > /dev/null
      rm -rf "$src"
    fi
    [ -f "$run/train/summary.json" ] || dlo train --spec "$FINE" \
      --init-from "$OUT/$c/train" --data "$data" --out "$run/train" --overwrite --json > /dev/null
    [ -f "$run/eval/summary.json" ] || dlo eval --checkpoint "$run/train" --data "$data" \
      --out "$run/eval" --overwrite --json > /dev/null
    echo "$c $n: $(python -c "import json;print(json.load(open('$run/eval/summary.json'))['model_score_cm'])") cm"
  done
done
python "$HERE/fine_tune_report.py" "$OUT" "$NAME"
