"""Specs of the marker-form commands (torch-free: the CLI builds its --help without torch)."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field

from dlocli.specs import Spec

DEFAULT_RATE_HZ = 100.0
MAX_RATE_HZ = 100_000


class ImportSpec(Spec):
    """`dlo import`: recorded marker trajectories -> a marker dataset run directory."""

    cli_flags: ClassVar[tuple[str, ...]] = ("source", "rate_hz", "out")
    cli_required: ClassVar[tuple[str, ...]] = ("source",)

    source: Path | None = Field(
        None,
        description="Folder of one cable's recordings in the DEFORM layout: train/*.pkl and "
        "eval/*.pkl, each a pickled (frames, 3, markers) list of metres.",
    )
    rate_hz: float = Field(
        DEFAULT_RATE_HZ, gt=0, le=MAX_RATE_HZ, description="Frames per second of the recording."
    )
    out: Path = Field(Path("runs/import"), description="Run directory for the dataset.")
