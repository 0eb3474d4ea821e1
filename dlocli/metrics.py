"""Shape error and reward (paper eq. 12), shared by the env, the planners and evaluation."""

from __future__ import annotations

import numpy as np

REWARD_CLIP = 1.5


def shape_distance(positions: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """||p - p_goal||_2 over all segment coordinates, (...,N,3) -> (...)."""
    diff = np.asarray(positions, dtype=np.float64) - np.asarray(goal, dtype=np.float64)
    return np.sqrt(np.sum(diff**2, axis=(-2, -1)))


def reward(positions: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Paper eq. 12: r = -||p_{t+1} - p_goal||_2, clipped to [-1.5, 0]."""
    return -np.minimum(shape_distance(positions, goal), REWARD_CLIP)


def shape_error_mm(positions: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Mean over segments of the Euclidean distance to the goal, in millimetres."""
    diff = np.asarray(positions, dtype=np.float64) - np.asarray(goal, dtype=np.float64)
    return 1000.0 * np.mean(np.linalg.norm(diff, axis=-1), axis=-1)
