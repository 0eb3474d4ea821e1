"""Baseline: one MLP from every node's inputs, flattened, to every node's output.

No structure: it sees the cable as a vector of N*F numbers (the view's F inputs per node).
Trained and evaluated exactly like ``in-bilstm`` (same view, normalisation, loss and
rollout), it shows what the graph + bi-LSTM structure buys. Its size depends on N, so a
trained one serves cables of its own node count only.
"""

from __future__ import annotations

from typing import ClassVar

from torch import Tensor

from dlocli.models.network import Network, Nodes, linear_layers, mlp
from dlocli.models.spec import MLPSpec, ModelSpec


class MLP(Network):
    """Flattened-inputs MLP baseline (``layers`` hidden layers, ``hidden`` wide)."""

    spec_cls: ClassVar[type[ModelSpec]] = MLPSpec
    spec: MLPSpec

    def __init__(self, spec: MLPSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        widths = [spec.hidden] * spec.layers
        self.net = mlp([nodes.count * nodes.inputs, *widths, nodes.count * nodes.outputs])

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        batch = nodes.shape[0]
        return self.net(nodes.reshape(batch, -1)).view(batch, self.nodes.count, -1)

    def flat_layers(self, count: int) -> list[tuple[Tensor, Tensor]]:
        return linear_layers(self.net)
