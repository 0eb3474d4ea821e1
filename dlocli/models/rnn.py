"""A bidirectional LSTM layer with a hand-written backward pass, for the gradient planners.

Same mathematics and the same parameters as one layer of ``torch.nn.LSTM(bidirectional=True)``
(gates i, f, g, o; ``c' = f c + i g``, ``h' = o tanh(c')``). A gradient planner (MPC with
``optimizer=adam`` or ``exact_gradient``) back-propagates through rollouts at small batches
with frozen weights; oneDNN's backward pass always computes the weight gradients too. Here:

- the input projections of all time steps and both directions are one matrix product;
- the two directions advance together: one batched matrix product and a handful of
  element-wise operations per step (the backward direction reads its inputs reversed);
- the backward pass (back-propagation through time) runs the same fused loop with the local
  derivatives of all steps precomputed in one vectorised pass, and gives the input gradient
  only: the weights are frozen;
- both loops are compiled by TorchScript (faster than the same Python at small batches);
- the weights are repacked only when they change (cached on the module).

Used only where it was measured faster (``benchmarks/results/lstm_backward.md``): a backward
pass with frozen weights at batches below :data:`LARGE_BATCH` on CPU. Training (weights that
want gradients) takes ``nn.LSTM``, and so do forward-only passes, or the whole rollout
:mod:`dlocli.models.fast_rollout`.

Shapes: ``x`` (B, T, I) -> (B, T, 2H), forward direction's hidden state then the backward
direction's, like ``nn.LSTM(batch_first=True, bidirectional=True)``.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

#: batch sizes from which the stock (oneDNN) LSTM is at least as fast on CPU
LARGE_BATCH = 32


# ---------------------------------------------------------------------- the two kernels
def _forward(
    x: Tensor, w_ih_t: Tensor, bias: Tensor, w_hh_t: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """x (B, T, I), W_ih^T (I, 8H), bias (8H), W_hh^T (2, H, 4H) -> output (B, T, 2H), and for
    the backward pass: activated gates (T, 2, B, 4H) and cells (T, 2, B, H), both in each
    direction's step order.

    The weights' g-gate rows come doubled (:func:`_pack`), so one sigmoid activates all four
    gates: tanh(x) = 2 sigma(2x) - 1. The saved g activation is sigma(2x)."""
    batch, steps = x.shape[0], x.shape[1]
    hidden = w_hh_t.shape[1]
    xt = x.transpose(0, 1).reshape(steps * batch, x.shape[2])
    gx = torch.addmm(bias, xt, w_ih_t).view(steps, batch, 8 * hidden)
    gx = torch.stack([gx.narrow(2, 0, 4 * hidden), gx.narrow(2, 4 * hidden, 4 * hidden).flip(0)], 1)
    h = x.new_zeros(2, batch, hidden)
    c = x.new_zeros(2, batch, hidden)
    acts: list[Tensor] = []
    cells: list[Tensor] = []
    hs: list[Tensor] = []
    for gx_s in gx.unbind(0):
        gates = torch.baddbmm(gx_s, h, w_hh_t)
        act = gates.sigmoid()  # the g rows are doubled: sigma(2x) = (1 + tanh(x)) / 2
        i, f, sg, o = act.chunk(4, dim=-1)
        c = torch.addcmul(f * c - i, i, sg, value=2.0)  # f c + i g with g = 2 sigma(2x) - 1
        h = o * c.tanh()
        acts.append(act)
        cells.append(c)
        hs.append(h)
    hs_t = torch.stack(hs)
    out = torch.cat([hs_t[:, 0], hs_t[:, 1].flip(0)], -1).transpose(0, 1)
    return out, torch.stack(acts), torch.stack(cells)


def _backward(grad_out: Tensor, acts: Tensor, cells: Tensor, w_hh: Tensor) -> Tensor:
    """Back-propagation through time: dL/d(output) (B, T, 2H) -> dL/d(gate pre-activations)
    (T*B, 8H) in natural time order, forward direction's gates then the backward one's.
    ``w_hh`` (2, 4H, H) holds the original (not doubled) recurrent weights."""
    steps, batch, hidden = cells.shape[0], cells.shape[2], cells.shape[3]
    go = grad_out.transpose(0, 1)
    dh_out = torch.stack([go.narrow(2, 0, hidden), go.narrow(2, hidden, hidden).flip(0)], 1)
    dh_out = dh_out.unbind(0)
    # local derivatives of every step at once (see module docstring)
    i, f, sg, o = acts.chunk(4, dim=-1)
    g = 2 * sg - 1
    tanhs = cells.tanh()
    c_prev = torch.cat([torch.zeros_like(cells[:1]), cells[:-1]])
    jac = torch.cat(
        [g * i * (1 - i), c_prev * f * (1 - f), i * (1 - g * g), tanhs * o * (1 - o)], -1
    ).unbind(0)  # d(pre-activation) per unit of (dc, dc, dc, dh)
    k_c = (o * (1 - tanhs * tanhs)).unbind(0)  # dc per unit dh through h = o tanh(c)
    forget = f.unbind(0)
    last = steps - 1
    dh = dh_out[last]
    dc = dh * k_c[last]
    dg = jac[last] * torch.cat([dc, dc, dc, dh], -1)
    dgates = [dg]
    for s in range(last - 1, -1, -1):
        dh = torch.baddbmm(dh_out[s], dg, w_hh)
        dc = torch.addcmul(dc * forget[s + 1], dh, k_c[s])
        dg = jac[s] * torch.cat([dc, dc, dc, dh], -1)
        dgates.append(dg)
    dgates.reverse()
    dg_all = torch.stack(dgates)  # (T, 2, B, 4H) in step order
    return torch.cat([dg_all[:, 0], dg_all[:, 1].flip(0)], -1).view(steps * batch, 8 * hidden)


@functools.cache
def _kernels() -> tuple[Callable[..., Any], Callable[..., Any]]:
    """:func:`_forward` and :func:`_backward` compiled by TorchScript (faster than Python at
    small batches, where per-operation overhead dominates); plain Python if scripting is
    unavailable. TorchScript is deprecated but still the fastest option here: ``torch.compile``
    compiles this LSTM far more slowly and runs it no faster
    (``benchmarks/results/lstm_backward.md``)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return torch.jit.script(_forward), torch.jit.script(_backward)
    except Exception:  # noqa: BLE001 - any scripting failure: the same code in Python
        return _forward, _backward


