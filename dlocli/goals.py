"""Reachable goal shapes (``dlo goal``): move the grippers from rest, let the rod settle."""

from __future__ import annotations

import numpy as np

from dlocli.env import make_env_from_spec
from dlocli.io import atomic_path
from dlocli.specs import GoalSpec


def make_goal(spec: GoalSpec) -> np.ndarray:
    """The (N,3) goal the env would use as its fixed goal for ``spec.seed``."""
    env = make_env_from_spec(
        spec.model_copy(
            update={"task": spec.task.model_copy(update={"goal": "fixed", "goal_file": None})}
        )
    )
    try:
        return np.asarray(env.goal, dtype=np.float64)
    finally:
        env.close()


def save_goal(goal: np.ndarray, path) -> None:
    """Write the goal .npy atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, goal)
