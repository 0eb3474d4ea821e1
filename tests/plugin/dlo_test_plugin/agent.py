"""A learning agent: it tries one constant action per training episode and acts with the
one whose episode returned most."""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.controllers.base import LearningAgent


class BestConstantAgent(LearningAgent):
    """The best constant action of the training episodes so far (zeros before the first)."""

    name = "best-constant"

    def __init__(self, env: Any, seed: int = 0) -> None:
        super().__init__(env, seed)
        self.rng = np.random.default_rng(seed)
        self.best = np.zeros(self.action_dim, dtype=np.float32)
        self.best_return = -np.inf
        self._obs: np.ndarray | None = None  # inside an episode: its latest observation
        self._trying = self.best
        self._return = 0.0

    def learn(self, transitions: int) -> None:
        for _ in range(transitions):
            if self._obs is None:  # a new episode, with a new action to try
                self._obs, _ = self.env.reset(seed=int(self.rng.integers(2**31)))
                self._trying = self.rng.uniform(-1, 1, self.action_dim).astype(np.float32)
                self._return = 0.0
            self._obs, reward, terminated, truncated, _ = self.env.step(self._trying)
            self._return += float(reward)
            self.transitions += 1
            if terminated or truncated:
                if self._return > self.best_return:
                    self.best, self.best_return = self._trying, self._return
                self._obs = None

    def _act(self, obs: np.ndarray) -> np.ndarray:
        return self.best
