"""The model spec (torch-free, so the CLI can build its --help without importing torch)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import Field

from dlocli.specs import TASK_LEGACY_VALUES, Spec


class ModelSpec(Spec):
    """Which dynamics model, and its sizes (paper defaults)."""

    name: str = Field("in-bilstm", description="Dynamics model (see `dlo list`).")
    velocity_input: bool = Field(
        True,
        description="Also give the model each segment's change over the previous control step "
        "(a finite-difference velocity): the rod has inertia, so position and orientation "
        "alone do not determine its next state.",
    )
    absolute_position: bool = Field(
        True,
        description="in-bilstm: give f_e and f_v each segment's absolute position (the paper's "
        "encoding). Off, the segments' own features are orientation and velocity, and "
        "positions enter only as neighbour differences: the model is then exactly "
        "translation-invariant, as a rod without contacts is.",
    )
    hidden: int = Field(150, gt=0, description="Width of every hidden layer and of the LSTM.")
    edge_layers: int = Field(4, gt=0, description="Layers of the relation-centric network f_e.")
    node_layers: int = Field(4, gt=0, description="Layers of the object-centric network f_v.")
    lstm_layers: int = Field(2, gt=0, description="Layers of the bidirectional LSTM along the rod.")
    mlp_layers: int = Field(4, gt=0, description="Hidden layers of the `mlp` baseline.")
    mlp_hidden: int = Field(512, gt=0, description="Width of the `mlp` baseline's hidden layers.")


#: ModelSpec fields added after models and runs were first saved, with the value that
#: rebuilds what was saved before the field existed
LEGACY_VALUES: dict[str, Any] = {"velocity_input": False, "absolute_position": True}


def with_legacy_fields(saved: Any) -> Any:
    """A saved model spec (dict) with the fields it predates set to their legacy values."""
    if not isinstance(saved, dict):
        return saved
    return {**{k: v for k, v in LEGACY_VALUES.items() if k not in saved}, **saved}


def saved_spec(path: Path) -> Any:
    """A run's spec.json as data, its model and task specs completed with the fields they
    predate (ValueError if it is not JSON)."""
    data = json.loads(Path(path).read_text())
    if isinstance(data, dict) and isinstance(data.get("model"), dict):
        data["model"] = with_legacy_fields(data["model"])
    if isinstance(data, dict) and isinstance(data.get("task"), dict):
        data["task"] = {**TASK_LEGACY_VALUES, **data["task"]}
    return data
