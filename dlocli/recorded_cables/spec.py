"""Specs of the marker-form commands (torch-free: the CLI builds its --help without torch)."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field

from dlocli.data.markers import DEFAULT_RATE_HZ, MAX_RATE_HZ
from dlocli.specs import Spec

DEFAULT_MEMORY_MIB = 1024
#: metres per unit of a recording's coordinates
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


class ImportSpec(Spec):
    """`dlo import`: recorded marker trajectories -> a marker dataset run directory."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "source", "topic", "rate_hz", "control_hz", "units", "held", "fill_gaps",
        "max_memory_mib", "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("source",)

    source: Path | None = Field(
        None,
        description="Folder of one cable's recordings in the DEFORM layout: train/ and eval/ "
        "of .pkl (DEFORM's pickled lists), .npy/.npz/.h5 ((frames, 3, markers) or (frames, "
        "markers, 3) arrays), .csv (frame,time,m0_x,m0_y,m0_z,m1_x,... one row per frame) "
        "files or ROS 2 bag folders (one per trajectory; the 'ros' extra).",
    )
    topic: str | None = Field(
        None,
        max_length=1000,
        description="The ROS 2 bags' topic of the tracked markers (PoseArray, MarkerArray or "
        "PointCloud2); default: a bag's only topic of those types.",
    )
    rate_hz: float | None = Field(
        None,
        gt=0,
        le=MAX_RATE_HZ,
        description=f"Frames per second of recordings without timestamps (default "
        f"{DEFAULT_RATE_HZ:g}); a CSV's time column and a bag's stamps give their own.",
    )
    control_hz: float | None = Field(
        None,
        gt=0,
        le=MAX_RATE_HZ,
        description="Resample every recording to this rate (linear interpolation), the "
        "control rate of the models trained on it; default: the recordings' own rate.",
    )
    units: Literal["m", "cm", "mm"] = Field(
        "m",
        description="Unit of the recordings' coordinates, converted to metres on import. A "
        "cable outside 0.02-10 m along its markers is refused as a unit error.",
    )
    held: list[int] | None = Field(
        None,
        description="Markers the grippers hold, by index in the recordings' marker order "
        "(-1 the last), e.g. 0,-1; default: the two at each end, as in DEFORM.",
    )
    fill_gaps: int = Field(
        0,
        ge=0,
        le=10_000,
        description="Interpolate gaps up to this many frames long (a CSV's empty cells, a "
        "marker's NaN, frames missing between timestamps); 0 refuses any gap.",
    )
    max_memory_mib: int = Field(
        DEFAULT_MEMORY_MIB,
        ge=16,
        le=2**20,
        description="Memory budget for reading the recordings (MiB): a file's bytes and what "
        "loading it builds, plus the numbers of the files read before it. A file past it is "
        "refused before it is loaded.",
    )
    out: Path = Field(Path("runs/import"), description="Run directory for the dataset.")
