"""One model trained on all four cables together, scored on each cable's eval split.

    OMP_NUM_THREADS=1 python examples/real_cables/all_cables.py DEFORM_DIR [SEED]

The same recipe as in-bilstm.yaml (the IN + bi-LSTM does not depend on the marker count, so
DLO1's 13 markers and the others' 12 share one network); each batch comes from one cable.
The model is told nothing about which cable it sees: it must tell them apart from their
motion. Writes all_cables.json beside this script.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from dlocli.markers import deform
from dlocli.models.marker_training import Cable, fit_markers, scores_cm
from dlocli.models.markers import build_marker_model
from dlocli.models.spec import TrainSpec
from dlocli.models.splits import split_episodes

HERE = Path(__file__).parent
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")


def main() -> None:
    source, seed = Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 0
    spec = TrainSpec.model_validate(
        {**yaml.safe_load((HERE / "in-bilstm.yaml").read_text()), "seed": seed}
    )
    train, val, evals = [], [], {}
    for name in CABLES:
        recorded = deform.read_folder(source / name)
        episodes = [a for _, a in recorded["train"]]
        held = deform.held_markers(episodes[0].shape[1])
        t, v = split_episodes(len(episodes), spec.val_fraction)
        train.append(Cable([episodes[i] for i in t], held))
        val.append(Cable([episodes[i] for i in v], held))
        evals[name] = Cable([a for _, a in recorded["eval"]], held)
    torch.manual_seed(seed)
    model = build_marker_model(spec.model, train[0].held.size, train[0].held)
    start = time.perf_counter()
    fit_markers(model, train, val, spec, lambda r: print(r, flush=True))
    result = {
        "seed": seed,
        "update_steps": spec.update_steps,
        "train_seconds": round(time.perf_counter() - start, 1),
        "score_cm": {
            name: round(float(np.mean(scores_cm(model, cable))), 4) for name, cable in evals.items()
        },  # fmt: skip
    }
    print(result)
    path = HERE / "all_cables.json"
    runs = json.loads(path.read_text()) if path.is_file() else []
    runs = [r for r in runs if r["seed"] != seed] + [result]
    path.write_text(json.dumps(sorted(runs, key=lambda r: r["seed"]), indent=1) + "\n")


if __name__ == "__main__":
    main()
