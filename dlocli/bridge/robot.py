"""A robot as a cell: subclass :class:`Robot`, fill in its four methods with your robot's and
your tracker's calls, and serve it with :func:`dlocli.bridge.server.serve`. Every request is
checked, and the session kept, by the same code as `dlo serve` before your methods run.
``examples/bridge/robot_cell.py`` is one in a page.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

import numpy as np

from dlocli.bridge import messages
from dlocli.bridge.server import CellHandler


class Robot(CellHandler):
    """Your robot and tracker. Units: metres, seconds, radians; world frame, z up.

    Build what is slow (drivers, the tracker, a simulated rod) in ``__init__``, before the
    cell listens: a controller's ``hello`` is then answered at once. ``reset_timeout_s`` tells
    the controller how long a reset may take (moving to the start, letting the cable settle).
    """

    #: how the cell names itself to controllers
    name = "robot"
    #: the longest a reset may take to answer (s)
    reset_timeout_s = 30.0
    #: your depth camera as a camera spec (a dict of dlocli.camera_spec.CameraSpec's fields),
    #: when :meth:`capture` gives its clouds
    camera: dict[str, Any] | None = None

    def __init__(
        self, n_segments: int, control_dt: float, backend: dict[str, Any] | None = None
    ) -> None:
        #: the nodes the tracker reports, the control period (s), and the rod spec a
        #: controller must bring (None: any rod of n_segments)
        self.n_segments, self.control_dt, self.backend = n_segments, control_dt, backend
        self.steps = 0

    # ------------------------------------------------------------------ yours
    @abstractmethod
    def reset(self, seed: int | None, limits: messages.Limits | None) -> None:
        """Bring the grippers to the start pose and wait for the cable to settle; keep the
        grippers inside ``limits`` (workspace box, separation; None: your own) from now on."""

    @abstractmethod
    def move(self, velocities: np.ndarray) -> None:
        """Send (2, 6) gripper twists (m/s, rad/s; left then right) for one control period."""

    @abstractmethod
    def stop(self) -> None:
        """Command zero velocity and hold the grippers where they are."""

    @abstractmethod
    def observe(self) -> dict[str, Any]:
        """The tracked cable and the grippers: ``positions`` (N, 3), ``quaternions`` (N, 4),
        ``grippers`` (2, 7: x y z qw qx qy qz), ``diverged`` (bool), and ``tracked`` (bool,
        optional: False when the tracker lost the cable)."""

    def capture(self) -> dict[str, Any] | None:
        """Optional: your depth camera's latest frame of the cable: ``points`` (P, 3) in the
        world frame, ``extrinsics`` (4, 4, camera to world), ``intrinsics`` (3, 3); None
        (the default) for a cell without a camera."""
        return None

    # ------------------------------------------------------------------ the protocol
    def info(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "backend": self.backend,
            "control_dt": self.control_dt,
            "realtime": False,
            "n_segments": self.n_segments,
            "reset_timeout_s": self.reset_timeout_s,
            "camera": self.camera,
        }

    def on_reset(self, request: messages.Reset) -> dict[str, Any]:
        self.reset(request.seed, request.limits)
        self.steps = 0
        return self._state()

    def on_step(self, request: messages.Step) -> dict[str, Any]:
        self.move(np.array(request.velocities, dtype=np.float64))
        self.steps += 1
        return self._state()

    def on_stop(self) -> dict[str, Any]:
        self.stop()
        return self._state()

    def on_capture(self, request: messages.Capture) -> dict[str, Any]:
        frame = self.capture()
        if frame is None:
            return super().on_capture(request)
        return {"type": "cloud", "time": self.steps * self.control_dt, **frame}

    def on_release(self) -> None:
        self.stop()

    def _state(self) -> dict[str, Any]:
        seen = self.observe()
        return {
            "type": "state",
            "step": self.steps,
            "time": self.steps * self.control_dt,
            "diverged": bool(seen["diverged"]),
            "tracked": bool(seen.get("tracked", True)),
            "positions": np.asarray(seen["positions"], dtype=np.float64),
            "quaternions": np.asarray(seen["quaternions"], dtype=np.float64),
            "grippers": np.asarray(seen["grippers"], dtype=np.float64),
            "late": 0,
            "dropped": 0,
        }
