"""The dynamics-model contract: s_{t+1} = f(s_t, a_t) for the rod's segments.

Shapes and units (every model, every device):
- state ``(B, N, 7)``: per segment position (metres, world frame) then unit quaternion (w,x,y,z).
- action ``(B, 2, 6)``: per-gripper commands in [-1, 1] (left, right; linear then angular),
  the same units as the dataset's ``actions``. A single-gripper task's left row is zero; a
  bimanual task fills both: models act on the end segments, which is what makes a model
  trained on the single task usable on the bimanual one (paper Fig. 5).
- ``forward`` returns the next state ``(B, N, 7)`` with unit quaternions.
- ``rollout(state, actions (B, H, 2, 6))`` returns ``(B, H, N, 7)``, differentiable with
  respect to ``actions``.
"""

from __future__ import annotations

from pydantic import Field

from dlocli.specs import Spec


class ModelSpec(Spec):
    """Which dynamics model, and its sizes (paper defaults)."""

    name: str = Field("in-bilstm", description="Dynamics model (see `dlo list`).")
    hidden: int = Field(150, gt=0, description="Width of every hidden layer and of the LSTM.")
    edge_layers: int = Field(4, gt=0, description="Layers of the relation-centric network f_e.")
    node_layers: int = Field(4, gt=0, description="Layers of the object-centric network f_v.")
    lstm_layers: int = Field(2, gt=0, description="Layers of the bidirectional LSTM along the rod.")
    mlp_layers: int = Field(4, gt=0, description="Hidden layers of the `mlp` baseline.")
    mlp_hidden: int = Field(512, gt=0, description="Width of the `mlp` baseline's hidden layers.")
