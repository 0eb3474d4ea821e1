"""A dynamics model with an option of its own: every segment through one small MLP."""

from __future__ import annotations

from typing import ClassVar

import torch
from pydantic import Field

from dlocli.models.base import ACTION_DIM, STATE_DIM, DynamicsModel, mlp, node_actions
from dlocli.models.spec import ModelSpec


class ChainSpec(ModelSpec):
    depth: int = Field(1, gt=0, le=8, description="Hidden layers of the per-segment network.")


class ChainModel(DynamicsModel):
    """Each segment on its own: one MLP from its features and its gripper's command."""

    spec_cls: ClassVar[type[ModelSpec]] = ChainSpec

    def __init__(self, spec: ChainSpec, n_segments: int) -> None:
        super().__init__(spec, n_segments)
        sizes = [self.feature_dim + ACTION_DIM] + [spec.hidden] * spec.depth + [STATE_DIM]
        self.net = mlp(sizes)

    def predict_delta(self, state_n: torch.Tensor, action_n: torch.Tensor) -> torch.Tensor:
        actions = node_actions(action_n, self.n_segments)
        return self.net(torch.cat([state_n, actions], -1))
