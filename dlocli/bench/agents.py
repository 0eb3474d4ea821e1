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
- ``mpc``: the paper's Algorithm 1 through :class:`dlocli.runs.online.OnlineRun`: an initial random
  dataset, then iterations of noisy trials of the spec's planner (gradient MPC unless
  ``planner`` names another), each followed by a model update; it is evaluated with the
  model trained on all data so far (the planner without noise).
- ``mpc-offline``: at each of ``mpc``'s points, a model trained from scratch on as many random
  transitions, trained as long as the online model had (its epochs, or its gradient steps
  under the steps schedule; paper Fig. 7).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dlocli.bench.spec import eval_points, mpc_points, mpc_schedule
from dlocli.cancel import CancelToken
from dlocli.controllers.base import LearningAgent, make_controller
from dlocli.data import Dataset
from dlocli.env.rollout import episode_scores, stream_seed
from dlocli.env.shape_env import load_goal, make_env, make_goal
from dlocli.errors import UnknownName
from dlocli.io import atomic_path, read_json, write_json_atomic
from dlocli.models.base import build_model, resolve_device
from dlocli.models.checkpoints import load_planning_model
from dlocli.models.update_steps import train_like_online
from dlocli.registry import controllers
from dlocli.runs.online import TRAIN, OnlineRun, OnlineSpec, random_data_episode
from dlocli.specs import BackendSpec, GoalSpec, TaskSpec
from dlocli.tensorboard import TENSORBOARD_DIR

if TYPE_CHECKING:
    from dlocli.bench.spec import BenchSpec
    from dlocli.controllers.base import Controller, LearningAgent
    from dlocli.data import Dataset
    from dlocli.env.shape_env import DLOShapeEnv
    from dlocli.models.base import DynamicsModel

#: seed stream of the controllers used in evaluation (random actions, MPC restarts)
EVAL_CONTROLLER = 7
#: the agent that learns its model online (paper Algorithm 1), planning with the spec's planner
ONLINE_AGENT = "mpc"


# ----------------------------------------------------------------------------- envs
@lru_cache(maxsize=8)
def _goal(backend_json: str, task_json: str, seed: int) -> np.ndarray:
    backend = BackendSpec.model_validate_json(backend_json)
    task = TaskSpec.model_validate_json(task_json)
    if task.goal_file is not None:
        return load_goal(task.goal_file, backend.rod.n_segments)
    return make_goal(GoalSpec(backend=backend, task=task, seed=seed))


def fixed_goal(spec: BenchSpec, task: str, seed: int) -> np.ndarray:
    """The fixed goal of job seed ``seed`` for ``task`` (or the spec's goal file)."""
    task_json = spec.task.model_copy(update={"name": task}).model_dump_json()
    return _goal(spec.backend.model_dump_json(), task_json, seed).copy()


def make_bench_env(
    spec: BenchSpec, task: str, goals: str, seed: int, cancel: CancelToken | None = None
) -> DLOShapeEnv:
    """A DLOShapeEnv of ``task`` with the seed's fixed goal or random goals; ``cancel`` stops
    it between physics steps."""
    task_spec = spec.task.model_copy(update={"name": task, "goal": goals, "goal_file": None})
    goal = fixed_goal(spec, task, seed) if goals == "fixed" else None
    return make_env(spec.backend, task_spec, goal=goal, seed=seed, cancel=cancel)


def train_env(spec: BenchSpec, seed: int, cancel: CancelToken | None = None) -> DLOShapeEnv:
    """The env an agent learns on (the bench's task and goal mode)."""
    return make_bench_env(spec, spec.task.name, spec.task.goal, seed, cancel)


# ----------------------------------------------------------------------------- agents
#: the suffix of an agent whose model is trained offline on random data (paper Fig. 7)
OFFLINE = "-offline"


