"""The options of the tracking room: the camera and the tracker
(:mod:`dlocli.camera_spec`), and `dlo track`'s spec."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field

from dlocli.camera_spec import CameraSpec, TrackerSpec
from dlocli.spec_base import Spec

__all__ = ["CameraSpec", "TrackSpec", "TrackerSpec"]


class TrackSpec(Spec):
    """`dlo track`: recorded point-cloud frame sequences -> a marker dataset run directory."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "source", "topic", "camera_position", "markers", "gripper_markers", "length", "radius",
        "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("source",)

    source: Path | None = Field(
        None,
        description="Folder of recorded clouds, one episode per .npz frame sequence "
        "(dlocli.tracking.frames: points, counts, times, extrinsics, and held, the held "
        "markers' positions) or ROS 2 bag folder (PointCloud2 in the world frame; the 'ros' "
        "extra): train/ and eval/ subfolders, or the episodes themselves (all train).",
    )
    topic: str | None = Field(
        None, max_length=1000,
        description="The bags' topic of the cable's clouds (PointCloud2); default: a bag's "
        "only PointCloud2 topic.",
    )  # fmt: skip
    camera_position: list[float] | None = Field(
        None, min_length=3, max_length=3,
        description="The camera's position (x,y,z, m, world frame) for bags, whose clouds do "
        "not say where they were seen from.",
    )  # fmt: skip
    markers: int = Field(
        10, ge=2, le=1000,
        description="Markers to track, evenly spaced from the cable's left end to its right "
        "end, where the grippers hold it.",
    )  # fmt: skip
    gripper_markers: float = Field(
        0.05, ge=0.0, le=0.5,
        description="A marker on each gripper this far behind the cable's end (a fraction of "
        "its length; 0: none); needs the recorded held positions.",
    )  # fmt: skip
    length: float = Field(1.0, gt=0.0, le=100.0, description="The cable's length (m).")
    radius: float = Field(0.01, gt=0.0, le=1.0, description="The cable's radius (m).")
    tracker: TrackerSpec = Field(default_factory=TrackerSpec, description="The tracker.")
    out: Path = Field(Path("runs/track"), description="Run directory for the dataset.")
