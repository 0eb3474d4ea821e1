"""`dlo track`: recorded point clouds (``.npz`` frame sequences, ROS 2 bags of PointCloud2)
into a marker dataset.

Each file or bag is one episode; the tracker follows the cable through its frames, ordered from
the grippers where the file records the held markers' positions, and the tracked markers
are saved as `dlo import` saves recorded ones, for `dlo train` and `dlo eval`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, save_dataset_run
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.rundir import refuse_out_by_source
from dlocli.tracking.bags import is_bag, read_cloud_bag
from dlocli.tracking.frames import FrameSequence, load_frames
from dlocli.tracking.spec import TrackSpec
from dlocli.tracking.tracker import CableTracker

SPLITS = ("train", "eval")
RATE_TOLERANCE = 0.05  # the files' frame rates may differ by this share
BAG_BUDGET = 2**30  # bytes one bag's clouds may take


def recorded_markers(spec: TrackSpec) -> tuple[np.ndarray, np.ndarray]:
    """(M,) arc lengths (m) of the markers to track and (M,) which of them the grippers hold:
    the cable's two ends, and the markers on the grippers."""
    arc = np.linspace(0.0, spec.length, spec.markers)
    if spec.gripper_markers > 0:
        behind = spec.gripper_markers * spec.length
        arc = np.concatenate([[-behind], arc, [spec.length + behind]])
    return arc, (arc <= 0.0) | (arc >= spec.length)


def episode_files(source: Path) -> dict[str, list[Path]]:
    """The episodes (``.npz`` files, bag folders) of each split: train/ and eval/, or the
    folder's own (train)."""
    if not source.is_dir():
        raise BadInput(f"--source {source} is not a folder; pass the folder of recorded clouds")
    split = {name: _episodes(source / name) for name in SPLITS}
    if not any(split.values()):
        split = {"train": _episodes(source), "eval": []}
    if not split["train"]:
        raise BadInput(
            f"--source {source} holds no .npz frame sequences or ROS 2 bag folders (in train/ "
            "or the folder itself)"
        )
    return split


def _episodes(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix == ".npz" or is_bag(p))


def read_episode(spec: TrackSpec, path: Path) -> FrameSequence:
    if not is_bag(path):
        return load_frames(path)
    if spec.camera_position is None:
        raise BadInput(
            f"{path} is a ROS 2 bag: pass --camera-position X,Y,Z (m, world frame), where the "
            "camera saw the clouds from"
        )
    return read_cloud_bag(path, spec.topic, np.array(spec.camera_position), BAG_BUDGET)


def track_file(
    spec: TrackSpec,
    path: Path,
    arc: np.ndarray,
    held: np.ndarray,
    cancel: CancelToken | None = None,
) -> dict:
    """One episode's tracked markers (F, M, 3), visibility and timing; ``cancel`` stops it
    before the file is read and between frames."""
    if cancel is not None:
        cancel.raise_if_cancelled()
    sequence = read_episode(spec, path)
    robot = _held_positions(sequence, path, spec, int(held.sum()))
    if len(sequence.frames) < 2:
        raise BadInput(f"{path} holds {len(sequence.frames)} frame; an episode needs at least 2")
    tracker = CableTracker(arc, held, spec.length, spec.radius, spec.tracker)
    markers, visible = [], []
    start = time.perf_counter()
    for i, frame in enumerate(sequence.frames):
        if cancel is not None:
            cancel.raise_if_cancelled()
        given = None if robot is None else robot[i]
        report = (tracker.start if i == 0 else tracker.step)(frame, given)
        markers.append(report.markers)
        visible.append(report.visible)
    times = np.array([frame.time for frame in sequence.frames])
    return {
        "markers": np.stack(markers),
        "visible": float(np.mean(visible)),
        "points": float(np.mean([len(frame.points) for frame in sequence.frames])),
        "rate_hz": 1.0 / float(np.median(np.diff(times))),
        "seconds": time.perf_counter() - start,
    }


