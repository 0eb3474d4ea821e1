"""How a `dlo online` run's model answers the moving gripper's motions, against the rod.

    python benchmarks/model_response.py RUN [--iteration K] [--trials N] [--rates 0.3,1]
                                            [--json FILE]

From iteration K's first N trial starts, the grippers go to the goal's own poses (no model,
PRE steps at the task's speed limits), then one motion of the moving gripper at a rate (a
share of the task's largest speed, either sign) for MOVE steps, then STILL steps standing
still; the same start standing still throughout is the baseline. A motion's effect is the
positions' difference from the baseline, in the simulator and in the model's open-loop
prediction from the same state under the same commands. Per motion (``roll``: about the
gripper's own x axis, the rod's where it is held; ``tilt``: about its z axis; ``move``: along
the world's y) and rate, at the motion's end and after standing still: the true and the
predicted effect (mean over segments, mm), their cosine (1: the model moves the rod the way
the rod moves) and the gain (the prediction's component along the truth, 1: as far). A
planner that trusts the model for a motion needs a positive cosine there.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

PRE, MOVE, STILL = 150, 30, 30  # control steps
MOTIONS = ("roll", "tilt", "move")


def motion_action(env: Any, motion: str, rate: float) -> np.ndarray:
    """The task action (A,) turning or moving the moving gripper at ``rate``."""
    from dlocli.backends.rotations import quat_to_matrix

    gripper = int(np.flatnonzero(env.task.moving)[0])
    frame = quat_to_matrix(np.asarray(env.backend.gripper_poses()[gripper, 3:], dtype=float))
    commands = np.zeros((2, 6))
    if motion == "move":
        commands[gripper, 1] = rate
    else:
        commands[gripper, 3:] = rate * frame[:, 0 if motion == "roll" else 2]
    return np.asarray(env.task.from_grippers(commands), dtype=np.float64).ravel()


def episode(env: Any, model: Any, seed: int, motion: str | None, rate: float) -> tuple:
    """(true, predicted) positions (MOVE + STILL, N, 3) after the grippers reach the goal's
    poses from the start ``seed`` (``motion`` None: standing still)."""
    import torch

    from dlocli.env.shapes import gripper_twists_towards, max_twist

    env.reset(seed=seed)
    task, targets = env.task_spec, env.goal_gripper_poses
    states = []
    for _ in range(PRE):
        twists = gripper_twists_towards(env.backend.gripper_poses(), targets, task, env.task.moving)
        env.step(env.task.from_grippers(twists / max_twist(task)))
        parts = env.state_parts()
        states.append(np.concatenate([parts["positions"], parts["quaternions"]], -1))
    still = np.zeros(env.action_space.shape)
    action = still if motion is None else motion_action(env, motion, rate)
    actions = [action] * MOVE + [still] * STILL
    true = []
    for a in actions:
        env.step(a)
        true.append(env.state_parts()["positions"])
    tensor = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    commands = env.task.to_grippers(tensor(np.stack(actions)))[None]  # (1, T, 2, 6)
    with torch.no_grad():
        predicted = model.rollout(tensor(states[-1])[None], commands, tensor(states[-2])[None])
    return np.array(true), predicted[0, ..., :3].numpy()


def compare(true: np.ndarray, predicted: np.ndarray) -> dict[str, float]:
    """Effects (N, 3), true and predicted: their sizes (mm), cosine and gain."""
    t, p = true.ravel(), predicted.ravel()
    return {
        "true_mm": 1000.0 * float(np.linalg.norm(true, axis=1).mean()),
        "predicted_mm": 1000.0 * float(np.linalg.norm(predicted, axis=1).mean()),
        "cosine": float(t @ p / max(np.linalg.norm(t) * np.linalg.norm(p), 1e-18)),
        "gain": float(t @ p / max(t @ t, 1e-18)),
    }


def response_report(run: Path, k: int, n: int, rates: list[float]) -> dict[str, Any]:
    import torch

    from dlocli.env.rollout import stream_seed
    from dlocli.env.shape_env import make_env_from_spec
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.resume import load_saved_spec
    from dlocli.runs.online.spec import TRIAL, OnlineSpec
    from dlocli.runs.online.trials import env_spec

    torch.set_num_threads(1)
    spec = load_saved_spec(OnlineSpec, run / "spec.json")
    model = load_planning_model(run / "checkpoints" / f"iter_{k:02d}.pt")
    env = make_env_from_spec(env_spec(spec))
    rows: dict[str, list[dict[str, float]]] = {}
    try:
        for j in range(1, n + 1):
            seed = stream_seed(spec.seed, TRIAL, k, j)
            base_true, base_predicted = episode(env, model, seed, None, 0.0)
            for motion in MOTIONS:
                for rate in (r * sign for r in rates for sign in (1.0, -1.0)):
                    true, predicted = episode(env, model, seed, motion, rate)
                    for at, when in ((MOVE - 1, "moved"), (MOVE + STILL - 1, "still")):
                        key = f"{motion} {rate:+g} {when}"
                        effect = compare(true[at] - base_true[at],
                                         predicted[at] - base_predicted[at])  # fmt: skip
                        rows.setdefault(key, []).append(effect)
    finally:
        env.close()
    mean = {key: {m: round(float(np.mean([r[m] for r in found])), 3) for m in found[0]}
            for key, found in rows.items()}  # fmt: skip
    return {"run": str(run), "iteration": k, "trials": n, "steps": [PRE, MOVE, STILL],
            "mean": mean}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--iteration", type=int, default=20)
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--rates", default="0.3,1", help="shares of the largest speed")
    parser.add_argument("--json", type=Path, default=None, help="also write the report here")
    args = parser.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    report = response_report(args.run, args.iteration, args.trials, rates)
    for key, effect in report["mean"].items():
        print(f"{key:22s} " + "  ".join(f"{m} {v:7.3f}" for m, v in effect.items()))
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
