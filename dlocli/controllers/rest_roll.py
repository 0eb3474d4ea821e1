"""The roll the rod rests best at, read from where it came to rest before.

The held-end servo (:mod:`dlocli.controllers.held_end`) reads from the goal where each moving
gripper holds the rod and which way the rod leaves it; the roll about the rod's own axis
barely shows in a goal, and a model learned from single steps barely sees it (a degree of roll
moves the rod's rest shape by about a tenth of a millimetre, a step's roll far less). Where the
rod came to rest before shows it: an online run's trials end at many rolls near the goal's
pose, and the shape each ended in says which roll rests nearest the goal.

**Rest states** (:func:`rest_states`): each episode's first state (the reset lets the rod
settle) and, where the moving grippers stood still through an episode's last
:data:`REST_WINDOW_S` seconds, the rod's mean positions over them (about one period of the
sideways swing, so the swing averages out), each with the grippers' poses. An online run's
checkpoints carry the rest states of the data they were trained on.

**The roll** (:class:`RestMap`): around the moving grippers' current poses, a locally weighted
linear map from their poses (position and rotation, in each gripper's own frame) to the rest
positions, fitted by weighted ridge least squares over the rest states; the roll offsets that
put its rest positions nearest the goal solve a small least-squares problem in the K rolls.
Where the rest states near the current poses weigh less than :data:`MIN_WEIGHT`, it says
nothing and the roll is kept.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.env.shapes import rotation_between

#: seconds at an episode's end the grippers must stand still through for a rest state
REST_WINDOW_S = 0.76
#: metres the moving grippers may move, and radians turn, through that window
STILL_M, STILL_RAD = 5e-3, np.radians(3.0)
#: kernel widths: position (m), tilt (rad, the turn about the gripper's y and z axes), roll
KERNEL_M, KERNEL_TILT, KERNEL_ROLL = 0.02, np.radians(10.0), 0.6
#: the least total kernel weight of the rest states near the current poses
MIN_WEIGHT = 5.0
#: ridge weight of the local map's slopes (m^2 per unit of feature^2)
RIDGE = 1e-6
#: the largest roll offset (rad) the map may ask for
MAX_ROLL = np.radians(45.0)


def rest_states(data: Any, moving: np.ndarray, control_dt: float) -> dict[str, np.ndarray]:
    """Rest states of a rod dataset's episodes (:class:`~dlocli.data.Dataset`). Returns
    {"grippers": (R, 2, 7), "positions": (R, N, 3)} float32."""
    window = max(int(round(REST_WINDOW_S / control_dt)), 1)
    found_grippers, found_positions = [], []
    for start, length in zip(data.state_offsets(), data.episode_lengths, strict=True):
        end = int(start + length + 1)
        found_grippers.append(data.grippers[start])
        found_positions.append(data.positions[start])
        if length >= window and _stood_still(data.grippers[end - window : end, moving]):
            found_grippers.append(data.grippers[end - 1])
            found_positions.append(data.positions[end - window : end].mean(axis=0))
    return {
        "grippers": np.asarray(found_grippers, dtype=np.float32),
        "positions": np.asarray(found_positions, dtype=np.float32),
    }


def _stood_still(poses: np.ndarray) -> bool:
    """Whether (W, K, 7) poses stay within STILL_M and STILL_RAD of the last."""
    moved = np.linalg.norm(poses[:, :, :3] - poses[-1:, :, :3], axis=-1)
    turned = np.linalg.norm(rotation_between(poses[:, :, 3:], poses[-1:, :, 3:]), axis=-1)
    return bool(moved.max() <= STILL_M and turned.max() <= STILL_RAD)


class RestMap:
    """Roll offsets for the moving grippers from rest states (see the module docstring)."""

    def __init__(self, grippers: np.ndarray, positions: np.ndarray, moving: np.ndarray) -> None:
        self.moving = np.flatnonzero(moving)
        self.poses = np.asarray(grippers, dtype=np.float64)[:, self.moving]  # (R, K, 7)
        self.frames = frame_of(self.poses[..., 3:])  # (R, K, 3, 3)
        self.shapes = np.asarray(positions, dtype=np.float64).reshape(len(self.poses), -1)

    @classmethod
    def of_model(cls, model: Any, moving: np.ndarray) -> RestMap | None:
        """The map of the rest states a planning model carries (None where it carries none)."""
        states = getattr(model, "rest_states", None)
        if not states or len(states["grippers"]) == 0:
            return None
        return cls(np.asarray(states["grippers"]), np.asarray(states["positions"]), moving)

    def roll_offsets(self, grippers: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """(K,) radians each moving gripper should turn about its own x axis so the rod rests
        nearest ``goal`` (N, 3), from the current ``grippers`` (2, 7); None where the rest
        states near these poses are too few or hold another shape than the goal's."""
        if goal.size != self.shapes.shape[1]:
            return None
        features, weights = self._local(np.asarray(grippers, dtype=np.float64)[self.moving])
        if weights.sum() < MIN_WEIGHT:
            return None
        design = np.concatenate([np.ones((len(weights), 1)), features], axis=1)
        root = np.sqrt(weights)[:, None]
        lhs, rhs = design * root, self.shapes * root
        ridge = RIDGE * np.eye(design.shape[1])
        ridge[0, 0] = 0.0  # the intercept is not shrunk
        coef = np.linalg.solve(lhs.T @ lhs + ridge, lhs.T @ rhs)  # (1 + 6K, N*3)
        rest, slopes = coef[0], coef[1 + 3 :: 6][: len(self.moving)]  # each gripper's roll row
        gram = slopes @ slopes.T + RIDGE * np.eye(len(slopes))
        offsets = np.linalg.solve(gram, slopes @ (goal.ravel() - rest))
        return np.clip(offsets, -MAX_ROLL, MAX_ROLL)

    def _local(self, current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each rest state's offsets from the ``current`` (K, 7) poses, (R, 6K): per moving
        gripper the position offset (m) then the rotation vector in the gripper's own frame
        (its x component the roll); and its kernel weight (R,)."""
        columns, distance = [], np.zeros(len(self.poses))
        for k, pose in enumerate(current):
            moved = self.poses[:, k, :3] - pose[:3]
            turned = rotation_vectors(frame_of(pose[3:]).T @ self.frames[:, k])
            columns += [moved, turned]
            distance += (moved**2).sum(axis=1) / KERNEL_M**2
            distance += (turned[:, 1:] ** 2).sum(axis=1) / KERNEL_TILT**2
            distance += turned[:, 0] ** 2 / KERNEL_ROLL**2
        return np.concatenate(columns, axis=1), np.exp(-0.5 * distance)


def frame_of(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of unit quaternions (..., 4) (w, x, y, z), in closed form
    (one call per control step: cheaper than rotating the axes one by one)."""
    w, x, y, z = np.moveaxis(quaternions, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def rotation_vectors(rotations: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (angle below pi) of rotation matrices (..., 3, 3)."""
    cosine = np.clip((np.trace(rotations, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cosine)
    skew = np.stack([rotations[..., 2, 1] - rotations[..., 1, 2],
                     rotations[..., 0, 2] - rotations[..., 2, 0],
                     rotations[..., 1, 0] - rotations[..., 0, 1]], axis=-1)  # fmt: skip
    # angle / (2 sin angle), 1/2 at no rotation
    scale = 0.5 / np.where(angle > 1e-8, np.sinc(angle / np.pi), 1.0)
    return skew * scale[..., None]
