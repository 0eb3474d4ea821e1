"""The references of an online run: what the registered reference controllers (doing
nothing, uniform random actions, the held-end servo) get from exactly the starts and goals of
its MPC trials.

A learning curve means little without them: on a task whose start and goal are close, doing
nothing already ends near the goal. Every trial (k, j) starts from ``env.reset(seed=stream_seed
(seed, TRIAL, k, j))``; each reference controller runs one episode from the same reset, so its
initial error is the trial's. The results live in one JSON file in the run directory, written
atomically after each iteration, so they resume like the trials. They cost simulation only,
one episode per reference and trial, shared among the trial workers.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.controllers.base import make_controller, references
from dlocli.env.rollout import episode_scores, rollout
from dlocli.io import read_json, write_json_atomic


def reference_episode_scores(
    env: Any, name: str, reset_seed: int, action_seed: int
) -> dict[str, float]:
    """Scores (:func:`episode_scores`) and seconds of one episode of the registered
    controller ``name`` from ``env.reset(seed=reset_seed)``."""
    start = time.perf_counter()
    controller = make_controller(name, env, seed=action_seed)
    episode = rollout(env, controller, reset_seed)
    scores = episode_scores(episode, env.task_spec.episode_steps)
    return {**scores, "seconds": round(time.perf_counter() - start, 3)}


class ReferenceTable:
    """``{name: {"k/j": scores}}`` of the reference episodes, kept in ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        try:
            self.table: dict[str, dict[str, dict[str, float]]] = read_json(self.path, dict)
        except FileNotFoundError:
            self.table = {}

    @staticmethod
    def key(k: int, j: int) -> str:
        return f"{k}/{j}"

    def missing(self, k: int, trials: int) -> list[tuple[str, int]]:
        """The (reference, trial) pairs of iteration ``k`` not yet run."""
        return [
            (name, j)
            for name in references()
            for j in range(1, trials + 1)
            if self.key(k, j) not in self.table.get(name, {})
        ]

    def add(self, name: str, k: int, j: int, scores: dict[str, float]) -> None:
        self.table.setdefault(name, {})[self.key(k, j)] = scores

    def save(self) -> None:
        write_json_atomic(self.path, self.table)

    def iteration(self, name: str, k: int, trials: int) -> dict[str, float] | None:
        """Mean final error (mm) and cumulative reward of ``name`` over iteration ``k``'s
        trials; None until all of them ran."""
        runs = self.table.get(name, {})
        found = [runs.get(self.key(k, j)) for j in range(1, trials + 1)]
        if any(r is None for r in found):
            return None
        return {
            f"{name}_final_error_mm_mean": float(np.mean([r["final_error_mm"] for r in found])),
            f"{name}_cumulative_reward_mean": float(
                np.mean([r["cumulative_reward"] for r in found])
            ),
        }

    def seconds(self) -> float:
        return float(sum(r["seconds"] for runs in self.table.values() for r in runs.values()))
