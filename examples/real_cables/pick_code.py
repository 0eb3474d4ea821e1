"""A cable the coded model never saw, given the code it picks instead of the mean code.

    python examples/real_cables/pick_code.py [runs/leave_one_out] [--recordings 1 2 4 56]

For each leave-one-out fold of a coded model (leave_one_out.sh with arc-mlp-long-coded.yaml:
OUT/<cable>/train, OUT/data/<cable>), every candidate code (each training cable's and their
mean) is scored on the left-out cable's first n train recordings, with no gradient step,
and the one that predicts them best is used on its eval split. Also scores every candidate
on the eval split, to show what the pick missed. Writes pick_code.json beside this script.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from dlocli.data import load_dataset
from dlocli.io import write_json_atomic
from dlocli.models.checkpoints import load_marker_model
from dlocli.models.marker_training import Cable, scores_cm

HERE = Path(__file__).parent
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
MEAN_CODE = "mean code"


def candidates(run: Path, model) -> dict[str, str | None]:
    """Candidate name -> the key that picks its code (None: the mean code)."""
    trained = json.loads((run / "summary.json").read_text())["cables"]
    names = [Path(cable["data"]).name for cable in trained]  # in the order of the model's keys
    codes = {f"{n}'s code": k for n, k in zip(names, model.cable_keys, strict=True)}
    return {MEAN_CODE: None, **codes}


def episode_scores(model, episodes, held, key: str | None) -> list[float]:
    """Each episode's score with the code of the training cable ``key``; None: the left-out
    cable's own key, which the model has no code for, so the mean code."""
    return scores_cm(model, Cable(episodes, held, key))


def fold(out: Path, cable: str, counts: list[int]) -> dict:
    """The candidates' eval scores, and per count of train recordings the pick and its score."""
    run = out / cable / "train"
    model = load_marker_model(run)
    data = load_dataset(out / "data" / cable)
    train, evaluation = data.episodes("train"), data.episodes("eval")
    codes = candidates(run, model)
    on_eval = {name: float(np.mean(episode_scores(model, evaluation, data.held, key)))
               for name, key in codes.items()}  # fmt: skip
    on_train = {name: episode_scores(model, train, data.held, key) for name, key in codes.items()}
    picks = {}
    for n in sorted({min(n, len(train)) for n in counts}):  # the first n of each, scored once
        fitted = {name: float(np.mean(scores[:n])) for name, scores in on_train.items()}
        picked = min(fitted, key=fitted.get)
        picks[str(n)] = {"picked": picked, "eval_cm": on_eval[picked], "train_cm": fitted}
    return {"eval_cm": on_eval, "picks": picks}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, nargs="?", default=Path("runs/leave_one_out"))
    parser.add_argument("--recordings", type=int, nargs="+", default=[1, 2, 4, 56])
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = {c: fold(args.out, c, args.recordings) for c in CABLES
            if (args.out / c / "train" / "summary.json").is_file()}  # fmt: skip
    write_json_atomic(HERE / "pick_code.json", rows)
    for cable, row in rows.items():
        picks = {n: f"{p['picked']} {p['eval_cm']:.2f}" for n, p in row["picks"].items()}
        print(cable, picks)


if __name__ == "__main__":
    main()
