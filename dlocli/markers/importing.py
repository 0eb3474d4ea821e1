"""`dlo import`: recorded trajectories into a marker dataset, with the references' scores."""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.dataset_format import DATASET_FILE
from dlocli.errors import BadInput
from dlocli.markers import deform, protocol
from dlocli.markers.dataset import MarkerDataset
from dlocli.markers.spec import ImportSpec


def run_import(spec: ImportSpec, overwrite: bool = False) -> dict[str, Any]:
    """Read ``spec.source`` (refusing anything but plain data), write OUT/dataset.h5,
    OUT/spec.json and OUT/summary.json; return the summary."""
    from dlocli.io import prepare_run_dir, write_json_atomic
    from dlocli.rundir import owned

    if spec.source is None:
        raise BadInput("no recordings given; pass --source FOLDER (holding train/ and eval/)")
    trajectories = deform.read_folder(spec.source)  # everything is checked before --out is touched
    n_markers = trajectories["train"][0][1].shape[1]
    held = deform.held_markers(n_markers)
    dataset = MarkerDataset.from_trajectories(
        trajectories, held, {"rate_hz": spec.rate_hz, "source": str(spec.source)}
    )
    summary = describe(dataset)
    with owned(spec.out):
        out = prepare_run_dir(spec.out, overwrite)
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        dataset.save(out / DATASET_FILE)
        summary["out"] = str(out)
        write_json_atomic(out / "summary.json", summary)
    return summary


def describe(dataset: MarkerDataset) -> dict[str, Any]:
    """Counts, speed and the references' benchmark scores on the eval split (train if none)."""
    split = "eval" if (dataset.split == 1).any() else "train"
    episodes = dataset.episodes(split)
    speed = np.mean([np.linalg.norm(np.diff(e, axis=0), axis=-1).mean() for e in episodes])
    summary: dict[str, Any] = {
        "markers": dataset.n_markers,
        "held_markers": np.flatnonzero(dataset.held).tolist(),
        "train_episodes": int((dataset.split == 0).sum()),
        "eval_episodes": int((dataset.split == 1).sum()),
        "frames": int(dataset.n_transitions + dataset.n_episodes),
        "mean_marker_speed_m_s": round(float(speed * dataset.rate_hz), 3),
    }
    for name, reference in protocol.REFERENCES.items():
        scores = [protocol.deform_score_cm(reference(e, dataset.held), e) for e in episodes]
        summary[f"{split}_{name}_cm"] = round(float(np.mean(scores)), 4)
    return summary
