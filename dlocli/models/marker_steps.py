"""The marker models' fixed arithmetic around the network, fused for CPU training.

One open-loop step of a marker model (:mod:`dlocli.models.marker_model`) is the network between
two pieces of fixed arithmetic: the features before it (centroid-relative positions,
velocities, held displacements, all scaled) and the advance after it (the Verlet update, the
held markers set, then ``length_projection`` sweeps of the neighbour-distance projection).
Written in PyTorch operations those two pieces are ~100 small operations per step forward and
as many autograd nodes backward; at the recipes' sizes (12 markers, batch 32) their fixed
cost per operation, not arithmetic, took most of a training step
(``benchmarks/training_throughput.py``). Here each piece is one autograd Function whose
forward and backward are numba loops over the batch: two calls per step each way.

The backward of the projection recomputes the sweeps' intermediate positions from the
pre-projection ones (six small states per sample for three sweeps) instead of keeping them.
The gradients are the exact derivatives of the PyTorch path's arithmetic (tested against its
autograd); the neighbour distances the projection aims at are constants (no gradient).
CPU float32 only: elsewhere (CUDA, float64) the PyTorch path runs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from dlocli.models.rollouts import loops_take

jit = numba.njit(cache=True, nogil=True, error_model="numpy")

_F = np.float32
TINY = _F(1e-9)  # the projection's smallest distance (as project_lengths' clamp)


# ---------------------------------------------------------------------- features
@jit
def features_forward(x, x_prev, held_next, held, position_scale, velocity_scale, out):
    """out (B, V, 10): (x - held centroid) / ps, (x - x_prev) / vs, (held_next - x) * held
    / vs, held flag; ``held`` (V,) is 1.0 for held markers, 0.0 for free ones."""
    batch, n = x.shape[0], x.shape[1]
    count = held.sum()
    for b in range(batch):
        for k in range(3):
            total = _F(0.0)
            for i in range(n):
                total += x[b, i, k] * held[i]
            centre = total / count
            for i in range(n):
                out[b, i, k] = (x[b, i, k] - centre) / position_scale[k]
                out[b, i, 3 + k] = (x[b, i, k] - x_prev[b, i, k]) / velocity_scale[k]
                out[b, i, 6 + k] = (held_next[b, i, k] - x[b, i, k]) * held[i] / velocity_scale[k]
        for i in range(n):
            out[b, i, 9] = held[i]


@jit
def features_backward(grad, held, position_scale, velocity_scale, g_x, g_prev, g_next):
    """The gradients of :func:`features_forward`'s inputs from ``grad`` (B, V, 10), added
    to g_x, g_prev, g_next (a rollout's backward sums every step's share in place)."""
    batch, n = grad.shape[0], grad.shape[1]
    count = held.sum()
    for b in range(batch):
        for k in range(3):
            spread = _F(0.0)  # the centroid's share: every marker's relative-position gradient
            for i in range(n):
                spread += grad[b, i, k] / position_scale[k]
            spread /= count
            for i in range(n):
                g_rel = grad[b, i, k] / position_scale[k]
                g_vel = grad[b, i, 3 + k] / velocity_scale[k]
                g_held = grad[b, i, 6 + k] * held[i] / velocity_scale[k]
                g_x[b, i, k] += g_rel - held[i] * spread + g_vel - g_held
                g_prev[b, i, k] -= g_vel
                g_next[b, i, k] += g_held


# ---------------------------------------------------------------------- advance
@jit
def _half_sweep(y, lengths_b, free, first):
    """One half of a projection sweep on one sample's positions y (V, 3), in place."""
    for a in range(first, y.shape[0] - 1, 2):
        d0 = y[a + 1, 0] - y[a, 0]
        d1 = y[a + 1, 1] - y[a, 1]
        d2 = y[a + 1, 2] - y[a, 2]
        dist = max(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), TINY)
        c = (dist - lengths_b[a]) / dist / max(free[a] + free[a + 1], _F(1.0))
        wa, wb = c * free[a], c * free[a + 1]
        y[a, 0] += d0 * wa
        y[a, 1] += d1 * wa
        y[a, 2] += d2 * wa
        y[a + 1, 0] -= d0 * wb
        y[a + 1, 1] -= d1 * wb
        y[a + 1, 2] -= d2 * wb


