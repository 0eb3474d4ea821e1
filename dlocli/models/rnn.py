"""A bidirectional LSTM layer with a hand-written backward pass, for small batches on CPU.

Same mathematics and the same parameters as one layer of ``torch.nn.LSTM(bidirectional=True)``
(gates i, f, g, o; ``c' = f c + i g``, ``h' = o tanh(c')``). At small batches (the MPC's
rollouts) the stock CPU kernels are bound by per-step overhead (FINDINGS.md: the LSTM is
75-85% of a forward at batch 1, and its backward several times that). Here:

- the input projections of all time steps and both directions are one matrix product;
- the two directions advance together: one batched matrix product and six element-wise
  operations per step (the backward direction reads its inputs reversed);
- the backward pass (back-propagation through time) runs the same fused loop with the local
  derivatives of all steps precomputed in one vectorised pass, and the weight and input
  gradients as three large matrix products after the loop, instead of autograd's dozen small
  nodes per step.

At large batches the work is matrix products and memory traffic, where oneDNN's fused LSTM
(``nn.LSTM``) is as fast; :func:`bilstm` switches to it there.

Shapes: ``x`` (B, T, I) -> (B, T, 2H), forward direction's hidden state then the backward
direction's, like ``nn.LSTM(batch_first=True, bidirectional=True)``.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

#: batch sizes from which the stock (oneDNN) LSTM is at least as fast on CPU
LARGE_BATCH = 32


def _pack(params: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, Tensor]:
    """Stack both directions' weights (gate order i, f, g, o as in nn.LSTM).

    Returns W_ih (8H, I) forward rows then backward rows, W_hh (2, 4H, H), bias (8H,).
    """
    w_ih_f, w_hh_f, b_ih_f, b_hh_f, w_ih_b, w_hh_b, b_ih_b, b_hh_b = params
    w_ih = torch.cat([w_ih_f, w_ih_b])
    w_hh = torch.stack([w_hh_f, w_hh_b])
    bias = torch.cat([b_ih_f + b_hh_f, b_ih_b + b_hh_b])
    return w_ih, w_hh, bias


class _BiLSTMLayer(torch.autograd.Function):
    @staticmethod
    def forward(ctx: FunctionCtx, x: Tensor, *params: Tensor) -> Tensor:  # type: ignore[override]
        batch, steps, _ = x.shape
        hidden = params[1].shape[1]
        w_ih, w_hh, bias = _pack(params)
        # input projections of every step, both directions: (B, T, 8H)
        gx = torch.addmm(bias, x.reshape(batch * steps, -1), w_ih.t()).view(batch, steps, -1)
        # (2, B, T, 4H) in each direction's step order (the backward direction reversed)
        gx = torch.stack([gx[..., : 4 * hidden], gx[..., 4 * hidden :].flip(1)])
        w_hh_t = w_hh.transpose(1, 2)
        h = x.new_zeros(2, batch, hidden)
        c = x.new_zeros(2, batch, hidden)
        acts, cells, hs = [], [], []
        g_slice = slice(2 * hidden, 3 * hidden)
        for s in range(steps):
            gates = torch.baddbmm(gx[:, :, s], h, w_hh_t)
            act = gates.sigmoid()
            torch.tanh(gates[..., g_slice], out=act[..., g_slice])
            i, f, g, o = act.chunk(4, dim=-1)
            c = torch.addcmul(f * c, i, g)
            h = o * c.tanh()
            acts.append(act)
            cells.append(c)
            hs.append(h)
        hs_t = torch.stack(hs, 1)  # (2, T, B, H)
        ctx.save_for_backward(x, w_ih, w_hh, torch.stack(acts, 1), torch.stack(cells, 1), hs_t)
        return torch.cat([hs_t[0].transpose(0, 1), hs_t[1].flip(0).transpose(0, 1)], -1)

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, w_ih, w_hh, acts, cells, hs = ctx.saved_tensors
        _, steps, batch, hidden = hs.shape
        go = grad_out.transpose(0, 1)  # (T, B, 2H)
        dh_out = torch.stack([go[..., :hidden], go[..., hidden:].flip(0)])  # (2, T, B, H)
        jac, k_c, forget = _local_derivatives(acts, cells)
        dgates: list[Tensor] = [acts] * steps
        dg = dc = None
        for s in range(steps - 1, -1, -1):
            dh = dh_out[:, s] if dg is None else torch.baddbmm(dh_out[:, s], dg, w_hh)
            carry = None if dc is None else dc * forget[:, s + 1]
            dc = dh * k_c[:, s] if carry is None else torch.addcmul(carry, dh, k_c[:, s])
            dg = jac[:, s] * torch.cat([dc, dc, dc, dh], -1)
            dgates[s] = dg
        dg_all = torch.stack(dgates, 1)  # (2, T, B, 4H) in step order
        # recurrent weights: sum over steps s >= 1 of dg_s^T h_{s-1}
        d_w_hh = torch.bmm(
            dg_all[:, 1:].reshape(2, -1, 4 * hidden).transpose(1, 2),
            hs[:, :-1].reshape(2, -1, hidden),
        )
        # input side in natural time order, batch first: (B, T, 8H)
        dg_nat = torch.cat(
            [dg_all[0].transpose(0, 1), dg_all[1].flip(0).transpose(0, 1)], -1
        ).reshape(batch * steps, 8 * hidden)
        d_w_ih = dg_nat.t() @ x.reshape(batch * steps, -1)
        d_bias = dg_nat.sum(0)
        grad_x = None
        if ctx.needs_input_grad[0]:
            grad_x = (dg_nat @ w_ih).view_as(x)
        return (grad_x, *_unpack_grads(d_w_ih, d_w_hh, d_bias))


def _local_derivatives(acts: Tensor, cells: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-step derivative factors, all steps at once (shapes (2, T, B, .)).

    Returns ``jac`` (..., 4H): d(gate pre-activation) per unit of (dc, dc, dc, dh);
    ``k_c`` (..., H) = dc/dh through h = o tanh(c); ``forget`` (..., H) the forget gate.
    """
    i, f, g, o = acts.chunk(4, dim=-1)
    tanhs = cells.tanh()
    c_prev = torch.cat([torch.zeros_like(cells[:, :1]), cells[:, :-1]], 1)
    jac = torch.cat(
        [g * i * (1 - i), c_prev * f * (1 - f), i * (1 - g * g), tanhs * o * (1 - o)], -1
    )
    return jac, o * (1 - tanhs * tanhs), f


