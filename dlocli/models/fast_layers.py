"""Standard layers of any network as one autograd operation each, for CPU training.

A rollout's gradient step runs the network k times at small sizes (batch 32, 12 markers): in
plain PyTorch each layer is ten to forty small operations and as many autograd nodes, whose
fixed costs rival the arithmetic (``benchmarks/training_throughput.py``). Inside
:func:`fused`, the layers of a network that have a fused form here run as one
:class:`torch.autograd.Function` each: the forward's operations without a graph, the backward
written out (the same products, no per-operation bookkeeping). What has no fused form, or a
configuration it does not cover, runs as it is; so does everything off CPU float32 or
without gradients (eval's own fast paths are better there).

Fused forms: ``nn.Sequential`` chains of ``Linear`` and ``ReLU`` (the models' MLPs) and
``nn.TransformerEncoderLayer`` (pre-norm, relu or gelu, no dropout, batch first, no masks).
``nn.LSTM`` is left to oneDNN: its arithmetic, not its overhead, bounds it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

aten = torch.ops.aten


@contextlib.contextmanager
def fused(network: torch.nn.Module) -> Iterator[None]:
    """Within: the submodules of ``network`` that have a fused form use it (see the module
    docstring); their own ``forward`` is back on exit."""
    swapped = []
    for module in network.modules():
        fast = _fast_forward(module)
        if fast is not None:
            object.__setattr__(module, "forward", fast)
            swapped.append(module)
    try:
        yield
    finally:
        for module in swapped:
            del module.__dict__["forward"]


def _applies(x: Tensor, module: torch.nn.Module) -> bool:
    """The fused forms' ground: CPU float32, gradients wanted, no dropout in effect."""
    return (
        torch.is_grad_enabled()
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and all(p.dtype == torch.float32 and p.device.type == "cpu" for p in module.parameters())
    )


def _fast_forward(module: torch.nn.Module) -> Any:
    """The fused forward of ``module`` (falling back to its own per call), or None."""
    if isinstance(module, torch.nn.Sequential) and _linear_relu_chain(module):
        return _chain_forward(module)
    if isinstance(module, torch.nn.TransformerEncoderLayer) and _encoder_layer_covered(module):
        return _encoder_forward(module)
    return None


# ---------------------------------------------------------------------- Linear/ReLU chains
def _linear_relu_chain(net: torch.nn.Sequential) -> bool:
    """Linear layers with biases, a ReLU between each pair, none after the last."""
    kinds = [type(m) for m in net]
    return (
        len(kinds) % 2 == 1
        and all(k is torch.nn.Linear for k in kinds[0::2])
        and all(k is torch.nn.ReLU for k in kinds[1::2])
        and all(m.bias is not None for m in net[0::2])
    )


def _chain_forward(net: torch.nn.Sequential) -> Any:
    plain = type(net).forward.__get__(net)
    params = [t for m in net[0::2] for t in (m.weight, m.bias)]

    def forward(x: Tensor) -> Tensor:
        if not _applies(x, net):
            return plain(x)
        return LinearChain.apply(x, *params)

    return forward


