"""Simulator backends: one module per simulator, all implementing :class:`Backend`."""

from dlocli.backends.base import Backend, GripperLimits

__all__ = ["Backend", "GripperLimits", "runnable_backends"]


def runnable_backends() -> list[str]:
    """The registered backends that run with the installed simulators (the composite cable
    needs MuJoCo 3, the flex rod MuJoCo 4); imports each one."""
    from dlocli.registry import backends

    return [name for name in backends.names() if not backends.get(name).unavailable()]
