"""A simulator served as a cell (``dlo serve``): the dlocli-cell protocol's REP side.

In lockstep (the default) the rod steps when a command comes, so a bridged run equals an
in-process one. In real time the cell keeps its own clock, as a robot does: a control period
whose command has not come by its tick is stepped with the held command and counted late; a
cell left without commands for ``hold_s`` stops (zero velocity) by itself. ``delay_s`` holds
every reply back (a tracker's latency), ``drop_probability`` loses commands (the held one
acts instead).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from dlocli.backends.base import Backend
from dlocli.bridge import protocol
from dlocli.bridge.spec import ServeSpec
from dlocli.env.shape_env import make_backend
from dlocli.errors import BadInput
from dlocli.processes import raise_if_stopped

#: how often the serving loop looks for a stop signal while no request comes (ms)
POLL_MS = 100


class Cell:
    """One backend behind the protocol: a request in, one reply out."""

    def __init__(self, backend: Backend, spec: ServeSpec) -> None:
        self.backend, self.spec = backend, spec
        self.rng = np.random.default_rng(spec.seed)
        self.held = np.zeros((2, 6))
        self.step_count = self.late = self.dropped = 0
        self.clock_start = self.commanded_at = time.monotonic()
        self.seen: dict[str, np.ndarray] = {}  # the cable as the tracker last saw it

    # ------------------------------------------------------------------ requests
    def handle(self, request: dict[str, Any]) -> bytes:
        handler = getattr(self, f"_on_{request['type']}", None)
        if handler is None:
            raise BadInput(f"unknown request type {request['type']!r}")
        return handler(request)

    def _on_hello(self, request: dict[str, Any]) -> bytes:
        spoken = (request.get("protocol"), request.get("version"))
        if spoken != (protocol.PROTOCOL, protocol.VERSION):
            raise BadInput(
                f"this cell speaks {protocol.PROTOCOL} version {protocol.VERSION}, not "
                f"{spoken[0]} {spoken[1]}"
            )
        self._check_same_rod(request)
        return protocol.encode(
            "welcome",
            protocol=protocol.PROTOCOL,
            version=protocol.VERSION,
            cell={
                "name": self.backend.name,
                "backend": self.backend.spec.model_dump(mode="json"),
                "control_dt": self.backend.control_dt,
                "realtime": self.spec.realtime,
                "n_segments": self.backend.n_segments,
            },
        )

    def _on_reset(self, request: dict[str, Any]) -> bytes:
        seed = request.get("seed")
        self._apply_limits(request.get("limits") or {})
        self.backend.reset(None if seed is None else int(seed))
        self.held = np.zeros((2, 6))
        self.step_count = self.late = self.dropped = 0
        self.clock_start = self.commanded_at = time.monotonic()
        return self._state(reset=True)

    def _on_step(self, request: dict[str, Any]) -> bytes:
        velocities = protocol.array(request, "velocities", (2, 6))
        if self.spec.realtime:
            self._catch_up()
        if self.rng.random() < self.spec.drop_probability:
            self.dropped += 1  # lost on the way: the held command acts in its period
        else:
            self.held, self.commanded_at = velocities, time.monotonic()
        self._advance(self.held)
        return self._state()

    def _on_stop(self, request: dict[str, Any]) -> bytes:
        self.held = np.zeros((2, 6))
        return self._state()

    def _on_get_state(self, request: dict[str, Any]) -> bytes:
        return protocol.encode("snapshot", state=self.backend.get_state())

    def _on_set_state(self, request: dict[str, Any]) -> bytes:
        state = np.asarray(request.get("state"), dtype=np.float64)
        self.backend.set_state(state)
        return self._state()

    def _on_bye(self, request: dict[str, Any]) -> bytes:
        return protocol.encode("bye")

    # ------------------------------------------------------------------ the rod
    def _check_same_rod(self, request: dict[str, Any]) -> None:
        theirs = request.get("backend")
        ours = self.backend.spec.model_dump(mode="json")
        if theirs != ours:
            raise BadInput(
                f"the controller's rod is not this cell's: start `dlo serve` with the same "
                f"backend spec (this cell: {ours['name']}, {self.backend.n_segments} segments)"
            )
        if request.get("control_dt") != self.backend.control_dt:
            raise BadInput(
                f"control period {request.get('control_dt')} s asked, this cell steps "
                f"{self.backend.control_dt} s: serve it with the task's control_dt"
            )

    def _apply_limits(self, limits: dict[str, Any]) -> None:
        if not limits:
            return
        own = self.backend.limits
        own.low = np.asarray(limits["workspace_low"], dtype=np.float64)
        own.high = np.asarray(limits["workspace_high"], dtype=np.float64)
        own.min_separation = float(limits["min_separation"])
        own.max_separation = float(limits["max_separation"])

    def _advance(self, velocities: np.ndarray) -> None:
        if self.spec.realtime:
            _sleep_until(self.clock_start + (self.step_count + 1) * self.backend.control_dt)
        self.backend.step(velocities)
        self.step_count += 1

    def _catch_up(self) -> None:
        """Real time: the periods whose tick passed before this command came run with the
        held command (late); from ``hold_s`` after the last command the held one is zero."""
        dt = self.backend.control_dt
        now = time.monotonic()
        while (tick := self.clock_start + (self.step_count + 1) * dt) < now:
            if tick - self.commanded_at > self.spec.hold_s:
                self.held = np.zeros((2, 6))
            self.backend.step(self.held)
            self.step_count += 1
            self.late += 1

    def _state(self, reset: bool = False) -> bytes:
        if self.spec.delay_s > 0:
            time.sleep(self.spec.delay_s)
        tracked = reset or self.rng.random() >= self.spec.frame_loss_probability
        if tracked:
            self.seen = {
                "positions": self.backend.segment_positions(),
                "quaternions": self.backend.segment_quaternions(),
            }
        return protocol.encode(
            "state",
            step=self.step_count,
            time=self.step_count * self.backend.control_dt,
            diverged=self.backend.diverged,
            tracked=tracked,
            **self.seen,
            grippers=self.backend.gripper_poses(),
            late=self.late,
            dropped=self.dropped,
        )


def _sleep_until(moment: float) -> None:
    remaining = moment - time.monotonic()
    if remaining > 0:
        time.sleep(remaining)


def serve(spec: ServeSpec, ready: Callable[[str], None] | None = None) -> None:
    """Serve ``spec.backend`` at ``spec.address`` until stopped (SIGINT, SIGTERM);
    ``ready(address)`` is called once the socket listens."""
    import zmq

    backend = make_backend(spec.backend, spec.control_dt)
    context = zmq.Context()
    socket = context.socket(zmq.REP)
    socket.setsockopt(zmq.LINGER, 0)
    try:
        try:
            socket.bind(spec.address)
        except zmq.ZMQError as exc:
            raise BadInput(f"--address {spec.address}: cannot listen there ({exc})") from None
        if ready is not None:
            ready(socket.getsockopt_string(zmq.LAST_ENDPOINT))
        _serve_loop(Cell(backend, spec), socket)
    finally:
        socket.close()
        context.term()
        backend.close()


def _serve_loop(cell: Cell, socket: Any) -> None:
    while True:
        raise_if_stopped()
        if not socket.poll(POLL_MS):
            continue
        message = socket.recv()
        try:
            reply = cell.handle(protocol.decode(message))
        except BadInput as exc:  # the controller hears why; the cell serves on
            reply = protocol.encode("error", message=str(exc))
        except (KeyError, TypeError, ValueError) as exc:  # a field missing or of a wrong kind
            reply = protocol.encode("error", message=f"a malformed request: {exc!r}")
        socket.send(reply)
