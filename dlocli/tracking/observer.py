"""The pointcloud observation: the env's markers from a depth camera and the tracker.

:class:`CloudObserver` takes the place of the markers observation's tracker
(:class:`dlocli.env.observation.Tracker`, same ``reset``/``report``/``lost``): every
``1 / (rate_hz * control_dt)`` control steps the camera takes a frame of the backend's
scene and the tracker finds the markers in it; between frames the last ones stand. The
robot knows its grippers: the held markers are placed from their poses at every step, as
the markers observation does, and reported seen (a gripper may hide them from the camera).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from dlocli.backends.base import Backend
from dlocli.camera_spec import CameraSpec, TrackerSpec
from dlocli.errors import BadInput
from dlocli.specs import ObservationSpec
from dlocli.tracking.camera import CloudFrame, DepthCamera
from dlocli.tracking.tracker import CableTracker, TrackedFrame


class CloudObserver:
    """A depth camera of ``spec.camera`` on ``backend`` and a tracker of ``layout``'s
    markers (a :class:`dlocli.env.observation.MarkerLayout`), stepped every ``control_dt``
    seconds; ``held_of`` places the held markers (H,3) for gripper poses (2,7)."""

    def __init__(
        self,
        spec: ObservationSpec,
        backend: Backend,
        layout: Any,
        control_dt: float,
        held_of: Callable[[np.ndarray], np.ndarray],
    ) -> None:
        self.backend, self.layout, self.held_of = backend, layout, held_of
        camera = spec.camera or CameraSpec()
        self.camera = DepthCamera(camera, backend.rod.length)
        #: a cell's camera, when the backend is a cell (``capture_cloud``); else None
        self.remote = _cell_camera(backend, camera)
        self.tracker = CableTracker.for_layout(
            layout, backend.rod.radius, spec.tracker or TrackerSpec()
        )
        self.every = max(1, round(1.0 / (camera.rate_hz * control_dt)))
        self.control_dt = control_dt
        self.rng = np.random.default_rng(0)
        self.seed = 0  # the episode's camera noise: rng is default_rng(seed)
        self._steps = 0
        self._last: TrackedFrame | None = None
        #: whether the latest frame held no cable point
        self.lost = False
        #: the latest frame the camera took (None before the first)
        self.last_cloud: CloudFrame | None = None

    def reset(self, rng: np.random.Generator, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start an episode: the camera must see the cable (BadInput if it cannot); the true
        ``frame`` is not read (the camera looks at the backend)."""
        del frame
        # one seed per episode: a cell's camera draws the same noise from it
        self.seed, self._steps = int(rng.integers(2**63)), 0
        self.rng = np.random.default_rng(self.seed)
        self.camera.check_view(self.backend)
        self._last = self.tracker.start(self._capture(), self._held())
        return self._reported()

    def report(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The markers after a control step: a new frame's at the camera's rate, else the
        last frame's, the held ones where the grippers are now."""
        del frame
        self._steps += 1
        if self._steps % self.every == 0 or self._last is None:
            self._last = self.tracker.step(self._capture(), self._held())
        return self._reported()

    def _capture(self) -> CloudFrame:
        time = self._steps * self.control_dt
        if self.remote is not None:
            taken = self.remote(self.seed, time)
            cloud = CloudFrame(taken["points"], taken["extrinsics"], taken["intrinsics"],
                               taken["time"], taken["segments"])  # fmt: skip
        else:
            cloud = self.camera.capture(self.backend, self.rng, time)
        self.lost = len(cloud.points) == 0
        self.last_cloud = cloud
        return cloud

    def _held(self) -> np.ndarray:
        return self.held_of(self.backend.gripper_poses())

    def _reported(self) -> tuple[np.ndarray, np.ndarray]:
        assert self._last is not None
        markers, visible = self._last.markers.copy(), self._last.visible.copy()
        markers[self.layout.held] = self._held()
        visible[self.layout.held] = True  # known from the robot's kinematics
        return markers, visible


def _cell_camera(backend: Backend, camera: CameraSpec) -> Callable[..., Any] | None:
    """A cell's ``capture_cloud`` when the backend is a cell; BadInput if that cell has no
    camera or another one than ``camera``."""
    capture = getattr(backend, "capture_cloud", None)
    if capture is None:
        return None
    theirs = backend.camera_spec()  # type: ignore[attr-defined]
    if theirs is None:
        raise BadInput(
            "--observation pointcloud through a cell needs the cell's camera: serve it with "
            "`dlo serve --camera` (or a robot cell that answers capture)"
        )
    if theirs != camera.model_dump(mode="json"):
        raise BadInput(
            "the cell's camera is not the one task.observation.camera describes: give the "
            "controller the cell's camera spec (its welcome's cell.camera)"
        )
    return capture
