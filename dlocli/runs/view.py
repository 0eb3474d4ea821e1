"""`dlo view RUN`: open a run's 3D recording in the Rerun viewer.

RUN is a recording (.rrd), a run directory whose summary names one (`dlo control --record`),
or a run directory of saved episodes (`dlo collect`'s dataset.h5, `dlo online`'s trials),
whose recording is written first, once, as RUN/recording.rrd. Without a display (no
``DISPLAY`` or ``WAYLAND_DISPLAY`` on Linux) the viewer is not started: one line says where
the recording is and how to open it elsewhere.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from dlocli.data import Dataset, load_dataset
from dlocli.errors import BadInput
from dlocli.extras import require
from dlocli.rundir import owned
from dlocli.runs.recording import RunRecording

WRITTEN = "recording.rrd"
#: the bytes every Rerun recording (.rrd) starts with; the viewer would open anything else
#: and show nothing, so `dlo view` checks them first
RRD_MAGIC = b"RRF2"


def recording_of(run: Path) -> Path:
    """The recording of ``run`` (see the module docstring), written if it must be."""
    run = Path(run)
    if run.is_file():
        if run.suffix != ".rrd":
            raise BadInput(f"{run} is neither a recording (.rrd) nor a run directory")
        return run
    if not run.is_dir():
        raise BadInput(f"{run} does not exist; pass a run directory or a .rrd recording")
    named = _named_recording(run)
    if named is not None:
        return named
    saved = _saved_datasets(run)
    if not saved:
        raise BadInput(
            f"{run} has no recording and no saved episodes; run `dlo control` again with "
            "--record RUN.rrd"
        )
    path = run / WRITTEN
    if not path.is_file():
        with owned(run):
            write_from_datasets(path, saved, run.name)
    return path


def _named_recording(run: Path) -> Path | None:
    summary = run / "summary.json"
    if not summary.is_file():
        return None
    try:
        named = json.loads(summary.read_text(encoding="utf-8")).get("recording")
    except (ValueError, OSError, AttributeError):
        return None
    if not isinstance(named, str):
        return None
    for candidate in (Path(named), run / Path(named).name):  # as given, or moved with the run
        if candidate.is_file():
            return candidate
    raise BadInput(f"{run}'s recording {named} is gone; run it again with --record")


def _saved_datasets(run: Path) -> list[Path]:
    """A collect run's dataset, or an online run's trials in order."""
    if (run / "dataset.h5").is_file():
        return [run / "dataset.h5"]
    return sorted((run / "data").glob("iter_*/trial_*.h5"))


def write_from_datasets(path: Path, datasets: list[Path], name: str) -> None:
    """A recording of every episode of ``datasets``, one after the other on the timeline."""
    loaded = [load_dataset(dataset_path) for dataset_path in datasets]
    for dataset, dataset_path in zip(loaded, datasets, strict=True):
        if not isinstance(dataset, Dataset):
            raise BadInput(f"{dataset_path} holds recorded markers, not simulated episodes")
    recording = RunRecording(path, name)
    try:
        step = 0
        for dataset in loaded:
            for e in range(dataset.n_episodes):
                step = recording.add_episode(dataset.episode(e), step)
    finally:
        recording.close()


def refuse_unless_recording(path: Path) -> None:
    """BadInput unless ``path`` starts as a Rerun recording does."""
    with open(path, "rb") as f:
        start = f.read(len(RRD_MAGIC))
    if start != RRD_MAGIC:
        what = "is empty" if not start else "is not a Rerun recording (it does not start with RRF2)"
        raise BadInput(
            f"{path} {what}; pass a recording written by `dlo control --record` or "
            "`dlo eval --record`, or the run directory that holds it"
        )


def has_display() -> bool:
    """Whether a viewer window can open here."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def view(run: Path) -> str:
    """Start the viewer on ``run``'s recording, or say where it is; the line to print."""
    require("view", "dlo view")
    path = recording_of(run)
    refuse_unless_recording(path)
    if not has_display():
        return (
            f"no display here: the recording is {path}; open it with `rerun {path}` where "
            f"there is one, or serve it to a browser with `rerun --web-viewer {path}`"
        )
    subprocess.Popen(
        [sys.executable, "-m", "rerun", str(path)], start_new_session=True,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    return f"opened {path} in the Rerun viewer"
