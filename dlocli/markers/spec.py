"""Specs of the marker-form commands (torch-free: the CLI builds its --help without torch)."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field

from dlocli.specs import Spec

DEFAULT_RATE_HZ = 100.0
MAX_RATE_HZ = 100_000
DEFAULT_MEMORY_MIB = 1024
#: metres per unit of a recording's coordinates
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


class ImportSpec(Spec):
    """`dlo import`: recorded marker trajectories -> a marker dataset run directory."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "source", "rate_hz", "units", "held", "fill_gaps", "max_memory_mib", "out",
    )  # fmt: skip
    cli_required: ClassVar[tuple[str, ...]] = ("source",)

    source: Path | None = Field(
        None,
        description="Folder of one cable's recordings in the DEFORM layout: train/ and eval/ "
        "of .pkl (DEFORM's pickled lists), .npy/.npz/.h5 ((frames, 3, markers) or (frames, "
        "markers, 3) arrays) or .csv (frame,time,m0_x,m0_y,m0_z,m1_x,... one row per frame) "
        "files.",
    )
    rate_hz: float = Field(
        DEFAULT_RATE_HZ, gt=0, le=MAX_RATE_HZ, description="Frames per second of the recording."
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
        description="Interpolate a CSV's gaps (empty cells) up to this many frames long; "
        "0 refuses any gap.",
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
