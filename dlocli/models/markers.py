"""The marker form of the dynamics models: positions only, held markers as the input.

What real setups observe: V tracked markers along the cable, no orientations, no gripper
commands. A state is the markers' positions x_t (B, V, 3) and the previous frame x_{t-1}
(their difference is the velocity); the input of a step is the recorded next position of
every held marker (the paper's per-vertex action a_i, as a boundary condition). A model
predicts each marker's acceleration; x_{t+1} = 2 x_t - x_{t-1} + a, and the held markers
are set to their recorded positions.

Per-marker features (all in world axes, so gravity keeps its direction): position relative
to the held markers' centroid, velocity, the held marker's next displacement (zero for free
ones) and a held flag, each divided by a scale fitted on the training data (buffers, so
they travel with the checkpoint).

A registered model names its marker form in its class attribute ``marker_form`` (a class,
or ``"module:attr"`` of one). Build one with :func:`build_marker_model`, load a trained one with
:func:`dlocli.models.checkpoints.load_marker_model`.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dlocli.data.format import MARKERS
from dlocli.errors import BadInput
from dlocli.models import marker_mlp_rollout, marker_steps
from dlocli.models.attention import AlongCable
from dlocli.models.base import mlp, valid_model_spec
from dlocli.models.in_bilstm import init_forget_bias
from dlocli.models.spec import ModelSpec
from dlocli.registry import import_target, models

FEATURES = 10  # relative position 3, velocity 3, held displacement 3, held flag 1
DESCRIPTORS = 9  # attention's: vectors to both neighbours 6, their lengths 2, cable length 1
FORM = MARKERS

#: the normalisation buffers, fitted on the training data
SCALES = ("position_scale", "velocity_scale", "acceleration_scale")


class MarkerModel(torch.nn.Module):
    """Base of the marker-form models; subclasses implement :meth:`predict`."""

    #: the form planners read it in (:mod:`dlocli.controllers.views`)
    form = FORM

    def __init__(self, spec: ModelSpec, n_markers: int, held: np.ndarray) -> None:
        super().__init__()
        held = torch.as_tensor(np.asarray(held, dtype=bool))
        if held.shape != (n_markers,) or not held.any() or held.all():
            raise BadInput(f"held markers must be a mask of {n_markers} with free ones")
        self.spec = spec
        self.n_segments = int(n_markers)  # the checkpoint's count field
        self.register_buffer("held", held)
        for name in SCALES:
            self.register_buffer(name, torch.ones(3))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        #: use the plain PyTorch operations throughout (the benchmarks' reference), not the
        #: fused steps of :mod:`dlocli.models.marker_steps`
        self.reference = False

    def predict(self, features: Tensor) -> Tensor:
        """Normalised accelerations (B, V, 3) from the features (B, V, FEATURES)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ normalisation
    def fit_normalization(self, episodes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Scales from training episodes ((T+1, V, 3) and their held mask (V,)): per axis,
        the RMS of the centroid-relative position, of the velocity and of the free markers'
        acceleration."""
        rel = np.concatenate([(e - e[:, h].mean(1, keepdims=True)).reshape(-1, 3)
                              for e, h in episodes])  # fmt: skip
        vel = np.concatenate([np.diff(e, axis=0).reshape(-1, 3) for e, _ in episodes])
        acc = np.concatenate([np.diff(e[:, ~h], 2, axis=0).reshape(-1, 3) for e, h in episodes])

        def rms(a: np.ndarray) -> np.ndarray:
            return np.maximum(np.sqrt(np.mean(a**2, 0)), 1e-6)

        for name, value in (("position_scale", rms(rel)), ("velocity_scale", rms(vel)),
                            ("acceleration_scale", rms(acc))):  # fmt: skip
            getattr(self, name).copy_(torch.as_tensor(value, dtype=torch.float32))
        self.fitted.fill_(True)

    def features(self, x: Tensor, x_prev: Tensor, held_next: Tensor, held: Tensor) -> Tensor:
        held = held[:, None].to(x.dtype)
        centre = (x * held).sum(1, keepdim=True) / held.sum()
        flag = held.expand(x.shape[0], -1, 1)
        return torch.cat([(x - centre) / self.position_scale,
                          (x - x_prev) / self.velocity_scale,
                          (held_next - x) * held / self.velocity_scale, flag], -1)  # fmt: skip

    def descriptors(self, x: Tensor) -> Tensor | None:
        """Per-marker inputs appended to :meth:`features` (B, V, D), for models that read
        more of the cable's geometry; None (the default): none."""
        return None

    def _described(self, features: Tensor, x: Tensor) -> Tensor:
        extra = self.descriptors(x)
        return features if extra is None else torch.cat([features, extra], -1)

    # ------------------------------------------------------------------ the contract
    def forward(
        self,
        x: Tensor,
        x_prev: Tensor,
        held_next: Tensor,
        lengths: Tensor | None = None,
        held: Tensor | None = None,
    ) -> Tensor:
        """Next positions (B, V, 3) from x_t, x_{t-1} and the held markers' x_{t+1} (the
        free rows of ``held_next`` are ignored); with ``lengths`` (B, V-1) and
        ``spec.length_projection``, projected onto those neighbour distances. ``held``: the
        mask of another cable (models whose size does not depend on V); default the model's."""
        held = self.held if held is None else held
        if self._fusable(x, lengths):
            sweeps = self.spec.length_projection if lengths is not None else 0
            return self._fused_step(x, x_prev, held_next, lengths,
                                    marker_steps.step_constants(self, held, sweeps))  # fmt: skip
        features = self._described(self.features(x, x_prev, held_next, held), x)
        acc = self.predict(features) * self.acceleration_scale
        nxt = torch.where(held[:, None], held_next, 2 * x - x_prev + acc)
        if lengths is not None and self.spec.length_projection:
            nxt = project_lengths(nxt, lengths, held, self.spec.length_projection)
        return nxt

    def rollout(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor, held: Tensor | None = None
    ) -> Tensor:
        """Open loop: (B, V, 3) x_t, x_{t-1} and (B, H, V, 3) frames t+1..t+H of which only
        the held markers are read -> predicted frames (B, H, V, 3)."""
        lengths = neighbour_distances(x)
        out = []
        if self._fusable(x, lengths):  # the step's constants prepared once
            held = self.held if held is None else held
            constants = marker_steps.step_constants(self, held, self.spec.length_projection)
            for k in range(held_future.shape[1]):
                x_prev, x = x, self._fused_step(x, x_prev, held_future[:, k], lengths, constants)
                out.append(x)
            return torch.stack(out, 1)
        for k in range(held_future.shape[1]):
            x_prev, x = x, self(x, x_prev, held_future[:, k], lengths, held)
            out.append(x)
        return torch.stack(out, 1)

    def _fusable(self, x: Tensor, lengths: Tensor | None) -> bool:
        """Whether :meth:`_fused_step` applies: the distances it aims at take no gradient,
        and a subclass changed neither the features nor the step (it fuses this class's)."""
        own = (
            type(self).features is MarkerModel.features
            and type(self).forward is MarkerModel.forward
        )
        return (
            own and marker_steps.usable(self, x) and (lengths is None or not lengths.requires_grad)
        )

    def _fused_step(
        self,
        x: Tensor,
        x_prev: Tensor,
        held_next: Tensor,
        lengths: Tensor | None,
        constants: marker_steps.StepConstants,
    ) -> Tensor:
        """:meth:`forward` with its fixed arithmetic as two fused operations around the
        network (:func:`~dlocli.models.marker_steps.step`)."""
        return marker_steps.step(self.predict, x, x_prev, held_next, lengths, constants,
                                 self._described)  # fmt: skip

    @property
    def device(self) -> torch.device:
        return self.held.device


def neighbour_distances(x: Tensor) -> Tensor:
    """(B, V, 3) -> (B, V-1) distances between neighbouring markers."""
    return (x[:, 1:] - x[:, :-1]).norm(dim=-1)


def project_lengths(x: Tensor, lengths: Tensor, held: Tensor, sweeps: int) -> Tensor:
    """Position-based projection onto the neighbour distances ``lengths``: each sweep
    corrects the even edges, then the odd ones (each half touches a marker once, so it is
    exact per edge and vectorised); held markers do not move (infinite mass). Without
    gradients on CPU, one compiled loop does the same (the ~100 small tensor operations
    would cost more than the model itself at batch 1)."""
    if x.device.type == "cpu" and not (torch.is_grad_enabled() and x.requires_grad):
        out = x.detach().contiguous().clone()
        weights = (~held).to(torch.float32).contiguous().numpy()
        _compiled_projection()(out.numpy(), lengths.detach().contiguous().numpy(), weights, sweeps)
        return out
    w = (~held).to(x.dtype)
    for _ in range(sweeps):
        for first in (0, 1):
            a = torch.arange(first, x.shape[1] - 1, 2, device=x.device)
            d = x[:, a + 1] - x[:, a]
            dist = d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
            wa, wb = w[a][:, None], w[a + 1][:, None]
            share = (dist - lengths[:, a, None]) / dist / (wa + wb).clamp_min(1.0) * d
            x = x.index_add(1, a, share * wa).index_add(1, a + 1, -share * wb)
    return x


@functools.cache
def _compiled_projection() -> Any:
    """:func:`project_lengths`' loop, compiled once (numba; cached on disk)."""
    import numba

    @numba.njit(cache=True, error_model="numpy")
    def project(x: np.ndarray, lengths: np.ndarray, w: np.ndarray, sweeps: int) -> None:
        for b in range(x.shape[0]):
            for _ in range(sweeps):
                for first in (0, 1):
                    for a in range(first, x.shape[1] - 1, 2):
                        d = x[b, a + 1] - x[b, a]
                        dist = max(np.sqrt(np.sum(d * d)), np.float32(1e-9))
                        share = (dist - lengths[b, a]) / dist / max(w[a] + w[a + 1], 1) * d
                        x[b, a] += share * w[a]
                        x[b, a + 1] -= share * w[a + 1]

    return project


class MarkerINBiLSTM(MarkerModel):
    """The paper's Interaction Network + bi-LSTM on the marker chain: f_e on each
    neighbour relation (receiver features, sender minus receiver), summed per receiver, a
    bidirectional LSTM along the cable, f_v on (own features, LSTM state)."""

    def __init__(self, spec: ModelSpec, n_markers: int, held: np.ndarray) -> None:
        super().__init__(spec, n_markers, held)
        h = spec.hidden
        self.edge_net = mlp([2 * FEATURES] + [h] * spec.edge_layers)
        self.lstm = torch.nn.LSTM(h, h, spec.lstm_layers, batch_first=True, bidirectional=True)
        self.node_net = mlp([FEATURES + 2 * h] + [h] * (spec.node_layers - 1) + [3])
        init_forget_bias(self.lstm, 1.0)

    def predict(self, f: Tensor) -> Tensor:
        diff = f[:, 1:] - f[:, :-1]
        n = f.shape[1]
        from_left = torch.cat([f[:, 1:], -diff], -1)  # receivers 1..V-1
        from_right = torch.cat([f[:, :-1], diff], -1)  # receivers 0..V-2
        out = self.edge_net(torch.cat([from_left, from_right], 1))
        left, right = out.split(n - 1, dim=1)
        pad = torch.nn.functional.pad
        effects = pad(left, (0, 0, 1, 0)) + pad(right, (0, 0, 0, 1))
        return self.node_net(torch.cat([f, self.lstm(effects)[0]], -1))


class MarkerMLP(MarkerModel):
    """The flattened baseline: one MLP from all markers' features to all accelerations."""

    def __init__(self, spec: ModelSpec, n_markers: int, held: np.ndarray) -> None:
        super().__init__(spec, n_markers, held)
        self.net = mlp([n_markers * FEATURES] + [spec.hidden] * spec.layers + [n_markers * 3])

    def predict(self, f: Tensor) -> Tensor:
        return self.net(f.reshape(len(f), -1)).view(len(f), self.n_segments, 3)

    def rollout(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor, held: Tensor | None = None
    ) -> Tensor:
        """:meth:`MarkerModel.rollout`; on CPU, with no gradient wanted for its inputs (as in
        training), the whole rollout is one operation (:mod:`~dlocli.models.marker_mlp_rollout`)."""
        own = type(self).predict is MarkerMLP.predict  # a subclass's network: step by step
        if own and self._fusable(x, None) and marker_mlp_rollout.usable(x, x_prev, held_future):
            held = self.held if held is None else held
            return marker_mlp_rollout.rollout(self, x, x_prev, held_future, held,
                                              neighbour_distances(x))  # fmt: skip
        return super().rollout(x, x_prev, held_future, held)


class MarkerAttention(MarkerModel):
    """Self-attention over the markers (:mod:`dlocli.models.attention`). Besides a marker's
    own features, its token holds the vectors to both neighbours (zero past the ends), their
    lengths and the cable's length along the markers, all over the mean position scale: what
    tells one cable from another, so one network can learn several cables (any count)."""

    def __init__(self, spec: ModelSpec, n_markers: int, held: np.ndarray) -> None:
        super().__init__(spec, n_markers, held)
        self.net = AlongCable(FEATURES + DESCRIPTORS, 3, spec)

    def descriptors(self, x: Tensor) -> Tensor:
        scale = self.position_scale.mean()
        edges = (x[:, 1:] - x[:, :-1]) / scale  # (B, V-1, 3)
        pad = torch.nn.functional.pad
        to_next, to_previous = pad(edges, (0, 0, 0, 1)), pad(-edges, (0, 0, 1, 0))
        spans = edges.norm(dim=-1, keepdim=True)  # (B, V-1, 1)
        length = spans.sum(1, keepdim=True).expand(-1, x.shape[1], 1)
        return torch.cat([to_previous, to_next, pad(spans, (0, 0, 1, 0)),
                          pad(spans, (0, 0, 0, 1)), length], -1)  # fmt: skip

    def predict(self, features: Tensor) -> Tensor:
        return self.net(features)


def build_marker_model(spec: ModelSpec, n_markers: int, held: np.ndarray) -> MarkerModel:
    """A fresh marker-form model of the registered kind ``spec.name``."""
    spec = valid_model_spec(spec)
    form = _marker_form(models.get(spec.name))
    if form is None:
        having = [name for name in models.names() if _marker_form(models.get(name)) is not None]
        raise BadInput(f"model '{spec.name}' has no marker form; use one of: {', '.join(having)}")
    return form(spec, n_markers, held)


def _marker_form(rod_model: Any) -> type[MarkerModel] | None:
    """The marker-form class a registered model names (imported if named as a string)."""
    form = getattr(rod_model, "marker_form", None)
    return import_target(form) if isinstance(form, str) else form
