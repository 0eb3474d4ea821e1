"""Learned dynamics models: one network per architecture, one module each, all implementing
:class:`~dlocli.models.network.Network` and registered here in :data:`dlocli.registry.models`,
seen through the rod view (:class:`~dlocli.models.base.DynamicsModel`) or the marker view
(:class:`~dlocli.models.marker_model.MarkerModel`); each declares its options as a
:class:`~dlocli.models.spec.ModelSpec` subclass, ``spec_cls`` (registered beside it, so
``--help`` lists them without importing torch).

Names are imported lazily, so ``dlocli.models.spec`` stays usable without importing torch.
"""

from __future__ import annotations

from typing import Any

from dlocli.registry import import_target, models

models.register(
    "in-bilstm",
    "dlocli.models.in_bilstm:INBiLSTM",
    "Interaction Network + bi-LSTM along the cable (the paper's model)",
    spec="dlocli.models.spec:INBiLSTMSpec",
)
models.register(
    "mlp",
    "dlocli.models.mlp:MLP",
    "flattened MLP baseline (one node count)",
    spec="dlocli.models.spec:MLPSpec",
)
models.register(
    "arc-mlp",
    "dlocli.models.arc_mlp:ArcMLP",
    "MLP over a fixed grid along the cable, any node count at the MLP's speed",
    spec="dlocli.models.spec:ArcMLPSpec",
)
models.register(
    "attention",
    "dlocli.models.attention:Attention",
    "self-attention along the cable, any node count (GA-Net family)",
    spec="dlocli.models.spec:AttentionSpec",
)

_EXPORTS = {
    "ModelSpec": "dlocli.models.spec",
    "model_spec": "dlocli.models.spec",
    "DynamicsModel": "dlocli.models.base",
    "MarkerModel": "dlocli.models.marker_model",
    "Network": "dlocli.models.network",
    "Nodes": "dlocli.models.network",
    "build_model": "dlocli.models.base",
    "load_model": "dlocli.models.checkpoints",
    "resolve_device": "dlocli.models.base",
    "save_checkpoint": "dlocli.models.checkpoints",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dlocli.models' has no attribute '{name}'")
    return import_target(f"{_EXPORTS[name]}:{name}")
