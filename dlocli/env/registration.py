"""Gymnasium ids: one per registered backend and task, ``dlocli/<Backend><Task>-v0``.

Gymnasium 1.x loads no plugins (its ``gymnasium.envs`` entry-point hook was removed in 1.0),
so the ids exist once ``dlocli`` is imported; ``gym.make("dlocli:dlocli/MujocoSingle-v0")``
imports it first. Keyword arguments of ``gym.make`` are those of
:class:`~dlocli.env.shape_env.DLOShapeEnv` (TaskSpec fields, ``goal``, ``seed``,
``render_mode``), validated there. Episodes end after the task's ``episode_steps``, and
``env.spec.max_episode_steps`` says so; Gymnasium's own ``max_episode_steps=`` sets both.

This module imports neither Gymnasium's envs nor dlocli's specs until an id is made, so that
``import dlocli`` stays light.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Any

from dlocli.errors import BadOption
from dlocli.registry import backends, tasks

if TYPE_CHECKING:
    import gymnasium as gym

#: namespace of every dlocli id
NAMESPACE = "dlocli"
#: the registered ``max_episode_steps``: TaskSpec's default ``episode_steps`` (a test checks)
DEFAULT_EPISODE_STEPS = 200
ENTRY_POINT = "dlocli.env.shape_env:DLOShapeEnv"


def _camel(name: str) -> str:
    return "".join(part.capitalize() for part in re.split(r"[^0-9A-Za-z]+", name) if part)


def gym_id(backend: str, task: str) -> str:
    """The Gymnasium id of a backend and task: ``gym_id("mujoco", "single")`` is
    ``"dlocli/MujocoSingle-v0"``."""
    return f"{NAMESPACE}/{_camel(backend)}{_camel(task)}-v0"


def gym_ids() -> dict[str, tuple[str, str]]:
    """Every dlocli id with its (backend, task), from the backend and task registries."""
    return {gym_id(b, t): (b, t) for b in backends.names() for t in tasks.names()}


def register_gym_envs() -> list[str]:
    """Register every id not yet in Gymnasium's registry; return all dlocli ids."""
    import gymnasium as gym
    from gymnasium.envs.registration import WrapperSpec

    limit = WrapperSpec(
        name="EpisodeSteps",
        entry_point="dlocli.env.registration:episode_time_limit",
        kwargs={},
    )
    ids = gym_ids()
    for env_id, (backend, task) in ids.items():
        if env_id not in gym.registry:
            gym.register(
                env_id,
                entry_point=ENTRY_POINT,
                kwargs={"backend": backend, "task": task},
                max_episode_steps=DEFAULT_EPISODE_STEPS,
                additional_wrappers=(limit,),
            )
    return list(ids)


def episode_time_limit(env: gym.Env[Any, Any]) -> gym.Env[Any, Any]:
    """One episode length for ``gym.make``: the TimeLimit it put around the env is set to the
    task's ``episode_steps``, or, when ``max_episode_steps=M`` was given, the task's
    ``episode_steps`` to M (giving both, different, is refused).

    Registered as an additional wrapper of every id, so it runs right after ``gym.make``
    applied its TimeLimit. ``max_episode_steps=-1`` (no TimeLimit) leaves the env's own
    truncation alone.
    """
    from gymnasium.wrappers import TimeLimit

    if not isinstance(env, TimeLimit):
        return env
    unwrapped: Any = env.unwrapped
    steps = unwrapped.task_spec.episode_steps
    limit = env._max_episode_steps
    if limit == steps:
        return env
    if limit == DEFAULT_EPISODE_STEPS:  # gym.make's default: the task decides
        return TimeLimit(env.env, steps)
    if steps != DEFAULT_EPISODE_STEPS:
        env.close()
        raise BadOption(
            f"max_episode_steps={limit} and episode_steps={steps} disagree; "
            "pass the episode length once"
        )
    unwrapped.task_spec = unwrapped.task_spec.model_copy(update={"episode_steps": limit})
    if unwrapped.spec is not None:  # so that gym.make(env.spec) makes the same env
        unwrapped.spec.kwargs["episode_steps"] = limit
    return env
