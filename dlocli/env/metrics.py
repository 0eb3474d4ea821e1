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


def diverged_remainder(steps_run: int, episode_steps: int) -> float:
    """Reward of the steps a diverged episode did not run: the clip, -1.5, for each, so that
    blowing the simulation up never scores better than trying."""
    return -REWARD_CLIP * max(episode_steps - steps_run, 0)


def score(initial_error: float, final_error: float) -> float:
    """The fraction of the initial error closed, ``1 - final/initial``: 1 = on the goal,
    0 = no better than doing nothing, negative = worse."""
    return float(1.0 - final_error / initial_error) if initial_error > 0 else 0.0


def episode_result(
    initial_error: float,
    final_error: float,
    reward_sum: float,
    steps_run: int,
    steps: int,
    *,
    diverged: bool,
) -> dict[str, float]:
    """One episode's numbers with their reference: initial and final error (mm), the score,
    and the cumulative reward: ``reward_sum`` of the ``steps_run`` steps run, plus, only if
    the rod ``diverged``, the steps of ``steps`` it skipped at the clip. An episode stopped
    early (Ctrl-C, SIGTERM, a lost cell) is charged nothing for the steps it never ran."""
    remainder = diverged_remainder(steps_run, steps) if diverged else 0.0
    return {
        "initial_error_mm": float(initial_error),
        "final_error_mm": float(final_error),
        "score": score(initial_error, final_error),
        "cumulative_reward": float(reward_sum) + remainder,
    }