@jit
def advance_forward(x, x_prev, held_next, acc, held, acceleration_scale, lengths, sweeps,
                    before, out):  # fmt: skip
    """out = the next positions: 2 x - x_prev + acc * as for free markers, held_next for held
    ones (also written to ``before``), then ``sweeps`` projection sweeps onto ``lengths``
    (B, V-1); ``sweeps`` 0 projects nothing."""
    batch, n = x.shape[0], x.shape[1]
    free = _F(1.0) - held
    for b in range(batch):
        for i in range(n):
            for k in range(3):
                if held[i] > 0:
                    y = held_next[b, i, k]
                else:
                    step = acc[b, i, k] * acceleration_scale[k]
                    y = _F(2.0) * x[b, i, k] - x_prev[b, i, k] + step
                before[b, i, k] = y
                out[b, i, k] = y
        for _ in range(sweeps):
            _half_sweep(out[b], lengths[b], free, 0)
            _half_sweep(out[b], lengths[b], free, 1)


@jit
def advance_backward(grad, before, held, acceleration_scale, lengths, sweeps, g_acc, g_x,
                     g_prev, g_next):  # fmt: skip
    """The gradients of :func:`advance_forward`'s inputs from ``grad`` (B, V, 3): back
    through the half sweeps in reverse (their inputs recomputed from ``before``), then the
    update. ``g_acc`` is written; the others are added to (as in :func:`features_backward`)."""
    batch, n = grad.shape[0], grad.shape[1]
    free = _F(1.0) - held
    states = np.empty((2 * sweeps, n, 3), np.float32)  # the input of every half sweep
    g = np.empty((n, 3), np.float32)
    for b in range(batch):
        y = before[b].copy()
        for h in range(2 * sweeps):
            states[h] = y
            _half_sweep(y, lengths[b], free, h % 2)
        g[:] = grad[b]
        for h in range(2 * sweeps - 1, -1, -1):
            _half_sweep_backward(states[h], g, lengths[b], free, h % 2)
        for i in range(n):
            for k in range(3):
                if held[i] > 0:
                    g_acc[b, i, k] = _F(0.0)
                    g_next[b, i, k] += g[i, k]
                else:
                    g_acc[b, i, k] = g[i, k] * acceleration_scale[k]
                    g_x[b, i, k] += _F(2.0) * g[i, k]
                    g_prev[b, i, k] -= g[i, k]


@jit
def _half_sweep_backward(y, g, lengths_b, free, first):
    """g (V, 3), the gradient at the output of the half sweep whose input was y, becomes the
    gradient at its input (in place). Per edge, with d = y[a+1] - y[a] and share s = c d,
    c = (|d| - L) / |d| / m: ds/dd = c I + L / (m |d|^3) d d^T (the distance clamped: c I)."""
    for a in range(first, y.shape[0] - 1, 2):
        d0 = y[a + 1, 0] - y[a, 0]
        d1 = y[a + 1, 1] - y[a, 1]
        d2 = y[a + 1, 2] - y[a, 2]
        norm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        dist = max(norm, TINY)
        m = max(free[a] + free[a + 1], _F(1.0))
        c = (dist - lengths_b[a]) / dist / m
        # the gradient at the share: y'[a] = y[a] + free_a s, y'[a+1] = y[a+1] - free_b s
        s0 = free[a] * g[a, 0] - free[a + 1] * g[a + 1, 0]
        s1 = free[a] * g[a, 1] - free[a + 1] * g[a + 1, 1]
        s2 = free[a] * g[a, 2] - free[a + 1] * g[a + 1, 2]
        outer = _F(0.0)
        if norm >= TINY:
            outer = lengths_b[a] / (m * dist * dist * dist) * (d0 * s0 + d1 * s1 + d2 * s2)
        e0, e1, e2 = c * s0 + outer * d0, c * s1 + outer * d1, c * s2 + outer * d2
        g[a, 0] -= e0
        g[a, 1] -= e1
        g[a, 2] -= e2
        g[a + 1, 0] += e0
        g[a + 1, 1] += e1
        g[a + 1, 2] += e2


