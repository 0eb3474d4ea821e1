"""dlocli: learn and control the 3D shape of deformable linear objects.

Library entry points (the CLI `dlo` is a thin layer over these)::

    import dlocli
    env = dlocli.make_env(backend="mujoco", task="single", seed=0)
    data = dlocli.load_dataset("runs/collect")
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "make_env": "dlocli.env.shape_env:make_env",
    "DLOShapeEnv": "dlocli.env.shape_env:DLOShapeEnv",
    "load_dataset": "dlocli.data:load_dataset",
    "Dataset": "dlocli.data:Dataset",
}


def __getattr__(name: str) -> Any:
    # lazy, so `import dlocli` does not import MuJoCo, PyBullet or torch
    if name not in _LAZY:
        raise AttributeError(f"module 'dlocli' has no attribute {name!r}")
    import importlib

    module_name, _, attr = _LAZY[name].partition(":")
    return getattr(importlib.import_module(module_name), attr)


def _register_gym_ids() -> None:
    import gymnasium as gym

    for backend in ("mujoco", "pybullet"):
        for task in ("single", "bimanual"):
            env_id = f"dlocli/{backend.capitalize()}{task.capitalize()}-v0"
            if env_id not in gym.registry:
                gym.register(
                    env_id,
                    entry_point="dlocli.env.shape_env:make_env",
                    kwargs={"backend": backend, "task": task},
                    max_episode_steps=None,
                )


_register_gym_ids()
