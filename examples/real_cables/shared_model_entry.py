"""One entry of examples/real_cables/shared_model.json from a shared_model.sh (or
joined_model.sh) output folder: the shared model's scores, its fine-tuned scores per
cable, and their seconds. An entry with the same spec, fine-tuning recipe, seed and way of
training (one run, or members joined) is replaced.

    python examples/real_cables/shared_model_entry.py OUT SPEC FINE SEED [--joined]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
TARGET = Path("examples/real_cables/shared_model.json")


def read(path: Path) -> dict:
    return json.loads(path.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("spec")
    parser.add_argument("fine")
    parser.add_argument("seed", type=int)
    parser.add_argument("--joined", action="store_true", help="members trained apart, joined")
    args = parser.parse_args()
    out = args.out
    entry = {"spec": args.spec, "fine_tune": args.fine, "seed": args.seed,
             **({"joined": True} if args.joined else {}),
             "train_seconds": read(out / "shared/train/summary.json")["seconds"],
             "score_cm": {c: read(out / f"shared/eval-{c}/summary.json")["model_score_cm"]
                          for c in CABLES},
             "finetuned_score_cm": {c: read(out / c / "eval/summary.json")["model_score_cm"]
                                    for c in CABLES},
             "finetune_seconds": {c: read(out / c / "train/summary.json")["seconds"]
                                  for c in CABLES}}  # fmt: skip
    saved = json.loads(TARGET.read_text()) if TARGET.is_file() else []
    key = (args.spec, args.fine, args.seed, args.joined)
    saved = [
        e for e in saved if (e["spec"], e["fine_tune"], e["seed"], e.get("joined", False)) != key
    ]
    TARGET.write_text(json.dumps(saved + [entry], indent=1) + "\n")
    print(json.dumps(entry, indent=1))


if __name__ == "__main__":
    main()
