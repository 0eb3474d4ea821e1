"""One job of the bench: an agent x seed learns to its budget and is evaluated on the way
(:func:`run_job`, the entry point of every executor)."""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.bench.agents import learner_class, make_bench_env
from dlocli.bench.checkpoint import JobCheckpoint, Standing
from dlocli.bench.spec import BenchSpec, fingerprint, resolved_options
from dlocli.cancel import CancelToken
from dlocli.env.rollout import episode_scores, rollout, stream_seed
from dlocli.io import versions
from dlocli.tensorboard import Scalars
from dlocli.threads import torch_threads

EVAL = 5  # seed stream of evaluation starts
#: the directory of a job's mid-job checkpoints, in its work directory
RESUME_DIR = "resume"


# ----------------------------------------------------------------------------- evaluation
def eval_episode(controller: Any, env: Any, seed: int) -> dict[str, float]:
    """Initial and final error, score and cumulative reward of one noise-free episode from
    ``seed`` (a diverged episode stops there; its missing steps count at the clip)."""
    return episode_scores(rollout(env, controller, seed), env.task_spec.episode_steps)


def evaluate(controller: Any, env: Any, spec: BenchSpec, seed: int) -> dict[str, float]:
    """Mean (and std) over ``eval_trials`` episodes from the seed's evaluation starts."""
    start = time.perf_counter()
    results = [
        eval_episode(controller, env, stream_seed(seed, EVAL, i)) for i in range(spec.eval_trials)
    ]
    column = {key: np.array([r[key] for r in results]) for key in results[0]}
    return {
        "cumulative_reward": float(column["cumulative_reward"].mean()),
        "cumulative_reward_std": float(column["cumulative_reward"].std()),
        "initial_error_mm": float(column["initial_error_mm"].mean()),
        "final_error_mm": float(column["final_error_mm"].mean()),
        "score": float(column["score"].mean()),
        "score_std": float(column["score"].std()),
        "eval_seconds": round(time.perf_counter() - start, 3),
    }


def curve_settings(spec: BenchSpec) -> list[tuple[str, str]]:
    """(task, goals) where agents are evaluated at every point: where they learn, and random
    goals after a fixed one (paper Fig. 6)."""
    settings = [(spec.task.name, spec.task.goal)]
    if spec.transfer and spec.task.goal == "fixed":
        settings.append((spec.task.name, "random"))
    return settings


def final_settings(spec: BenchSpec) -> list[tuple[str, str]]:
    """(task, goals) where final agents are also evaluated: the bimanual task after the
    single-gripper one (paper Fig. 5)."""
    if spec.transfer and spec.task.name == "single":
        return [("bimanual", spec.task.goal)]
    return []


# ----------------------------------------------------------------------------- one job
def _seed_globals(seed: int) -> None:
    import random

    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@contextmanager
def _workdir(scratch: str | None) -> Iterator[Path]:
    if scratch is not None:
        yield Path(scratch)  # created by the agents that write there
        return
    with tempfile.TemporaryDirectory(prefix="dlo-bench-") as tmp:
        yield Path(tmp)


