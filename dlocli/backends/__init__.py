"""Simulator backends: one module per simulator, all implementing :class:`Backend`.

The built-ins register here; each names its facts class (``dlocli.backends.facts``), so
specs and ``--help`` learn its limits without importing the simulator. Names are imported
lazily: importing this package imports no simulator.
"""

from __future__ import annotations

from typing import Any

from dlocli.registry import backends, import_target

backends.register(
    "mujoco",
    "dlocli.backends.mujoco_cable:MujocoCable",
    "MuJoCo 3.x composite cable (elasticity plugin), grippers as mocap bodies",
    facts="dlocli.backends.facts:MujocoFacts",
)
backends.register(
    "mujoco-flex",
    "dlocli.backends.mujoco_flex:MujocoFlex",
    "MuJoCo 4 flex rod (1D flex, discrete elastic rod with twist), grippers as welded pads",
    facts="dlocli.backends.facts:FlexFacts",
)
backends.register(
    "pybullet",
    "dlocli.backends.pybullet_chain:PybulletChain",
    "PyBullet chain of capsules, joint stiffness from EI/l and GJ/l",
    facts="dlocli.backends.facts:PybulletFacts",
)

_EXPORTS = {"Backend": "dlocli.backends.base", "GripperLimits": "dlocli.backends.base"}
__all__ = [*sorted(_EXPORTS), "runnable_backends"]


def runnable_backends() -> list[str]:
    """The registered backends that run with the installed simulators (the composite cable
    needs MuJoCo 3, the flex rod MuJoCo 4); imports each one."""
    return [name for name in backends.names() if not backends.get(name).unavailable()]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dlocli.backends' has no attribute '{name}'")
    return import_target(f"{_EXPORTS[name]}:{name}")
