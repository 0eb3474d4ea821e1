"""The marker view of the dynamics models: positions only, held markers as the input.

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

Any registered network (:mod:`dlocli.models.network`) works in this view: each marker is a
node whose inputs are its features (all compared between neighbours in the relations, at
the features' scale), and, for a network that reads the cable's geometry
(``cable_geometry``), the vectors to both neighbours (zero past the ends), their lengths and
the cable's length along the markers, over the mean position scale; its output is the
normalised acceleration. Build one with :func:`build_marker_model`, load a trained one with
:func:`dlocli.models.checkpoints.load_model` (form ``"markers"``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dlocli.data.format import MARKERS
from dlocli.errors import BadInput
from dlocli.limits import refuse_unless_fits
from dlocli.models import cable_codes, marker_mlp_rollout, marker_steps, rollouts
from dlocli.models.base import valid_model_spec
from dlocli.models.ensemble import build_network, side_by_side
from dlocli.models.network import Nodes
from dlocli.models.spec import ModelSpec
from dlocli.registry import models

FEATURES = 10  # relative position 3, velocity 3, held displacement 3, held flag 1
DESCRIPTORS = 9  # the cable's geometry: vectors to both neighbours 6, lengths 2, cable length 1
FORM = MARKERS

#: the normalisation buffers, fitted on the training data
SCALES = ("position_scale", "velocity_scale", "acceleration_scale")


class MarkerModel(torch.nn.Module):
    """The marker view of a registered network (see the module docstring)."""

    #: the form of data it learns from and planners read it in (:mod:`dlocli.controllers.views`)
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
        network = models.get(spec.name)
        #: whether each marker's inputs include the cable's geometry (:meth:`descriptors`)
        self.geometry = bool(network.cable_geometry)
        #: one learned code per training cable (:mod:`~dlocli.models.cable_codes`; an
        #: ensemble's members each their own), their keys
        codes = cable_codes.no_codes(spec.cable_code, spec.members) if spec.cable_code else None
        self.register_parameter("codes", None if codes is None else torch.nn.Parameter(codes))
        self.cable_keys: list[str] = []
        self.cable: int | None = None  # the code in use: a row of ``codes``, None the mean
        self.network = build_network(spec, node_features(spec, n_markers))

    @property
    def reference(self) -> bool:
        """Plain PyTorch operations throughout (the benchmarks' reference), not the fused
        steps of :mod:`dlocli.models.marker_steps`."""
        return self.network.reference

    @reference.setter
    def reference(self, value: bool) -> None:
        self.network.reference = bool(value)

    def predict(self, inputs: Tensor) -> Tensor:
        """Normalised accelerations (B, V, 3) from the per-marker inputs (B, V, W), or an
        ensemble's per-member inputs (M, B, V, W) (per-member cable codes)."""
        return self.network(inputs, inputs[..., 1:, :] - inputs[..., :-1, :])

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

    def descriptors(self, x: Tensor) -> Tensor:
        """The cable's geometry per marker (B, V, DESCRIPTORS): the vectors to both
        neighbours (zero past the ends), their lengths and the cable's length, over the mean
        position scale: what tells one cable from another."""
        scale = self.position_scale.mean()
        edges = (x[:, 1:] - x[:, :-1]) / scale  # (B, V-1, 3)
        pad = torch.nn.functional.pad
        to_next, to_previous = pad(edges, (0, 0, 0, 1)), pad(-edges, (0, 0, 1, 0))
        spans = edges.norm(dim=-1, keepdim=True)  # (B, V-1, 1)
        length = spans.sum(1, keepdim=True).expand(-1, x.shape[1], 1)
        return torch.cat([to_previous, to_next, pad(spans, (0, 0, 1, 0)),
                          pad(spans, (0, 0, 0, 1)), length], -1)  # fmt: skip

    def _described(self, features: Tensor, x: Tensor) -> Tensor:
        if self.spec.cable_code:
            features = cable_codes.with_code(features, self.code())
        if not self.geometry:
            return features
        descriptors = self.descriptors(x)
        return torch.cat([features, descriptors.expand(*features.shape[:-1], -1)], -1)

    # ------------------------------------------------------------------ cable codes
    def code(self) -> Tensor:
        """The code in use (``cable_code``,), an ensemble's (members, ``cable_code``): the
        cable's row, or the mean code."""
        return cable_codes.chosen_code(self.codes, self.cable)

    def use_cable(self, key: str | None) -> int | None:
        """Use the code of the cable whose recordings have ``key`` (:func:`cable_key`), the
        mean code where it trained on no such cable; returns its row (None: the mean)."""
        self.cable = self.cable_keys.index(key) if key in self.cable_keys else None
        return self.cable

    def use_recorded_cable(self, held: np.ndarray, episodes: list[np.ndarray]) -> int | None:
        """:meth:`use_cable` of the cable whose train recordings are ``episodes``."""
        return self.use_cable(cable_codes.cable_key(held, episodes))

    def add_cables(self, keys: list[str]) -> list[int]:
        """The code rows of the cables with ``keys``, new rows (the mean code) for the new."""
        for key in keys:
            if key not in self.cable_keys:
                self.cable_keys.append(key)
        if self.codes is None:  # no codes: the keys alone
            return [self.cable_keys.index(k) for k in keys]
        rows = cable_codes.grown(self.codes.data, len(self.cable_keys))
        if rows.shape[0] != self.codes.shape[0]:
            self.codes = torch.nn.Parameter(rows.to(self.codes.device))
        return [self.cable_keys.index(k) for k in keys]

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
        held = self.held if held is None else held
        inputs = (x, x_prev, held_future, held, neighbour_distances(x))
        return rollouts.rollout(self, inputs, self._rollout_by_steps)

    def _rollout_by_steps(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor, held: Tensor, lengths: Tensor
    ) -> Tensor:
        """The plain rollout: :meth:`forward` step by step, ``lengths`` (B, V-1) kept."""
        step = functools.partial(self, lengths=lengths, held=held)
        return rollouts.open_loop(step, x, x_prev, held_future)

    def _offer_whole_rollout(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor, held: Tensor, lengths: Tensor
    ) -> Callable[[], Tensor] | None:
        """The rollout as one operation (:mod:`~dlocli.models.marker_mlp_rollout`) where
        :meth:`_whole_rollout_layers` has the layers for it."""
        layers = self._whole_rollout_layers(x, x_prev, held_future)
        if layers is None:
            return None
        return functools.partial(marker_mlp_rollout.rollout, self, layers, x, x_prev,
                                 held_future, held, lengths)  # fmt: skip

    def _offer_fused_steps(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor, held: Tensor, lengths: Tensor
    ) -> Callable[[], Tensor] | None:
        """The rollout through :meth:`_fused_step`, its constants prepared once, where it
        applies (:meth:`_fusable`)."""
        if not self._fusable(x, lengths):
            return None
        constants = marker_steps.step_constants(self, held, self.spec.length_projection)
        step = functools.partial(self._fused_step, lengths=lengths, constants=constants)
        return functools.partial(rollouts.open_loop, step, x, x_prev, held_future)

    #: tried in order by :func:`dlocli.models.rollouts.rollout`, before the plain rollout
    fused_rollouts: tuple[rollouts.Offer, ...] = (_offer_whole_rollout, _offer_fused_steps)

    def _fusable(self, x: Tensor, lengths: Tensor | None) -> bool:
        """Whether :meth:`_fused_step` applies: the distances it aims at take no gradient,
        and a subclass changed neither the features nor the step (it fuses this class's)."""
        own = self._plain_view() and not self.spec.cable_code  # the fused features: no code
        return (
            own and marker_steps.usable(self, x) and (lengths is None or not lengths.requires_grad)
        )

    def _plain_view(self) -> bool:
        """Whether a subclass changed neither the features nor the step."""
        own_features = type(self).features is MarkerModel.features
        return own_features and type(self).forward is MarkerModel.forward

    def _whole_rollout_layers(
        self, x: Tensor, x_prev: Tensor, held_future: Tensor
    ) -> list[tuple[Tensor, Tensor]] | None:
        """The network's fully connected layers when its whole rollout runs as one operation
        (:mod:`~dlocli.models.marker_mlp_rollout`): on CPU, with no gradient wanted for its
        inputs (as in training), for a network that is such layers over the flattened
        features (``flat_layers``: ``mlp``, ``arc-mlp``) without the cable's geometry; else
        None."""
        if self.geometry or not (self._plain_view() and marker_steps.usable(self, x)):
            return None
        if not marker_mlp_rollout.usable(x, x_prev, held_future):
            return None
        count = x.shape[1]
        if not self.spec.cable_code:
            return self.network.flat_layers(count)
        code = self.code()
        if code.dim() == 1:
            return _folded(self.network.flat_layers(count), count, code)
        members = self.network.members  # type: ignore[union-attr]
        return side_by_side([_folded(m.flat_layers(count), count, c)
                             for m, c in zip(members, code, strict=True)])  # fmt: skip

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


def _folded(
    layers: list[tuple[Tensor, Tensor]] | None, count: int, code: Tensor
) -> list[tuple[Tensor, Tensor]] | None:
    """Fully connected ``layers`` over features and ``code`` as layers over the features."""
    return None if layers is None else cable_codes.fold_code(layers, count, FEATURES, code)


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


def build_marker_model(spec: ModelSpec | dict, n_markers: int, held: np.ndarray) -> MarkerModel:
    """A fresh (untrained) model of the registered kind ``spec.name`` in the marker view;
    BadInput if its training would not fit in memory."""
    spec = valid_model_spec(spec)
    refuse_oversized_marker_model(spec, n_markers)
    return MarkerModel(spec, n_markers, held)


def node_features(spec: ModelSpec, n_markers: int) -> Nodes:
    """The nodes the network of ``spec`` sees: one per marker, with the marker view's
    features, the cable's code and (for a network that reads it) the cable's geometry."""
    geometry = bool(models.get(spec.name).cable_geometry)
    width = FEATURES + spec.cable_code + (DESCRIPTORS if geometry else 0)
    return Nodes(n_markers, width, 3, relative=width)


def refuse_oversized_marker_model(spec: ModelSpec, n_markers: int) -> None:
    """BadInput if the network's weights, gradients and Adam's two moments (4 float32 copies,
    every member of an ensemble) exceed the memory this run may use, as for a rod model
    (:func:`~dlocli.models.base.refuse_oversized_model`): counted on the meta device."""
    with torch.device("meta"):
        network = build_network(spec, node_features(spec, n_markers))
        parameters = sum(p.numel() for p in network.parameters())
    refuse_unless_fits(
        f"model {spec.name} (hidden {spec.hidden}, {spec.members} member(s), {n_markers} "
        f"markers: {parameters:,} parameters)",
        16.0 * parameters,
        "choose a smaller --hidden, fewer --members or fewer layers",
    )
