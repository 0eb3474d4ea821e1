"""Simulator backends: one module per simulator, all implementing :class:`Backend`."""

from dlocli.backends.base import Backend, GripperLimits

__all__ = ["Backend", "GripperLimits"]
