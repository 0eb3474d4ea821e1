"""Self-attention along the cable: every segment (or marker) is a token, each token attends
to all others through ``encoder_layers`` pre-norm Transformer encoder layers (the stock
``nn.TransformerEncoderLayer``), and a linear head reads each token's normalised change.

Where the paper's model passes messages between neighbours and carries them along the cable
with a bi-LSTM, attention lets every part of the cable read every other in one layer (the
graph-attention family of GA-Net, Wang et al.). Tokens know where they sit along the cable
from Fourier features of their arc position s = i / (N - 1) in [0, 1], so one network serves
cables of any segment or marker count (:data:`ARC_FREQUENCIES` pairs of sin/cos).

In the rod view a token holds a segment's normalised features and the gripper commands on
the end segments; in the marker view a marker's features and, since it reads the cable's
geometry (``cable_geometry``), the vectors to both neighbours, their lengths and the cable's
length: what tells one cable from another, so one network can learn several cables.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models.network import Network, Nodes
from dlocli.models.spec import AttentionSpec, ModelSpec

ARC_FREQUENCIES = 4


def arc_features(n: int, like: Tensor) -> Tensor:
    """(N, 2 * ARC_FREQUENCIES) sin/cos of the arc position i / (N - 1) at frequencies
    pi/2, pi, 2 pi, 4 pi: the coarse ones tell the ends apart, the fine ones neighbours."""
    s = torch.linspace(0.0, 1.0, n, dtype=like.dtype, device=like.device)[:, None]
    angles = s * (math.pi / 2) * 2.0 ** torch.arange(ARC_FREQUENCIES, device=like.device)
    return torch.cat([torch.sin(angles), torch.cos(angles)], -1)


class AlongCable(torch.nn.Module):
    """Tokens (B, N, n_in) -> (B, N, n_out): input projection with the arc features, the
    encoder layers, a final norm and a linear head (started small: early rollouts stay near
    the data, and gradients still reach the inputs)."""

    def __init__(self, n_in: int, n_out: int, spec: AttentionSpec) -> None:
        super().__init__()
        d = spec.hidden
        self.embed = torch.nn.Linear(n_in + 2 * ARC_FREQUENCIES, d)
        layer = torch.nn.TransformerEncoderLayer(
            d, spec.heads, 2 * d, dropout=0.0, activation="gelu", batch_first=True,
            norm_first=True,
        )  # fmt: skip
        self.encoder = torch.nn.TransformerEncoder(
            layer, spec.encoder_layers, enable_nested_tensor=False
        )
        self.norm = torch.nn.LayerNorm(d)
        self.head = torch.nn.Linear(d, n_out)
        with torch.no_grad():
            self.head.weight.mul_(0.1)
            self.head.bias.zero_()

    def forward(self, tokens: Tensor) -> Tensor:
        arc = arc_features(tokens.shape[1], tokens).expand(tokens.shape[0], -1, -1)
        hidden = self.encoder(self.embed(torch.cat([tokens, arc], -1)))
        return self.head(self.norm(hidden))


class Attention(Network):
    """Self-attention over the nodes along the cable (see the module docstring)."""

    any_count: ClassVar[bool] = True
    spec_cls: ClassVar[type[ModelSpec]] = AttentionSpec
    cable_geometry: ClassVar[bool] = True
    spec: AttentionSpec

    def __init__(self, spec: AttentionSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        self.net = AlongCable(nodes.inputs, nodes.outputs, spec)

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        return self.net(nodes)