def _held_positions(
    sequence: FrameSequence, path: Path, spec: TrackSpec, count: int
) -> np.ndarray | None:
    if sequence.held is None:
        if spec.gripper_markers > 0:
            raise BadInput(
                f"{path} records no held positions, which place the gripper markers; record "
                "them (held) or pass --gripper-markers 0"
            )
        return None
    if sequence.held.shape[1] != count:
        raise BadInput(
            f"{path}: held records {sequence.held.shape[1]} markers per frame, the tracked "
            f"markers have {count} held ones (the cable's ends and the grippers' markers)"
        )
    return sequence.held


def run_track(
    spec: TrackSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Track every file of ``spec.source``; write OUT/dataset.h5, spec.json, summary.json.

    ``progress`` gets a Began of the episodes (unit "episode"), then an Event per tracked
    file (``values``: its ``episode`` name, ``split``, ``visible`` share and ``ms_per_frame``).
    ``cancel`` stops it between frames: the episodes tracked so far are saved as the dataset
    (its summary marked ``stopped``) before the stop is raised again."""
    if spec.source is None:
        raise BadInput("no recordings given; pass --source FOLDER of .npz frame sequences")
    refuse_out_by_source(spec)
    progress, cancel = progress or ignore, cancel or CancelToken()
    files = episode_files(Path(spec.source))
    arc, held = recorded_markers(spec)
    tracked: dict[str, list[tuple[str, dict]]] = {s: [] for s in SPLITS}
    total = sum(len(files[s]) for s in SPLITS)
    progress(Began("episode", 0, total))
    try:
        for split in SPLITS:
            for path in files[split]:
                run = track_file(spec, path, arc, held, cancel)
                tracked[split].append((path.stem, run))
                frames_ms = 1e3 * run["seconds"] / len(run["markers"])
                values = {"episode": path.stem, "split": split, "visible": run["visible"],
                          "ms_per_frame": frames_ms}  # fmt: skip
                progress(Event("episode", sum(map(len, tracked.values())), total, values))
    except KeyboardInterrupt as stop:  # the episodes tracked so far are kept
        if tracked["train"]:
            _save(spec, tracked, arc, held, overwrite, stopped=type(stop).__name__)
        raise
    return _save(spec, tracked, arc, held, overwrite)


def _save(
    spec: TrackSpec,
    tracked: dict[str, list[tuple[str, dict]]],
    arc: np.ndarray,
    held: np.ndarray,
    overwrite: bool,
    stopped: str | None = None,
) -> dict[str, Any]:
    """The tracked episodes as the run's dataset, and its summary (``stopped``: what ended
    the run before every file was tracked)."""
    runs = [run for items in tracked.values() for _, run in items]
    rates = np.array([run["rate_hz"] for run in runs])
    if rates.max() > rates.min() * (1 + RATE_TOLERANCE):
        raise BadInput(
            f"the recordings' frame rates differ ({rates.min():.4g} to {rates.max():.4g} Hz); "
            "track recordings of one rate together"
        )
    trajectories = {s: [(name, run["markers"]) for name, run in items]
                    for s, items in tracked.items() if items}  # fmt: skip
    attrs = {"rate_hz": float(np.median(rates)), "source": str(spec.source), "tracked": True}
    dataset = MarkerDataset.from_trajectories(trajectories, held, attrs)
    frames = sum(len(run["markers"]) for run in runs)
    summary: dict[str, Any] = {
        "markers": int(len(arc)),
        "held_markers": np.flatnonzero(held).tolist(),
        "train_episodes": len(tracked["train"]),
        "eval_episodes": len(tracked["eval"]),
        "frames": frames,
        "rate_hz": round(attrs["rate_hz"], 4),
        "points_per_frame": round(float(np.mean([run["points"] for run in runs])), 1),
        "visible_share": round(float(np.mean([run["visible"] for run in runs])), 4),
        "ms_per_frame": round(1e3 * sum(run["seconds"] for run in runs) / frames, 3),
    }
    if stopped is not None:
        summary["stopped"] = stopped
    return save_dataset_run(spec, dataset, summary, overwrite)
