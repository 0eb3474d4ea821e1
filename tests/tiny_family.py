"""A new, small model family, written as a family in the tree is: its module (its options,
its network) and one registration line. tests/test_new_family.py trains it in both views, as
an ensemble and with cable codes, and imports this module only there (so the family joins
the registry for those tests alone)."""

from __future__ import annotations

from typing import ClassVar

import torch
from pydantic import Field
from torch import Tensor

from dlocli.models.network import Network, Nodes, mlp
from dlocli.models.spec import ModelSpec
from dlocli.registry import models

NAME = "tiny-neighbours"


class NeighboursSpec(ModelSpec):
    """The per-node network's depth (``hidden`` wide)."""

    depth: int = Field(1, ge=1, le=4, description="Hidden layers of the per-node network.")


class Neighbours(Network):
    """Each node through one small MLP from its own inputs and its relations to both
    neighbours (zero past the ends): any node count."""

    spec_cls: ClassVar[type[ModelSpec]] = NeighboursSpec
    any_count: ClassVar[bool] = True

    def __init__(self, spec: NeighboursSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        width = nodes.inputs + 2 * nodes.relative
        self.net = mlp([width] + [spec.hidden] * spec.depth + [nodes.outputs])

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        pad = torch.nn.functional.pad
        around = torch.cat([pad(relations, (0, 0, 1, 0)), pad(relations, (0, 0, 0, 1))], -1)
        return self.net(torch.cat([nodes, around], -1))


models.register(NAME, Neighbours, "a node and its neighbours", spec=NeighboursSpec)