def learner_class(name: str) -> type[BenchLearner]:
    """How the registered controller ``name`` learns in the bench, from what it is: a
    LearningAgent (sac, td3, pilco, ...) learns by itself; ``mpc`` learns its model online
    (paper Algorithm 1), ``mpc-offline`` from as much random data, both planning with the
    spec's planner; a controller that needs nothing (zero, random, ...) does not learn."""
    check_agent(name)
    if name.endswith(OFFLINE):
        return OfflineMPCLearner
    if issubclass(controllers.facts(name), LearningAgent):
        return AgentLearner
    return OnlineMPCLearner if name == ONLINE_AGENT else FixedLearner


def is_reference(name: str) -> bool:
    """Whether the agent ``name`` learns nothing (zero, random): a reference whose results
    do not depend on the run's learning settings. False for names no longer registered."""
    try:
        return learner_class(name) is FixedLearner
    except UnknownName:
        return False


def agent_names() -> list[str]:
    """Every registered controller the bench can run, and ``mpc-offline``."""
    names = []
    for name in controllers.names():
        cls = controllers.facts(name)
        if issubclass(cls, LearningAgent) or not cls.needs or name == ONLINE_AGENT:
            names.append(name)
    return sorted([*names, ONLINE_AGENT + OFFLINE])


def check_agent(name: str) -> None:
    """UnknownName listing the bench's agents if ``name`` is not one of them."""
    import difflib

    names = agent_names()
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise UnknownName(f"unknown agent '{name}'; valid agents: {', '.join(names)}.{hint}")


class BenchLearner(ABC):
    """One agent x seed of a benchmark. ``transitions``: env steps used so far; ``cancel``
    stops its learning (its envs between physics steps, its fits between gradient steps)."""

    def __init__(
        self, name: str, spec: BenchSpec, seed: int, work: Path, cancel: CancelToken | None = None
    ) -> None:
        self.name = name
        self.spec = spec
        self.seed = seed
        self.work = Path(work)
        self.cancel = cancel
        self.transitions = 0

    def points(self) -> list[int]:
        """Transition counts after which the agent is evaluated (the bench's schedule)."""
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

    def save_policy(self, directory: Path) -> bool:
        """Save the final policy for `dlo control --policy`; False if it has none to save."""
        return False

    def save_state(self, slot: Path, shared: Path) -> bool:
        """Write what :meth:`load_state` needs to continue learning exactly from here into
        ``slot`` (and, growing, into ``shared``: :mod:`dlocli.bench.checkpoint`); False if
        it cannot now. The default keeps the transition count: all that a learner needs
        whose state is made again from its seeds (zero, random, mpc-offline)."""
        write_json_atomic(slot / "learner.json", {"transitions": self.transitions})
        return True

    def load_state(self, slot: Path, shared: Path) -> None:
        """Continue from :meth:`save_state`'s files (on a freshly built learner)."""
        self.transitions = read_json(slot / "learner.json")["transitions"]

    def close(self) -> None:  # noqa: B027 (optional hook)
        """Release the training env, if any."""


class FixedLearner(BenchLearner):
    """A controller that learns nothing (zero, random): the references every agent must beat."""

    def learn_to(self, transitions: int) -> None:
        self.transitions = transitions  # learns nothing: a flat line at the schedule's points

    def controller(self, env: DLOShapeEnv) -> Controller:
        return make_controller(self.name, env, seed=stream_seed(self.seed, EVAL_CONTROLLER))


class AgentLearner(BenchLearner):
    """A registered :class:`LearningAgent` (sac, td3, pilco) on its own training env."""

    def __init__(
        self, name: str, spec: BenchSpec, seed: int, work: Path, cancel: CancelToken | None = None
    ) -> None:
        super().__init__(name, spec, seed, work, cancel)
        self.env = train_env(spec, seed, cancel)
        options = spec.options.get(name)
        self.agent: LearningAgent = make_controller(name, self.env, options=options, seed=seed)
        self.agent.log_to(self.work / TENSORBOARD_DIR)

    def learn_to(self, transitions: int) -> None:
        self.agent.learn(transitions - self.agent.transitions)
        self.transitions = self.agent.transitions

    def controller(self, env: DLOShapeEnv) -> Controller | None:
        if env.action_space.shape != self.env.action_space.shape:
            return None
        return self.agent

    def training_returns(self) -> list[float]:
        return list(self.env.episode_returns)

    def save_policy(self, directory: Path) -> bool:
        return self.agent.save_policy(directory)

    def save_state(self, slot: Path, shared: Path) -> bool:
        return self.agent.save_state(slot, shared)

    def load_state(self, slot: Path, shared: Path) -> None:
        self.agent.load_state(slot, shared)
        self.transitions = self.agent.transitions

    def close(self) -> None:
        self.env.close()


