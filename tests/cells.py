"""Cells for the bridge's tests: `dlo serve` and the README's example robot cell in their own
processes on free ports (real ZeroMQ, the real MuJoCo rod), and a raw client that sends what
it likes."""

from __future__ import annotations

import csv
import json
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bridge" / "robot_cell.py"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def lan_address() -> str:
    """An address of this machine that is not loopback (the interface a route out would
    take; 0.0.0.0, which reaches this machine on Linux, if there is none)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("10.255.255.255", 1))  # UDP: nothing is sent
            found = probe.getsockname()[0]
        except OSError:
            found = "0.0.0.0"
    return "0.0.0.0" if found.startswith("127.") else found


@contextmanager
def listening(argv: list[str], pattern: str, kill: bool = False) -> Iterator[tuple[str, Any]]:
    """The cell process of ``argv``; yields the address its first stderr line names (by
    ``pattern``) and the process; stops it after (Ctrl-C, or SIGKILL with ``kill``)."""
    cell = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
    try:
        assert cell.stderr is not None
        line = cell.stderr.readline()
        found = re.search(pattern, line)
        assert found, f"the cell did not start: {line}{cell.stderr.read()}"
        yield found.group(1), cell
    finally:
        if cell.poll() is None:
            cell.send_signal(signal.SIGKILL if kill else signal.SIGINT)
            code = cell.wait(timeout=30)
            assert kill or code == 0, cell.stderr.read()  # Ctrl-C is how a server ends


@contextmanager
def served(*flags: str, kill: bool = False, address: str = "tcp://127.0.0.1:*") -> Iterator[str]:
    """A `dlo serve` process; yields its address, stops it after (Ctrl-C, or SIGKILL with
    ``kill``)."""
    argv = [sys.executable, "-m", "dlocli.cli", "serve", "--address", address, *flags]
    with listening(argv, r" at (tcp://\S+);", kill) as (bound, _):
        yield bound


@contextmanager
def example_cell(*flags: str) -> Iterator[str]:
    """examples/bridge/robot_cell.py, the robot side a user copies, on a free port."""
    address = f"tcp://127.0.0.1:{free_port()}"
    argv = [sys.executable, str(EXAMPLE), "--address", address, *flags]
    with listening(argv, r"serving at (tcp://\S+);", kill=False) as (bound, _):
        yield bound


class RawClient:
    """A client that sends any bytes, one request on a fresh socket each (a REQ socket whose
    request went unanswered cannot send again)."""

    def __init__(self, address: str, timeout_ms: int = 10_000) -> None:
        import zmq

        self.address, self.timeout_ms = address, timeout_ms
        self.context = zmq.Context()

    def send(self, *frames: bytes, timeout_ms: int | None = None) -> dict[str, Any] | None:
        """The reply to ``frames`` as one message (None if none came in time)."""
        import zmq

        sock = self.context.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.address)
        try:
            for frame in frames[:-1]:
                sock.send(frame, zmq.SNDMORE)
            sock.send(frames[-1])
            if not sock.poll(self.timeout_ms if timeout_ms is None else timeout_ms):
                return None
            return json.loads(sock.recv())
        finally:
            sock.close()

    def ask(self, kind: str, **fields: Any) -> dict[str, Any] | None:
        return self.send(json.dumps({"type": kind, **fields}).encode())

    def close(self) -> None:
        self.context.term()


def control_argv(goal: Path, policy: Path, out: Path, *flags: str, steps: int = 12) -> list[str]:
    """`dlo control` arguments: ``steps`` steps of the SAC policy towards the goal, --json."""
    from tiny import control_with_policy

    argv = control_with_policy(goal, policy, out)
    argv[argv.index("--steps") + 1] = str(steps)
    return [*argv, "--json", *flags]


def step_errors(out: Path) -> list[str]:
    """A run's shape errors as metrics.csv writes them (every digit)."""
    with open(out / "metrics.csv", newline="") as f:
        return [row["shape_error_mm"] for row in csv.DictReader(f)]


def summary_of(out: Path) -> dict[str, Any]:
    return json.loads((out / "summary.json").read_text())


def stepping_controller(argv: list[str], address: str) -> subprocess.Popen:
    """`dlo` ``argv`` (a control run without --json) against the cell at ``address`` in a
    process of its own, returned once its first progress line says the steps have begun."""
    control = subprocess.Popen(
        [sys.executable, "-m", "dlocli.cli", *argv, "--cell", address],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert control.stdout is not None
    progress = control.stdout.readline()
    assert progress.startswith("step"), progress + (control.stderr.read() if control.stderr else "")
    return control
