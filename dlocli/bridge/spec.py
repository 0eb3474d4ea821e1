"""Specs of the bridge: a served cell (`dlo serve`) and a run's choice of one."""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar

from pydantic import Field, field_validator

from dlocli.specs import EnvSpec, Spec

#: ZeroMQ endpoints the bridge takes: tcp://host:port or ipc://path
ADDRESS = re.compile(r"(tcp://[^\s:]+:(\d+|\*)|ipc://\S+)")


def check_address(address: str) -> str:
    found = ADDRESS.fullmatch(address)
    if not found:
        raise ValueError(
            f"{address!r} is not a cell address: pass tcp://HOST:PORT (e.g. "
            "tcp://127.0.0.1:5555) or ipc://PATH"
        )
    port = found.group(2)
    if port is not None and port != "*" and not 1 <= int(port) <= 65535:
        raise ValueError(f"{address!r}: a port is a number from 1 to 65535")
    return address


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


class CellChoice(Spec):
    """A run stepped through a cell (a served simulator or a robot) instead of a simulator in
    this process."""

    cell: str | None = Field(
        None,
        description="Address of a cell (`dlo serve`, or a robot speaking the dlocli-cell "
        "protocol): tcp://HOST:PORT or ipc://PATH. Default: the simulator runs in this process.",
    )
    cell_timeout_s: float = Field(
        2.0,
        gt=0.0,
        le=600.0,
        description="A cell that does not answer a request within this time ends the run "
        "(the steps done are kept).",
    )

    cell_keys: Path | None = Field(
        None,
        description="The CURVE keys folder of the cell (`dlo keys --out DIR`, the same as its "
        "`dlo serve --keys`): required for a cell off loopback.",
    )

    _cell = field_validator("cell")(
        classmethod(lambda cls, v: v if v is None else check_cell_address(v))
    )


def check_cell_address(address: str) -> str:
    """A cell's address as a controller connects to it: a port number, not ``*``."""
    check_address(address)
    if address.startswith("tcp://") and address.endswith(":*"):
        raise ValueError(
            f"{address!r} names no port: a controller connects to the cell's port "
            "(tcp://HOST:5555); '*' is for `dlo serve --address`"
        )
    return address


class KeysSpec(Spec):
    """`dlo keys`: CURVE key pairs for a cell and its controller, in a new folder."""

    cli_flags: ClassVar[tuple[str, ...]] = ("out",)

    out: Path = Field(
        Path("cell-keys"),
        description="A new folder for the keys: cell.key(_secret) for `dlo serve --keys`, "
        "controller.key(_secret) for `dlo control --cell-keys`; pass the same folder to both.",
    )
