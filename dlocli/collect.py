"""Random-action data collection (``dlo collect --random``), in one or several processes.

Every episode's randomness comes from ``(seed, episode index)`` only, so any number of
workers produce the same dataset as one worker. Random actions are uniform in [-1, 1] and
held for a random 1..``MAX_HOLD`` control steps, which explores further than white noise.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.data import DATASET_FILE, Dataset, Episode
from dlocli.env import DLOShapeEnv, make_env_from_spec
from dlocli.io import prepare_run_dir, versions, write_json_atomic
from dlocli.specs import CollectSpec, EnvSpec

MAX_HOLD = 10


def episode_seed(seed: int, episode: int) -> int:
    """Independent, reproducible seed of one episode."""
    return int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])


def random_actions(rng: np.random.Generator, steps: int, action_dim: int) -> np.ndarray:
    """(steps, action_dim) uniform actions, each held for 1..MAX_HOLD steps."""
    actions = np.empty((steps, action_dim), dtype=np.float32)
    t = 0
    while t < steps:
        hold = int(rng.integers(1, MAX_HOLD + 1))
        actions[t : t + hold] = rng.uniform(-1.0, 1.0, action_dim)
        t += hold
    return actions


def run_episode(
    env: DLOShapeEnv, seed: int, actions: np.ndarray | Callable[[np.ndarray], np.ndarray]
) -> Episode:
    """Run one episode from ``env.reset(seed)``; ``actions`` is an array or a policy(obs).

    A step on which the physics diverged ends the episode and is not recorded.
    """
    obs, _ = env.reset(seed=seed)
    steps = len(actions) if isinstance(actions, np.ndarray) else env.task_spec.episode_steps
    n = env.n_segments
    pos, quat, grip = [], [], []
    commands, rewards = [], []

    def record(o: np.ndarray) -> None:
        parts = env.split_observation(o)
        pos.append(parts["positions"])
        quat.append(parts["quaternions"])
        grip.append(parts["grippers"])

    record(obs)
    diverged = False
    for t in range(steps):
        action = actions[t] if isinstance(actions, np.ndarray) else actions(obs)
        obs, reward, terminated, _, info = env.step(action)
        if info["diverged"]:
            diverged = True
            break
        record(obs)
        commands.append(info["commands"])
        rewards.append(reward)
        if terminated:
            break
    return Episode(
        positions=np.array(pos).reshape(-1, n, 3),
        quaternions=np.array(quat).reshape(-1, n, 4),
        grippers=np.array(grip).reshape(-1, 2, 7),
        actions=np.array(commands, dtype=np.float32).reshape(-1, 2, 6),
        rewards=np.array(rewards, dtype=np.float32),
        goal=np.asarray(env.goal),
        diverged=diverged,
    )


# One env per worker process, built once (the goal is derived from the spec's seed, so every
# worker has the same fixed goal).
_worker_env: DLOShapeEnv | None = None
_worker_spec: CollectSpec | None = None


def _init_worker(spec_json: str) -> None:
    global _worker_env, _worker_spec
    _worker_spec = CollectSpec.model_validate_json(spec_json)
    _worker_env = make_env_from_spec(_worker_spec)


def _collect_one(episode: int) -> Episode:
    assert _worker_env is not None and _worker_spec is not None
    seed = episode_seed(_worker_spec.seed, episode)
    rng = np.random.default_rng([_worker_spec.seed, episode, 7])
    actions = random_actions(rng, _worker_spec.steps, _worker_env.action_space.shape[0])
    return run_episode(_worker_env, seed, actions)


def _episodes(spec: CollectSpec) -> Iterator[Episode]:
    """Yield episodes in index order, from this process or a pool."""
    if spec.workers == 1:
        _init_worker(spec.model_dump_json())
        for e in range(spec.episodes):
            yield _collect_one(e)
        return
    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    ctx = mp.get_context(method)
    with ctx.Pool(spec.workers, _init_worker, (spec.model_dump_json(),)) as pool:
        yield from pool.imap(_collect_one, range(spec.episodes), chunksize=1)


def dataset_attrs(spec: EnvSpec) -> dict[str, Any]:
    return {
        "spec": spec.model_dump(mode="json"),
        "backend": spec.backend.name,
        "task": spec.task.name,
        "rod": spec.backend.rod.model_dump(mode="json"),
        "versions": versions(),
        "max_linear_velocity": spec.task.max_linear_velocity,
        "max_angular_velocity": spec.task.max_angular_velocity,
    }


def collect_random(
    spec: CollectSpec,
    overwrite: bool = False,
    on_episode: Callable[[int, Episode], None] | None = None,
) -> dict[str, Any]:
    """Collect ``spec.episodes`` random episodes into ``spec.out/dataset.h5``; return a summary.

    On KeyboardInterrupt the finished episodes are saved (atomically) before re-raising.
    """
    out = prepare_run_dir(spec.out, overwrite)
    spec = spec.model_copy(
        update={"task": spec.task.model_copy(update={"episode_steps": spec.steps})}
    )
    write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
    start = time.perf_counter()
    episodes: list[Episode] = []
    try:
        for i, episode in enumerate(_episodes(spec)):
            episodes.append(episode)
            if on_episode is not None:
                on_episode(i, episode)
    finally:
        if episodes:
            Dataset.from_episodes(episodes, dataset_attrs(spec)).save(out / DATASET_FILE)
    seconds = time.perf_counter() - start
    transitions = sum(len(e) for e in episodes)
    summary = {
        "episodes": len(episodes),
        "transitions": transitions,
        "diverged_episodes": sum(e.diverged for e in episodes),
        "seconds": round(seconds, 3),
        "transitions_per_s": round(transitions / seconds, 1) if seconds > 0 else None,
        "workers": spec.workers,
        "path": str(Path(out) / DATASET_FILE),
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
