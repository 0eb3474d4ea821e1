"""The task's scale: how far starts and goals are apart, and that every goal is reachable.

    python benchmarks/task_scale.py [--backend mujoco] [--tasks single,bimanual] [--seeds 20]
                                    [--shapes random-pose|near-rest] [--json out.json]

For each task and seed s (random goals, ``env.reset(seed=s)``), three policies run one
200-step episode from the same start to the same goal:

- ``zero``: all-zero actions (do nothing). Its mean initial error is the task's scale; the
  paper's starts and goals are tens of centimetres apart (acceptance: >= 100 mm).
- ``random``: uniform random actions.
- ``oracle``: drive the grippers straight to the poses that made the goal, at no more than the
  task's maximum velocities (``dlocli.shapes.gripper_twists_towards``): proof that the goal
  is reachable within the episode, and the step at which the grippers arrive.

Also counted: episodes whose simulation diverged, and random shapes that needed more than
one simulation (an earlier one diverged and was redrawn).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from dlocli.env.shape_env import make_env
from dlocli.env.shapes import ARRIVED, gripper_twists_towards
from dlocli.specs import BackendSpec, TaskSpec


def episode(env, policy: str, seed: int) -> dict[str, float]:
    """One episode of ``policy`` from ``env.reset(seed)``: errors (mm), reward, arrival."""
    _, info = env.reset(seed=seed)
    redraws = env.shape_attempts - 1
    initial, total, arrived, diverged = info["shape_error_mm"], 0.0, -1, False
    rng = np.random.default_rng(seed)
    for t in range(env.task_spec.episode_steps):
        if policy == "oracle":
            twists = gripper_twists_towards(
                env.backend.gripper_poses(), env.goal_gripper_poses, env.task_spec, env.task.moving
            )
            if arrived < 0 and np.abs(twists).max() * env.task_spec.control_dt < ARRIVED:
                arrived = t
            action = env.task.from_grippers(twists / env._scale)
        elif policy == "random":
            action = rng.uniform(-1, 1, env.action_space.shape)
        else:
            action = np.zeros(env.action_space.shape)
        _, reward, _, _, info = env.step(action)
        total += reward
        diverged |= info["diverged"]
    return {
        "initial_mm": initial,
        "final_mm": info["shape_error_mm"],
        "reward": total,
        "arrived_step": arrived,
        "diverged": diverged,
        "redraws": redraws,
    }


def spread(values: np.ndarray) -> str:
    return f"{values.mean():7.1f} ± {values.std():5.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--backend", default="mujoco")
    parser.add_argument("--tasks", default="single,bimanual")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--shapes", default="random-pose")
    parser.add_argument("--json", default=None, help="also write the per-episode rows here")
    args = parser.parse_args()
    rows = []
    print(f"backend {args.backend}, shapes {args.shapes}, {args.seeds} seeds, random goals")
    print(
        f"{'task':9s} {'policy':7s} {'initial mm':>16s} {'final mm':>16s} {'reward':>14s} "
        f"{'diverged':>8s} {'redraws':>7s} {'arrived (step)':>16s}"
    )
    for task in args.tasks.split(","):
        task_spec = TaskSpec(name=task, goal="random", shapes=args.shapes)
        env = make_env(BackendSpec(name=args.backend), task_spec, seed=0)
        for policy in ("zero", "random", "oracle"):
            start = time.perf_counter()
            runs = [episode(env, policy, seed) for seed in range(args.seeds)]
            rows += [{"task": task, "policy": policy, "seed": s, **r} for s, r in enumerate(runs)]
            col = {key: np.array([r[key] for r in runs], dtype=float) for key in runs[0]}
            arrived = col["arrived_step"][col["arrived_step"] >= 0]
            arrival = f"{np.median(arrived):.0f} (max {arrived.max():.0f})" if arrived.size else "-"
            arrival = arrival if policy == "oracle" else ""
            print(
                f"{task:9s} {policy:7s} {spread(col['initial_mm'])} {spread(col['final_mm'])} "
                f"{spread(col['reward'])} {int(col['diverged'].sum()):5d}/{args.seeds} "
                f"{int(col['redraws'].sum()):7d} {arrival:>16s}   "
                f"({time.perf_counter() - start:.0f} s)"
            )
        env.close()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1, default=float)


if __name__ == "__main__":
    main()
