"""A backend with a fact of its own: MuJoCo's cable, limited to short rods."""

from __future__ import annotations

from typing import ClassVar

from dlocli.backends.mujoco_cable import MujocoCable


class ShortCable(MujocoCable):
    """MuJoCo's cable of at most 24 segments."""

    name = "short-cable"
    max_segments: ClassVar[int | None] = 24