class LinearChain(torch.autograd.Function):
    """Linear, ReLU, ..., Linear on the last axis; ``params``: each layer's weight, bias."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, *params: Tensor) -> Tensor:
        rows = x.reshape(-1, x.shape[-1])
        inputs = [rows]
        for i in range(0, len(params), 2):
            rows = torch.addmm(params[i + 1], rows, params[i].t())
            if i + 2 < len(params):
                rows.relu_()
                inputs.append(rows)
        ctx.save_for_backward(*inputs, *params[0::2])
        ctx.shape = x.shape
        return rows.view(*x.shape[:-1], rows.shape[-1])

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors
        layers = len(saved) // 2
        inputs, weights = saved[:layers], saved[layers:]
        g = grad.reshape(-1, grad.shape[-1])
        grads: list[Tensor] = []
        for i in range(layers - 1, -1, -1):
            grads[:0] = [g.t() @ inputs[i], g.sum(0)]
            g = g @ weights[i]
            if i > 0:  # through the ReLU whose output was this layer's input
                g = aten.threshold_backward(g, inputs[i], 0)
        return (g.view(ctx.shape), *grads)


# ---------------------------------------------------------------------- encoder layers
def _encoder_layer_covered(layer: torch.nn.TransformerEncoderLayer) -> bool:
    attention = layer.self_attn
    norms = (layer.norm1, layer.norm2)
    return (
        layer.norm_first
        and getattr(layer, "activation_relu_or_gelu", 0) in (1, 2)
        and getattr(layer.activation, "approximate", "none") == "none"
        and attention.batch_first
        and attention._qkv_same_embed_dim
        and attention.in_proj_bias is not None
        and attention.bias_k is None
        and not attention.add_zero_attn
        and attention.out_proj.bias is not None
        and layer.linear1.bias is not None
        and layer.linear2.bias is not None
        and all(n.weight is not None and n.bias is not None for n in norms)
    )


def _encoder_forward(layer: torch.nn.TransformerEncoderLayer) -> Any:
    plain = type(layer).forward.__get__(layer)
    attention = layer.self_attn
    params = (layer.norm1.weight, layer.norm1.bias, attention.in_proj_weight,
              attention.in_proj_bias, attention.out_proj.weight, attention.out_proj.bias,
              layer.norm2.weight, layer.norm2.bias, layer.linear1.weight, layer.linear1.bias,
              layer.linear2.weight, layer.linear2.bias)  # fmt: skip

    def forward(src: Tensor, src_mask: Tensor | None = None,
                src_key_padding_mask: Tensor | None = None, is_causal: bool = False) -> Tensor:  # fmt: skip
        dropping = layer.training and (layer.dropout.p > 0 or attention.dropout > 0)
        if (src_mask is not None or src_key_padding_mask is not None or dropping
                or src.dim() != 3 or not _applies(src, layer)):  # fmt: skip
            return plain(src, src_mask, src_key_padding_mask, is_causal)
        shape = (attention.num_heads, layer.activation_relu_or_gelu == 2,
                 layer.norm1.eps, layer.norm2.eps)  # fmt: skip
        return EncoderLayer.apply(src, shape, *params)

    return forward


def _heads(qkv: Tensor, batch: int, heads: int) -> tuple[Tensor, ...]:
    """(B N, 3 d) -> q, k, v, each (B, heads, N, d / heads) (views)."""
    n, d = qkv.shape[0] // batch, qkv.shape[1] // 3
    return qkv.view(batch, n, 3, heads, d // heads).permute(2, 0, 3, 1, 4).unbind(0)


class EncoderLayer(torch.autograd.Function):
    """A pre-norm encoder layer: x + attention(norm1 x), then + linear2 act linear1 (norm2).
    ``config``: (heads, gelu (else relu), norm1's eps, norm2's eps)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, config: tuple, *params: Tensor) -> Tensor:
        heads, gelu, eps1, eps2 = config
        n1w, n1b, w_in, b_in, w_out, b_out, n2w, n2b, w1, b1, w2, b2 = params
        batch, n, d = x.shape
        x = x.reshape(batch * n, d)
        h1, mean1, rstd1 = aten.native_layer_norm(x, [d], n1w, n1b, eps1)
        qkv = torch.addmm(b_in, h1, w_in.t())  # (B N, 3 d)
        scale = 1.0 / math.sqrt(d // heads)
        mixed, logsumexp = aten._scaled_dot_product_flash_attention_for_cpu(
            *_heads(qkv, batch, heads), 0.0, False, scale=scale
        )
        mixed = mixed.transpose(1, 2).reshape(batch * n, d)
        x1 = torch.addmm(b_out, mixed, w_out.t()).add_(x)
        h2, mean2, rstd2 = aten.native_layer_norm(x1, [d], n2w, n2b, eps2)
        pre = torch.addmm(b1, h2, w1.t())
        act = torch.nn.functional.gelu(pre) if gelu else torch.relu(pre)
        y = torch.addmm(b2, act, w2.t()).add_(x1)
        ctx.save_for_backward(x, h1, mean1, rstd1, qkv, logsumexp, mixed, x1, h2, mean2,
                              rstd2, pre, act, *params)  # fmt: skip
        ctx.config, ctx.shape, ctx.scale = config, (batch, n, d), scale
        return y.view(batch, n, d)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        (x, h1, mean1, rstd1, qkv, logsumexp, mixed, x1, h2, mean2, rstd2, pre, act,
         n1w, n1b, w_in, _, w_out, _, n2w, n2b, w1, _, w2, _) = ctx.saved_tensors  # fmt: skip
        heads, gelu, _, _ = ctx.config
        batch, n, d = ctx.shape
        both = [True, True, True]
        g = grad.reshape(batch * n, d)
        # the feed-forward block
        g_w2, g_b2 = g.t() @ act, g.sum(0)
        g_act = g @ w2
        if gelu:
            g_pre = aten.gelu_backward(g_act, pre)
        else:
            g_pre = aten.threshold_backward(g_act, act, 0)
        g_w1, g_b1 = g_pre.t() @ h2, g_pre.sum(0)
        g_x1, g_n2w, g_n2b = aten.native_layer_norm_backward(g_pre @ w1, x1, [d], mean2, rstd2,
                                                             n2w, n2b, both)  # fmt: skip
        g_x1 += g
        # the attention block
        g_wout, g_bout = g_x1.t() @ mixed, g_x1.sum(0)
        g_mixed = (g_x1 @ w_out).view(batch, n, heads, d // heads).transpose(1, 2)
        q, k, v = _heads(qkv, batch, heads)
        out = mixed.view(batch, n, heads, d // heads).transpose(1, 2)
        g_q, g_k, g_v = aten._scaled_dot_product_flash_attention_for_cpu_backward(
            g_mixed, q, k, v, out, logsumexp, 0.0, False, scale=ctx.scale
        )
        g_qkv = torch.stack([g_q, g_k, g_v], 2).transpose(1, 3).reshape(batch * n, 3 * d)
        g_win, g_bin = g_qkv.t() @ h1, g_qkv.sum(0)
        g_x, g_n1w, g_n1b = aten.native_layer_norm_backward(g_qkv @ w_in, x, [d], mean1, rstd1,
                                                            n1w, n1b, both)  # fmt: skip
        g_x += g_x1
        return (g_x.view(batch, n, d), None, g_n1w, g_n1b, g_win, g_bin, g_wout, g_bout,
                g_n2w, g_n2b, g_w1, g_b1, g_w2, g_b2)  # fmt: skip
