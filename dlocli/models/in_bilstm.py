"""The paper's model: an Interaction Network over the chain of nodes with a bi-LSTM.

Yang, Stork, Stoyanov, "Online Model Learning for Shape Control of Deformable Linear
Objects", Sec. IV-B. Each node i (a rod's segment or a tracked marker) has its view's inputs
x_i = (v_i, a_i): its state v_i and the commands a_i acting on it (:class:`~dlocli.models.
network.Nodes`: ``commands`` trailing inputs). Neighbouring nodes are joined by two directed
relations.

- eq. 4: e_i = sum over neighbours j of f_e(x_i, r_ij, u_j), the relation-centric network
  (``edge_layers`` fully connected layers, ``hidden`` wide, ReLU), summed per receiver i,
  where r_ij is the view's relation (the sender's coordinates less the receiver's, at unit
  scale) and u_j the sender's other inputs: an invertible linear change of coordinates of
  (x_i, x_j), so f_e sees the neighbours' relative pose at unit scale instead of a small
  difference of two large absolute coordinates;
- eqs. 6-7: a ``lstm_layers``-layer bidirectional LSTM with ``hidden`` units runs along the
  cable over e_0..e_{N-1}, giving h_left_i (left to right) and h_right_i (right to left);
- eq. 5: the object-centric network f_v(v_i, [h_left_i, h_right_i]) (``node_layers`` layers)
  gives node i's output.

Without ``absolute_position``, x_i stands for x_i less its absolute position, so positions
are seen only relative to the neighbours.

Implementation: every relation of every sample goes through f_e as one batch, the sum per
receiver is two shifted adds on the chain, and the bi-LSTM is the stock ``nn.LSTM`` (oneDNN
on CPU, cuDNN on CUDA) but in two cases, both on CPU at small batches: the rod view's
rollouts that want no gradient (the default MPC's) run whole in
:mod:`dlocli.models.fast_rollout`, and back-propagation through frozen weights (the
gradient planners') takes :mod:`dlocli.models.rnn`. ``reference = True`` runs stock
``nn.LSTM`` throughout (the benchmarks' eager reference).
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models.network import Network, Nodes, mlp
from dlocli.models.rnn import bilstm
from dlocli.models.spec import INBiLSTMSpec, ModelSpec


class INBiLSTM(Network):
    """Interaction Network + bi-LSTM along the cable (the paper's model)."""

    any_count: ClassVar[bool] = True
    spec_cls: ClassVar[type[ModelSpec]] = INBiLSTMSpec
    spec: INBiLSTMSpec

    def __init__(self, spec: INBiLSTMSpec, nodes: Nodes) -> None:
        super().__init__(spec, nodes)
        h = spec.hidden
        own = nodes.inputs - (0 if spec.absolute_position else nodes.absolute)
        # f_e, eq. 4: the receiver's own inputs, the relation, the sender's other inputs
        self.edge_net = mlp([own + nodes.inputs] + [h] * spec.edge_layers)
        self.lstm = torch.nn.LSTM(
            h, h, spec.lstm_layers, batch_first=True, bidirectional=True
        )  # eqs. 6-7
        self.node_net = mlp([own - nodes.commands + 2 * h] + [h] * (spec.node_layers - 1)
                            + [nodes.outputs])  # fmt: skip
        init_forget_bias(self.lstm, 1.0)

    def forward(self, nodes: Tensor, relations: Tensor) -> Tensor:
        own = self.own(nodes)
        hidden = self._lstm(self._effects(own, relations, nodes[..., self.nodes.relative :]))
        state = own[..., : own.shape[-1] - self.nodes.commands]
        return self.node_net(torch.cat([state, hidden], -1))  # eq. 5

    def _effects(self, own: Tensor, relations: Tensor, rest: Tensor) -> Tensor:
        """Eq. 4, the summed effects per node (B, N, H): own (B, N, O) inputs of each
        receiver, relations (B, N-1, R) of node i+1 to node i, rest (B, N, U) the inputs a
        sender adds."""
        from_left = torch.cat([own[:, 1:], -relations, rest[:, :-1]], -1)  # receivers 1..N-1
        from_right = torch.cat([own[:, :-1], relations, rest[:, 1:]], -1)  # receivers 0..N-2
        out = self.edge_net(torch.cat([from_left, from_right], 1))
        left, right = out.split(own.shape[1] - 1, dim=1)
        pad = torch.nn.functional.pad
        return pad(left, (0, 0, 1, 0)) + pad(right, (0, 0, 0, 1))

    def _lstm(self, effects: Tensor) -> Tensor:
        """Eqs. 6-7: (B, N, H) summed effects -> (B, N, 2H) [h_left_i, h_right_i]."""
        if self.reference:
            return self.lstm(effects)[0]
        if effects.is_cuda:
            # cuDNN; its backward needs training mode, which changes nothing here (no dropout)
            mode = self.lstm.training
            self.lstm.training = True
            try:
                return self.lstm(effects)[0]
            finally:
                self.lstm.training = mode
        return bilstm(effects, self.lstm)


@torch.no_grad()
def init_forget_bias(lstm: torch.nn.LSTM, value: float) -> None:
    """Start the forget gates open (bias ``value``), so the commands at the rod's ends reach
    the far segments early in training (Jozefowicz et al. 2015); initialisation only."""
    h = lstm.hidden_size
    for name, param in lstm.named_parameters():
        if name.startswith("bias_ih"):
            param[h : 2 * h].fill_(value)
        elif name.startswith("bias_hh"):
            param[h : 2 * h].zero_()
