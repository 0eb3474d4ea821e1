"""The in-bilstm's forward-only rollout in the rod view, for the planners' small batches on CPU.

The default MPC rolls the model out H = 5 steps at batch 1 once per control step, with no
gradient. Through plain PyTorch most of that rollout's time goes to the stock LSTM, whose
2 x N recurrent steps per layer cost about twice their bare matrix-vector products, and to
about 100 small operations per model step (``benchmarks/results/lstm_backward.md``). Here
the same mathematics runs as:

- the matrix products of many rows (f_e, the LSTM's input projections, f_v) as PyTorch
  ``addmm`` into preallocated buffers (oneDNN/MKL, one thread under ``dlo control``);
- everything per segment or per recurrent step (features, relations, the sum per receiver,
  the LSTM recurrences of both directions, the state update) as loops compiled by numba,
  on the same buffers (numpy views of the torch tensors: no copies);
- f_e's last layer folded into the first LSTM layer's input projection: both are linear and
  the sum per receiver sits between them, so sum_j (z_ij W_e + b_e) W_ih =
  (sum_j z_ij) (W_e W_ih) + deg_i b_e W_ih, one product fewer per step;
- the LSTM's sigmoid and tanh as a rational function (max. error 3.4e-7 in float32, vs
  6e-8 for the library's tanh): vectorisable, where the library's exp is not.

Results equal the rod view's plain PyTorch rollout to float32 rounding (tested against
float64). Its speed against PyTorch's: ``benchmarks/mpc_latency.py`` and docs/benchmarks.md.
The rod view offers it (:mod:`dlocli.models.rollouts`) when no gradient is wanted, on CPU, up
to :data:`MAX_BATCH`; otherwise its plain PyTorch rollout runs. The first call compiles the
loops (cached on disk, so later processes only load them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from dlocli.models.in_bilstm import INBiLSTM
from dlocli.models.rnn import layer_params
from dlocli.models.rollouts import dense_layers, loops_take, wants_gradient

#: batch sizes up to which this path is faster than oneDNN (benchmarks/model_throughput.py):
#: its recurrences run per sample, oneDNN batches them into matrix products
MAX_BATCH = 4


# ---------------------------------------------------------------------- numba kernels
jit = numba.njit(fastmath=True, cache=True, nogil=True, error_model="numpy")

# tanh(x) ~ x P(x^2) / Q(x^2) on [-9, 9] (fitted for this module: relative-error least
# squares, refined by reweighting; max. abs. error 3.4e-7 in float32). float32 constants:
# a float64 one would turn the whole expression into scalar float64 code.
_F = np.float32
P0, P1, P2, P3 = _F(0.9999999944), _F(0.1308961796), _F(0.003110233852), _F(1.122043568e-05)
P4, P5, P6 = _F(-2.049675237e-08), _F(5.41063274e-11), _F(-8.834617825e-14)
Q1, Q2, Q3 = _F(0.4642294593), _F(0.0245201389), _F(0.0002555312764)
CLAMP, HALF, ONE = _F(9.0), _F(0.5), _F(1.0)


@jit
def tanh(x):
    x = min(max(x, -CLAMP), CLAMP)
    u = x * x
    p = P0 + u * (P1 + u * (P2 + u * (P3 + u * (P4 + u * (P5 + u * P6)))))
    return x * p / (ONE + u * (Q1 + u * (Q2 + u * Q3)))


@jit
def sigmoid(x):
    return HALF + HALF * tanh(HALF * x)


@jit
def prepare(state, previous, has_previous, action, norm, action_scale, velocity,
            absolute, features, edge_in, node_in):  # fmt: skip
    """Segment features, f_e's relation inputs and f_v's own features of one step.

    state, previous (B, N, 7); action (B, 2, 6); norm (5, 7): state mean, state std,
    delta mean, delta std, relation scale. Writes features (B, N, F), edge_in
    (B * 2(N-1), E) (from-left relations of receivers 1..N-1, then from-right ones of
    receivers 0..N-2, per sample), node_in[:, :own]."""
    batch, n = state.shape[0], state.shape[1]
    width = features.shape[2]
    own0 = 0 if absolute else 3
    own = width - own0
    for b in range(batch):
        for i in range(n):
            for k in range(7):
                features[b, i, k] = (state[b, i, k] - norm[0, k]) / norm[1, k]
            if velocity:
                sign = 1.0
                if has_previous:
                    dot = 0.0
                    for k in range(3, 7):
                        dot += previous[b, i, k] * state[b, i, k]
                    sign = 1.0 if dot >= 0 else -1.0
                for k in range(7):
                    change = 0.0
                    if has_previous:
                        scale = sign if k >= 3 else 1.0
                        change = state[b, i, k] * scale - previous[b, i, k]
                    features[b, i, 7 + k] = (change - norm[2, k]) / norm[3, k]
            for k in range(own):
                node_in[b * n + i, k] = features[b, i, own0 + k]
        for side in range(2):  # 0: from the left neighbour, 1: from the right one
            for r in range(n - 1):
                receiver = r + 1 if side == 0 else r
                sender = r if side == 0 else r + 1
                row = edge_in[b * 2 * (n - 1) + side * (n - 1) + r]
                col = 0
                for k in range(own):
                    row[col] = features[b, receiver, own0 + k]
                    col += 1
                col = _put_action(row, col, action, action_scale, b, receiver, n)
                for k in range(7):
                    diff = (features[b, r + 1, k] - features[b, r, k]) * norm[4, k]
                    row[col] = diff if side == 1 else -diff
                    col += 1
                for k in range(7, width):
                    row[col] = features[b, sender, k]
                    col += 1
                _put_action(row, col, action, action_scale, b, sender, n)


@jit
def _put_action(row, col, action, action_scale, b, segment, n):
    """Segment's gripper command / scale (zeros unless an end segment) at row[col:col+6]."""
    gripper = 0 if segment == 0 else (1 if segment == n - 1 else -1)
    for k in range(6):
        row[col + k] = action[b, gripper, k] / action_scale[k] if gripper >= 0 else 0.0
    return col + 6


