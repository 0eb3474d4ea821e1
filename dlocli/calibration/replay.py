"""Replay a recorded cable motion on a simulated rod and score it with the DEFORM protocol.

The simulated rod is the cable between its grip points (what lies beyond them is in the
grippers): its length is the markers' mean polyline length between them over the given
recordings, its linear density the real cable's (mass / length). Where a gripper holds the
rod depends on the rod's clamp (:func:`grip_markers`): a rigid clamp makes the end segment
part of the gripper, so the grip is at the end markers and the held pair lies in that
segment; a half-segment clamp lets the rod bend at the grip, so the grip is where the real
cable leaves the gripper, at the inner held marker, and the outer one rides on the gripper.
Marker i is read off the rod at the arc length of the mean marker spacing from the left
grip to i (negative for a marker behind the left grip).

Each gripper follows its grip marker (position) and the direction of its held marker pair
(the rod's axis at that end). The roll about that axis is not recorded; it is chosen by a
:data:`ROLLS` rule. The recording is shifted into the backend's workspace
(physics does not depend on where the rod is: there is no floor) and shifted back.

The rod starts at rest: from the backend's rest state the grippers move to the recording's
frame-0 poses in ``approach_s`` and hold still for ``settle_s``; the recorded cable is
moving at frame 0, the simulated one is not (the start's cost is measured: ``start_error``).
Then the grippers follow the recording frame by frame at its rate, and the predicted
markers are scored against the recorded ones (held markers overwritten with their recorded
positions, as the protocol gives them).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dlocli.backends.base import Backend, GripperLimits
from dlocli.backends.rotations import quat_from_rotvec, quat_multiply, quat_normalize, quat_rotate
from dlocli.data import protocol
from dlocli.errors import BadInput
from dlocli.recorded_cables.deform import held_markers

WORKSPACE_MARGIN = 0.1  # m around the recorded gripper positions
#: closest two held markers at one end may be (m): the gripper's axis runs through them
#: (DEFORM's come no closer than 14 mm)
MIN_PAIR_GAP = 1e-3
X_AXIS = np.array([1.0, 0.0, 0.0])
Z_AXIS = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- rod geometry
def grip_markers(held: np.ndarray, clamp_compliance: str) -> tuple[int, int]:
    """The markers the left and right grippers hold the rod at (see the module doc), given
    the (V,) held mask: the end markers, or the innermost of each end's held run."""
    n_markers = len(held)
    if clamp_compliance == "rigid":
        return 0, n_markers - 1
    free = np.flatnonzero(~np.asarray(held, dtype=bool))
    if len(free) == 0:
        return 0, n_markers - 1
    return max(int(free[0]) - 1, 0), min(int(free[-1]) + 1, n_markers - 1)


@dataclass(frozen=True)
class RecordedArcs:
    """Where the recorded markers sit along the cable, as the recordings measure it: arc
    lengths (m) from marker 0 (where markers sit on a simulated rod: ``MarkerLayout``)."""

    arc: np.ndarray

    @property
    def rod_length(self) -> float:
        return float(self.arc[-1])

    @classmethod
    def from_recordings(cls, recordings: list[np.ndarray]) -> RecordedArcs:
        """Mean marker spacing over every frame of (T,V,3) recordings."""
        frames = np.concatenate(recordings)
        spacing = np.linalg.norm(np.diff(frames, axis=1), axis=-1).mean(0)
        return cls(np.concatenate([[0.0], np.cumsum(spacing)]))

    def between(self, grip: tuple[int, int]) -> RecordedArcs:
        """Arc lengths from the left grip marker (the rod's length: up to the right one)."""
        return RecordedArcs(self.arc - self.arc[grip[0]])

    def span(self, grip: tuple[int, int]) -> float:
        """The rod's length between the grip markers (m)."""
        return float(self.arc[grip[1]] - self.arc[grip[0]])


def check_rod_fits(
    rod_length: float, recordings: list[np.ndarray], names: list[str], grip: tuple[int, int]
) -> None:
    """BadInput if a rod of ``rod_length`` cannot span the recorded grip markers."""
    for name, rec in zip(names, recordings, strict=True):
        span = float(np.linalg.norm(rec[:, grip[1]] - rec[:, grip[0]], axis=-1).max())
        if span >= rod_length:
            raise BadInput(
                f"the rod ({rod_length:.3f} m) is shorter than the grip markers' separation "
                f"in {name} ({span:.3f} m); pass a --rod-length above that (the cable between "
                "its grip markers)"
            )


def check_end_pairs(recordings: list[np.ndarray], names: list[str]) -> None:
    """BadInput if the two markers at an end of a recording come closer than MIN_PAIR_GAP
    in some frame: the gripper's axis runs through them (:func:`gripper_targets`)."""
    for name, rec in zip(names, recordings, strict=True):
        last = rec.shape[1] - 1
        for side, (a, b) in (("left", (0, 1)), ("right", (last - 1, last))):
            gaps = np.linalg.norm(rec[:, b] - rec[:, a], axis=-1)
            if gaps.min() < MIN_PAIR_GAP:
                raise BadInput(
                    f"{name}: its {side} end markers {a} and {b} coincide in frame "
                    f"{int(gaps.argmin())} ({gaps.min() * 1e3:.2f} mm apart), so the gripper "
                    "there has no direction; fix the recording's markers or move it out of "
                    "the source folder"
                )