def _unpack_grads(d_w_ih: Tensor, d_w_hh: Tensor, d_bias: Tensor) -> list[Tensor]:
    """Gradients of the stacked layout back to the eight nn.LSTM parameters of one layer."""
    gi_f, gi_b = d_w_ih.chunk(2)
    gb_f, gb_b = d_bias.chunk(2)
    return [gi_f, d_w_hh[0], gb_f, gb_f, gi_b, d_w_hh[1], gb_b, gb_b]


def layer_params(lstm: torch.nn.LSTM, layer: int) -> tuple[Tensor, ...]:
    """The eight parameters of one bidirectional layer of ``lstm``, in _BiLSTMLayer's order."""
    names = ("weight_ih_l{}{}", "weight_hh_l{}{}", "bias_ih_l{}{}", "bias_hh_l{}{}")
    return tuple(
        getattr(lstm, name.format(layer, suffix)) for suffix in ("", "_reverse") for name in names
    )


def bilstm(x: Tensor, lstm: torch.nn.LSTM) -> Tensor:
    """Run ``lstm`` (bidirectional, batch_first, with biases, no dropout/projection) on x.

    x (B, T, I) -> (B, T, 2H); equal to ``lstm(x)[0]`` up to float rounding. Small batches on
    CPU take the fused path of this module, large ones and CUDA the stock kernels.
    """
    if x.is_cuda or x.shape[0] >= LARGE_BATCH:
        return lstm(x)[0]
    for layer in range(lstm.num_layers):
        x = _BiLSTMLayer.apply(x, *layer_params(lstm, layer))
    return x
