#!/usr/bin/env bash
# Zero-shot on a cable the model never saw: for each DEFORM cable, train one model on the
# other three (`dlo train --data A --data B --data C`), then score it on the left-out cable's
# eval split (`dlo eval`) without fine-tuning. Results: OUT/CABLE/{train,eval}/summary.json,
# gathered into examples/real_cables/leave_one_out.json.
#   DEFORM=/path/to/DEFORM/data_set examples/real_cables/leave_one_out.sh [OUT] [SPEC] [SEED]
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
OUT=${1:-runs/leave_one_out}
SPEC=${2:-examples/real_cables/attention.yaml}
SEED=${3:-0}
CABLES=${CABLES:-DLO1 DLO2 DLO3 DLO4}
for c in DLO1 DLO2 DLO3 DLO4; do
  [ -f "$OUT/data/$c/dataset.h5" ] || dlo import --source "$DEFORM/$c" --out "$OUT/data/$c" --json > /dev/null
done
for held_out in $CABLES; do
  run="$OUT/$held_out"
  data=()
  for c in DLO1 DLO2 DLO3 DLO4; do [ "$c" = "$held_out" ] || data+=(--data "$OUT/data/$c"); done
  [ -f "$run/train/summary.json" ] || dlo train --spec "$SPEC" "${data[@]}" --seed "$SEED" \
    --out "$run/train" --overwrite --json > /dev/null
  [ -f "$run/eval/summary.json" ] || dlo eval --checkpoint "$run/train" \
    --data "$OUT/data/$held_out" --out "$run/eval" --overwrite --json > /dev/null
done
python - "$OUT" "$SPEC" "$SEED" <<'PY'
import json, sys
from pathlib import Path
out, spec, seed = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
rows = {}
for run in sorted(p for p in out.iterdir() if (p / "eval" / "summary.json").is_file()):
    train = json.loads((run / "train" / "summary.json").read_text())
    scored = json.loads((run / "eval" / "summary.json").read_text())
    rows[run.name] = {"zero_shot_cm": scored["model_score_cm"],
                      "freeze_cm": scored["freeze_score_cm"],
                      "straight_line_cm": scored["straight_line_score_cm"],
                      "trained_on": [Path(c["data"]).name for c in train["cables"]],
                      "train_seconds": train["seconds"]}
target = Path("examples/real_cables/leave_one_out.json")
saved = json.loads(target.read_text()) if target.is_file() else []
saved = [r for r in saved if (r["spec"], r["seed"]) != (spec, seed)]
saved.append({"spec": spec, "seed": seed, "cables": rows})
target.write_text(json.dumps(saved, indent=1) + "\n")
print(json.dumps(rows, indent=1))
PY
