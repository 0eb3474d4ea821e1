"""The rod view of the dynamics models: s_{t+1} = f(s_t, a_t) for the rod's segments.

Shapes and units (every model, every device):
- state ``(B, N, 7)``: per segment position (metres, world frame) then unit quaternion (w,x,y,z).
- action ``(B, 2, 6)``: per-gripper commands in [-1, 1] (left, right; linear then angular),
  the same units as the dataset's ``actions``. A single-gripper task's left row is zero; a
  bimanual task fills both: models act on the end segments, which is what makes a model
  trained on the single task usable on the bimanual one (paper Fig. 5).
- ``previous`` ``(B, N, 7)``: the state one control step earlier. A model with
  ``spec.velocity_input`` reads the change ``state - previous`` (a finite-difference
  velocity); ``None`` means the rod was at rest.
- ``forward(state, action, previous=None)`` returns the next state ``(B, N, 7)`` with unit
  quaternions.
- ``rollout(state, actions (B, H, 2, 6), previous=None)`` returns ``(B, H, N, 7)``,
  differentiable with respect to ``actions``.

The view normalises the state (dataset statistics held in buffers, so they travel with the
checkpoint), its network predicts the change of the state in normalised units, and the view
adds it to the state and renormalises the quaternions. Build one with :func:`build_model`,
load a trained one with :func:`dlocli.models.checkpoints.load_model`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError
from torch import Tensor

from dlocli.backends.rotations import state_change
from dlocli.data.format import ROD
from dlocli.errors import BadInput
from dlocli.limits import refuse_unless_fits
from dlocli.models import fast_rollout, rollouts
from dlocli.models.ensemble import build_network
from dlocli.models.network import Nodes
from dlocli.models.spec import ModelSpec, model_spec
from dlocli.specs import format_validation_error

STATE_DIM = 7  # position (3) + quaternion (4)
ACTION_DIM = 6  # per gripper: linear (3) + angular (3) velocity command
_STD_FLOOR = {"state": 1e-3, "delta": 1e-6}
#: why the online loop refuses an ensemble (``{members}``: its size)
ONE_NETWORK_ONLINE = (
    "the online loop updates one network between trials; an ensemble ({members} members) "
    "trains its members apart in `dlo train`: drop --members"
)
#: why the rod view has no cable codes: a rod dataset is one simulated rod (one backend, one
#: material; `dlo train` takes one), so there is no second cable for a code to tell apart
NO_CABLE_CODES = (
    "cable codes tell recorded cables apart (marker datasets from `dlo import`); a rod "
    "dataset is one simulated rod, so a rod model has no cable to tell apart: drop --cable-code"
)


class DynamicsModel(torch.nn.Module):
    """The rod view of a registered network (:mod:`dlocli.models.network`): a learned
    one-step model of the rod's segments.

    Each segment is a node whose inputs are its normalised state (7), with
    ``spec.velocity_input`` its normalised change over the previous step (7), and the
    normalised command of the gripper holding it (6; zeros elsewhere); the relations between
    neighbours are their normalised poses' difference at unit scale; the network's output is
    the segment's normalised change (7).

    With ``spec.members`` > 1 its network is an ensemble (:mod:`dlocli.models.ensemble`),
    the members trained apart (:func:`dlocli.models.member_fits.fit_rod_members`) and their
    predicted changes averaged at every step, so planners read it as one model. It has no
    cable codes (:data:`NO_CABLE_CODES`).

    Buffers (saved with the weights): ``state_mean``/``state_std`` (7,) normalise the input
    state per feature over all segments; ``delta_mean``/``delta_std`` (7,) the predicted change;
    ``action_scale`` (6,) divides the commands (no shift, so "no gripper" stays zero);
    ``relation_scale`` (7,) is the inverse RMS of the normalised difference between
    neighbouring segments' states.
    """

    #: the form of data it learns from and planners read it in
    form = ROD

    def __init__(self, spec: ModelSpec, n_segments: int) -> None:
        super().__init__()
        if n_segments < 2:
            raise BadInput(f"a rod model needs at least 2 segments, got {n_segments}")
        if spec.cable_code:
            raise BadInput(NO_CABLE_CODES)
        self.spec = spec
        self.n_segments = int(n_segments)
        for name, size, value in (
            ("state_mean", STATE_DIM, 0.0),
            ("state_std", STATE_DIM, 1.0),
            ("delta_mean", STATE_DIM, 0.0),
            ("delta_std", STATE_DIM, 1.0),
            ("action_scale", ACTION_DIM, 1.0),
            ("relation_scale", STATE_DIM, 1.0),
        ):
            self.register_buffer(name, torch.full((size,), value))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        nodes = Nodes(n_segments, self.feature_dim + ACTION_DIM, STATE_DIM, relative=STATE_DIM,
                      absolute=3, commands=ACTION_DIM)  # fmt: skip
        self.network = build_network(spec, nodes)

    @property
    def reference(self) -> bool:
        """Plain PyTorch throughout (the benchmarks' eager reference), no fast paths."""
        return self.network.reference

    @reference.setter
    def reference(self, value: bool) -> None:
        self.network.reference = bool(value)

    def predict_delta(self, state_n: Tensor, action_n: Tensor) -> Tensor:
        """Normalised state change (B, N, 7) from the normalised segment features (B, N, F)
        and the normalised per-gripper commands (B, 2, 6).

        The features are the normalised state (7), followed, with ``spec.velocity_input``, by
        the normalised change over the previous step (7): F = :attr:`feature_dim`."""
        pose = state_n[..., :STATE_DIM]
        relations = (pose[:, 1:] - pose[:, :-1]) * self.relation_scale
        nodes = torch.cat([state_n, node_actions(action_n, self.n_segments)], -1)
        return self.network(nodes, relations)

    @property
    def feature_dim(self) -> int:
        """Per-segment input features F: the state (7), and its last change if used (7)."""
        return 2 * STATE_DIM if self.spec.velocity_input else STATE_DIM

    # ------------------------------------------------------------------ normalisation
    def fit_normalization(self, transitions: dict[str, np.ndarray]) -> None:
        """Set the normalisation buffers from ``Dataset.transitions()`` arrays."""
        state = np.asarray(transitions["state"], dtype=np.float64)
        delta = target_delta(state, np.asarray(transitions["next_state"], dtype=np.float64))
        action = np.asarray(transitions["action"], dtype=np.float64).reshape(-1, ACTION_DIM)
        active = action[np.any(action != 0, axis=1)]
        scale = np.sqrt(np.mean(active**2, axis=0)) if len(active) else np.ones(ACTION_DIM)
        flat_s, flat_d = state.reshape(-1, STATE_DIM), delta.reshape(-1, STATE_DIM)
        state_std = np.maximum(flat_s.std(0), _STD_FLOOR["state"])
        neighbours = np.diff(state, axis=1).reshape(-1, STATE_DIM) / state_std
        rms = np.sqrt(np.mean(neighbours**2, axis=0))
        values = {
            "state_mean": flat_s.mean(0),
            "state_std": state_std,
            "delta_mean": flat_d.mean(0),
            "delta_std": np.maximum(flat_d.std(0), _STD_FLOOR["delta"]),
            "action_scale": np.where(scale > 1e-6, scale, 1.0),
            "relation_scale": 1.0 / np.maximum(rms, 1e-3),
        }
        for name, value in values.items():
            getattr(self, name).copy_(torch.as_tensor(value, dtype=torch.float32))
        self.fitted.fill_(True)

    def normalize(
        self, state: Tensor, action: Tensor, previous: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Normalised segment features (B, N, F) and commands (B, 2, 6); see predict_delta."""
        features = (state - self.state_mean) / self.state_std
        if self.spec.velocity_input:
            change = torch.zeros_like(state) if previous is None else target_delta(previous, state)
            features = torch.cat([features, (change - self.delta_mean) / self.delta_std], -1)
        return features, action / self.action_scale

    # ------------------------------------------------------------------ the contract
    def forward(self, state: Tensor, action: Tensor, previous: Tensor | None = None) -> Tensor:
        """Next state (B, N, 7) from state (B, N, 7), action (B, 2, 6) and the previous state
        (B, N, 7; None: at rest); unit quaternions."""
        self._check(state, action, previous)
        delta_n = self.predict_delta(*self.normalize(state, action, previous))
        return apply_delta(state, delta_n * self.delta_std + self.delta_mean)

    def rollout(self, state: Tensor, actions: Tensor, previous: Tensor | None = None) -> Tensor:
        """Open-loop prediction: (B, N, 7) and (B, H, 2, 6) -> (B, H, N, 7).

        ``previous`` (B, N, 7) is the state one step before ``state`` (None: at rest); later
        steps take the model's own predictions as their previous state. Differentiable with
        respect to ``actions`` (and ``state``); the batch dimension can carry independent
        plans (e.g. MPC restarts).
        """
        if actions.dim() != 4:
            raise BadInput(f"actions must be (B, H, 2, 6), got {tuple(actions.shape)}")
        return rollouts.rollout(self, (state, actions, previous), self._rollout_by_steps)

    def _rollout_by_steps(self, state: Tensor, actions: Tensor, previous: Tensor | None) -> Tensor:
        """The plain rollout: :meth:`forward` step by step."""

        def step(state: Tensor, previous: Tensor | None, action: Tensor) -> Tensor:
            return self(state, action, previous)

        return rollouts.open_loop(step, state, previous, actions)

    def _offer_fast_rollout(
        self, state: Tensor, actions: Tensor, previous: Tensor | None
    ) -> Callable[[], Tensor] | None:
        """:mod:`~dlocli.models.fast_rollout` (the planners' small batches) where it applies."""
        if not fast_rollout.usable(self, state, actions, previous):
            return None
        self._check(state, actions[:, 0], previous)  # as forward checks every step's
        return functools.partial(fast_rollout.rollout, self, state, actions, previous)

    #: tried by :func:`dlocli.models.rollouts.rollout`, before the plain rollout
    fused_rollouts: tuple[rollouts.Offer, ...] = (_offer_fast_rollout,)

    def loss(
        self,
        state: Tensor,
        action: Tensor,
        next_state: Tensor,
        noise: Tensor | None = None,
        previous: Tensor | None = None,
    ) -> Tensor:
        """Mean squared error of the normalised state change (the training objective).

        ``noise`` (B, N, 7), in normalised units, is added to the input state (paper
        Sec. IV-C); the target is the change from the noisy state, so the model learns to
        pull a perturbed state back onto the data. The velocity input (if any) is the change
        from ``previous`` to the noisy state, as a rollout feeds back its own predictions.
        """
        if noise is not None:
            state = state + noise * self.state_std
        target = (target_delta(state, next_state) - self.delta_mean) / self.delta_std
        return torch.mean(
            (self.predict_delta(*self.normalize(state, action, previous)) - target) ** 2
        )

    def _check(self, state: Tensor, action: Tensor, previous: Tensor | None = None) -> None:
        n = self.n_segments
        if state.dim() != 3 or state.shape[1:] != (n, STATE_DIM):
            raise BadInput(f"state must be (B, {n}, 7), got {tuple(state.shape)}")
        if action.dim() != 3 or action.shape[1:] != (2, ACTION_DIM) or len(action) != len(state):
            raise BadInput(f"action must be ({len(state)}, 2, 6), got {tuple(action.shape)}")
        if previous is not None and previous.shape != state.shape:
            raise BadInput(
                f"previous state must be {tuple(state.shape)}, got {tuple(previous.shape)}"
            )

    @property
    def device(self) -> torch.device:
        return self.state_mean.device


# ---------------------------------------------------------------------- state algebra
#: next_state - state with the quaternion sign aligned (numpy or torch), see rotations
target_delta = state_change


def apply_delta(state: Tensor, delta: Tensor) -> Tensor:
    """state + delta with the quaternion renormalised to unit length and w >= 0."""
    nxt = state + delta
    quat = torch.nn.functional.normalize(nxt[..., 3:], dim=-1)
    quat = quat * torch.where(quat[..., :1] < 0, -1.0, 1.0)
    return torch.cat([nxt[..., :3], quat], -1)


def node_actions(action: Tensor, n_segments: int) -> Tensor:
    """(B, 2, 6) gripper commands -> (B, N, 6): left on segment 0, right on N-1, else zero."""
    middle = action.new_zeros(action.shape[0], n_segments - 2, ACTION_DIM)
    return torch.cat([action[:, :1], middle, action[:, 1:]], 1)


# ---------------------------------------------------------------------- building, devices
def build_model(spec: ModelSpec | dict[str, Any], n_segments: int) -> DynamicsModel:
    """A fresh (untrained) model of the registered kind ``spec.name`` (a spec, or its fields
    as a dict); BadInput if its training would not fit in memory."""
    spec = valid_model_spec(spec)
    refuse_oversized_model(spec, n_segments, members_apart=True)
    return DynamicsModel(spec, n_segments)


def valid_model_spec(spec: ModelSpec | dict[str, Any], source: str = "model spec") -> ModelSpec:
    """``spec`` as its model's own spec class; BadInput naming the bad field if it is not one."""
    try:
        return model_spec(spec)
    except ValidationError as exc:
        raise BadInput(format_validation_error(exc, source)) from exc


def refuse_oversized_model(spec: ModelSpec, n_segments: int, members_apart: bool = False) -> None:
    """BadInput if the model's weights, gradients and Adam's two moments (4 float32 copies)
    exceed the memory this run may use, or if it is an ensemble and the run does not train
    members apart (``members_apart``: `dlo train` does; the online loop, which checks its
    model here before it starts, updates one network: :data:`ONE_NETWORK_ONLINE`). The model
    is built on the meta device, which counts its parameters exactly without allocating them."""
    if spec.members > 1 and not members_apart:
        raise BadInput(ONE_NETWORK_ONLINE.format(members=spec.members))
    with torch.device("meta"):
        parameters = sum(p.numel() for p in DynamicsModel(spec, n_segments).parameters())
    refuse_unless_fits(
        f"model {spec.name} (hidden {spec.hidden}: {parameters:,} parameters)",
        16.0 * parameters,
        "choose a smaller --hidden or fewer layers",
    )


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """ "auto" (CUDA if present, else CPU), "cpu", "cuda", "cuda:K"; BadInput if unavailable."""
    name = str(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise BadInput(f"--device '{name}' is not a device; use auto, cpu, cuda or cuda:K") from exc
    if dev.type == "cpu":
        return torch.device("cpu")
    if dev.type != "cuda":
        raise BadInput(f"--device '{name}' is not supported; use auto, cpu, cuda or cuda:K")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    index = 0 if dev.index is None else dev.index
    if index >= count:
        have = f"{count} CUDA device(s)" if count else "no CUDA device"
        raise BadInput(f"--device '{name}' does not exist (this machine has {have}); use cpu")
    return torch.device("cuda", index)


# ---------------------------------------------------------------------- control periods
def check_control_rate(
    model: torch.nn.Module, control_dt: float, name: str, used: str, fix: str
) -> None:
    """BadInput if ``model`` (called ``name``) learned from data at another control period than
    the ``control_dt`` (s) it is ``used`` at ("the task runs", "--data is"): each of its steps
    would stand for the wrong time. ``fix`` ends the line; ``{dt}`` and ``{hz}`` in it are the
    model's period (s) and rate, ``{used_hz}`` the other rate. A model that does not record
    its period passes (nothing to compare: checkpoints written before they recorded it)."""
    trained = getattr(model, "control_dt", None)
    if trained is None or abs(trained - control_dt) <= 1e-4 * control_dt:
        return
    ours = {"dt": f"{trained:.6g}", "hz": f"{1 / trained:.6g}", "used_hz": f"{1 / control_dt:.6g}"}
    raise BadInput(
        f"{name} was trained on data at {ours['hz']} Hz ({ours['dt']} s steps) but {used} at "
        f"{ours['used_hz']} Hz ({control_dt:.6g} s); {fix.format(**ours)}"
    )
