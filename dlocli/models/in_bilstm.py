"""The paper's model: an Interaction Network over the rod's chain graph with a bi-LSTM.

Yang, Stork, Stoyanov, "Online Model Learning for Shape Control of Deformable Linear
Objects", Sec. IV-B. Each segment i is a node with encoding x_i = (v_i, a_i): its state v_i
(position, quaternion, and with ``velocity_input`` its change over the last control step)
and the command a_i of the gripper holding it (zeros for segments no gripper holds).
Neighbouring segments are joined by two directed relations.

- eq. 4: e_i = sum over neighbours j of f_e(v_i, a_i, v_j, a_j), the relation-centric network
  (``edge_layers`` fully connected layers, ``hidden`` wide, ReLU), summed per receiver i;
- eqs. 6-7: a ``lstm_layers``-layer bidirectional LSTM with ``hidden`` units runs along the
  rod over e_0..e_{N-1}, giving h_left_i (left to right) and h_right_i (right to left);
- eq. 5: the object-centric network f_v(v_i, [h_left_i, h_right_i]) (``node_layers`` layers)
  gives segment i's normalised state change.

Implementation: every relation of every sample goes through f_e as one batch, the sum per
receiver is two shifted adds on the chain, and the bi-LSTM is the stock ``nn.LSTM`` (oneDNN
on CPU, cuDNN on CUDA) but in two cases, both on CPU at small batches: rollouts that want no
gradient (the default MPC's) run whole in :mod:`dlocli.models.fast_rollout`, and
back-propagation through frozen weights (the gradient planners') takes
:mod:`dlocli.models.rnn`. ``model.reference = True`` runs stock ``nn.LSTM`` throughout (the
benchmarks' eager reference).
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models import fast_rollout
from dlocli.models.base import ACTION_DIM, STATE_DIM, DynamicsModel, mlp, node_actions
from dlocli.models.rnn import bilstm
from dlocli.models.spec import INBiLSTMSpec, ModelSpec


class INBiLSTM(DynamicsModel):
    """Interaction Network + bi-LSTM along the rod (the paper's model)."""

    spec_cls: ClassVar[type[ModelSpec]] = INBiLSTMSpec
    marker_form: ClassVar[str] = "dlocli.models.markers:MarkerINBiLSTM"
    spec: INBiLSTMSpec

    def __init__(self, spec: INBiLSTMSpec, n_segments: int) -> None:
        super().__init__(spec, n_segments)
        h = spec.hidden
        own = self.feature_dim - (0 if spec.absolute_position else 3)  # a segment's own features
        # f_e, eq. 4: (v_i, a_i) of the receiver, and the sender's relative pose, rest and a_j
        self.edge_net = mlp([own + self.feature_dim + 2 * ACTION_DIM] + [h] * spec.edge_layers)
        self.lstm = torch.nn.LSTM(
            h, h, spec.lstm_layers, batch_first=True, bidirectional=True
        )  # eqs. 6-7
        self.node_net = mlp([own + 2 * h] + [h] * (spec.node_layers - 1) + [STATE_DIM])
        init_forget_bias(self.lstm, 1.0)

    def rollout(self, state: Tensor, actions: Tensor, previous: Tensor | None = None) -> Tensor:
        """:meth:`DynamicsModel.rollout`; forward-only small batches on CPU (the planners')
        take :mod:`dlocli.models.fast_rollout`, several times faster at batch 1."""
        if actions.dim() == 4 and fast_rollout.usable(self, state, actions, previous):
            self._check(state, actions[:, 0], previous)
            return fast_rollout.rollout(self, state, actions, previous)
        return super().rollout(state, actions, previous)

    def predict_delta(self, state_n: Tensor, action_n: Tensor) -> Tensor:
        effects = self._effects(state_n, node_actions(action_n, self.n_segments))
        hidden = self._lstm(effects)  # (B, N, 2H): [h_left_i, h_right_i]
        return self.node_net(torch.cat([self._own(state_n), hidden], -1))  # eq. 5

    def _own(self, v: Tensor) -> Tensor:
        """A segment's own features: all of v, or without the absolute position."""
        return v if self.spec.absolute_position else v[..., 3:]

    def _effects(self, v: Tensor, a: Tensor) -> Tensor:
        """Eq. 4, the summed effects per segment: v (B, N, F), a (B, N, 6) -> (B, N, H).

        The relation j -> i is presented to f_e as (v_i, a_i, k (p_j - p_i), u_j, a_j), with
        p the pose part of v (its first 7 features), u the rest (the velocity, if any) and k
        the buffer ``relation_scale``: an invertible linear change of coordinates of
        (v_i, a_i, v_j, a_j), so f_e is the same family of functions, but its first layer
        sees the neighbours' relative pose at unit scale instead of a small difference of two
        large absolute coordinates. Without ``absolute_position``, v_i stands for v_i less
        its position, so positions are seen only relative to the neighbours.
        """
        pose, rest = v[..., :STATE_DIM], v[..., STATE_DIM:]
        diff = (pose[:, 1:] - pose[:, :-1]) * self.relation_scale  # k (p_{i+1} - p_i)
        x = torch.cat([self._own(v), a], -1)
        from_left = torch.cat([x[:, 1:], -diff, rest[:, :-1], a[:, :-1]], -1)  # receivers 1..N-1
        from_right = torch.cat([x[:, :-1], diff, rest[:, 1:], a[:, 1:]], -1)  # receivers 0..N-2
        return self._sum_per_receiver(self.edge_net(torch.cat([from_left, from_right], 1)))

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
