"""The process that writes a run's Rerun recording (:mod:`dlocli.runs.recording`).

Started when a run's recording path is checked, it imports Rerun (about a second of CPU,
which the run would otherwise wait for) while the run builds its env and model and steps,
then reads the run's buffered steps from stdin as one ``.npz`` (no pickles) and writes them
to the path named there as columns, one call per entity. Empty stdin (a run refused later,
or one that stopped before its first step) writes nothing.

    python -m dlocli.runs.recording_writer < steps.npz
"""

from __future__ import annotations

import io
import os
import sys
import uuid
from typing import Any

import numpy as np

TIMELINE = "step"
APPLICATION = "dlocli"
#: RGB colours: the rod, the goal, the grippers, seen and hidden markers, the plan, boxes
ROD, GOAL, GRIPPERS = (70, 130, 230), (60, 200, 90), (240, 150, 40)
SEEN, HIDDEN, PLAN = (250, 220, 40), (150, 150, 150), (220, 60, 220)
CLOUD = (200, 90, 70)
WORKSPACE, ENVELOPE = (120, 120, 120), (230, 80, 60)
GRIPPER_HALF_SIZE = 0.01  # m
#: the envelope's limits in the order of the clip counts (dlocli.env.envelope.LIMITS)
LIMITS_KEY = "limits"


def write(payload: dict[str, np.ndarray], rr: Any) -> None:
    """Write ``payload`` (see :func:`dlocli.runs.recording.RunRecording.payload`)."""
    stream = rr.RecordingStream(APPLICATION, recording_id=uuid.uuid4())
    stream.save(str(payload["path"]))
    stream.send_recording_name(str(payload["name"]))
    stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    limits = [str(name) for name in payload[LIMITS_KEY]]
    for key in sorted(payload):
        if key.startswith("box:"):
            low, high = payload[key]
            color = WORKSPACE if key.endswith("workspace") else ENVELOPE
            stream.log(key[4:], rr.Boxes3D(mins=[low], sizes=[high - low], colors=[color],
                                           fill_mode="majorwireframe"), static=True)  # fmt: skip
        elif key.endswith("/steps"):
            entity = key[: -len("/steps")]
            stream.log(entity, _style(rr, entity, limits), static=True)
            lengths = payload[f"{entity}/lengths"]
            columns = _columns(rr, entity, payload[f"{entity}/rows"]).partition(lengths)
            steps = [rr.TimeColumn(TIMELINE, sequence=payload[key])]
            stream.send_columns(entity, indexes=steps, columns=columns)
    stream.flush()
    stream.disconnect()


def _columns(rr: Any, entity: str, rows: np.ndarray) -> Any:
    if entity.startswith(("metrics/", "envelope/")):
        return rr.Scalars.columns(scalars=rows)
    if entity == "world/grippers":  # ours are w x y z, Rerun's x y z w
        return rr.Boxes3D.columns(centers=rows[:, :3], quaternions=rows[:, [4, 5, 6, 3]])
    if entity.startswith(("world/markers/", "world/camera/")):
        return rr.Points3D.columns(positions=rows)
    return rr.LineStrips3D.columns(strips=list(rows))


def _style(rr: Any, entity: str, limits: list[str]) -> Any:
    """The colours, sizes and names of ``entity``'s every row."""
    if entity == "envelope/clipped":
        return rr.SeriesLines(names=limits)
    if entity.startswith("metrics/"):
        return rr.SeriesLines(names=[entity.split("/")[-1]])
    if entity == "world/grippers":
        return rr.Boxes3D.from_fields(half_sizes=[[GRIPPER_HALF_SIZE] * 3], colors=[GRIPPERS])
    if entity == "world/camera/cloud":
        return rr.Points3D.from_fields(colors=[CLOUD], radii=[0.002])
    if entity.startswith("world/markers/"):
        return rr.Points3D.from_fields(colors=[SEEN if entity.endswith("seen") else HIDDEN])
    if entity.startswith("world/plan/") or entity == "world/predicted":
        return rr.LineStrips3D.from_fields(colors=[PLAN], radii=[0.001])
    return rr.LineStrips3D.from_fields(colors=[GOAL if entity == "world/goal" else ROD])


def main() -> int:
    import rerun as rr  # first: the run is still going

    rr.Scalars.columns(scalars=np.zeros(1, np.float32))  # Rerun's own imports on first use
    data = sys.stdin.buffer.read()
    if not data:
        return 0
    with np.load(io.BytesIO(data), allow_pickle=False) as loaded:
        payload = {key: loaded[key] for key in loaded.files}
    write(payload, rr)
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # the file is closed; Rerun's exit hooks would only cost the run time