@jit
def sum_per_receiver(z, n, out):
    """(B * 2(N-1), W) relation rows -> (B * N, W) sums per receiving segment."""
    batch = out.shape[0] // n
    width = out.shape[1]
    for b in range(batch):
        base = b * 2 * (n - 1)
        for i in range(n):
            for k in range(width):
                total = 0.0
                if i >= 1:
                    total += z[base + i - 1, k]
                if i <= n - 2:
                    total += z[base + n - 1 + i, k]
                out[b * n + i, k] = total


@jit
def recurrence(gx, w_hh_t, n, out, col0):
    """Both directions of one LSTM layer from the input gates gx (B * N, 8H) (bias
    included; forward direction's i, f, g, o, then the backward one's) and W_hh^T
    (2, H, 4H); writes h (forward, backward) to out[:, col0 : col0 + 2H]."""
    batch = gx.shape[0] // n
    hidden = w_hh_t.shape[1]
    gates = np.empty((batch, 4 * hidden), np.float32)
    h = np.empty((batch, hidden), np.float32)
    c = np.empty((batch, hidden), np.float32)
    for d in range(2):
        h[:] = 0.0
        c[:] = 0.0
        w = w_hh_t[d]
        for s in range(n):
            i = s if d == 0 else n - 1 - s
            for b in range(batch):
                gates[b] = gx[b * n + i, d * 4 * hidden : (d + 1) * 4 * hidden]
            _add_matmul(gates, h, w)
            for b in range(batch):
                _cell(gates[b], h[b], c[b])
                out[b * n + i, col0 + d * hidden : col0 + (d + 1) * hidden] = h[b]


