"""A dynamics model with an option of its own: every node through one small MLP.

One network, two views: dlocli shows it the rod's segments (state and gripper command per
segment) or a recorded cable's markers (positions, velocity, held markers' motion) alike."""

from __future__ import annotations

from typing import ClassVar

import torch
from pydantic import Field

from dlocli.models.network import Network, Nodes, mlp
from dlocli.models.spec import ModelSpec


class ChainSpec(ModelSpec):
    depth: int = Field(1, gt=0, le=8, description="Hidden layers of the per-node network.")


class ChainNetwork(Network):
    """Each node on its own: one MLP from its inputs to its output."""

    spec_cls: ClassVar[type[ModelSpec]] = ChainSpec
    any_count: ClassVar[bool] = True  # one MLP per node, whatever their number

    def __init__(self, spec: ChainSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        self.net = mlp([nodes.inputs] + [spec.hidden] * spec.depth + [nodes.outputs])

    def forward(self, nodes: torch.Tensor, relations: torch.Tensor) -> torch.Tensor:
        return self.net(nodes)
