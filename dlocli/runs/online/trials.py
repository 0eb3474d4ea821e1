"""The jobs of an online run that an executor runs anywhere (:mod:`dlocli.executors`): one
trial of the planner through the model, and reference episodes from the trials' starts. Each
gets the spec as JSON and the model's checkpoint as bytes, and returns what happened; the
driver writes every file. Each also gets the run's cancel token: in the driver's process it
stops the episode between physics steps; a copy in another process is never cancelled (that
process's own signals end it)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.controllers.base import make_controller
from dlocli.data import Episode
from dlocli.env.rollout import NoisyPolicy, episode_scores, random_episode, rollout, stream_seed
from dlocli.env.shape_env import make_env_from_spec
from dlocli.runs.online.spec import INITIAL, NOISE, REFERENCE, TRIAL, OnlineSpec, job_threads
from dlocli.runs.references import reference_episode_scores
from dlocli.specs import EnvSpec
from dlocli.threads import torch_threads


def random_data_episode(env: Any, seed: int, e: int) -> Episode:
    """Random episode ``e`` of the run ``seed``: the initial data D_0, and its continuation
    for the models trained offline on as much random data (paper Fig. 7)."""
    return random_episode(env, stream_seed(seed, INITIAL, e), stream_seed(seed, INITIAL, e, 1))


def env_spec(spec: OnlineSpec) -> EnvSpec:
    """The env every episode of the run plays on."""
    return EnvSpec(backend=spec.backend, task=spec.task, seed=spec.seed)


class TimedController:
    """A controller whose ``act`` time is added up (the planner's share of a trial)."""

    def __init__(self, controller: Any) -> None:
        self.controller = controller
        self.seconds = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)

    def act(self, obs: np.ndarray) -> np.ndarray:
        start = time.perf_counter()
        try:
            return self.controller.act(obs)
        finally:
            self.seconds += time.perf_counter() - start


def trial_episode(
    spec: OnlineSpec, checkpoint: bytes, k: int, j: int, cancel: CancelToken | None = None
) -> tuple[Episode, float]:
    """One trial of the spec's planner through the model ``checkpoint`` holds (seeds from
    (seed, k, j)), and the seconds the planner took in it."""
    from dlocli.models.checkpoints import load_planning_model

    env = make_env_from_spec(env_spec(spec), cancel=cancel)
    try:
        model = load_planning_model(checkpoint, spec.fit.device)
        seed = stream_seed(spec.seed, TRIAL, k, j)
        planner = make_controller(spec.planner, env, options=spec.mpc, seed=seed, model=model)
        timed = TimedController(planner)
        noise_rng = np.random.default_rng(stream_seed(spec.seed, NOISE, k, j))
        policy = NoisyPolicy(timed, noise_rng, spec.noise_probability, spec.noise_std)
        return rollout(env, policy, stream_seed(spec.seed, TRIAL, k, j)), timed.seconds
    finally:
        env.close()


def run_trial(
    spec_json: str, checkpoint: bytes, k: int, j: int, cancel: CancelToken | None = None
) -> tuple[Episode, dict[str, Any]]:
    """Trial j of iteration k through the model whose checkpoint file holds ``checkpoint``:
    its episode and scores (an executor's job; the driver writes the file)."""
    import torch

    spec = OnlineSpec.model_validate_json(spec_json)
    start = time.perf_counter()
    with torch_threads(job_threads(spec)):
        episode, planner_seconds = trial_episode(spec, checkpoint, k, j, cancel)
        threads = torch.get_num_threads()
    attrs = {
        **episode_scores(episode, spec.task.episode_steps),
        "trial_seconds": round(time.perf_counter() - start, 3),
        "mpc_seconds": round(planner_seconds, 3),
        "threads": threads,
    }
    return episode, attrs


def reference_episodes(
    spec_json: str, k: int, runs: list[tuple[str, int]], cancel: CancelToken | None = None
) -> list[tuple[str, int, dict[str, float]]]:
    """The reference episodes ``runs`` ((controller, trial) pairs) of iteration k, on one
    env, from the trials' starts (an executor's job)."""
    spec = OnlineSpec.model_validate_json(spec_json)
    env = make_env_from_spec(env_spec(spec), cancel=cancel)
    try:
        return [
            (name, j, reference_episode_scores(env, name, stream_seed(spec.seed, TRIAL, k, j),
                                               stream_seed(spec.seed, REFERENCE, k, j)))
            for name, j in runs
        ]  # fmt: skip
    finally:
        env.close()


def returned(result: Any) -> Any:
    """An executor's result, raised if it is the error the call raised."""
    if isinstance(result, BaseException):
        raise result
    return result