def run_job(
    spec_json: str,
    agent: str,
    seed: int,
    scratch: str | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Learn and evaluate one agent x seed; returns its result (rows of results.csv).
    ``cancel`` stops it between physics and gradient steps, its last evaluation point kept
    in ``scratch``'s checkpoint (a copy in another process: that process's signals end it)."""
    spec = BenchSpec.model_validate_json(spec_json)
    _seed_globals(seed)
    with torch_threads(spec.threads), _workdir(scratch) as work:
        # a scratch directory is the job's own directory in the run: its policy stays,
        # and a stopped job continues there from its last evaluation point
        policy = work / "policy" if scratch is not None else None
        checkpoint = None
        if scratch is not None:
            checkpoint = JobCheckpoint(work / RESUME_DIR, fingerprint(spec, agent))
        progress, saved = _learn_and_evaluate(spec, agent, seed, work, policy, checkpoint, cancel)
        if checkpoint is not None:
            checkpoint.remove()
    return {
        "agent": agent,
        "seed": seed,
        "fingerprint": fingerprint(spec, agent),
        "options": resolved_options(spec, agent),
        "rows": progress.rows,
        "resumed_at": progress.resumed_at,
        "policy": str(policy) if saved else None,
        "seconds": round(progress.seconds, 1),  # over every process of the job
        "versions": versions(),
    }


def _learn_and_evaluate(
    spec: BenchSpec,
    agent: str,
    seed: int,
    work: Path,
    policy: Path | None,
    checkpoint: JobCheckpoint | None = None,
    cancel: CancelToken | None = None,
) -> tuple[Standing, bool]:
    """The job's evaluation rows (in its final Standing), and whether its final policy was
    saved in ``policy``; with ``checkpoint``, continued from the last one and checkpointed
    after every point."""
    learner, progress = _start(spec, agent, seed, work, checkpoint, cancel)
    envs = {s: make_bench_env(spec, *s, seed, cancel) for s in curve_settings(spec)}
    rows, wall, trained = progress.rows, progress.wall, progress.trained
    began = time.perf_counter() - progress.seconds  # as if never stopped
    scalars = Scalars(work)
    clock = JobClock(f"{agent}-s{seed}", learner.transitions)
    try:
        points = learner.points()
        for index, point in enumerate(points):
            if index <= progress.index:
                continue
            start = time.perf_counter()
            learner.learn_to(point)
            wall += time.perf_counter() - start
            point_row = _point_row(spec, learner, index, wall, trained)
            trained += point_row["train_episodes"]
            evaluated = []
            for setting, env in envs.items():
                evaluated += _evaluation_rows(spec, learner, env, setting, seed, point_row)
            rows += evaluated
            _log_point(scalars, evaluated, learner.transitions)
            seconds = time.perf_counter() - began
            progress = Standing(index, rows, wall, trained, progress.resumed_at, seconds)
            if checkpoint is not None and index < len(points) - 1:
                checkpoint.save(learner, progress)
            clock.report(learner.transitions, points[-1], evaluated)
        for setting in final_settings(spec):
            env = make_bench_env(spec, *setting, seed, cancel)
            try:
                rows += _evaluation_rows(spec, learner, env, setting, seed, point_row)
            finally:
                env.close()
        saved = policy is not None and learner.save_policy(policy)
    finally:
        for env in envs.values():
            env.close()
        learner.close()
        scalars.close()
    seconds = time.perf_counter() - began
    return Standing(progress.index, rows, wall, trained, progress.resumed_at, seconds), saved


class JobClock:
    """One line on stderr per evaluation point of a job: how far it is, how good it is now,
    and the time left at this job's pace since it (re)started. Workers share the terminal."""

    def __init__(self, name: str, transitions: int) -> None:
        self.name = name
        self.start = time.perf_counter()
        self.first = transitions

    def report(self, done: int, budget: int, rows: list[dict[str, Any]]) -> None:
        elapsed = time.perf_counter() - self.start
        left = elapsed / max(done - self.first, 1) * (budget - done)
        goals = {"fixed": "fixed goal", "random": "random goals"}
        errors = "".join(
            f", {goals[row['eval_goals']]} {row['final_error_mm']:.1f} mm" for row in rows
        )
        sys.stderr.write(
            f"  {self.name}: {done:,}/{budget:,} transitions{errors}; "
            f"{_clock(elapsed)} elapsed, about {_clock(left)} left\n"
        )
        sys.stderr.flush()


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    return f"{minutes // 60}:{minutes % 60:02d}:{secs:02d}"


def _point_row(
    spec: BenchSpec, learner: Any, index: int, wall: float, trained: int
) -> dict[str, Any]:
    """The columns shared by the evaluations of point ``index``: what the agent learned from
    (its training episodes after the first ``trained``) and how long it took."""
    returns = learner.training_returns()[trained:]
    return {
        "agent": learner.name,
        "seed": learner.seed,
        "train_task": spec.task.name,
        "train_goals": spec.task.goal,
        "eval": index,
        "transitions": learner.transitions,
        "wall_seconds": round(wall, 3),
        "train_reward": float(np.mean(returns)) if returns else None,
        "train_episodes": len(returns),
    }


def _start(
    spec: BenchSpec,
    agent: str,
    seed: int,
    work: Path,
    checkpoint: JobCheckpoint | None,
    cancel: CancelToken | None = None,
) -> tuple[Any, Standing]:
    """The job's learner and progress: at its last checkpoint, or new (and no stale
    checkpoint files left) where there is none or it does not load."""
    learner = learner_class(agent)(agent, spec, seed, work, cancel)
    progress = None
    if checkpoint is not None:
        try:
            progress = checkpoint.restore(learner)
        except Exception as exc:  # a damaged checkpoint costs its work, never the job
            sys.stderr.write(
                f"  {agent}-s{seed}: its checkpoint does not load ({type(exc).__name__}: "
                f"{exc}); starting again\n"
            )
            learner.close()
            _seed_globals(seed)
            learner = learner_class(agent)(agent, spec, seed, work, cancel)
        if progress is None:
            checkpoint.remove()  # not this job's (another fingerprint or versions), or damaged
    return learner, progress or Standing(-1, [], 0.0, 0)


def _log_point(scalars: Scalars, rows: list[dict[str, Any]], transitions: int) -> None:
    """One point's evaluations, at ``transitions``, as TensorBoard scalars per setting."""
    for row in rows:
        scalars.add(
            transitions,
            f"eval/{row['eval_task']}-{row['eval_goals']}",
            final_error_mm=row["final_error_mm"],
            score=row["score"],
            cumulative_reward=row["cumulative_reward"],
        )


def _evaluation_rows(
    spec: BenchSpec, learner: Any, env: Any, setting: tuple[str, str], seed: int, point: dict
) -> list[dict[str, Any]]:
    """The row of one evaluation of ``learner`` on ``env`` (none where it cannot act)."""
    controller = learner.controller(env)
    if controller is None:
        return []
    task, goals = setting
    return [
        {**point, "eval_task": task, "eval_goals": goals, **evaluate(controller, env, spec, seed)}
    ]


# ----------------------------------------------------------------------------- jobs
@dataclass(frozen=True)
class Job:
    """One agent x seed; ``scratch``: its work directory (None: a temporary one)."""

    agent: str
    seed: int
    scratch: str | None = None

    @property
    def name(self) -> str:
        return f"{self.agent}-s{self.seed}"
