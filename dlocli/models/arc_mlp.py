"""The MLP over a fixed grid of points along the cable: any node count, the MLP's speed.

The ``mlp`` baseline reads every node's inputs flattened, so its size fixes the node count.
Here the nodes' inputs are first interpolated linearly, by their arc position
s = i / (N - 1), onto ``points`` grid positions s = j / (points - 1); the MLP maps the grid's
flattened inputs to the grid's outputs, which are interpolated back onto the nodes. Both
interpolations are fixed linear maps, so for N nodes the whole network is again an MLP over
the N nodes' flattened inputs (its first and last layers composed with them,
:meth:`ArcMLP.flat_layers`): the marker view's fused rollout trains it exactly as fast as
``mlp``, and one trained network serves cables of any marker count (13 or 12 markers, a
cable it has never seen).

With ``points`` >= N the grid loses nothing of the nodes' inputs (the interpolation onto it
has full rank), so on one cable it can learn what ``mlp`` learns. A cable is told from
another by what the MLP reads of its whole shape at once: the markers' positions relative
to the held ones (their spacing, the cable's length) and their motion.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models.network import Network, Nodes, linear_layers, mlp
from dlocli.models.spec import ArcMLPSpec, ModelSpec


def interpolation(targets: int, sources: int, like: Tensor) -> Tensor:
    """(targets, sources): linear interpolation in arc position from ``sources`` evenly
    spaced points on [0, 1] onto ``targets`` evenly spaced points; each row sums to 1."""
    s = torch.linspace(0.0, 1.0, targets, dtype=like.dtype, device=like.device)
    position = s * (sources - 1)
    left = position.floor().clamp(max=sources - 2).long()
    right_weight = position - left.to(like.dtype)
    out = like.new_zeros(targets, sources)
    rows = torch.arange(targets, device=like.device)
    out[rows, left] = 1.0 - right_weight
    out[rows, left + 1] += right_weight
    return out


class ArcMLP(Network):
    """An MLP (``layers`` hidden layers, ``hidden`` wide) over ``points`` positions along the
    cable, the nodes interpolated onto them and back (see the module docstring)."""

    any_count: ClassVar[bool] = True
    spec_cls: ClassVar[type[ModelSpec]] = ArcMLPSpec
    spec: ArcMLPSpec

    def __init__(self, spec: ArcMLPSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        widths = [spec.hidden] * spec.layers
        self.net = mlp([spec.points * nodes.inputs, *widths, spec.points * nodes.outputs])

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        batch, count = nodes.shape[:2]
        onto_grid = interpolation(self.spec.points, count, nodes)
        back = interpolation(count, self.spec.points, nodes)
        grid = torch.einsum("jn,bnf->bjf", onto_grid, nodes).reshape(batch, -1)
        out = self.net(grid).view(batch, self.spec.points, -1)
        return torch.einsum("nj,bjf->bnf", back, out)

    def flat_layers(self, count: int) -> list[tuple[Tensor, Tensor]]:
        """The network for ``count`` nodes as an MLP over their flattened inputs: the first
        layer's weight composed with the interpolation onto the grid, the last layer's
        weight and bias with the one back (autograd reaches the grid's weights)."""
        layers = linear_layers(self.net)
        points, width_in, width_out = self.spec.points, self.nodes.inputs, self.nodes.outputs
        first, last = layers[0][0], layers[-1]  # spec.layers >= 1: two Linear layers at least
        onto_grid = interpolation(points, count, first)
        back = interpolation(count, points, first)
        w_in = torch.einsum("hjf,jn->hnf", first.view(first.shape[0], points, width_in),
                            onto_grid).reshape(first.shape[0], count * width_in)  # fmt: skip
        weight, bias = last
        w_out = torch.einsum("nj,jfh->nfh", back, weight.view(points, width_out, -1))
        b_out = (back @ bias.view(points, width_out)).reshape(-1)
        return [(w_in, layers[0][1]), *layers[1:-1], (w_out.reshape(count * width_out, -1), b_out)]