# ---------------------------------------------------------------------- autograd
class _BiLSTMLayer(torch.autograd.Function):
    """One bidirectional layer with frozen weights. Inputs: x, then the packed weights."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, x: Tensor, packed: tuple[Tensor, ...]
    ) -> Tensor:
        w_ih_t, bias, w_hh_t = packed[:3]
        out, acts, cells = _kernels()[0](x, w_ih_t, bias, w_hh_t)
        ctx.save_for_backward(acts, cells)
        ctx.packed = packed
        return out

    @staticmethod
    @once_differentiable
    def backward(  # type: ignore[override]
        ctx: FunctionCtx, grad_out: Tensor
    ) -> tuple[Tensor, None]:
        acts, cells = ctx.saved_tensors
        w_ih, w_hh = ctx.packed[3:]
        steps, _, batch, _ = cells.shape
        dg = _kernels()[1](grad_out, acts, cells, w_hh)  # (T*B, 8H)
        return (dg @ w_ih).view(steps, batch, -1).transpose(0, 1), None


def _pack(params: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Both directions' weights in the kernels' layouts (gate order i, f, g, o as nn.LSTM).

    For the forward kernel, g-gate rows doubled (see :func:`_forward`): W_ih^T (I, 8H) forward
    columns then backward ones, bias (8H), W_hh^T (2, H, 4H); for the backward pass, as they
    are: W_ih (8H, I), W_hh (2, 4H, H).
    """
    w_ih_f, w_hh_f, b_ih_f, b_hh_f, w_ih_b, w_hh_b, b_ih_b, b_hh_b = (p.detach() for p in params)
    hidden = w_hh_f.shape[1]
    w_ih = torch.cat([w_ih_f, w_ih_b])
    w_hh = torch.stack([w_hh_f, w_hh_b])
    bias = torch.cat([b_ih_f + b_hh_f, b_ih_b + b_hh_b])
    scale = torch.ones(4 * hidden, dtype=w_ih.dtype, device=w_ih.device)
    scale[2 * hidden : 3 * hidden] = 2.0
    w_ih_t = (w_ih * scale.repeat(2)[:, None]).t().contiguous()
    w_hh_t = (w_hh * scale[:, None]).transpose(1, 2).contiguous()
    return w_ih_t, bias * scale.repeat(2), w_hh_t, w_ih, w_hh.contiguous()


# ---------------------------------------------------------------------- public
def layer_params(lstm: torch.nn.LSTM, layer: int) -> tuple[Tensor, ...]:
    """The eight parameters of one bidirectional layer of ``lstm``: weight_ih, weight_hh,
    bias_ih, bias_hh of the forward direction, then of the reverse one."""
    names = ("weight_ih_l{}{}", "weight_hh_l{}{}", "bias_ih_l{}{}", "bias_hh_l{}{}")
    return tuple(
        getattr(lstm, name.format(layer, suffix)) for suffix in ("", "_reverse") for name in names
    )


def bilstm(x: Tensor, lstm: torch.nn.LSTM) -> Tensor:
    """Run ``lstm`` (bidirectional, batch_first, with biases, no dropout/projection) on x.

    x (B, T, I) -> (B, T, 2H); equal to ``lstm(x)[0]`` up to float rounding. A backward pass
    with frozen weights at small batches on CPU takes the kernels of this module; everything
    else the stock ``nn.LSTM`` (see the module docstring).
    """
    if x.is_cuda or x.shape[0] >= LARGE_BATCH or not _frozen_backward(x, lstm):
        return lstm(x)[0]
    for layer in range(lstm.num_layers):
        params = layer_params(lstm, layer)
        x = _BiLSTMLayer.apply(x, _packed(lstm, layer, params))
    return x


def _frozen_backward(x: Tensor, lstm: torch.nn.LSTM) -> bool:
    """A gradient with respect to the input only will follow."""
    if not torch.is_grad_enabled() or not x.requires_grad:
        return False
    return not any(p.requires_grad for p in lstm.parameters())


def _packed(lstm: torch.nn.LSTM, layer: int, params: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """:func:`_pack` of one layer, cached on the module until a weight changes (a planner
    rolls out through fixed weights; a training step updates them in place, which bumps
    their version counters)."""
    key = tuple((p.data_ptr(), p._version) for p in params)
    cache: dict[int, tuple[tuple, tuple[Tensor, ...]]] = lstm.__dict__.setdefault("_dlo_packed", {})
    hit = cache.get(layer)
    if hit is None or hit[0] != key:
        hit = (key, _pack(params))
        cache[layer] = hit
    return hit[1]
