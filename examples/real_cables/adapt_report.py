"""Gather adapt_leave_one_out.sh's runs into examples/real_cables/adapt_leave_one_out.json: per
left-out cable, the eval score (cm) of freezing the cable, the model with the mean code, the
code picked from one recording, and that code or the whole model fine-tuned on it.

    python examples/real_cables/adapt_report.py OUT SPEC SEED
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

TARGET = Path(__file__).resolve().parent / "adapt_leave_one_out.json"


def read(path: Path) -> dict:
    return json.loads(path.read_text())


def cable_row(run: Path) -> dict:
    mean = read(run / "mean-eval.json")
    picked, code, whole = (read(run / f"{how}.json") for how in ("pick", "code", "all"))
    return {
        "freeze_cm": mean["freeze_score_cm"],
        "mean_code_cm": mean["model_score_cm"],
        "picked_cm": read(run / "pick-eval.json")["model_score_cm"],
        "picked": picked["picked"],
        "pick_seconds": picked["pick_seconds"],
        "code_tuned_cm": read(run / "code-eval.json")["model_score_cm"],
        "code_tune_seconds": code["fit_seconds"],
        "all_tuned_cm": read(run / "all-eval.json")["model_score_cm"],
        "all_tune_seconds": whole["fit_seconds"],
        "recordings": picked["recordings"],
        "update_steps": whole["update_steps"],
    }


def main(out: Path, spec: str, seed: int) -> None:
    cables = sorted(p.name for p in out.iterdir() if (p / "all-eval.json").is_file())
    rows = {cable: cable_row(out / cable) for cable in cables}
    TARGET.write_text(json.dumps({"spec": spec, "seed": seed, "cables": rows}, indent=1) + "\n")
    for cable, row in rows.items():
        print(cable, row)


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]))
