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

    cli_flags: ClassVar[tuple[str, ...]] = ("source", "rate_hz", "units", "max_memory_mib", "out")
    cli_required: ClassVar[tuple[str, ...]] = ("source",)

    source: Path | None = Field(
        None,
        description="Folder of one cable's recordings in the DEFORM layout: train/*.pkl and "
        "eval/*.pkl, each a pickled (frames, 3, markers) list of metres.",
    )
    rate_hz: float = Field(
        DEFAULT_RATE_HZ, gt=0, le=MAX_RATE_HZ, description="Frames per second of the recording."
    )
    units: Literal["m", "cm", "mm"] = Field(
        "m",
        description="Unit of the recordings' coordinates, converted to metres on import. A "
        "cable outside 0.02-10 m along its markers is refused as a unit error.",
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
