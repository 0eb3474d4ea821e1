"""Baseline: one MLP from the flattened state and action to the flattened state change.

No structure: it sees the rod as a vector of N*F numbers (F = 7 per segment, 14 with the
velocity input). Trained and evaluated exactly like
``in-bilstm`` (same normalisation, loss and rollout), it shows what the graph + bi-LSTM
structure buys.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from dlocli.models.base import ACTION_DIM, STATE_DIM, DynamicsModel, mlp
from dlocli.models.spec import MLPSpec, ModelSpec


class MLPDynamics(DynamicsModel):
    """Flattened state + action MLP baseline (``layers`` hidden layers, ``hidden`` wide)."""

    spec_cls: ClassVar[type[ModelSpec]] = MLPSpec
    marker_form: ClassVar[str] = "dlocli.models.markers:MarkerMLP"
    spec: MLPSpec

    def __init__(self, spec: MLPSpec, n_segments: int) -> None:
        super().__init__(spec, n_segments)
        n_in = n_segments * self.feature_dim + 2 * ACTION_DIM
        widths = [spec.hidden] * spec.layers
        self.net = mlp([n_in, *widths, n_segments * STATE_DIM])

    def predict_delta(self, state_n: Tensor, action_n: Tensor) -> Tensor:
        batch = state_n.shape[0]
        flat = torch.cat([state_n.reshape(batch, -1), action_n.reshape(batch, -1)], -1)
        return self.net(flat).view(batch, self.n_segments, STATE_DIM)
