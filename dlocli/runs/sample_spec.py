"""`dlo sample`'s spec (torch- and simulator-free: the CLI builds its --help from it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import Field, model_validator

from dlocli.limits import MAX_COUNT
from dlocli.specs import EnvSpec, TaskSpec

#: what `dlo sample` makes: a recorded cable (for `dlo import`), a camera's clouds (`dlo track`)
KINDS = ("cable", "clouds")
#: frames per second of each kind by default: DEFORM's motion capture, the depth camera's
DEFAULT_RATE_HZ = {"cable": 100.0, "clouds": 25.0}


#: the task a sample runs unless its spec names another: both grippers, a goal per recording
BOTH_GRIPPERS = {"name": "bimanual", "goal": "random"}


def _bimanual() -> TaskSpec:
    return TaskSpec(**BOTH_GRIPPERS)


class SampleSpec(EnvSpec):
    """`dlo sample`: a simulated recording in the form real data comes in, from the rod and
    task of the spec (both grippers moving): a recorded cable or a depth camera's clouds."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "out", "train", "eval", "seconds", "rate_hz", "format", "units", "noise_mm",
        "task.observation.markers", "task.observation.gripper_markers",
        "task.observation.marker_arc_lengths", "backend.name", "seed",
    )  # fmt: skip

    kind: Literal["cable", "clouds"] = Field(
        "cable",
        description="'cable': marker recordings in DEFORM's layout, for `dlo import` and `dlo "
        "calibrate`; 'clouds': a depth camera's point clouds (.npz frame sequences) for `dlo "
        "track`.",
    )
    train: int = Field(8, ge=1, le=MAX_COUNT, description="Recordings in train/.")
    eval: int = Field(2, ge=0, le=MAX_COUNT, description="Recordings in eval/.")
    seconds: float = Field(
        3.0, gt=0.0, le=600.0, description="Length of each recording (s)."
    )  # fmt: skip
    rate_hz: float | None = Field(
        None, ge=1.0, le=1000.0,
        description="Frames per second, the rate the rod is controlled at; unless given, 100 "
        "for a cable (DEFORM's motion capture) and the camera's 25 for clouds.",
    )  # fmt: skip
    format: Literal["pkl", "csv"] = Field(
        "pkl",
        description="A cable's files: 'pkl', DEFORM's pickled (frames, 3, markers) lists; "
        "'csv', motion capture with a time column (header frame,time,m0_x,m0_y,m0_z,...).",
    )
    units: Literal["m", "cm", "mm"] = Field("m", description="A cable's coordinate unit.")
    noise_mm: float = Field(
        0.5, ge=0.0, le=100.0,
        description="A cable's motion-capture noise (standard deviation per coordinate, mm); "
        "clouds have their camera's (task.observation.camera).",
    )  # fmt: skip
    out: Path = Field(
        Path("samples/cable"),
        description="Folder of the recordings (for clouds, samples/clouds unless given).",
    )
    task: TaskSpec = Field(
        default_factory=_bimanual,
        description="Task: both grippers move each recording's start towards its goal; the "
        "markers are task.observation's, the camera its camera.",
    )

    @model_validator(mode="before")
    @classmethod
    def _both_grippers(cls, data: Any) -> Any:
        """A task given in part (a calibrated.yaml's) keeps both grippers moving; the folder
        is named after the kind unless given."""
        if not isinstance(data, dict):
            return data
        if isinstance(data.get("task"), dict):
            data = {**data, "task": {**BOTH_GRIPPERS, **data["task"]}}
        if data.get("out") is None and data.get("kind") in KINDS:
            data = {**data, "out": Path("samples") / data["kind"]}
        return data
