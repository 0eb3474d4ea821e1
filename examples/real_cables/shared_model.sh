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
python - "$OUT" "$SPEC" "$FINE" "$SEED" <<'PY'
import json, sys
from pathlib import Path
out, spec, fine, seed = Path(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
def read(path):
    return json.loads(path.read_text())
cables = ("DLO1", "DLO2", "DLO3", "DLO4")
entry = {"spec": spec, "fine_tune": fine, "seed": seed,
         "train_seconds": read(out / "shared/train/summary.json")["seconds"],
         "score_cm": {c: read(out / f"shared/eval-{c}/summary.json")["model_score_cm"] for c in cables},
         "finetuned_score_cm": {c: read(out / c / "eval/summary.json")["model_score_cm"] for c in cables},
         "finetune_seconds": {c: read(out / c / "train/summary.json")["seconds"] for c in cables}}
target = Path("examples/real_cables/shared_model.json")
saved = json.loads(target.read_text()) if target.is_file() else []
saved = [e for e in saved if (e["spec"], e["fine_tune"], e["seed"]) != (spec, fine, seed)]
target.write_text(json.dumps(saved + [entry], indent=1) + "\n")
print(json.dumps(entry, indent=1))
PY