# ---------------------------------------------------------------------- autograd
@dataclass(frozen=True)
class StepConstants:
    """What every step of one rollout shares, as numpy arrays for the loops."""

    held: np.ndarray  # (V,) 1.0 held, 0.0 free
    position_scale: np.ndarray
    velocity_scale: np.ndarray
    acceleration_scale: np.ndarray
    sweeps: int


def step_constants(model: Any, held: Tensor, sweeps: int) -> StepConstants:
    def array(t: Tensor) -> np.ndarray:
        return t.detach().to(torch.float32).contiguous().numpy()

    return StepConstants(array(held.to(torch.float32)), array(model.position_scale),
                         array(model.velocity_scale), array(model.acceleration_scale),
                         int(sweeps))  # fmt: skip


def step(
    network: Callable[[Tensor], Tensor],
    x: Tensor,
    x_prev: Tensor,
    held_next: Tensor,
    lengths: Tensor | None,
    constants: StepConstants,
    describe: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> Tensor:
    """One open-loop step, the features and the advance fused around ``network``: any
    callable from per-marker inputs (B, V, F) to normalised accelerations (B, V, 3), its
    layers as they are (plain PyTorch, autograd through them). ``describe``: (features, x)
    -> the network's inputs, for networks that read more than the features; ``lengths``
    (B, V-1): the distances the projection keeps, None when ``constants.sweeps`` is 0."""
    if lengths is None:  # not read: no sweeps
        lengths = x.new_zeros(x.shape[0], x.shape[1] - 1)
    features = Features.apply(x, x_prev, held_next, constants)
    acc = network(features if describe is None else describe(features, x))
    return Advance.apply(acc, x, x_prev, held_next, lengths, constants)


def usable(model: Any, x: Tensor) -> bool:
    """Whether the fused steps apply: CPU float32 (the loops' layout), not the reference."""
    return (
        not getattr(model, "reference", False)
        and loops_take(x)
        and model.position_scale.device.type == "cpu"
    )


def _arrays(*tensors: Tensor) -> list[np.ndarray]:
    return [t.detach().contiguous().numpy() for t in tensors]


class Features(torch.autograd.Function):
    """:meth:`MarkerModel.features` as one operation."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, x_prev: Tensor, held_next: Tensor, k: StepConstants) -> Tensor:
        out = x.new_empty(*x.shape[:2], 10)
        features_forward(*_arrays(x, x_prev, held_next), k.held, k.position_scale,
                         k.velocity_scale, out.numpy())  # fmt: skip
        ctx.constants = k
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        k = ctx.constants
        g_x, g_prev, g_next = (grad.new_zeros(*grad.shape[:2], 3) for _ in range(3))
        features_backward(*_arrays(grad), k.held, k.position_scale, k.velocity_scale,
                          g_x.numpy(), g_prev.numpy(), g_next.numpy())  # fmt: skip
        return g_x, g_prev, g_next, None


class Advance(torch.autograd.Function):
    """The next positions from the network's normalised accelerations: the update, the held
    markers set, the projection onto ``lengths`` (a constant), as one operation."""

    @staticmethod
    def forward(ctx: Any, acc: Tensor, x: Tensor, x_prev: Tensor, held_next: Tensor,
                lengths: Tensor, k: StepConstants) -> Tensor:  # fmt: skip
        out, before = torch.empty_like(x), torch.empty_like(x)
        lengths = lengths.detach().contiguous()
        advance_forward(*_arrays(x, x_prev, held_next, acc), k.held, k.acceleration_scale,
                        lengths.numpy(), k.sweeps, before.numpy(), out.numpy())  # fmt: skip
        ctx.save_for_backward(before, lengths)
        ctx.constants = k
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        before, lengths = ctx.saved_tensors
        k = ctx.constants
        g_acc = torch.empty_like(before)
        g_x, g_prev, g_next = (torch.zeros_like(before) for _ in range(3))
        advance_backward(*_arrays(grad, before), k.held, k.acceleration_scale, lengths.numpy(),
                         k.sweeps, g_acc.numpy(), g_x.numpy(), g_prev.numpy(),
                         g_next.numpy())  # fmt: skip
        return g_acc, g_x, g_prev, g_next, None, None