# ----------------------------------------------------------------------------- MPC agents
class MPCLearner(BenchLearner):
    """Base of the model-based agents: evaluated with the spec's planner through ``model()``."""

    def points(self) -> list[int]:
        return mpc_points(self.spec, self.name)

    @abstractmethod
    def model(self) -> DynamicsModel:
        """The current dynamics model."""

    def controller(self, env: DLOShapeEnv) -> Controller:
        seed = stream_seed(self.seed, EVAL_CONTROLLER)
        spec = self.spec
        return make_controller(spec.planner, env, options=spec.mpc, seed=seed, model=self.model())


class OnlineMPCLearner(MPCLearner):
    """Algorithm 1 (``dlocli.runs.online``) in ``work``; evaluated after every model update."""

    def __init__(
        self, name: str, spec: BenchSpec, seed: int, work: Path, cancel: CancelToken | None = None
    ) -> None:
        super().__init__(name, spec, seed, work, cancel)
        self.run = OnlineRun(online_spec(spec, seed, work), cancel=cancel)
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

    def save_state(self, slot: Path, shared: Path) -> bool:
        # the online run keeps its own record in work/online; this says how far it counts
        state = {"updates": self.updates, "transitions": self.transitions}
        write_json_atomic(slot / "learner.json", state)
        return True

    def load_state(self, slot: Path, shared: Path) -> None:
        state = read_json(slot / "learner.json")
        self.updates, self.transitions = state["updates"], state["transitions"]

    def model(self) -> DynamicsModel:
        return load_planning_model(self.run.paths.checkpoint(self.updates), self.spec.fit.device)

    def training_returns(self) -> list[float]:
        if self.updates == 0:
            return []
        initial = dataset_returns(self.run.initial_dataset(), self.spec.task.episode_steps)
        return initial + [row["cumulative_reward"] for row in self.run.results.rows()]


class OfflineMPCLearner(MPCLearner):
    """At each of ``mpc``'s points: a fresh model trained offline on as much random data.
    Its checkpoint is the transition count alone (:meth:`BenchLearner.save_state`): every
    point trains a fresh model, and the random episodes are seeded one by one."""

    def __init__(
        self, name: str, spec: BenchSpec, seed: int, work: Path, cancel: CancelToken | None = None
    ) -> None:
        super().__init__(name, spec, seed, work, cancel)
        self.data: Dataset | None = None
        self._model: DynamicsModel | None = None

    def learn_to(self, transitions: int) -> None:
        import torch

        k = self.points().index(transitions)
        data = self._random_data(transitions)
        torch.manual_seed(stream_seed(self.seed, TRAIN, 0))  # as the online model's first update
        device = resolve_device(self.spec.fit.device)
        model = build_model(self.spec.model, data.n_segments).to(device)
        fit = self.spec.fit.model_copy(update={"seed": stream_seed(self.seed, TRAIN, 1) % 2**31})
        # as long as the online model's updates so far
        train_like_online(model, data, fit, k + 1, cancel=self.cancel)
        self._model = model
        self.transitions = data.n_transitions

    def _random_data(self, transitions: int) -> Dataset:
        """Random episodes (those of ``mpc``'s initial dataset first) up to ``transitions``."""
        episodes = self.data.n_episodes if self.data is not None else 0
        needed = transitions // self.spec.task.episode_steps - episodes
        if needed <= 0:
            assert self.data is not None
            return self.data
        env = train_env(self.spec, self.seed, self.cancel)
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
        planner=spec.planner,
        mpc=spec.mpc,
        workers=1,
        out=Path(work) / "online",
    )