@jit
def _cell(gates, h, c):
    """The LSTM cell update from the pre-activations (i, f, g, o) of one sample."""
    hidden = h.shape[0]
    g_i, g_f = gates[:hidden], gates[hidden : 2 * hidden]
    g_g, g_o = gates[2 * hidden : 3 * hidden], gates[3 * hidden :]
    for j in range(hidden):
        c[j] = sigmoid(g_f[j]) * c[j] + sigmoid(g_i[j]) * tanh(g_g[j])
        h[j] = sigmoid(g_o[j]) * tanh(c[j])


@jit
def _add_matmul(y, x, w):
    """y += x w for x (B, K), w (K, J), y (B, J): four rows of w at a time for every sample
    (fewer passes over y, and w read once per step whatever the batch)."""
    k, rows = 0, x.shape[1]
    while k + 4 <= rows:
        w0, w1, w2, w3 = w[k], w[k + 1], w[k + 2], w[k + 3]
        for b in range(x.shape[0]):
            x0, x1, x2, x3 = x[b, k], x[b, k + 1], x[b, k + 2], x[b, k + 3]
            yb = y[b]
            for j in range(yb.shape[0]):
                yb[j] += x0 * w0[j] + x1 * w1[j] + x2 * w2[j] + x3 * w3[j]
        k += 4
    while k < rows:
        wk = w[k]
        for b in range(x.shape[0]):
            xk, yb = x[b, k], y[b]
            for j in range(yb.shape[0]):
                yb[j] += xk * wk[j]
        k += 1


@jit
def apply_delta(state, delta_n, norm, out):
    """out = state + delta_n * delta std + delta mean, quaternion normalised, w >= 0."""
    batch, n = state.shape[0], state.shape[1]
    for b in range(batch):
        for i in range(n):
            row = delta_n[b * n + i]
            for k in range(7):
                out[b, i, k] = state[b, i, k] + row[k] * norm[3, k] + norm[2, k]
            length = 0.0
            for k in range(3, 7):
                length += out[b, i, k] * out[b, i, k]
            scale = 1.0 / max(np.sqrt(length), 1e-12)
            if out[b, i, 3] < 0:
                scale = -scale
            for k in range(3, 7):
                out[b, i, k] *= scale


# ---------------------------------------------------------------------- weights, buffers
@dataclass
class _Weights:
    """The model's parameters in the layouts above (float32, CPU), rebuilt when one changes."""

    key: tuple
    norm: np.ndarray  # (5, 7)
    action_scale: np.ndarray  # (6,)
    edge: list[tuple[Tensor, Tensor]]  # f_e's layers but the last: (bias, W^T)
    folded: Tensor  # W_e,last^T W_ih,0^T (in, 8H)
    folded_bias: Tensor  # (N, 8H): deg_i b_e,last W_ih,0^T + the layer's LSTM biases
    lstm_in: list[tuple[Tensor, Tensor]]  # layers 1..L-1: (bias (8H), W_ih^T (2H, 8H))
    w_hh_t: list[np.ndarray]  # per layer (2, H, 4H)
    node: list[tuple[Tensor, Tensor]]  # f_v's layers: (bias, W^T)
    workspaces: dict[int, _Workspace] = field(default_factory=dict)  # by batch size


def _linears(net: torch.nn.Sequential) -> list[torch.nn.Linear]:
    return [m for m in net if isinstance(m, torch.nn.Linear)]


def _lstm_layer(lstm: torch.nn.LSTM, layer: int) -> tuple[Tensor, Tensor, Tensor]:
    """W_ih (8H, I), bias (8H), W_hh (2, 4H, H) of one layer, forward direction first."""
    w_ih_f, w_hh_f, b_ih_f, b_hh_f, w_ih_b, w_hh_b, b_ih_b, b_hh_b = (
        p.detach() for p in layer_params(lstm, layer)
    )
    bias = torch.cat([b_ih_f + b_hh_f, b_ih_b + b_hh_b])
    return torch.cat([w_ih_f, w_ih_b]), bias, torch.stack([w_hh_f, w_hh_b])


