"""A simulator served as a cell (``dlo serve``): what it does with the requests that passed
the checks and the session of :mod:`dlocli.bridge.server`.

In lockstep (the default) the rod steps when a command comes, so a bridged run equals an
in-process one. In real time the cell keeps its own clock, as a robot does, from the first
step after a reset (what a controller does before it, planning included, costs no period): a
control period whose command has not come by its tick is stepped with the held command, and
a command that came after one or more such ticks is counted late once (``step`` counts every
period, so the periods missed are ``step`` less the commands sent); a cell left without
commands for ``hold_s`` stops (zero velocity) by itself. ``delay_s`` holds
every reply back (a tracker's latency), ``drop_probability`` loses commands (the held one
acts instead).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dlocli.backends import make_backend
from dlocli.backends.base import Backend
from dlocli.bridge import messages
from dlocli.bridge.keys import require_keys_off_loopback
from dlocli.bridge.server import CellHandler
from dlocli.bridge.server import serve as serve_handler
from dlocli.bridge.spec import ServeSpec
from dlocli.camera_spec import CameraSpec
from dlocli.cancel import CancelToken
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.tracking.camera import DepthCamera

#: a simulated reset settles the rod in well under a second; this leaves room on a busy CPU
RESET_TIMEOUT_S = 10.0


class Cell(CellHandler):
    """A simulator behind the protocol, with the faults of a real cell it was asked for."""

    def __init__(self, backend: Backend, spec: ServeSpec) -> None:
        self.backend, self.spec = backend, spec
        self.rng = np.random.default_rng(spec.seed)
        self.held = np.zeros((2, 6))
        self.step_count = self.late = self.dropped = 0
        #: when the first step after the reset came (real time: the periods' ticks count
        #: from it); None until then
        self.clock_start: float | None = None
        self.commanded_at = time.monotonic()
        self.seen: dict[str, np.ndarray] = {}  # the cable as the tracker last saw it
        self.state_size = self.backend.get_state().size
        self.camera = served_camera(spec, backend.rod.length)
        self._camera_seed, self._camera_rng = -1, np.random.default_rng(0)

    def info(self) -> dict[str, Any]:
        return {
            "name": self.backend.name,
            "backend": self.backend.spec.model_dump(mode="json"),
            "control_dt": self.backend.control_dt,
            "realtime": self.spec.realtime,
            "n_segments": self.backend.n_segments,
            "reset_timeout_s": RESET_TIMEOUT_S,
            "camera": None if self.camera is None else self.camera.spec.model_dump(mode="json"),
        }

    # ------------------------------------------------------------------ requests
    def on_reset(self, request: messages.Reset) -> dict[str, Any]:
        if request.limits is not None:
            self._apply_limits(request.limits)
        self.backend.reset(request.seed)
        self.held = np.zeros((2, 6))
        self.step_count = self.late = self.dropped = 0
        self.clock_start, self.commanded_at = None, time.monotonic()
        return self._state(reset=True)

    def on_step(self, request: messages.Step) -> dict[str, Any]:
        velocities = np.array(request.velocities, dtype=np.float64)
        if self.spec.realtime:
            self._start_clock_or_catch_up()
        if self.rng.random() < self.spec.drop_probability:
            self.dropped += 1  # lost on the way: the held command acts in its period
        else:
            self.held, self.commanded_at = velocities, time.monotonic()
        self._advance(self.held)
        return self._state()

    def on_stop(self) -> dict[str, Any]:
        self.held = np.zeros((2, 6))
        return self._state()

    def on_get_state(self) -> dict[str, Any]:
        return {"type": "snapshot", "state": self.backend.get_state()}

    def on_set_state(self, request: messages.SetState) -> dict[str, Any]:
        if len(request.state) != self.state_size:
            raise BadInput(
                f"set_state request: a state of {len(request.state)} numbers, this cell's "
                f"has {self.state_size} (send what get_state gave)"
            )
        state = np.array(request.state, dtype=np.float64)
        quaternion_norms = np.linalg.norm(state[:14].reshape(2, 7)[:, 3:], axis=1)
        if not np.allclose(quaternion_norms, 1.0, atol=1e-6):
            raise BadInput("set_state request: the grippers' quaternions are not unit ones")
        self.backend.set_state(state)
        return self._state()

    def on_capture(self, request: messages.Capture) -> dict[str, Any]:
        if self.camera is None:
            return super().on_capture(request)
        if request.seed != self._camera_seed:  # a new episode: its noise from its seed
            self._camera_seed, self._camera_rng = request.seed, np.random.default_rng(request.seed)
        frame = self.camera.capture(self.backend, self._camera_rng, request.time)
        return {
            "type": "cloud",
            "points": frame.points,
            "extrinsics": frame.extrinsics,
            "intrinsics": frame.intrinsics,
            "time": frame.time,
            "segments": frame.segment,
        }

    def on_release(self) -> None:
        self.held = np.zeros((2, 6))
        self.clock_start = None  # the next controller's first step starts the clock again

    # ------------------------------------------------------------------ the rod
    def _apply_limits(self, limits: messages.Limits) -> None:
        """The controller's envelope, refused if the rod's start lies outside it."""
        low, high = np.array(limits.workspace_low), np.array(limits.workspace_high)
        start = self.backend.rest_gripper_poses()[:, :3]
        separation = float(np.linalg.norm(start[1] - start[0]))
        if np.any(start < low) or np.any(start > high):
            raise BadInput(
                "reset request: the limits' workspace excludes the grippers' start "
                f"{np.round(start, 3).tolist()}: widen workspace_low/workspace_high"
            )
        both_held = bool(self.backend.moving.all())
        if both_held and not limits.min_separation <= separation <= limits.max_separation:
            raise BadInput(
                f"reset request: the grippers start {separation:.3f} m apart, outside the "
                f"limits' separation [{limits.min_separation:g}, {limits.max_separation:g}] m"
            )
        own = self.backend.limits
        own.low, own.high = low, high
        own.min_separation, own.max_separation = limits.min_separation, limits.max_separation

    def _advance(self, velocities: np.ndarray) -> None:
        if self.spec.realtime and self.clock_start is not None:
            _sleep_until(self.clock_start + (self.step_count + 1) * self.backend.control_dt)
        self.backend.step(velocities)
        self.step_count += 1

    def _start_clock_or_catch_up(self) -> None:
        """Real time: the first step after a reset starts the clock (its period ends one
        control period later). Later, the periods whose tick passed before this command came
        run with the held command, and the command counts late once; from ``hold_s`` after
        the last command the held one is zero."""
        now = time.monotonic()
        if self.clock_start is None:
            self.clock_start = now - self.step_count * self.backend.control_dt
            return
        dt = self.backend.control_dt
        missed = 0
        while (tick := self.clock_start + (self.step_count + 1) * dt) < now:
            if tick - self.commanded_at > self.spec.hold_s:
                self.held = np.zeros((2, 6))
            self.backend.step(self.held)
            self.step_count += 1
            missed += 1
        self.late += int(missed > 0)

    def _state(self, reset: bool = False) -> dict[str, Any]:
        if self.spec.delay_s > 0:
            time.sleep(self.spec.delay_s)
        tracked = reset or self.rng.random() >= self.spec.frame_loss_probability
        if tracked:
            self.seen = {
                "positions": self.backend.segment_positions(),
                "quaternions": self.backend.segment_quaternions(),
            }
        return dict(
            type="state",
            step=self.step_count,
            time=self.step_count * self.backend.control_dt,
            diverged=self.backend.diverged,
            tracked=tracked,
            **self.seen,
            grippers=self.backend.gripper_poses(),
            late=self.late,
            dropped=self.dropped,
        )


def served_camera(spec: ServeSpec, rod_length: float) -> DepthCamera | None:
    """The depth camera of ``spec.task.observation.camera`` (its defaults if unset), with
    ``spec.camera``; else None."""
    if not spec.camera:
        return None
    return DepthCamera(spec.task.observation.camera or CameraSpec(), rod_length)


def _sleep_until(moment: float) -> None:
    remaining = moment - time.monotonic()
    if remaining > 0:
        time.sleep(remaining)


def serve(
    spec: ServeSpec,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> None:
    """Serve ``spec.backend`` at ``spec.address`` until stopped (KeyboardInterrupt, or
    ``cancel``: the command hands it SIGINT and SIGTERM); ``progress`` gets a
    :class:`~dlocli.bridge.server.Listening` once the socket listens, then a
    :class:`~dlocli.bridge.server.Logged` per line for the log (sessions, refusals)."""
    require_keys_off_loopback(spec.address, spec.keys, "--address", "--keys")  # before the rod
    backend = make_backend(spec.backend, spec.control_dt)
    try:
        cell = Cell(backend, spec)
        serve_handler(cell, spec.address, spec.keys, spec.session_idle_s, progress, cancel)
    finally:
        backend.close()
