"""dlocli: learn and control the 3D shape of deformable linear objects.

Library entry points (the CLI `dlo` is a thin layer over these)::

    import dlocli
    env = dlocli.make_env(backend="mujoco", task="single", seed=0)
    data = dlocli.load_dataset("runs/collect")

Importing dlocli registers the Gymnasium ids ``dlocli/<Backend><Task>-v0``;
``gym.make("dlocli:dlocli/MujocoSingle-v0")`` imports it on the way.
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
    # Gymnasium ids for every registered backend x task (dlocli/env/registration.py)
    from dlocli.env.registration import register_gym_envs

    register_gym_envs()


_register_gym_ids()
