"""One model trained on all four cables together, scored on each cable's eval split; then
the same model fine-tuned briefly on each cable and scored again.

    OMP_NUM_THREADS=1 python examples/real_cables/all_cables.py DEFORM_DIR [--seed S]
        [--spec attention.yaml] [--update-steps N] [--finetune-steps 300] [--finetune-lr 3e-4]

The model (``--spec``, default ``attention.yaml``) must not depend on the marker count
(DLO1 has 13 markers, the others 12). It is not told which cable it sees: the attention
model reads what identifies one (its neighbour distances and length along the markers, and
its motion). Each batch comes from one cable; validation is the held-out train trajectories
of all four. Fine-tuning starts from the shared weights and trains on one cable's train
split (k fixed at the recipe's longest, cosine decay from ``--finetune-lr``), keeping its
best validated weights. Writes all_cables.json beside this script (one entry per seed).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch
import yaml

from dlocli.models.fit import fit
from dlocli.models.marker_model import build_marker_model
from dlocli.models.marker_training import Cable, Cables, validation_score
from dlocli.models.spec import TrainSpec
from dlocli.models.splits import split_episodes
from dlocli.recorded_cables import deform

HERE = Path(__file__).parent
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")


def read_cables(source: Path, spec: TrainSpec) -> tuple[list[Cable], list[Cable], list[Cable]]:
    """Each cable's train, validation and eval trajectories, split as `dlo train` splits."""
    train, val, evals = [], [], []
    for name in CABLES:
        recorded = deform.read_folder(source / name)
        episodes = [a for _, a in recorded["train"]]
        held = deform.held_markers(episodes[0].shape[1])
        t, v = split_episodes(len(episodes), spec.val_fraction)
        train.append(Cable([episodes[i] for i in t], held))
        val.append(Cable([episodes[i] for i in v], held))
        evals.append(Cable([a for _, a in recorded["eval"]], held))
    return train, val, evals


def score(model: torch.nn.Module, cable: Cable) -> float:
    return round(validation_score(model, [cable]), 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="folder holding DLO1 ... DLO4")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--spec", type=Path, default=HERE / "attention.yaml")
    parser.add_argument("--update-steps", type=int, help="of the shared fit (default: the spec's)")
    parser.add_argument("--finetune-steps", type=int, default=300)
    parser.add_argument("--finetune-lr", type=float, default=3e-4)
    args = parser.parse_args()
    given = {**yaml.safe_load(args.spec.read_text()), "seed": args.seed}
    if args.update_steps:
        given["update_steps"] = args.update_steps
    spec = TrainSpec.model_validate(given)
    train, val, evals = read_cables(args.source, spec)
    torch.manual_seed(args.seed)
    shared = build_marker_model(spec.model, train[0].held.size, train[0].held)
    start = time.perf_counter()
    fit(shared, Cables(train, val), spec, progress=lambda r: print(r, flush=True))
    result = {
        "seed": args.seed,
        "model": spec.model.name,
        "update_steps": spec.update_steps,
        "rollout_steps": spec.rollout_steps,
        "train_seconds": round(time.perf_counter() - start, 1),
        "score_cm": {n: score(shared, c) for n, c in zip(CABLES, evals, strict=True)},
        "finetune_steps": args.finetune_steps,
        "finetune_lr": args.finetune_lr,
        "finetuned_score_cm": {},
        "finetune_seconds": {},
    }
    tune = spec.model_copy(update={"update_steps": args.finetune_steps, "lr": args.finetune_lr,
                                   "rollout_start": spec.rollout_steps})  # fmt: skip
    for name, t, v, e in zip(CABLES, train, val, evals, strict=True):
        model = copy.deepcopy(shared)
        start = time.perf_counter()
        fit(model, Cables([t], [v]), tune, progress=lambda r, n=name: print(n, r, flush=True))
        result["finetune_seconds"][name] = round(time.perf_counter() - start, 1)
        result["finetuned_score_cm"][name] = score(model, e)
    print(result)
    path = HERE / "all_cables.json"
    runs = json.loads(path.read_text()) if path.is_file() else []
    runs = [r for r in runs if (r["seed"], r.get("model")) != (args.seed, spec.model.name)]
    runs.append(result)
    path.write_text(json.dumps(sorted(runs, key=lambda r: (r.get("model", ""), r["seed"])),
                               indent=1) + "\n")  # fmt: skip


if __name__ == "__main__":
    main()
