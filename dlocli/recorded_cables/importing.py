"""`dlo import`: recorded trajectories into a marker dataset, with the references' scores."""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, protocol, save_dataset_run
from dlocli.errors import BadInput
from dlocli.events import Callback, ignore
from dlocli.recorded_cables import deform, formats, rosbag, timing
from dlocli.recorded_cables.spec import UNITS, ImportSpec
from dlocli.rundir import refuse_out_by_source

#: plausible length (m) of a recorded cable along its markers; outside it, a unit error
CABLE_LENGTH_M = (0.02, 10.0)


def run_import(
    spec: ImportSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Read ``spec.source`` (refusing anything but plain data), write OUT/dataset.h5,
    OUT/spec.json and OUT/summary.json; return the summary.

    ``progress`` gets a Began of the recording files (unit "recording"), then an Event as
    each is read (``values``: its ``split`` and ``file``). ``cancel`` stops it before each
    file and before writing: nothing is written (an earlier run's files there are left as
    they were)."""
    progress, cancel = progress or ignore, cancel or CancelToken()
    if spec.source is None:
        raise BadInput("no recordings given; pass --source FOLDER (holding train/ and eval/)")
    refuse_out_by_source(spec)
    # everything is checked before --out is touched
    budget = spec.max_memory_mib * 2**20
    bags = rosbag.reader(spec.topic)
    read = formats.read_folder(spec.source, budget, spec.fill_gaps, bags, progress, cancel)
    kept = sum(deform.KEPT_PER_BYTE * t.positions.nbytes for items in read.values() for t in items)
    timed, rate_hz, timing_report = timing.to_control_rate(read, spec, budget - kept)
    trajectories = in_metres(timed, spec)
    held = formats.held_mask(trajectories["train"][0][1].shape[1], spec.held)
    dataset = MarkerDataset.from_trajectories(
        trajectories, held, {"rate_hz": rate_hz, "source": str(spec.source)}
    )
    summary = {**describe(dataset), **timing_report}
    gaps = {f"{s}/{t.name}": t.gaps for s, items in read.items() for t in items if t.gaps}
    if gaps:
        summary["gaps_filled"] = gaps
    cancel.raise_if_cancelled()  # the last file read, before anything is written
    return save_dataset_run(spec, dataset, summary, overwrite)


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


def in_metres(
    trajectories: dict[str, list[tuple[str, np.ndarray]]], spec: ImportSpec
) -> dict[str, list[tuple[str, np.ndarray]]]:
    """The recordings scaled from ``spec.units`` to metres; BadInput naming the first whose
    cable is not of a plausible length (frame 0, along its markers) in metres."""
    low, high = CABLE_LENGTH_M
    scaled = {
        s: [(n, a * UNITS[spec.units]) for n, a in items] for s, items in trajectories.items()
    }
    for split, items in scaled.items():
        for name, array in items:
            length = float(np.linalg.norm(np.diff(array[0], axis=0), axis=-1).sum())
            if not low <= length <= high:
                raise BadInput(
                    f"{spec.source}/{split}/{name}: the cable is {length:.4g} m long along "
                    f"its markers (read in {spec.units}), not {low:g}-{high:g} m; pass --units "
                    "with the recording's unit (m, cm or mm)"
                )
    return scaled
