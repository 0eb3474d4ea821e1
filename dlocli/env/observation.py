"""What a controller sees of the rod through tracked markers, and the tracker's faults.

A marker sits at an arc length s along the rod (metres from its left end). A free marker
lies on the polyline of the segment centres (extended straight beyond the end centres); a
marker on a held end segment j moves with that segment, x = c_j + (s - s_j) R_j e_x (c_j the
centre, s_j = (j + 1/2) l its arc length, e_x the segment's axis), and the robot, which
knows its own poses, predicts it as x = p_g + d R_g e_x, with d = s for the left gripper
(it holds the rod's start) and d = s - L for the right one. That prediction is exact at the
grippers' points (s = 0 and s = L, where the default markers sit); the clamp lets the end
segment pivot about them, so a held marker further in is predicted a few mm off.

The rod's end point does not show how a gripper turns, so by default each gripper carries
a marker of its own, behind the rod's end on the gripper's axis (arc length -d or L + d):
held, and placed by the gripper's pose alone. Markers placed by ``marker_arc_lengths`` below
0 or beyond L sit on the grippers the same way (a recorded cable's held marker behind where
it leaves the gripper, as DEFORM's arms hold two markers at each end).

A goal shape holds segment centres only, so all of a goal's markers lie on its polyline.

:class:`Tracker` turns true marker frames into what a tracker reports: a latency of k
frames, Gaussian noise of sigma per coordinate, lost frames and occlusions (a span of
neighbouring markers missing for a stretch of frames). A missing marker is reported at its
last seen position with its ``visible`` flag 0: never NaN.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from dlocli.errors import BadInput
from dlocli.registry import observers
from dlocli.specs import ObservationSpec

MM = 1e-3


@dataclass(frozen=True)
class MarkerLayout:
    """Where M markers sit on a rod of N segments and which gripper holds each."""

    #: (M,) arc length of each marker, metres from the rod's left end
    arc: np.ndarray
    #: (M,) segment each marker sits on
    segment: np.ndarray
    #: (M,) the marker's offset from its segment's centre along the segment's axis (m)
    offset: np.ndarray
    #: (M,) gripper holding the marker's segment: 0 left, 1 right, -1 none (a free marker)
    holder: np.ndarray
    #: (M,) the marker's offset from its gripper's point along the gripper's axis (m)
    lever: np.ndarray
    #: (M,) whether the marker sits on a gripper (not on the rod)
    on_gripper: np.ndarray
    #: rod length (m)
    length: float

    @property
    def held(self) -> np.ndarray:
        """(M,) whether each marker moves with a gripper."""
        return self.holder >= 0

    def __len__(self) -> int:
        return len(self.arc)


def marker_layout(
    spec: ObservationSpec, length: float, n_segments: int, held_grippers: tuple[bool, bool]
) -> MarkerLayout:
    """The markers of ``spec`` on a rod of ``length`` m and ``n_segments`` segments whose ends
    are held by the grippers flagged in ``held_grippers`` (left, right). BadInput unless some
    markers are held and some free (the marker model needs both)."""
    seg = length / n_segments
    if spec.marker_arc_lengths is None:
        arc = np.linspace(0.0, length, spec.markers)
    else:
        arc = np.asarray(spec.marker_arc_lengths, dtype=np.float64) * length
    # marker_arc_lengths past the rod's ends: on a gripper, as gripper_markers places them
    on_gripper = (arc < -1e-9 * length) | (arc > (1 + 1e-9) * length)
    on_rod = int((~on_gripper).sum())
    if spec.gripper_markers > 0:
        behind = spec.gripper_markers * length
        arc = np.concatenate([[-behind], arc, [length + behind]])
        on_gripper = np.concatenate([[True], on_gripper, [True]])
    segment = np.clip(np.floor(arc / seg).astype(int), 0, n_segments - 1)
    holder = np.full(len(arc), -1)
    if held_grippers[0]:
        holder[segment == 0] = 0
    if held_grippers[1]:
        holder[segment == n_segments - 1] = 1
    holder[on_gripper] = np.where(arc[on_gripper] < 0, 0, 1)
    if not (holder[~on_gripper] < 0).any() or not (holder >= 0).any():
        raise BadInput(
            f"observation markers: {int((holder[~on_gripper] >= 0).sum())} of {on_rod} sit on a "
            f"held end segment (the first or last {seg:.3f} m); keep one between them, and one "
            "there or on the grippers (gripper_markers)"
        )
    lever = np.where(holder == 1, arc - length, arc)
    offset = arc - (segment + 0.5) * seg
    return MarkerLayout(arc, segment, offset, holder, lever, on_gripper, float(length))


def axis_x(quaternions: Any) -> Any:
    """(..., 3) the x axis of frames with unit quaternions (..., 4) (w, x, y, z); numpy
    arrays or torch tensors (a planner's, differentiable)."""
    w, x, y, z = (quaternions[..., i] for i in range(4))
    axis = [1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)]
    if isinstance(quaternions, np.ndarray):
        return np.stack(axis, -1)
    import torch  # only a planner passes tensors: the env stays free of torch

    return torch.stack(axis, -1)


