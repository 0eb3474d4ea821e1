"""The held-end servo: shape control with no model, read from the goal's held ends.

With both ends of the rod held, the shape the rod comes to rest in is decided by the grippers'
poses, and of a pose almost only by where the held end sits and which way the rod leaves it:
the roll about the rod's own axis barely shows (docs: benchmarks, the held ends decide the
shape). A goal the rod rests in shows both: the point each gripper holds and the rod's
direction there, the end tangent of the three points nearest the gripper. At every step the
servo turns each moving gripper so the observed end tangent lies along the goal's (the
smallest turn, the roll kept) and moves it so the held point lands on the goal's, at the
task's speed limits. Estimating both tangents the same way from the points observed makes
the estimate's bias cancel as the rod nears the goal.

It runs beside doing nothing and random actions as a reference (``held-end``), and the
planners' ``servo_cost`` pulls their plans towards its action in all but the roll
(:func:`without` the :func:`roll_directions`), which the model's shape cost is left to find
(or, with ``roll_search``, a search over the roll through the model picks,
:mod:`dlocli.controllers.planning`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.backends.rotations import (
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
)
from dlocli.controllers.base import Controller, Reference
from dlocli.env.shapes import gripper_twists_towards, max_twist

#: points an end tangent is estimated from
TANGENT_POINTS = 3


def end_tangent(points: np.ndarray, held: int, inward: int) -> np.ndarray:
    """The rod's direction (3,) leaving ``points[held]`` towards ``held + inward``: the
    one-sided second-order difference of three points (unnormalised)."""
    p0, p1, p2 = points[held], points[held + inward], points[held + 2 * inward]
    return (-3.0 * p0 + 4.0 * p1 - p2) / 2.0


def smallest_turn(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """The quaternion (w, x, y, z) of the smallest rotation taking direction ``start`` to
    ``end`` (identity where either has no length or they are opposite)."""
    a, b = start / np.linalg.norm(start), end / np.linalg.norm(end)
    axis = np.cross(a, b)
    sin = float(np.linalg.norm(axis))
    if not np.isfinite(sin) or sin < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return quat_from_rotvec(axis / sin * np.arctan2(sin, float(a @ b)))


def servo_targets(
    points: np.ndarray, goal: np.ndarray, grippers: np.ndarray, moving: np.ndarray
) -> np.ndarray | None:
    """(2, 7) gripper poses that put each moving gripper's held point and end tangent where
    the goal has them, from the observed ``points`` (M, 3) ordered along the rod, ``goal``
    (M, 3) and ``grippers`` (2, 7); None where the rod shows too few points or none is
    finite near a gripper."""
    if len(points) < 2 * TANGENT_POINTS or not np.isfinite(points).any():
        return None
    targets = np.array(grippers, dtype=np.float64)
    for k in np.flatnonzero(moving):
        position, orientation = targets[k, :3], targets[k, 3:]
        held = int(np.nanargmin(np.linalg.norm(points - position, axis=1)))
        inward = 1 if held < len(points) / 2 else -1
        end = held + (TANGENT_POINTS - 1) * inward
        if not (0 <= end < len(points)):
            return None
        now, wanted = end_tangent(points, held, inward), end_tangent(goal, held, inward)
        if not (np.isfinite(now).all() and np.isfinite(wanted).all()):
            return None
        offset = quat_to_matrix(orientation).T @ (points[held] - position)
        turned = quat_normalize(quat_multiply(smallest_turn(now, wanted), orientation))
        targets[k, 3:] = turned
        targets[k, :3] = goal[held] - quat_to_matrix(turned) @ offset
    return targets


def servo_action(env: Any, task: Any, obs: np.ndarray) -> np.ndarray | None:
    """The held-end servo's action (A,) in [-1, 1] for the flat observation ``obs`` of
    ``env`` (full or markers), None where it cannot read the held ends."""
    return action_of(env.split_observation(obs), env.task_spec, task)


def servo_pull(env: Any, task: Any, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The servo's action (A,) and each moving gripper's roll direction (K, A)
    (:func:`roll_directions`) for the flat observation ``obs``, from one reading of it; None
    where the held ends cannot be read."""
    parts = env.split_observation(obs)
    action = action_of(parts, env.task_spec, task)
    return None if action is None else (action, roll_directions(task, parts["grippers"]))


def action_of(parts: dict[str, np.ndarray], spec: Any, task: Any) -> np.ndarray | None:
    """:func:`servo_action` from the observation's parts and the task spec."""
    points = parts["positions"] if "positions" in parts else parts["markers"]
    if "visible" in parts:
        points = np.where(parts["visible"] > 0.5, points, np.nan)
    targets = servo_targets(points, parts["goal"], parts["grippers"], task.moving)
    if targets is None:
        return None
    twists = gripper_twists_towards(parts["grippers"], targets, spec, task.moving)
    return np.asarray(task.from_grippers(twists / max_twist(spec)), dtype=np.float64)


def roll_directions(task: Any, grippers: np.ndarray) -> np.ndarray:
    """(K, A) unit actions turning each of the K moving grippers about its own x axis (the
    rod's axis where it is held): the roll the goal barely shows, which the servo keeps
    rather than knows."""
    size, directions = int(np.asarray(task.from_grippers(np.zeros((2, 6)))).size), []
    for k in np.flatnonzero(task.moving):
        commands = np.zeros((2, 6))
        commands[k, 3:] = quat_to_matrix(np.asarray(grippers[k, 3:], dtype=np.float64))[:, 0]
        directions.append(np.asarray(task.from_grippers(commands), dtype=np.float64).ravel())
    return np.array(directions, dtype=np.float64).reshape(len(directions), size)


def without(directions: np.ndarray) -> np.ndarray:
    """(A, A) projection removing the orthonormal ``directions`` (K, A) from an action."""
    return np.eye(directions.shape[1]) - directions.T @ directions


class HeldEndServo(Controller):
    """No model: each moving gripper servoed to where the goal holds its end (a reference)."""

    name = "held-end"
    reference = Reference("held-end servo, no model", rank=2, line="-.", colour="tab:olive")

    def __init__(self, env: Any, seed: int = 0, **_: Any) -> None:
        super().__init__(env)

    def _act(self, obs: np.ndarray) -> np.ndarray:
        action = servo_action(self.env, self.task, obs)
        return np.zeros(self.action_dim) if action is None else action
