"""Random-action data collection (``dlo collect --random``), in one or several processes.

Every episode's randomness comes from ``(seed, episode index)`` only, so any number of
workers produce the same dataset as one worker. The episodes are
:func:`dlocli.rollout.random_episode`.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from dlocli.data import DATASET_FILE, Dataset, Episode
from dlocli.env.rollout import random_episode, stream_seed
from dlocli.env.shape_env import DLOShapeEnv, make_env_from_spec
from dlocli.io import prepare_run_dir, versions, write_json_atomic
from dlocli.specs import CollectSpec, EnvSpec

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
    seed = _worker_spec.seed
    return random_episode(_worker_env, stream_seed(seed, episode), [seed, episode, 7])


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
