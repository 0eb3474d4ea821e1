"""Tasks map an agent's action vector in [-1, 1] to per-gripper commands (2, 6).

``single``: 6-D action moves the right gripper; the left one stays where it is (paper).
``bimanual``: 12-D action, left gripper then right gripper, each linear then angular.
The maps work on numpy arrays and torch tensors alike, with any leading batch axes, so
planners can push gradients through them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.registry import tasks as task_registry


def _zeros_like(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return np.zeros_like(x)
    import torch

    return torch.zeros_like(x)


def _stack_rows(left: Any, right: Any) -> Any:
    if isinstance(left, np.ndarray):
        return np.stack([left, right], axis=-2)
    import torch

    return torch.stack([left, right], dim=-2)


class Task:
    """Base task: action size and the action -> gripper-command map."""

    name = ""
    action_dim = 0
    #: which grippers this task moves (left, right)
    moving = np.array([False, False])

    def to_grippers(self, action: Any) -> Any:
        """(..., action_dim) -> (..., 2, 6) per-gripper commands in [-1, 1]."""
        raise NotImplementedError

    def from_grippers(self, commands: Any) -> Any:
        """Inverse of :meth:`to_grippers` on the moving grippers' rows."""
        raise NotImplementedError


@task_registry.decorator("single", "6-D action: right gripper moves")
class SingleGripperTask(Task):
    """One gripper (the right) moves; 6-D action."""

    name = "single"
    action_dim = 6
    moving = np.array([False, True])

    def to_grippers(self, action: Any) -> Any:
        return _stack_rows(_zeros_like(action), action)

    def from_grippers(self, commands: Any) -> Any:
        return commands[..., 1, :]


@task_registry.decorator("bimanual", "12-D action: both grippers move")
class BimanualTask(Task):
    """Both grippers move; 12-D action (left then right)."""

    name = "bimanual"
    action_dim = 12
    moving = np.array([True, True])

    def to_grippers(self, action: Any) -> Any:
        return _stack_rows(action[..., :6], action[..., 6:])

    def from_grippers(self, commands: Any) -> Any:
        return commands.reshape(*commands.shape[:-2], 12)


def make_task(name: str) -> Task:
    return task_registry.get(name)()
