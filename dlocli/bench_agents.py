"""The agents of ``dlo bench``: how each learns under a transition budget and what it evaluates.

Every agent is a :class:`BenchLearner`: built for one (spec, seed, scratch directory), it lists
the transition counts at which it can be evaluated (:meth:`BenchLearner.points`), learns up to
each of them (:meth:`BenchLearner.learn_to`) and hands out a controller for an evaluation env
(:meth:`BenchLearner.controller`), possibly of another task or goal mode than it learned on
(transfer, paper Figs. 5 and 6); ``None`` where it cannot act there (a 6-D policy on the
12-D bimanual task).

- ``sac``, ``td3``, ``pilco``: the registered :class:`LearningAgent` controllers, interacting
  with their own training env for exactly the budget.
- ``zero`` and ``random``: all-zero and uniform random actions, the references; they learn
  nothing (and step no training env).
- ``mpc``: the paper's Algorithm 1 through :class:`dlocli.online.OnlineRun`: an initial random
  dataset, then iterations of noisy MPC trials, each followed by a model update; it is
  evaluated with the model trained on all data so far (noise-free MPC).
- ``mpc-offline``: at each of ``mpc``'s points, a model trained from scratch on as many random
  transitions, as many epochs as the online model had (paper Fig. 7).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dlocli.online import TRAIN, OnlineRun, OnlineSpec, random_data_episode
from dlocli.rollout import episode_scores, stream_seed

if TYPE_CHECKING:
    from dlocli.bench import BenchSpec
    from dlocli.controllers.base import Controller, LearningAgent
    from dlocli.data import Dataset
    from dlocli.env import DLOShapeEnv
    from dlocli.models.base import DynamicsModel

#: seed stream of the controllers used in evaluation (random actions, MPC restarts)
EVAL_CONTROLLER = 7


# ----------------------------------------------------------------------------- envs
@lru_cache(maxsize=8)
def _goal(backend_json: str, task_json: str, seed: int) -> np.ndarray:
    from dlocli.env import load_goal
    from dlocli.goals import make_goal
    from dlocli.specs import BackendSpec, GoalSpec, TaskSpec

    backend = BackendSpec.model_validate_json(backend_json)
    task = TaskSpec.model_validate_json(task_json)
    if task.goal_file is not None:
        return load_goal(task.goal_file, backend.rod.n_segments)
    return make_goal(GoalSpec(backend=backend, task=task, seed=seed))


def fixed_goal(spec: BenchSpec, task: str, seed: int) -> np.ndarray:
    """The fixed goal of job seed ``seed`` for ``task`` (or the spec's goal file)."""
    task_json = spec.task.model_copy(update={"name": task}).model_dump_json()
    return _goal(spec.backend.model_dump_json(), task_json, seed).copy()


def make_bench_env(spec: BenchSpec, task: str, goals: str, seed: int) -> DLOShapeEnv:
    """A DLOShapeEnv of ``task`` with the seed's fixed goal or random goals."""
    from dlocli.env import make_env

    task_spec = spec.task.model_copy(update={"name": task, "goal": goals, "goal_file": None})
    goal = fixed_goal(spec, task, seed) if goals == "fixed" else None
    return make_env(spec.backend, task_spec, goal=goal, seed=seed)


def train_env(spec: BenchSpec, seed: int) -> DLOShapeEnv:
    """The env an agent learns on (the bench's task and goal mode)."""
    return make_bench_env(spec, spec.task.name, spec.task.goal, seed)


# ----------------------------------------------------------------------------- agents
class BenchLearner(ABC):
    """One agent x seed of a benchmark. ``transitions``: env steps used so far."""

    def __init__(self, name: str, spec: BenchSpec, seed: int, work: Path) -> None:
        self.name = name
        self.spec = spec
        self.seed = seed
        self.work = Path(work)
        self.transitions = 0

    def points(self) -> list[int]:
        """Transition counts after which the agent is evaluated (the bench's schedule)."""
        from dlocli.bench import eval_points

        return eval_points(self.spec, self.name)

    @abstractmethod
    def learn_to(self, transitions: int) -> None:
        """Learn until ``transitions`` env steps are used (one of :meth:`points`)."""

    @abstractmethod
    def controller(self, env: DLOShapeEnv) -> Controller | None:
        """A controller of the current agent for ``env``; None if it cannot act there."""

    def training_returns(self) -> list[float]:
        """Cumulative reward of every finished training episode so far, in order (with the
        agent's exploration: the paper's Fig. 4 protocol); none for agents that do not learn."""
        return []

    def close(self) -> None:  # noqa: B027 (optional hook)
        """Release the training env, if any."""


class RandomLearner(BenchLearner):
    """Uniform random actions: the floor every agent must beat."""

    def learn_to(self, transitions: int) -> None:
        self.transitions = transitions  # learns nothing: a flat line at the schedule's points

    def controller(self, env: DLOShapeEnv) -> Controller:
        from dlocli.controllers.base import RandomController

        return RandomController(env, seed=stream_seed(self.seed, EVAL_CONTROLLER))


class ZeroLearner(RandomLearner):
    """All-zero actions: doing nothing, the reference of every score."""

    def controller(self, env: DLOShapeEnv) -> Controller:
        from dlocli.controllers.base import ZeroController

        return ZeroController(env)


class AgentLearner(BenchLearner):
    """A registered :class:`LearningAgent` (sac, td3, pilco) on its own training env."""

    def __init__(self, name: str, spec: BenchSpec, seed: int, work: Path) -> None:
        from dlocli.controllers.base import make_controller

        super().__init__(name, spec, seed, work)
        self.env = train_env(spec, seed)
        options = spec.options.get(name)
        self.agent: LearningAgent = make_controller(name, self.env, options=options, seed=seed)

    def learn_to(self, transitions: int) -> None:
        self.agent.learn(transitions - self.agent.transitions)
        self.transitions = self.agent.transitions

    def controller(self, env: DLOShapeEnv) -> Controller | None:
        if env.action_space.shape != self.env.action_space.shape:
            return None
        return self.agent

    def training_returns(self) -> list[float]:
        return list(self.env.episode_returns)

    def close(self) -> None:
        self.env.close()


# ----------------------------------------------------------------------------- MPC agents
def mpc_schedule(spec: BenchSpec, agent: str = "mpc") -> tuple[int, int, int]:
    """(initial episodes I, trials per iteration N, iterations K) of ``agent`` (mpc or
    mpc-offline) in its budget.

    Iterations are as long as the bench's evaluation interval; the initial dataset as well,
    but at least two episodes (a validation split needs two). ``mpc`` uses I*T + K*N*T
    transitions: at most the budget, less by a remainder shorter than one iteration.
    """
    from dlocli.bench import budget_of, eval_interval

    steps = spec.task.episode_steps
    trials = eval_interval(spec) // steps
    initial = max(2, trials)
    iterations = max(0, (budget_of(spec, agent) // steps - initial) // trials)
    return initial, trials, iterations


def mpc_points(spec: BenchSpec, agent: str = "mpc") -> list[int]:
    """Where ``agent`` is evaluated: after the initial data and after every iteration."""
    initial, trials, iterations = mpc_schedule(spec, agent)
    steps = spec.task.episode_steps
    return [(initial + k * trials) * steps for k in range(iterations + 1)]


class MPCLearner(BenchLearner):
    """Base of the model-based agents: evaluated with gradient MPC through ``model()``."""

    def points(self) -> list[int]:
        return mpc_points(self.spec, self.name)

    @abstractmethod
    def model(self) -> DynamicsModel:
        """The current dynamics model."""

    def controller(self, env: DLOShapeEnv) -> Controller:
        from dlocli.controllers.mpc import GradientMPC

        seed = stream_seed(self.seed, EVAL_CONTROLLER)
        return GradientMPC(env, self.model(), self.spec.mpc, seed=seed)


class OnlineMPCLearner(MPCLearner):
    """Algorithm 1 (``dlocli.online``) in ``work``; evaluated after every model update."""

    def __init__(self, name: str, spec: BenchSpec, seed: int, work: Path) -> None:
        super().__init__(name, spec, seed, work)
        self.run = OnlineRun(online_spec(spec, seed, work))
        self.updates = 0  # model updates done: the model of point k is update k+1

    def learn_to(self, transitions: int) -> None:
        k = self.points().index(transitions)
        if self.updates == 0:
            self.run.update_model(1, self.run.initial_dataset())
            self.updates = 1
        while self.updates <= k:  # iteration `updates`: trials, then the next model
            self.run.run_trials(self.updates, self.run.paths.checkpoint(self.updates))
            data = self.run.dataset_until(self.updates)
            self.run.update_model(self.updates + 1, data)
            self.updates += 1
        self.transitions = self.run.dataset_until(self.updates - 1).n_transitions

    def model(self) -> DynamicsModel:
        from dlocli.models.base import load_model

        return load_model(self.run.paths.checkpoint(self.updates), self.spec.fit.device)

    def training_returns(self) -> list[float]:
        if self.updates == 0:
            return []
        initial = dataset_returns(self.run.initial_dataset(), self.spec.task.episode_steps)
        return initial + [row["cumulative_reward"] for row in self.run.rows()]


class OfflineMPCLearner(MPCLearner):
    """At each of ``mpc``'s points: a fresh model trained offline on as much random data."""

    def __init__(self, name: str, spec: BenchSpec, seed: int, work: Path) -> None:
        super().__init__(name, spec, seed, work)
        self.data: Dataset | None = None
        self._model: DynamicsModel | None = None

    def learn_to(self, transitions: int) -> None:
        import torch

        from dlocli.models.base import build_model, resolve_device
        from dlocli.training import train_model

        k = self.points().index(transitions)
        data = self._random_data(transitions)
        torch.manual_seed(stream_seed(self.seed, TRAIN, 0))  # as the online model's first update
        device = resolve_device(self.spec.fit.device)
        model = build_model(self.spec.model, data.n_segments).to(device)
        fit = self.spec.fit.model_copy(
            update={
                "epochs": self.spec.fit.epochs * (k + 1),  # the online model's passes so far
                "seed": stream_seed(self.seed, TRAIN, 1) % 2**31,
            }
        )
        train_model(model, data, fit)
        self._model = model
        self.transitions = data.n_transitions

    def _random_data(self, transitions: int) -> Dataset:
        """Random episodes (those of ``mpc``'s initial dataset first) up to ``transitions``."""
        from dlocli.data import Dataset

        episodes = self.data.n_episodes if self.data is not None else 0
        needed = transitions // self.spec.task.episode_steps - episodes
        if needed <= 0:
            assert self.data is not None
            return self.data
        env = train_env(self.spec, self.seed)
        try:
            new = []
            for e in range(episodes, episodes + needed):
                new.append(random_data_episode(env, self.seed, e))
        finally:
            env.close()
        more = Dataset.from_episodes(new)
        self.data = more if self.data is None else self.data.concat(more)
        return self.data

    def model(self) -> DynamicsModel:
        assert self._model is not None, "learn_to() before controller()"
        return self._model

    def training_returns(self) -> list[float]:
        return [] if self.data is None else dataset_returns(self.data, self.spec.task.episode_steps)


def dataset_returns(data: Dataset, steps: int) -> list[float]:
    """Cumulative reward of every episode of ``data`` (diverged steps counted at the clip)."""
    return [
        episode_scores(data.episode(e), steps)["cumulative_reward"] for e in range(data.n_episodes)
    ]


def online_spec(spec: BenchSpec, seed: int, work: Path) -> OnlineSpec:
    """The OnlineSpec of ``mpc`` for one seed, its run directory in ``work``.

    A fixed goal is written to ``work/goal.npy`` so the online run's envs use the seed's goal.
    """
    from dlocli.io import atomic_path

    initial, trials, iterations = mpc_schedule(spec)
    task = spec.task
    if task.goal == "fixed":
        goal_path = Path(work) / "goal.npy"
        with atomic_path(goal_path) as tmp, open(tmp, "wb") as f:
            np.save(f, fixed_goal(spec, task.name, seed))
        task = task.model_copy(update={"goal_file": goal_path})
    return OnlineSpec(
        backend=spec.backend,
        task=task,
        seed=seed,
        iters=iterations + 1,
        trials=trials,
        initial_episodes=initial,
        noise_probability=spec.noise_probability,
        noise_std=spec.noise_std,
        model=spec.model,
        fit=spec.fit,
        mpc=spec.mpc,
        workers=1,
        out=Path(work) / "online",
    )