def _build_weights(model: Any, key: tuple) -> _Weights:
    n = model.n_segments
    edge = _linears(model.network.edge_net)
    last = edge[-1]
    w_ih0, bias0, w_hh0 = _lstm_layer(model.network.lstm, 0)
    folded = (w_ih0 @ last.weight.detach()).t().contiguous()  # (in, 8H)
    degree = torch.full((n, 1), 2.0)
    degree[0] = degree[-1] = 1.0
    folded_bias = degree * (w_ih0 @ last.bias.detach()) + bias0
    layers = [_lstm_layer(model.network.lstm, k) for k in range(1, model.network.lstm.num_layers)]
    norm = torch.stack([model.state_mean, model.state_std, model.delta_mean, model.delta_std,
                        model.relation_scale])  # fmt: skip
    return _Weights(
        key=key,
        norm=norm.detach().float().numpy().copy(),
        action_scale=model.action_scale.detach().float().numpy().copy(),
        edge=[(m.bias.detach(), m.weight.detach().t().contiguous()) for m in edge[:-1]],
        folded=folded,
        folded_bias=folded_bias.contiguous(),
        lstm_in=[(b, w.t().contiguous()) for w, b, _ in layers],
        w_hh_t=[w.transpose(1, 2).contiguous().numpy() for _, _, w in [(0, 0, w_hh0), *layers]],
        node=[
            (m.bias.detach(), m.weight.detach().t().contiguous())
            for m in _linears(model.network.node_net)
        ],  # fmt: skip
    )


def _sources(model: Any) -> list[Tensor]:
    """Every tensor :func:`_build_weights` reads (without walking the module tree, whose
    cost is a noticeable share of a rollout)."""
    linears = _linears(model.network.edge_net) + _linears(model.network.node_net)
    lstm = model.network.lstm
    return [
        *(t for m in linears for t in (m.weight, m.bias)),
        *(p for k in range(lstm.num_layers) for p in layer_params(lstm, k)),
        *model._buffers.values(),
    ]


def _weights(model: Any) -> _Weights:
    """:func:`_build_weights`, cached on the model until a parameter or buffer changes."""
    key = tuple((t.data_ptr(), t._version) for t in _sources(model))
    cached = model.__dict__.get("_dlo_fast_weights")
    if cached is None or cached.key != key:
        # normal tensors even under inference mode: the buffers are written in place later,
        # possibly outside it
        with torch.inference_mode(False), torch.no_grad():
            cached = _build_weights(model, key)
        model.__dict__["_dlo_fast_weights"] = cached
    return cached


@dataclass
class _Workspace:
    """Preallocated buffers of one batch size: torch tensors for the matrix products, and
    numpy views of the same memory for the compiled loops."""

    features: np.ndarray  # (B, N, F)
    edge_in: Tensor  # (B * 2(N-1), E)
    edge_out: list[Tensor]  # per f_e layer but the last (B * 2(N-1), H)
    summed: Tensor  # (B * N, H): the last f_e layer's inputs summed per receiver
    gates: Tensor  # (B * N, 8H)
    hs: list[Tensor]  # outputs of the LSTM layers but the last (B * N, 2H)
    node_in: Tensor  # (B * N, own + 2H): own features, then the last LSTM layer's output
    node_out: list[Tensor]  # per f_v layer
    folded_bias: Tensor  # (B * N, 8H)


def _workspace(model: Any, w: _Weights, batch: int) -> _Workspace:
    """The buffers of ``batch``, made once per weights (not thread-safe: one planner at a
    time per model, as in every caller)."""
    if batch not in w.workspaces:
        w.workspaces[batch] = _new_workspace(model, w, batch)
    return w.workspaces[batch]


