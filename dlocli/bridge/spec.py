"""Specs of the bridge: a served cell (`dlo serve`) and a run's choice of one."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field, field_validator

from dlocli.cell_spec import ADDRESS, CellChoice, check_address, check_cell_address  # noqa: F401
from dlocli.specs import EnvSpec, Spec


class ServeSpec(EnvSpec):
    """`dlo serve`: a simulator served as a cell, for controllers that speak the dlocli-cell
    protocol (docs/real-cell.md, "A robot bridge")."""

    cli_flags: ClassVar[tuple[str, ...]] = (
        "address", "backend.name", "backend.rod.n_segments", "task.control_dt", "realtime",
        "delay_ms", "drop_probability", "frame_loss_probability", "hold_s", "camera", "keys",
        "session_idle_s", "seed",
    )  # fmt: skip

    address: str = Field(
        "tcp://127.0.0.1:5555", description="Where the cell listens: tcp://HOST:PORT or ipc://PATH."
    )
    realtime: bool = Field(
        False,
        description="Keep the cell's own clock at the control rate: a command that comes after "
        "its period's tick is late (the held command acts). Without it the rod steps when a "
        "command comes (lockstep: a bridged run equals an in-process one).",
    )
    delay_ms: float = Field(
        0.0,
        ge=0.0,
        le=10_000.0,
        description="Hold every reply back this long (a tracker's latency).",
    )
    drop_probability: float = Field(
        0.0, ge=0.0, lt=1.0, description="Probability that a command is lost (the held one acts)."
    )
    frame_loss_probability: float = Field(
        0.0, ge=0.0, lt=1.0,
        description="Probability that the tracker loses a frame: the reply repeats the last "
        "tracked shape, marked tracked: false (the grippers' poses stay current).",
    )  # fmt: skip
    hold_s: float = Field(
        0.5,
        gt=0.0,
        le=60.0,
        description="Real time: with no command for this long the cell stops the grippers.",
    )

    camera: bool = Field(
        False,
        description="Serve a depth camera's point clouds (`capture` requests): the camera of "
        "task.observation.camera in a --spec file, its defaults otherwise. Controllers with "
        "--observation pointcloud then track the cable in the cell's clouds.",
    )
    keys: Path | None = Field(
        None,
        description="A folder of CURVE keys (`dlo keys --out DIR`): only controllers holding its "
        "controller key get in, encrypted. Required off loopback (any address but "
        "127.0.0.1, localhost and ipc://).",
    )
    session_idle_s: float = Field(
        30.0,
        gt=0.0,
        le=3600.0,
        description="A controller's session (from its hello) ends after this long without a "
        "request; the grippers are stopped and another controller may take the cell.",
    )

    _address = field_validator("address")(classmethod(lambda cls, v: check_address(v)))

    @property
    def delay_s(self) -> float:
        return self.delay_ms / 1000.0

    @property
    def control_dt(self) -> float:
        return self.task.control_dt


class KeysSpec(Spec):
    """`dlo keys`: CURVE key pairs for a cell and its controller, in a new folder."""

    cli_flags: ClassVar[tuple[str, ...]] = ("out",)

    out: Path = Field(
        Path("cell-keys"),
        description="A new folder for the keys: cell.key(_secret) for `dlo serve --keys`, "
        "controller.key(_secret) for `dlo control --cell-keys`; pass the same folder to both.",
    )
