"""The safety envelope every controller's gripper commands pass through, in one place (the
env's step): speed and acceleration limits and a workspace box per gripper, on top of the
task's workspace and separation limits, which the backend (or the cell) keeps. A command
that would break a limit is clipped and counted; the counts go into the run's summary.

With its defaults the envelope clips nothing beyond what the task always kept: runs without
one are bit for bit what they were.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from dlocli.backends.base import GripperLimits
from dlocli.errors import BadInput
from dlocli.specs import EnvelopeSpec

LINEAR, ANGULAR = slice(0, 3), slice(3, 6)
#: the envelope's limits, in the order they are applied; the counts' keys
LIMITS = ("tracking_lost", "speed", "acceleration", "gripper_workspace", "workspace", "separation")


class Envelope:
    """Clips (2,6) gripper twists to an :class:`EnvelopeSpec` and counts what it clipped
    (and what the task's workspace and separation limits will clip)."""

    def __init__(
        self, spec: EnvelopeSpec, limits: GripperLimits, moving: np.ndarray, dt: float
    ) -> None:
        self.spec, self.limits, self.moving, self.dt = spec, limits, moving, dt
        self.boxes = [
            None if getattr(spec, f"{side}_low") is None
            else (np.array(getattr(spec, f"{side}_low")), np.array(getattr(spec, f"{side}_high")))
            for side in ("left", "right")
        ]  # fmt: skip
        self.counts: Counter[str] = Counter()
        self.previous = np.zeros((2, 6))
        self.lost_s = 0.0  # how long the cable's tracking has been lost
        self.active = any(value is not None for value in spec.model_dump().values())

    def reset(self) -> None:
        """A new episode: the grippers start at rest."""
        self.previous = np.zeros((2, 6))
        self.lost_s = 0.0

    def check_start(self, poses: np.ndarray) -> None:
        """BadInput if a moving gripper starts outside its own box."""
        for gripper, box in enumerate(self.boxes):
            if box is None or not self.moving[gripper]:
                continue
            position = poses[gripper, :3]
            if np.any(position < box[0]) or np.any(position > box[1]):
                side = ("left", "right")[gripper]
                raise BadInput(
                    f"the {side} gripper starts at {np.round(position, 3).tolist()} m, outside "
                    f"its envelope box {box[0].tolist()}..{box[1].tolist()}: widen the box"
                )

    def apply(self, velocities: np.ndarray, poses: np.ndarray, tracked: bool = True) -> np.ndarray:
        """The twists to send: ``velocities`` itself when no limit is broken. ``tracked``:
        whether the observation the command was computed from saw the cable."""
        if self.active:
            clipped = velocities.copy()
            self._stop_when_lost(clipped, tracked)
            self._limit_speed(clipped)
            self._limit_acceleration(clipped)
            self._keep_in_boxes(clipped, poses)
            if not np.array_equal(clipped, velocities):
                velocities = clipped
        self._count_task_limits(velocities, poses)
        self.previous = velocities
        return velocities

    # ------------------------------------------------------------------ the limits
    def _stop_when_lost(self, twist: np.ndarray, tracked: bool) -> None:
        self.lost_s = 0.0 if tracked else self.lost_s + self.dt
        limit = self.spec.stop_after_lost_s
        if limit is not None and self.lost_s > limit:
            twist[:] = 0.0  # the limits below see a stop, which breaks none of them
            self.counts["tracking_lost"] += 1

    def _limit_speed(self, twist: np.ndarray) -> None:
        clipped = False
        for part, limit in ((LINEAR, self.spec.max_linear_speed),
                            (ANGULAR, self.spec.max_angular_speed)):  # fmt: skip
            if limit is not None:
                clipped |= _clip_norms(twist[:, part], limit)
        self.counts["speed"] += clipped

    def _limit_acceleration(self, twist: np.ndarray) -> None:
        clipped = False
        for part, limit in ((LINEAR, self.spec.max_linear_acceleration),
                            (ANGULAR, self.spec.max_angular_acceleration)):  # fmt: skip
            if limit is None:
                continue
            change = twist[:, part] - self.previous[:, part]
            if _clip_norms(change, limit * self.dt):
                twist[:, part] = self.previous[:, part] + change
                clipped = True
        self.counts["acceleration"] += clipped

    def _keep_in_boxes(self, twist: np.ndarray, poses: np.ndarray) -> None:
        for gripper, box in enumerate(self.boxes):
            if box is None:
                continue
            position = poses[gripper, :3]
            lowest, highest = (box[0] - position) / self.dt, (box[1] - position) / self.dt
            inside = np.clip(twist[gripper, :3], lowest, highest)
            if not np.array_equal(inside, twist[gripper, :3]):
                twist[gripper, :3] = inside
                self.counts["gripper_workspace"] += 1

    def _count_task_limits(self, twist: np.ndarray, poses: np.ndarray) -> None:
        """Counts the steps the backend's own workspace and separation limits will clip."""
        ends = poses[:, :3] + np.where(self.moving[:, None], twist[:, :3] * self.dt, 0.0)
        if np.any((ends < self.limits.low) | (ends > self.limits.high)):
            self.counts["workspace"] += 1
        if self.moving.all():
            separation = float(np.linalg.norm(ends[1] - ends[0]))
            if not self.limits.min_separation <= separation <= self.limits.max_separation:
                self.counts["separation"] += 1

    def summary(self) -> dict[str, int]:
        """Steps clipped by each limit since the env was made."""
        return {f"clipped_{name}": self.counts[name] for name in LIMITS}


def _clip_norms(rows: np.ndarray, limit: float) -> bool:
    """Scale each row of ``rows`` (in place) down to norm ``limit``; True if any was."""
    norms = np.linalg.norm(rows, axis=1)
    over = norms > limit
    if over.any():
        rows[over] *= (limit / norms[over])[:, None]
    return bool(over.any())
