"""Simulator throughput: env steps/s per backend and task, and our overhead over raw physics.

    python benchmarks/sim_throughput.py [--steps 400] [--backends mujoco,pybullet] [--workers]

For each backend the raw physics cost (the backend's own stepping with no Python wrapper,
``Backend.raw_physics_seconds``) and the full env step (action scaling, gripper kinematics,
observation, reward) are measured in the same run; the overhead is their ratio minus one.
With ``--workers`` it also times `collect_random` with 1 and 2 worker processes.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import dlocli
from dlocli.runs.collect import collect_random
from dlocli.specs import CollectSpec


def time_env(backend: str, task: str, steps: int) -> tuple[float, float]:
    """(env steps/s, raw physics seconds per control step) measured back to back."""
    env = dlocli.make_env(backend=backend, task=task, seed=0, episode_steps=10**6)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, env.action_space.shape[0])).astype(np.float32)
    for a in actions[:20]:  # warm-up
        env.step(a)
    start = time.perf_counter()
    for a in actions:
        env.step(a)
    env_seconds = (time.perf_counter() - start) / steps
    raw_seconds = env.backend.raw_physics_seconds(steps)
    env.close()
    return env_seconds, raw_seconds


def time_collect(workers: int, episodes: int, steps: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        spec = CollectSpec(episodes=episodes, steps=steps, workers=workers, out=Path(tmp) / "d")
        start = time.perf_counter()
        summary = collect_random(spec)
        return summary["transitions"] / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--backends", default="mujoco,pybullet")
    parser.add_argument("--workers", action="store_true", help="also time --workers 1 vs 2")
    args = parser.parse_args()
    print(f"{'backend':10} {'task':9} {'env steps/s':>12} {'raw steps/s':>12} {'overhead':>9}")
    for backend in args.backends.split(","):
        for task in ("single", "bimanual"):
            env_s, raw_s = time_env(backend, task, args.steps)
            print(
                f"{backend:10} {task:9} {1 / env_s:12.0f} {1 / raw_s:12.0f} "
                f"{100 * (env_s / raw_s - 1):8.1f}%"
            )
    if args.workers:
        one = time_collect(1, 8, 200)
        two = time_collect(2, 8, 200)
        print(
            f"collect mujoco single, 8 episodes x 200 steps: 1 worker {one:.0f} transitions/s, "
            f"2 workers {two:.0f} transitions/s, speed-up {two / one:.2f}x"
        )


if __name__ == "__main__":
    main()
