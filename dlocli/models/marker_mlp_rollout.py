"""The marker MLP's whole open-loop rollout as one autograd operation, for CPU training.

Training rolls the ``mlp`` network in the marker view out k steps (64 in the recipe) at
batch 32 and back-propagates through all of them. Per step the arithmetic is three small
matrix products forward and five backward; through autograd each step adds ~15 graph nodes
whose fixed costs were most of the step's time even with the fixed arithmetic fused
(:mod:`dlocli.models.marker_steps`). Here the rollout records no graph:

- forward, per step: the features loop, the layers as ``addmm`` into preallocated
  time-major buffers (each step's activations kept there), the advance loop;
- backward, per step in reverse: the advance's backward loop, the gradient through the
  layers to the features (one product per layer), the features' backward loop; each step's
  position gradients are summed in place into the two steps before it (as x_t and x_{t-1});
- the weights' gradients at the end as one product per layer over all k x B rows, not k
  products of B rows (the same sum, faster to compute in one go).

The rollout's inputs (starts, held markers' futures) take no gradient here; where they want
one the per-step path of :class:`~dlocli.models.marker_model.MarkerModel` runs.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from dlocli.models import marker_steps
from dlocli.models.marker_steps import (
    StepConstants,
    advance_backward,
    advance_forward,
    features_backward,
    features_forward,
)
from dlocli.models.rollouts import dense_layers, wants_gradient


def usable(x: Tensor, x_prev: Tensor, held_future: Tensor) -> bool:
    """Whether :func:`rollout` applies where the fused steps do: no gradient is wanted for
    the rollout's inputs."""
    return not wants_gradient([x, x_prev, held_future])


def rollout(
    model: Any,
    layers: list[tuple[Tensor, Tensor]],
    x: Tensor,
    x_prev: Tensor,
    held_future: Tensor,
    held: Tensor,
    lengths: Tensor,
) -> Tensor:
    """``model.rollout`` (B, V, 3), (B, V, 3), (B, H, V, 3) -> (B, H, V, 3) as one operation;
    ``layers``: the network's (weight, bias) for V markers (``flat_layers``), ReLU between;
    ``lengths`` (B, V-1): the neighbour distances the projection keeps."""
    constants = marker_steps.step_constants(model, held, model.spec.length_projection)
    params = [t for layer in layers for t in layer]
    return MLPRollout.apply(x, x_prev, held_future, lengths, constants, *params)


class MLPRollout(torch.autograd.Function):
    """See the module docstring; ``params``: each layer's weight and bias in order."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, x_prev: Tensor, held_future: Tensor, lengths: Tensor,
                k: StepConstants, *params: Tensor) -> Tensor:  # fmt: skip
        batch, horizon, n = held_future.shape[:3]
        weights, biases = params[0::2], params[1::2]
        # time-major buffers: step t's rows are contiguous
        inputs = [x.new_empty(horizon, batch, w.shape[1]) for w in weights]  # of every layer
        acc = x.new_empty(batch, n * 3)
        before = x.new_empty(horizon, batch, n, 3)
        out = x.new_empty(horizon, batch, n, 3)
        future = held_future.detach().transpose(0, 1).contiguous().numpy()
        lengths = lengths.detach().contiguous().numpy()
        cur, prev = x.detach().contiguous().numpy(), x_prev.detach().contiguous().numpy()
        steps = [buffer.unbind(0) for buffer in inputs]  # per-step views, made at once
        layers = list(zip(biases, [w.t() for w in weights], strict=True))
        for t in range(horizon):
            features_forward(cur, prev, future[t], k.held, k.position_scale,
                             k.velocity_scale, steps[0][t].view(batch, n, 10).numpy())  # fmt: skip
            # each layer's output is the next one's input, kept for the backward
            outs = [*(s[t] for s in steps[1:]), acc]
            dense_layers(steps[0][t], layers, outs, relu_last=False)
            advance_forward(cur, prev, future[t], acc.view(batch, n, 3).numpy(), k.held,
                            k.acceleration_scale, lengths, k.sweeps, before[t].numpy(),
                            out[t].numpy())  # fmt: skip
            prev, cur = cur, out[t].numpy()
        ctx.save_for_backward(*weights, *inputs, before)
        ctx.lengths, ctx.constants, ctx.layers = lengths, k, len(weights)
        return out.transpose(0, 1).contiguous()

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors
        layers = ctx.layers
        weights, inputs, before = saved[:layers], saved[layers : 2 * layers], saved[-1]
        k, lengths = ctx.constants, ctx.lengths
        horizon, batch, n = before.shape[:3]
        # the positions' gradients, two leading rows for the starts x_{t-1} and x_t (unused)
        g_pos = grad.new_zeros(horizon + 2, batch, n, 3)
        g_pos[2:] = grad.transpose(0, 1)
        g_pos_np = g_pos.numpy()
        g_next = grad.new_zeros(batch, n, 3).numpy()  # the held futures': not wanted
        # the gradient at each layer's output, every step (for the weights' products)
        g_out = [grad.new_empty(horizon, batch, w.shape[0]) for w in weights]
        g_steps = [g.unbind(0) for g in g_out]
        a_steps = [a.unbind(0) for a in inputs]
        before_np = before.numpy()
        g_features = grad.new_empty(batch, n * 10)
        g_hidden = [grad.new_empty(batch, w.shape[1]) for w in weights[1:]]
        relu_backward = torch.ops.aten.threshold_backward.grad_input
        for t in range(horizon - 1, -1, -1):
            advance_backward(g_pos_np[t + 2], before_np[t], k.held, k.acceleration_scale,
                             lengths, k.sweeps, g_steps[-1][t].view(batch, n, 3).numpy(),
                             g_pos_np[t + 1], g_pos_np[t], g_next)  # fmt: skip
            for i in range(layers - 1, 0, -1):  # through layer i, then the ReLU before it
                torch.mm(g_steps[i][t], weights[i], out=g_hidden[i - 1])
                relu_backward(g_hidden[i - 1], a_steps[i][t], 0, grad_input=g_steps[i - 1][t])
            torch.mm(g_steps[0][t], weights[0], out=g_features)
            features_backward(g_features.view(batch, n, 10).numpy(), k.held, k.position_scale,
                              k.velocity_scale, g_pos_np[t + 1], g_pos_np[t], g_next)  # fmt: skip
        grads: list[Tensor] = []
        for g, a in zip(g_out, inputs, strict=True):
            rows = g.reshape(horizon * batch, -1)
            grads += [rows.t() @ a.reshape(horizon * batch, -1), rows.sum(0)]
        return None, None, None, None, None, *grads
