"""The controller contract shared by MPC, sampling MPC, RL agents and PILCO.

A controller is built for one environment (its task fixes the action size), is reset with a
goal shape (N,3) in metres, and maps the env's flat observation to an action in [-1, 1]^A.
``last_latency_ms`` is the wall time of the latest :meth:`act`, for live displays and the
latency statistics of ``dlo control``.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import Any

import numpy as np


class Controller(ABC):
    """Observation in, action out. Subclasses implement :meth:`_act`."""

    name: str = ""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.task = env.task
        self.action_dim = int(env.action_space.shape[0])
        self.goal: np.ndarray | None = None
        self.last_latency_ms = 0.0

    def reset(self, goal: np.ndarray) -> None:
        """Start a new episode towards ``goal`` (N,3) metres."""
        self.goal = np.asarray(goal, dtype=np.float64)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Action in [-1, 1]^A for the flat observation ``obs``; times itself."""
        start = time.perf_counter()
        action = np.clip(np.asarray(self._act(obs), dtype=np.float32), -1.0, 1.0)
        self.last_latency_ms = 1000.0 * (time.perf_counter() - start)
        return action

    @abstractmethod
    def _act(self, obs: np.ndarray) -> np.ndarray: ...


class RandomController(Controller):
    """Uniform random actions (a floor every method must beat)."""

    name = "random"

    def __init__(self, env: Any, seed: int = 0, **_: Any) -> None:
        super().__init__(env)
        self.rng = np.random.default_rng(seed)

    def _act(self, obs: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.action_dim)
