"""The model spec (torch-free, so the CLI can build its --help without importing torch)."""

from __future__ import annotations

from pydantic import Field

from dlocli.specs import Spec


class ModelSpec(Spec):
    """Which dynamics model, and its sizes (paper defaults)."""

    name: str = Field("in-bilstm", description="Dynamics model (see `dlo list`).")
    velocity_input: bool = Field(
        True,
        description="Also give the model each segment's change over the previous control step "
        "(a finite-difference velocity): the rod has inertia, so position and orientation "
        "alone do not determine its next state.",
    )
    hidden: int = Field(150, gt=0, description="Width of every hidden layer and of the LSTM.")
    edge_layers: int = Field(4, gt=0, description="Layers of the relation-centric network f_e.")
    node_layers: int = Field(4, gt=0, description="Layers of the object-centric network f_v.")
    lstm_layers: int = Field(2, gt=0, description="Layers of the bidirectional LSTM along the rod.")
    mlp_layers: int = Field(4, gt=0, description="Hidden layers of the `mlp` baseline.")
    mlp_hidden: int = Field(512, gt=0, description="Width of the `mlp` baseline's hidden layers.")
