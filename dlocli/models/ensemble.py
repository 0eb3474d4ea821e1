"""Several independently trained copies of one network, their predictions averaged.

A model whose spec says ``members`` > 1 holds that many networks of its architecture, each
initialised and trained on its own from its own seed (:mod:`dlocli.models.member_fits`
trains them in parallel, one per core); the view reads their mean output. Errors that one
network makes and another does not partly cancel, most where a long open-loop rollout
drifts, so the mean holds a rollout closer than its members do (`results.md`).

The views build their network through :func:`build_network`, so an ensemble serves
wherever a network does: `dlo eval`, the planners, the twins. It takes any node count where
its members do. Members that are fully connected layers (``flat_layers``: ``mlp``,
``arc-mlp``) are, averaged, again one stack of such layers, with the members' hidden layers
side by side (block diagonal): the marker view's fused rollout runs the whole ensemble.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dlocli.models.network import Network, Nodes
from dlocli.models.spec import ModelSpec
from dlocli.registry import models


class Ensemble(Network):
    """``spec.members`` networks of the registered kind ``spec.name``; the mean of their
    outputs."""

    def __init__(self, spec: ModelSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        network = models.get(spec.name)
        self.members = torch.nn.ModuleList(network(spec, nodes) for _ in range(spec.members))
        # what a view asks of its network's class, the members' answer
        self.any_count = network.any_count
        self.cable_geometry = network.cable_geometry

    @property
    def reference(self) -> bool:  # type: ignore[override]
        return all(m.reference for m in self.members)

    @reference.setter
    def reference(self, value: bool) -> None:
        for member in getattr(self, "members", ()):  # Network.__init__ sets it before them
            member.reference = bool(value)

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        """The members' mean output. ``nodes`` (B, V, W) go to every member; (M, B, V, W)
        give member i row i (a view with per-member cable codes), relations alike."""
        if nodes.dim() == 4:
            outputs = [m(n, r) for m, n, r in zip(self.members, nodes, relations, strict=True)]
        else:
            outputs = [m(nodes, relations) for m in self.members]
        return torch.stack(outputs).mean(0)

    def flat_layers(self, count: int) -> list[tuple[Tensor, Tensor]] | None:
        """The members as one stack (:func:`side_by_side`); None unless every member is
        fully connected layers."""
        return side_by_side([m.flat_layers(count) for m in self.members])


def side_by_side(
    stacks: list[list[tuple[Tensor, Tensor]] | None],
) -> list[tuple[Tensor, Tensor]] | None:
    """Members' fully connected layers as the one stack that computes their mean: their
    first layers stacked, hidden layers block diagonal, last layers' outputs averaged. None
    unless every member is such layers, all of one depth."""
    if any(s is None for s in stacks) or len({len(s) for s in stacks}) != 1:  # type: ignore[arg-type]
        return None
    layers = list(zip(*stacks, strict=True))  # per depth: every member's (weight, bias)
    first = (torch.cat([w for w, _ in layers[0]]), torch.cat([b for _, b in layers[0]]))
    hidden = [(torch.block_diag(*[w for w, _ in depth]), torch.cat([b for _, b in depth]))
              for depth in layers[1:-1]]  # fmt: skip
    share = 1.0 / len(stacks)
    last = (torch.cat([w for w, _ in layers[-1]], 1) * share,
            torch.stack([b for _, b in layers[-1]]).mean(0))  # fmt: skip
    return [first, *hidden, last]


def build_network(spec: ModelSpec, nodes: Nodes) -> Network:
    """The network a view holds: the registered kind ``spec.name``, or an :class:`Ensemble`
    of them when ``spec.members`` > 1."""
    if spec.members > 1:
        return Ensemble(spec, nodes)
    return models.get(spec.name)(spec, nodes)
