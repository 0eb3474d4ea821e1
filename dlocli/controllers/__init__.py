"""Controllers: everything that turns an observation into an action (MPC, RL agents, ...).

The built-ins register here. Each names its light stand-ins (``dlocli.registry``): the spec
of its options and a base class whose attributes tell what it is (a planner, a learning
agent, a reference), so ``--help``, specs and reports ask without importing torch or
stable-baselines3. Names are imported lazily.
"""

from __future__ import annotations

from typing import Any

from dlocli.registry import controllers, import_target

PLANNER = "dlocli.controllers.base:Planner"
LEARNING_AGENT = "dlocli.controllers.base:LearningAgent"

controllers.register(
    "mpc",
    "dlocli.controllers.mpc:GradientMPC",
    "gradient-based shooting MPC through the learned model (paper eqs. 8-10)",
    spec="dlocli.controllers.specs:MPCSpec",
    facts=PLANNER,
)
controllers.register(
    "mppi",
    "dlocli.controllers.mppi:MPPI",
    "sampling MPC (MPPI) through the learned model",
    spec="dlocli.controllers.specs:MPPISpec",
    facts=PLANNER,
)
controllers.register("random", "dlocli.controllers.base:RandomController", "uniform random actions")
controllers.register(
    "zero", "dlocli.controllers.base:ZeroController", "all-zero actions: do nothing (reference)"
)
controllers.register(
    "held-end",
    "dlocli.controllers.held_end:HeldEndServo",
    "no model: each moving gripper servoed to where the goal holds its end (reference)",
)
controllers.register(
    "sac",
    "dlocli.controllers.sb3_agents:SACAgent",
    "Soft Actor-Critic (stable-baselines3) on the flat observation",
    facts=LEARNING_AGENT,
)
controllers.register(
    "td3",
    "dlocli.controllers.sb3_agents:TD3Agent",
    "TD3 (stable-baselines3) with Gaussian exploration noise",
    facts=LEARNING_AGENT,
)
controllers.register(
    "pilco",
    "dlocli.controllers.pilco:PilcoAgent",
    "PILCO: GP dynamics, moment matching, RBF policy (Deisenroth 2011)",
    spec="dlocli.controllers.specs:PilcoSpec",
    facts=LEARNING_AGENT,
)

_EXPORTS = {"Controller": "dlocli.controllers.base"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dlocli.controllers' has no attribute '{name}'")
    return import_target(f"{_EXPORTS[name]}:{name}")
