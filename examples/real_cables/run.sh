#!/usr/bin/env bash
# The real-cable results: import each DEFORM cable, train every model with 3 seeds on its
# train split, score on its eval split by the published protocol. Usage:
#   DEFORM=/path/to/DEFORM/data_set examples/real_cables/run.sh [runs/real]
# Two jobs at a time, one torch thread each (a 2-core machine); about an hour there.
# The runs stay in RUNS (outside the repository); report.py writes what results.md quotes:
#   MODELS="in-bilstm mlp attention mlp-long" examples/real_cables/run.sh runs/real
#   MODELS=mlp-long-all CABLES=DLO1 examples/real_cables/run.sh runs/real
#   MODELS=mlp-long-all-x2 CABLES=DLO1 SEEDS="0 2 4" examples/real_cables/run.sh runs/real
#   MODELS=mlp-long-x2 CABLES="DLO2 DLO3 DLO4" SEEDS="0 2" examples/real_cables/run.sh runs/real
#   python examples/real_cables/report.py runs/real
# The validation runs behind the recipes: validation.py (validation.json).
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
RUNS=${1:-runs/real}
HERE=$(dirname "$0")
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
CABLES=${CABLES:-DLO1 DLO2 DLO3 DLO4}
MODELS=${MODELS:-in-bilstm mlp}
SEEDS=${SEEDS:-0 1 2}
for c in $CABLES; do
  [ -f "$RUNS/$c/data/dataset.h5" ] || dlo import --source "$DEFORM/$c" --out "$RUNS/$c/data" --json > /dev/null
done
job() {  # cable model seed
  local run="$RUNS/$1/$2-s$3"
  [ -f "$run-eval/summary.json" ] && return 0
  dlo train --spec "$HERE/$2.yaml" --data "$RUNS/$1/data" --seed "$3" --out "$run" --overwrite --json > /dev/null || return 1
  dlo eval --checkpoint "$run" --data "$RUNS/$1/data" --out "$run-eval" --plot "$run-eval/horizon.png" --overwrite --json > /dev/null || return 1
  echo "$1 $2 seed $3: $(python -c "import json;print(json.load(open('$run-eval/summary.json'))['model_score_cm'])") cm"
}
export -f job; export RUNS HERE
for m in $MODELS; do for c in $CABLES; do for s in $SEEDS; do echo "$c $m $s"; done; done; done \
  | xargs -P "${JOBS:-2}" -L 1 bash -c 'job "$0" "$1" "$2"'
