"""The paper's model: an Interaction Network over the rod's chain graph with a bi-LSTM.

Yang, Stork, Stoyanov, "Online Model Learning for Shape Control of Deformable Linear
Objects", Sec. IV-B. Each segment i is a node with encoding x_i = (v_i, a_i): its state v_i
(position, quaternion) and the command a_i of the gripper holding it (zeros for segments no
gripper holds). Neighbouring segments are joined by two directed relations.

- eq. 4: e_i = sum over neighbours j of f_e(v_i, a_i, v_j, a_j), the relation-centric network
  (``edge_layers`` fully connected layers, ``hidden`` wide, ReLU), summed per receiver i;
- eqs. 6-7: a ``lstm_layers``-layer bidirectional LSTM with ``hidden`` units runs along the
  rod over e_0..e_{N-1}, giving h_left_i (left to right) and h_right_i (right to left);
- eq. 5: the object-centric network f_v(v_i, [h_left_i, h_right_i]) (``node_layers`` layers)
  gives segment i's normalised state change.

Fast path (same mathematics): f_e's first layer is split into receiver and sender halves
applied once per node instead of once per relation (W [x_i; x_j] = W_r x_i + W_s x_j), every
relation of every sample goes through f_e as one batch, the sum per receiver is two shifted
adds on the chain, and the LSTM is :mod:`dlocli.models.rnn` on CPU (cuDNN on CUDA).
``model.reference = True`` runs the plain PyTorch formulation instead (benchmarks).
"""

from __future__ import annotations

import torch
from torch import Tensor

from dlocli.models.base import ACTION_DIM, STATE_DIM, DynamicsModel, ModelSpec, mlp, node_actions
from dlocli.models.rnn import bilstm

NODE_DIM = STATE_DIM + ACTION_DIM


class INBiLSTM(DynamicsModel):
    """Interaction Network + bi-LSTM along the rod (the paper's model)."""

    def __init__(self, spec: ModelSpec, n_segments: int) -> None:
        super().__init__(spec, n_segments)
        h = spec.hidden
        self.edge_net = mlp([2 * NODE_DIM] + [h] * spec.edge_layers)  # f_e, eq. 4
        self.lstm = torch.nn.LSTM(
            h, h, spec.lstm_layers, batch_first=True, bidirectional=True
        )  # eqs. 6-7
        self.node_net = mlp([STATE_DIM + 2 * h] + [h] * (spec.node_layers - 1) + [STATE_DIM])
        init_forget_bias(self.lstm, 1.0)


    def predict_delta(self, state_n: Tensor, action_n: Tensor) -> Tensor:
        x = torch.cat([state_n, node_actions(action_n, self.n_segments)], -1)  # (B, N, 13)
        effects = self._effects_reference(x) if self.reference else self._effects(x)
        hidden = self._lstm(effects)  # (B, N, 2H): [h_left_i, h_right_i]
        return self.node_net(torch.cat([state_n, hidden], -1))  # eq. 5

    def _effects(self, x: Tensor) -> Tensor:
        """Eq. 4, summed relation effects per segment: (B, N, 13) -> (B, N, H)."""
        first = self.edge_net[0]
        w_recv, w_send = first.weight.split(NODE_DIM, dim=1)
        recv = torch.nn.functional.linear(x, w_recv, first.bias)  # (B, N, H)
        send = torch.nn.functional.linear(x, w_send)
        # relations j -> i: from the left neighbour (i = 1..N-1) and the right one (i = 0..N-2)
        pre = torch.cat([recv[:, 1:] + send[:, :-1], recv[:, :-1] + send[:, 1:]], 1)
        out = self.edge_net[1:](pre)  # (B, 2(N-1), H)
        return self._sum_per_receiver(out)

    def _effects_reference(self, x: Tensor) -> Tensor:
        """Eq. 4 written plainly: build each relation's (x_i, x_j) input, apply f_e."""
        pairs = torch.cat(
            [torch.cat([x[:, 1:], x[:, :-1]], -1), torch.cat([x[:, :-1], x[:, 1:]], -1)], 1
        )
        return self._sum_per_receiver(self.edge_net(pairs))

    def _sum_per_receiver(self, out: Tensor) -> Tensor:
        """(B, 2(N-1), H) relation effects -> (B, N, H), summed per receiving segment."""
        from_left, from_right = out.split(self.n_segments - 1, dim=1)
        pad = torch.nn.functional.pad
        return pad(from_left, (0, 0, 1, 0)) + pad(from_right, (0, 0, 0, 1))

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
