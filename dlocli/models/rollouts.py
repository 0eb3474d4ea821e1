"""How both views roll a model out: a fused rollout where one is offered, else step by step.

A view lists the offers of its fused rollouts (hand-written CPU rollouts; the offers are the
view's methods, as they read its internals) in ``fused_rollouts`` on its class, in the order
tried: the rod view the in-bilstm's forward-only one
(:mod:`dlocli.models.fast_rollout`), the marker view the fully connected networks' whole
rollout (:mod:`dlocli.models.marker_mlp_rollout`), then any network's fused steps
(:mod:`dlocli.models.marker_steps`). Each is an :data:`Offer`: from the model and the
rollout's inputs, the rollout ready to run, or None where it does not compute it (another
network, a device, dtype or gradient its loops do not take). :func:`rollout` is the one
place that decides; :func:`open_loop` is the step-by-step loop of both views.

Each fused rollout keeps its own kernels, weights and buffers: the rod's weights are repacked
and its buffers kept per batch size across the planners' calls (the weights are frozen
there); the marker's weights are the live parameters and its buffers made per call (its
backward reads every step's activations). What they share sits here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

#: (model, *the rollout's inputs) -> the fused rollout ready to run, or None
Offer = Callable[..., Callable[[], Tensor] | None]


def rollout(model: Any, inputs: tuple, plain: Callable[..., Tensor]) -> Tensor:
    """The first of the view's fused rollouts that offers to compute ``plain(*inputs)``,
    else ``plain(*inputs)``."""
    for offer in type(model).fused_rollouts:
        run = offer(model, *inputs)
        if run is not None:
            return run()
    return plain(*inputs)


def open_loop(
    step: Callable[[Tensor, Tensor | None, Tensor], Tensor],
    x: Tensor,
    previous: Tensor | None,
    inputs: Tensor,
) -> Tensor:
    """The states ``step(x_t, x_{t-1}, inputs[:, t]) -> x_{t+1}`` from t = 0, each fed back,
    stacked (B, H, ...) for ``inputs`` (B, H, ...)."""
    out = []
    for t in range(inputs.shape[1]):
        previous, x = x, step(x, previous, inputs[:, t])
        out.append(x)
    return torch.stack(out, 1)


def loops_take(*tensors: Tensor) -> bool:
    """Whether the compiled loops read these tensors: CPU float32, their layout."""
    return all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)


def wants_gradient(tensors: Sequence[Tensor]) -> bool:
    """Whether autograd would record a gradient for any of ``tensors``."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def dense_layers(
    x: Tensor, layers: Sequence[tuple[Tensor, Tensor]], outs: Sequence[Tensor], relu_last: bool
) -> Tensor:
    """``x`` through fully connected ``layers`` (bias, W^T), ReLU between them (and after the
    last with ``relu_last``), each layer's output written into its buffer in ``outs``."""
    last = len(layers) - 1
    for i, ((bias, weight_t), out) in enumerate(zip(layers, outs, strict=True)):
        x = torch.addmm(bias, x, weight_t, out=out)
        if i < last or relu_last:
            x.relu_()
    return x