def markers_on_rod(backend: Backend, arc: np.ndarray) -> np.ndarray:
    """(V,3) points of the simulated rod at arc lengths ``arc`` (m) from its left grip; a
    point behind a grip (arc < 0 or > the rod's length) rides on that gripper's x axis."""
    centres = backend.segment_positions()
    axes = quat_rotate(backend.segment_quaternions(), X_AXIS)
    seg = backend.rod.segment_length
    index = np.clip((arc // seg).astype(int), 0, len(centres) - 1)
    along = arc - (index + 0.5) * seg
    points = centres[index] + along[:, None] * axes[index]
    grippers = backend.gripper_poses()
    gripper_x = quat_rotate(grippers[:, 3:], X_AXIS)
    tolerance = 1e-9 * seg  # the right grip marker's arc is the rod's length up to rounding
    behind_left, behind_right = arc < -tolerance, arc > backend.rod.length + tolerance
    points[behind_left] = grippers[0, :3] + arc[behind_left, None] * gripper_x[0]
    beyond = arc[behind_right, None] - backend.rod.length
    points[behind_right] = grippers[1, :3] + beyond * gripper_x[1]
    return points


# --------------------------------------------------------------------------- gripper poses
def _frame_quat(x: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """(...,4) quaternions of frames with x axis ``x`` and z axis nearest ``up_hint``."""
    y = np.cross(up_hint, x)
    y /= np.linalg.norm(y, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return _matrix_to_quat(np.stack([x, y, z], axis=-1))


def _matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(...,3,3) rotation matrices -> (...,4) unit quaternions (w,x,y,z), w >= 0."""
    w = np.sqrt(np.maximum(0.0, 1.0 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2])) / 2
    x = np.sqrt(np.maximum(0.0, 1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2])) / 2
    y = np.sqrt(np.maximum(0.0, 1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2])) / 2
    z = np.sqrt(np.maximum(0.0, 1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2])) / 2
    x = np.copysign(x, m[..., 2, 1] - m[..., 1, 2])
    y = np.copysign(y, m[..., 0, 2] - m[..., 2, 0])
    z = np.copysign(z, m[..., 1, 0] - m[..., 0, 1])
    return quat_normalize(np.stack([w, x, y, z], axis=-1))


def level_roll(axes: np.ndarray) -> np.ndarray:
    """(T,4) orientations with x along ``axes`` (T,3) and y horizontal (z as up as it goes)."""
    return _frame_quat(axes, np.broadcast_to(Z_AXIS, axes.shape))


def transported_roll(axes: np.ndarray) -> np.ndarray:
    """(T,4) orientations: level at frame 0, then each frame the smallest rotation that
    turns the previous axis into the next (no spin about the axis: parallel transport)."""
    quats = np.empty((len(axes), 4))
    quats[0] = level_roll(axes[:1])[0]
    cross = np.cross(axes[:-1], axes[1:])
    sin = np.linalg.norm(cross, axis=-1, keepdims=True)
    angle = np.arctan2(sin, np.einsum("ij,ij->i", axes[:-1], axes[1:])[:, None])
    turns = quat_from_rotvec(np.where(sin > 1e-12, cross / np.maximum(sin, 1e-12), 0) * angle)
    for t, turn in enumerate(turns, start=1):
        quats[t] = quat_normalize(quat_multiply(turn, quats[t - 1]))
    return quats


#: how the unrecorded roll of each gripper about the rod axis is chosen
ROLLS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "level": level_roll,
    "transported": transported_roll,
}


def gripper_targets(
    recording: np.ndarray, roll: str, grip: tuple[int, int] | None = None
) -> np.ndarray:
    """(T,2,7) gripper poses following a (T,V,3) recording: positions of the ``grip``
    markers (default: the end markers), x axes along each end's held pair, from the left
    end into the rod and from the rod into the right end."""
    grip = grip or (0, recording.shape[1] - 1)
    left_axis = recording[:, 1] - recording[:, 0]
    right_axis = recording[:, -1] - recording[:, -2]
    poses = np.empty((len(recording), 2, 7))
    for side, (position, axis) in enumerate(
        [(recording[:, grip[0]], left_axis), (recording[:, grip[1]], right_axis)]
    ):
        axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        poses[:, side, :3] = position
        poses[:, side, 3:] = ROLLS[roll](axis)
    return poses


def twist_to(current: np.ndarray, target: np.ndarray, dt: float) -> np.ndarray:
    """(2,6) twists that move (2,7) gripper poses ``current`` onto ``target`` in ``dt``."""
    linear = (target[:, :3] - current[:, :3]) / dt
    conj = current[:, 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    delta = quat_multiply(target[:, 3:], conj)  # world-frame rotation current -> target
    delta *= np.copysign(1.0, delta[:, :1])
    sin = np.linalg.norm(delta[:, 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin, delta[:, :1])
    rotvec = np.where(sin > 1e-12, delta[:, 1:] / np.maximum(sin, 1e-12), 0.0) * angle
    return np.concatenate([linear, rotvec / dt], axis=1)


def _interpolate(start: np.ndarray, end: np.ndarray, fraction: float) -> np.ndarray:
    """(2,7) poses a ``fraction`` of the way (positions linearly, orientations by nlerp)."""
    end = end.copy()
    flip = np.einsum("ij,ij->i", start[:, 3:], end[:, 3:]) < 0
    end[flip, 3:] *= -1
    out = start + fraction * (end - start)
    out[:, 3:] = quat_normalize(out[:, 3:])
    return out


# --------------------------------------------------------------------------- replay
@dataclass
class Replay:
    """One replayed recording, in the recording's frame: the simulated markers (T,V,3), the
    protocol's prediction (held markers and frames 0-1 as recorded), and what it cost to
    start and to follow."""

    simulated: np.ndarray
    predicted: np.ndarray
    score_cm: float
    start_error_mm: float  # free markers at frame 0, settled rod vs recording
    held_error_mm: float  # simulated held markers vs recorded, mean over frames
    diverged_at: int | None  # first frame the simulation failed, if it did


@dataclass(frozen=True)
class ReplaySettings:
    """How a recording is replayed (the rod and backend are given separately)."""

    roll: str = "transported"
    approach_s: float = 1.0
    settle_s: float = 1.0
    #: (V,) which markers the grippers hold; None: DEFORM's two at each end
    held: tuple[bool, ...] | None = None

    def held_mask(self, n_markers: int) -> np.ndarray:
        return held_markers(n_markers) if self.held is None else np.array(self.held, dtype=bool)


def workspace_offset(recording: np.ndarray, backend: Backend) -> np.ndarray:
    """Shift (3,) that centres the recorded end markers at the backend's rest height."""
    return centring_offset(recording[:, [0, -1]].reshape(-1, 3), backend.rest_height)


def centring_offset(points: np.ndarray, height: float) -> np.ndarray:
    """Shift (3,) that puts the centre of the box around ``points`` (N,3) at (0, 0, height)."""
    centre = 0.5 * (points.min(0) + points.max(0))
    return np.array([0.0, 0.0, height]) - centre


def fit_limits(targets: np.ndarray, rod_length: float) -> GripperLimits:
    """Limits that let the grippers go wherever the (shifted) recording goes."""
    positions = targets[..., :3].reshape(-1, 3)
    return GripperLimits(
        low=positions.min(0) - WORKSPACE_MARGIN,
        high=positions.max(0) + WORKSPACE_MARGIN,
        min_separation=0.0,
        max_separation=rod_length,
    )


def replay(
    backend: Backend, recording: np.ndarray, arc: np.ndarray, settings: ReplaySettings
) -> Replay:
    """Drive ``backend`` with a (T,V,3) recording's held-marker motion (see module doc).

    The backend's control period must be the recording's frame period; ``arc`` is measured
    from the left grip marker (:meth:`RecordedArcs.between`)."""
    dt = backend.control_dt
    offset = workspace_offset(recording, backend)
    held = settings.held_mask(recording.shape[1])
    grip = grip_markers(held, backend.rod.clamp_compliance)
    targets = gripper_targets(recording + offset, settings.roll, grip)
    backend.reset()
    backend.limits = fit_limits(np.concatenate([targets, backend.gripper_poses()[None]]), arc[-1])
    _approach(backend, targets[0], settings, dt)
    predicted = np.empty_like(recording)
    predicted[0] = markers_on_rod(backend, arc) - offset
    diverged_at = None
    for t in range(1, len(recording)):
        if diverged_at is None and backend.step(twist_to(backend.gripper_poses(), targets[t], dt)):
            predicted[t] = markers_on_rod(backend, arc) - offset
        else:
            diverged_at = t if diverged_at is None else diverged_at
            predicted[t] = predicted[t - 1]
    held_error = np.linalg.norm(predicted[:, held] - recording[:, held], axis=-1).mean() * 1e3
    start_error = np.linalg.norm(predicted[0, ~held] - recording[0, ~held], axis=-1).mean() * 1e3
    scored = predicted.copy()
    scored[:, held] = recording[:, held]
    scored[:2] = recording[:2]  # frames 0 and 1 are given by the protocol
    return Replay(
        simulated=predicted,
        predicted=scored,
        score_cm=protocol.deform_score_cm(scored, recording),
        start_error_mm=float(start_error),
        held_error_mm=float(held_error),
        diverged_at=diverged_at,
    )


def _approach(backend: Backend, first: np.ndarray, settings: ReplaySettings, dt: float) -> None:
    """Move the grippers from rest to ``first`` (2,7), then hold still: the rod at rest."""
    start = backend.gripper_poses()
    steps = max(1, math.ceil(settings.approach_s / dt))
    for k in range(1, steps + 1):
        target = _interpolate(start, first, k / steps)
        backend.step(twist_to(backend.gripper_poses(), target, dt))
    still = np.zeros((2, 6))
    for _ in range(math.ceil(settings.settle_s / dt)):
        backend.step(still)