def markers_of_state(
    layout: MarkerLayout, positions: np.ndarray, quaternions: np.ndarray, grippers: np.ndarray
) -> np.ndarray:
    """(..., M, 3) true marker positions from segment centres (..., N, 3), orientations
    (..., N, 4) and gripper poses (..., 2, 7): held ones on their segment or gripper, free
    ones on the centres' polyline."""
    centres = positions[..., layout.segment, :]
    on_segment = centres + layout.offset[:, None] * axis_x(quaternions[..., layout.segment, :])
    markers = np.where(layout.held[:, None], on_segment, markers_of_shape(layout, positions))
    return np.where(layout.on_gripper[:, None], held_markers(layout, grippers), markers)


def markers_of_shape(layout: MarkerLayout, positions: np.ndarray) -> np.ndarray:
    """(..., M, 3) markers on the polyline of segment centres (..., N, 3), extended straight
    beyond the end centres (a goal's markers: a goal has no orientations)."""
    n = positions.shape[-2]
    at = layout.arc * n / layout.length - 0.5  # in centre spacings from the first centre
    low = np.clip(np.floor(at).astype(int), 0, n - 2)
    frac = (at - low)[:, None]
    return positions[..., low, :] + frac * (positions[..., low + 1, :] - positions[..., low, :])


def held_markers(layout: MarkerLayout, grippers: np.ndarray) -> np.ndarray:
    """(..., M, 3) where the held markers are for gripper poses (..., 2, 7) (free rows 0)."""
    holder = np.maximum(layout.holder, 0)
    poses = grippers[..., holder, :]
    placed = poses[..., :3] + layout.lever[:, None] * axis_x(poses[..., 3:])
    return np.where(layout.held[:, None], placed, 0.0)


def marker_tracker(
    spec: ObservationSpec, layout: MarkerLayout, backend: Any, control_dt: float
) -> Any:
    """What reports the markers: :class:`Tracker` (the markers observation's faults on the
    true markers), or the observer registered for the observation's kind
    (:data:`dlocli.registry.observers`; the pointcloud observation's is a depth camera on
    ``backend`` and the cable tracker, :class:`dlocli.tracking.observer.CloudObserver`, the
    same interface)."""
    if spec.kind not in observers:
        return Tracker(spec, len(layout))
    observer = observers.get(spec.kind)

    def held_of(grippers: np.ndarray) -> np.ndarray:
        return held_markers(layout, grippers)[layout.held]

    return observer(spec, backend, layout, control_dt, held_of)


class Tracker:
    """A marker tracker's faults (:class:`ObservationSpec`) on true marker frames; its own
    random stream, so faults never change the starts and goals the env draws."""

    def __init__(self, spec: ObservationSpec, n_markers: int) -> None:
        self.spec = spec
        self.n_markers = n_markers
        self.rng = np.random.default_rng(0)
        self._frames: deque[np.ndarray] = deque(maxlen=spec.latency_steps + 1)
        self._last_seen = np.zeros((n_markers, 3))
        self._occluded = np.zeros(n_markers, dtype=bool)
        self._occlusion_left = 0
        #: whether the latest frame was lost whole
        self.lost = False

    def reset(self, rng: np.random.Generator, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start an episode at rest at ``frame`` (M, 3): the first report sees every marker."""
        self.rng = rng
        self._frames.clear()
        self._frames.extend([frame] * self._frames.maxlen)
        self._occluded[:] = False
        self._occlusion_left = 0
        self.lost = False
        seen = self._noisy(frame)
        self._last_seen = seen
        return seen, np.ones(self.n_markers, dtype=bool)

    def report(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The report after a step to the true ``frame`` (M, 3): positions (M, 3) and which
        markers were seen (M,); a missing marker keeps its last seen position."""
        self._frames.append(frame)
        seen = self._noisy(self._frames[0])
        self.lost = bool(self.spec.dropout > 0 and self.rng.random() < self.spec.dropout)
        visible = ~self._occlusion() & (not self.lost)
        self._last_seen = np.where(visible[:, None], seen, self._last_seen)
        return self._last_seen, visible

    def _noisy(self, frame: np.ndarray) -> np.ndarray:
        if self.spec.noise_mm == 0:
            return frame.copy()
        return frame + self.rng.normal(0.0, self.spec.noise_mm * MM, frame.shape)

    def _occlusion(self) -> np.ndarray:
        """(M,) the markers an occlusion hides in this frame."""
        spec = self.spec
        if self._occlusion_left > 0:
            self._occlusion_left -= 1
        else:
            self._occluded[:] = False
            if spec.occlusion_probability > 0 and self.rng.random() < spec.occlusion_probability:
                span = min(spec.occlusion_markers, self.n_markers)
                first = int(self.rng.integers(self.n_markers - span + 1))
                self._occluded[first : first + span] = True
                self._occlusion_left = spec.occlusion_steps - 1
        return self._occluded.copy()
