"""Typed errors. The library raises them; the CLI turns them into one line and an exit code."""

from __future__ import annotations


class DloError(Exception):
    """Base class of every error dlocli raises on purpose."""

    exit_code = 1


class BadInput(DloError):
    """The user's input (flag, spec, file, name) is wrong. The message names the fix. Exit 2."""

    exit_code = 2


class UnknownName(BadInput):
    """A registry lookup failed; the message lists the valid names and the closest match."""


class UnknownOption(BadInput, TypeError):
    """An unknown keyword argument (of the env, through ``gym.make``); the message lists the
    valid ones. Also a TypeError, as Python raises for unknown keywords."""


class BadOption(BadInput, ValueError):
    """A keyword argument with a bad value; the message says what is expected."""


class SimulationDiverged(DloError):
    """The physics produced NaN or exploded; episodes end with a flag instead of raising."""


class UnworkablePhysics(BadInput):
    """Parameters within their ranges that together make the simulation diverge (a rod too
    light for its stiffness at this time step, say): the message names them and the fix."""
