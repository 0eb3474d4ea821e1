"""The network contract: one network per architecture, over the nodes along a cable.

A network maps per-node inputs to per-node outputs and knows nothing of what the nodes are.
A view (:mod:`dlocli.models.base`, the rod's segments; :mod:`dlocli.models.marker_model`, tracked
markers) turns what it observes into the inputs, normalised, and the outputs back into the
next state; it tells the network the layout of its inputs in a :class:`Nodes`. So a network
written once works in both views: `dlo train` and `dlo eval` on rod or marker datasets,
`dlo online` with any observation, the planners, the bench and the twins.

- ``forward(nodes, relations)``: ``nodes`` (B, N, ``inputs``) are the per-node inputs,
  ``relations`` (B, N-1, ``relative``) the first ``relative`` inputs of node i+1 less those of
  node i, at unit scale (what a network that compares neighbours reads); returns
  (B, N, ``outputs``). A network may ignore ``relations``.
- ``spec_cls``: the model's options (a :class:`~dlocli.models.spec.ModelSpec` subclass),
  registered beside it: ``models.register(name, "module:Network", help, spec="module:Spec")``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models.spec import ModelSpec


@dataclass(frozen=True)
class Nodes:
    """The layout of a view's per-node inputs.

    ``count``: nodes along the cable (a network may size itself by it, or serve any count);
    ``inputs``/``outputs``: per-node widths; ``relative``: the leading inputs that are
    coordinates, compared between neighbours in ``relations``; ``absolute``: of those, the
    leading ones that are absolute positions in the world (a network whose spec says
    ``absolute_position=False`` reads them only through ``relations``); ``commands``: the
    trailing inputs that are what the robot commands (a network may read them only where
    nodes interact)."""

    count: int
    inputs: int
    outputs: int
    relative: int
    absolute: int = 0
    commands: int = 0


class Network(torch.nn.Module):
    """Base of the registered networks; subclasses implement :meth:`forward`."""

    #: the options of this model: ModelSpec's fields and its own
    spec_cls: ClassVar[type[ModelSpec]] = ModelSpec
    #: the marker view appends each marker's neighbour vectors, their lengths and the
    #: cable's length to its inputs: for networks that serve cables of any marker count
    cable_geometry: ClassVar[bool] = False
    #: its weights do not depend on the node count: one trained network serves cables of
    #: any marker count (`dlo train` on several cables, `dlo eval` on a new one)
    any_count: ClassVar[bool] = False

    def __init__(self, spec: ModelSpec, nodes: Nodes) -> None:
        super().__init__()
        self.spec = spec
        self.nodes = nodes
        #: use plain PyTorch throughout (the benchmarks' eager reference), no fast paths
        self.reference = False

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:  # pragma: no cover
        raise NotImplementedError

    def flat_layers(self, count: int) -> list[tuple[Tensor, Tensor]] | None:
        """This network for ``count`` nodes as fully connected layers (weight, bias), ReLU
        between, over the nodes' flattened inputs, when it is one: the marker view then
        trains it through one fused rollout (:mod:`dlocli.models.marker_mlp_rollout`).
        None (the default): it runs as written."""
        return None

    def own(self, nodes: Tensor) -> Tensor:
        """A node's own inputs: all of them, or without its absolute position when the spec
        says ``absolute_position=False``."""
        if getattr(self.spec, "absolute_position", True):
            return nodes
        return nodes[..., self.nodes.absolute :]


def mlp(sizes: list[int]) -> torch.nn.Sequential:
    """Fully connected layers ``sizes[0] -> ... -> sizes[-1]``, ReLU between, linear output.

    He initialisation (weights N(0, 2/fan_in), zero biases) keeps the signal's scale through
    deep stacks such as f_e -> LSTM -> f_v; PyTorch's default shrinks it layer by layer.
    """
    layers: list[torch.nn.Module] = []
    for k in range(len(sizes) - 1):
        linear = torch.nn.Linear(sizes[k], sizes[k + 1])
        torch.nn.init.kaiming_normal_(linear.weight, nonlinearity="relu")
        torch.nn.init.zeros_(linear.bias)
        layers.append(linear)
        if k < len(sizes) - 2:
            layers.append(torch.nn.ReLU())
    return torch.nn.Sequential(*layers)


def linear_layers(net: torch.nn.Sequential) -> list[tuple[Tensor, Tensor]]:
    """(weight, bias) of each Linear layer of a :func:`mlp`, in order (ReLU between)."""
    return [(m.weight, m.bias) for m in net if isinstance(m, torch.nn.Linear)]
