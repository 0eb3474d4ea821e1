#!/usr/bin/env bash
# Calibrate the simulated rod to each DEFORM cable (MuJoCo; PyBullet on DLO3) and keep the
# small reports here. Usage:
#   DEFORM=/path/to/DEFORM/data_set examples/calibration/run.sh [runs/calibration]
# One cable at a time, two replay workers each (a 2-core machine): 5-10 minutes per cable.
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
RUNS=${1:-runs/calibration}
HERE=$(dirname "$0")
CABLES=${CABLES:-DLO1 DLO2 DLO3 DLO4}
BACKENDS=${BACKENDS:-mujoco}
for b in $BACKENDS; do
  for c in $CABLES; do
    run="$RUNS/$c-$b"
    [ -f "$run/report.json" ] || dlo calibrate --spec "$HERE/$c.yaml" --source "$DEFORM/$c" \
      --backend "$b" --workers 2 --out "$run" --overwrite --json > /dev/null
    mkdir -p "$HERE/results/$c-$b"
    cp "$run/report.json" "$run/report.md" "$run/calibrated.yaml" "$HERE/results/$c-$b/"
    python -c "import json;r=json.load(open('$run/report.json'));print('$c $b', r['eval_default_cm'], '->', r['eval_calibrated_cm'], 'cm in', r['fit_seconds'], 's')"
  done
done
