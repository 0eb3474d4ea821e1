"""dlocli: learn and control the 3D shape of deformable linear objects.

The library behind the `dlo` command, in one namespace (docs/python.md's notebook section runs
these end to end)::

    import dlocli
    data = dlocli.random_dataset(dlocli.CollectSpec(episodes=4))   # random actions, in memory
    model = dlocli.build_model(dlocli.ModelSpec(hidden=32), data.n_segments)
    dlocli.fit(model, data, dlocli.FitSpec(epochs=5, lr=1e-3))     # the schedule: epochs
    env = dlocli.make_env(backend="mujoco", task="single", seed=0)
    episode = dlocli.rollout(env, dlocli.make_controller("mpc", env, model=model), seed=1)
    dlocli.episode_scores(episode, env.task_spec.episode_steps)   # plain floats, mm

Every name is imported on first use, so ``import dlocli`` loads no torch or simulator.
Importing dlocli registers the Gymnasium ids ``dlocli/<Backend><Task>-v0``;
``gym.make("dlocli:dlocli/MujocoSingle-v0")`` imports it on the way.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

#: public name -> "module:attribute", imported on first access
_LAZY = {
    # specs: every field validated and described (the CLI's flags come from them)
    "BackendSpec": "dlocli.specs:BackendSpec",
    "TaskSpec": "dlocli.specs:TaskSpec",
    "CollectSpec": "dlocli.specs:CollectSpec",
    "ModelSpec": "dlocli.models.spec:ModelSpec",
    "FitSpec": "dlocli.models.spec:FitSpec",
    "ControlSpec": "dlocli.runs.control:ControlSpec",
    # the environment and data
    "make_env": "dlocli.env.shape_env:make_env",
    "DLOShapeEnv": "dlocli.env.shape_env:DLOShapeEnv",
    "load_dataset": "dlocli.data:load_dataset",
    "Dataset": "dlocli.data:Dataset",
    "Episode": "dlocli.data:Episode",
    "random_dataset": "dlocli.runs.collect:random_dataset",
    # models
    "build_model": "dlocli.models.base:build_model",
    "load_model": "dlocli.models.checkpoints:load_model",
    "save_checkpoint": "dlocli.models.checkpoints:save_checkpoint",
    "fit": "dlocli.models.fit:fit",
    # control, episodes and their scores
    "make_controller": "dlocli.controllers.base:make_controller",
    "rollout": "dlocli.env.rollout:rollout",
    "random_episode": "dlocli.env.rollout:random_episode",
    "episode_scores": "dlocli.env.rollout:episode_scores",
    "shape_error_mm": "dlocli.env.metrics:shape_error_mm",
    "score": "dlocli.env.metrics:score",
    # what a long run reports to its ``progress`` callback, and how it is stopped
    "Event": "dlocli.events:Event",
    "CancelToken": "dlocli.cancel:CancelToken",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    # lazy, so `import dlocli` does not import MuJoCo, PyBullet or torch
    if name not in _LAZY:
        raise AttributeError(f"module 'dlocli' has no attribute {name!r}")
    from dlocli.registry import import_target

    value = import_target(_LAZY[name])
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


def _register_gym_ids() -> None:
    # Gymnasium ids for every registered backend x task (dlocli/env/registration.py)
    from dlocli.env.registration import register_gym_envs

    register_gym_envs()


_register_gym_ids()
