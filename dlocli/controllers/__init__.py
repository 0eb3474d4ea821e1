"""Controllers: everything that turns an observation into an action (MPC, RL agents, ...)."""

from dlocli.controllers.base import Controller

__all__ = ["Controller"]