@torch.inference_mode(False)
def _new_workspace(model: Any, w: _Weights, batch: int) -> _Workspace:
    """Normal tensors (see :func:`_weights`)."""
    n, hidden, width = model.n_segments, model.network.lstm.hidden_size, model.feature_dim
    own = width - (0 if model.spec.absolute_position else 3)
    rows, relations = batch * n, batch * 2 * (n - 1)
    with torch.no_grad():
        return _Workspace(
            features=np.empty((batch, n, width), np.float32),
            edge_in=torch.empty(relations, w.edge[0][1].shape[0] if w.edge else w.folded.shape[0]),
            edge_out=[torch.empty(relations, b.shape[0]) for b, _ in w.edge],
            summed=torch.empty(rows, w.folded.shape[0]),
            gates=torch.empty(rows, 8 * hidden),
            hs=[torch.empty(rows, 2 * hidden) for _ in w.lstm_in],
            node_in=torch.empty(rows, own + 2 * hidden),
            node_out=[torch.empty(rows, b.shape[0]) for b, _ in w.node],
            folded_bias=w.folded_bias.repeat(batch, 1),
        )


# ---------------------------------------------------------------------- the rollout
def usable(model: Any, state: Tensor, actions: Tensor, previous: Tensor | None) -> bool:
    """Whether :func:`rollout` applies: CPU float32, no gradient wanted, a small batch."""
    if type(model.network) is not INBiLSTM:  # these loops compute the paper's model only
        return False
    tensors = [state, actions] + ([] if previous is None else [previous])
    if model.reference or len(state) > MAX_BATCH or not loops_take(*tensors, model.state_mean):
        return False
    return not wants_gradient([*tensors, *model.parameters()])


def rollout(model: Any, state: Tensor, actions: Tensor, previous: Tensor | None) -> Tensor:
    """``model.rollout`` (B, N, 7), (B, H, 2, 6) -> (B, H, N, 7) on the path above."""
    w = _weights(model)
    batch, horizon, n = actions.shape[0], actions.shape[1], model.n_segments
    net = model.network
    spec, own = model.spec, net.node_net[0].in_features - 2 * net.lstm.hidden_size
    ws = _workspace(model, w, batch)
    edge_in, summed, node_in = ws.edge_in.numpy(), ws.summed.numpy(), ws.node_in.numpy()
    gates = ws.gates.numpy()
    # where each LSTM layer writes: its own buffer, the last one f_v's input after `own`
    outputs = [h.numpy() for h in ws.hs] + [node_in]
    columns = [0] * len(ws.hs) + [own]
    predicted = np.empty((horizon, batch, n, 7), np.float32)  # time-major: contiguous steps
    state_np = state.detach().contiguous().numpy()
    prev_np = state_np if previous is None else previous.detach().contiguous().numpy()
    actions_np = actions.detach().transpose(0, 1).contiguous().numpy()
    has_previous = previous is not None
    for t in range(horizon):
        prepare(state_np, prev_np, has_previous, actions_np[t], w.norm, w.action_scale,
                spec.velocity_input, spec.absolute_position, ws.features, edge_in,
                node_in)  # fmt: skip
        x = dense_layers(ws.edge_in, w.edge, ws.edge_out, relu_last=True)
        sum_per_receiver(x.numpy(), n, summed)
        torch.addmm(ws.folded_bias, ws.summed, w.folded, out=ws.gates)
        recurrence(gates, w.w_hh_t[0], n, outputs[0], columns[0])
        for k, (bias, weight) in enumerate(w.lstm_in):
            torch.addmm(bias, ws.hs[k], weight, out=ws.gates)
            recurrence(gates, w.w_hh_t[k + 1], n, outputs[k + 1], columns[k + 1])
        x = dense_layers(ws.node_in, w.node, ws.node_out, relu_last=False)
        apply_delta(state_np, x.numpy(), w.norm, predicted[t])
        prev_np, state_np, has_previous = state_np, predicted[t], True
    return torch.from_numpy(predicted).transpose(0, 1).contiguous()
