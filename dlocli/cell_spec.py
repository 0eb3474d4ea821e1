"""A run's choice of a cell (a served simulator or a robot) and the addresses a cell takes:
below the env and the bridge, so the env builds a cell's client without importing the bridge
(:func:`dlocli.backends.make_backend`)."""

from __future__ import annotations

import re
from pathlib import Path

from pydantic import Field, field_validator

from dlocli.spec_base import Spec

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
