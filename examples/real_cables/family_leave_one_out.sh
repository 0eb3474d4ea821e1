#!/usr/bin/env bash
# A new cable from one recording, with simulated cables in training: each DEFORM cable left out,
# a coded model is trained on the other three, once alone and once beside a family of simulated
# cables (`dlo family`: materials drawn over the other three's calibrated flex rods, widened 2x
# each way, driven by the first other cable's recorded motion); then `dlo adapt` from the
# left-out cable's first train recording picks a code (no gradient) or fits the code alone
# (--fine-tune code, 200 steps), and `dlo eval` scores each, and the mean code, on its eval
# split. Results: OUT/CABLE-{with,without}/..., gathered by family_report.py into
# examples/real_cables/family_leave_one_out.json.
# STEPS (optional) overrides the spec's update_steps; the report is then family_leave_one_out_STEPS.json.
# SOURCES: "first" (default) drives the family by the first other cable's motion; "all" by each
# other cable's in turn (--source per cable, each rod as long as its calibration took it); the
# report is then family_leave_one_out[_STEPS]_all.json.
#   DEFORM=/path/to/DEFORM/data_set examples/real_cables/family_leave_one_out.sh [OUT] [SPEC] [SEED] [CABLES] [STEPS] [SOURCES]
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
OUT=${1:-runs/family_leave_one_out}
SPEC=${2:-examples/real_cables/arc-mlp-coded-small.yaml}
SEED=${3:-0}
CABLES=${4:-16}
STEPS=${5:-}
SOURCES=${6:-first}
steps=(); [ -z "$STEPS" ] || steps=(--update-steps "$STEPS")
RODS=examples/calibration/results
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/data/$c/dataset.h5" ] || dlo import --source "$DEFORM/$c" --out "$OUT/data/$c" --json > /dev/null
done
for held_out in DLO1 DLO2 DLO3 DLO4; do
  data=(); rods=(); source=""; every=(); lengths=""
  for c in DLO1 DLO2 DLO3 DLO4; do
    [ "$c" = "$held_out" ] && continue
    data+=(--data "$OUT/data/$c"); rods+=(--calibrated "$RODS/$c-mujoco-flex/calibrated.yaml")
    [ -n "$source" ] || source=$c
    every+=(--source "$DEFORM/$c")
    lengths+="${lengths:+,}$(python -c "import sys, yaml; print(yaml.safe_load(open(sys.argv[1]))['backend']['rod']['length'])" "$RODS/$c-mujoco-flex/calibrated.yaml")"
  done
  for family in without with; do
    run="$OUT/$held_out-$family"
    mkdir -p "$run"
    trained=("${data[@]}")
    if [ "$family" = with ]; then
      # the source's rod as its calibration took it (DLO1's is longer than its markers' mean)
      if [ "$SOURCES" = all ]; then
        sources=("${every[@]}" --rod-length "$lengths")
      else
        sources=(--source "$DEFORM/$source" $(sed -n 's/^rod_length: /--rod-length /p' "examples/calibration/$source.yaml"))
      fi
      [ -f "$run/family/summary.json" ] || dlo family "${rods[@]}" "${sources[@]}" \
        --cables "$CABLES" --train 8 --eval 2 --seed "$SEED" --out "$run/family" --overwrite --json > "$run/family.json"
      for d in "$run"/family/sim-*/dataset.h5; do trained+=(--data "$(dirname "$d")"); done
    fi
    [ -f "$run/model/summary.json" ] || dlo train --spec "$SPEC" "${trained[@]}" "${steps[@]}" --seed "$SEED" \
      --out "$run/model" --overwrite --json > "$run/train.json"
    dlo eval --checkpoint "$run/model" --data "$OUT/data/$held_out" --json > "$run/mean-eval.json"
    for how in pick code; do
      tune=(); [ "$how" = pick ] || tune=(--fine-tune "$how")
      dlo adapt --checkpoint "$run/model" --data "$OUT/data/$held_out" "${tune[@]}" --out "$run/$how" --overwrite --json > "$run/$how.json"
      dlo eval --checkpoint "$run/$how" --data "$OUT/data/$held_out" --json > "$run/$how-eval.json"
    done
  done
done
python examples/real_cables/family_report.py "$OUT" "$SPEC" "$SEED" "$SOURCES" $STEPS
