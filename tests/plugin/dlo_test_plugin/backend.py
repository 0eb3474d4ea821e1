"""A backend with a fact of its own: the installed MuJoCo's rod (the composite cable on
MuJoCo 3, the flex rod on MuJoCo 4), limited to short rods."""

from __future__ import annotations

from typing import ClassVar

from dlocli.backend_spec import default_backend
from dlocli.registry import backends

MujocoRod = backends.get(default_backend())


class ShortCable(MujocoRod):
    """The installed MuJoCo's rod of at most 24 segments."""

    name = "short-cable"
    max_segments: ClassVar[int | None] = 24
