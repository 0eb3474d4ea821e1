"""The online loop's model update with the markers observation: the marker form of the model
(:mod:`dlocli.models.marker_model`) learns from what the tracker reported, as it would on a real
cell, never from the simulator's exact state.

Each episode of D gives the tracker's reports with the held markers placed by the gripper
poses of the frame's own time (the robot's kinematics; under a latency of k the report of
step t shows the rod at t - k), cut where a frame had markers missing: the model learns
from complete frames only. Training is :func:`dlocli.models.fit.fit` on those runs
(``fit.update_steps`` steps of k-step rollouts, ``fit.rollout_steps``), continued from the
previous iteration's weights.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.env.observation import MarkerLayout, held_markers, marker_layout
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.models.fit import fit as fit_model
from dlocli.models.fitting import TrainResult
from dlocli.models.marker_model import build_marker_model
from dlocli.models.marker_training import Cable, Cables
from dlocli.models.splits import split_episodes
from dlocli.specs import EnvSpec

#: the shortest run of complete frames worth training on
MIN_FRAMES = 8

ONLINE_CABLE = "online"  # the key of the online cable's code


def run_marker_layout(spec: EnvSpec) -> MarkerLayout:
    """The markers the run's task observes."""
    rod = spec.backend.rod
    held = (True, spec.backend.held_ends == "both")
    return marker_layout(spec.task.observation, rod.length, rod.n_segments, held)


def complete_runs(
    data: Dataset, episodes: np.ndarray, layout: MarkerLayout, latency: int
) -> list[np.ndarray]:
    """The reported frames (T, M, 3) of ``episodes``, held markers from the gripper poses of
    each frame's time, cut into runs of complete frames of at least MIN_FRAMES."""
    if data.markers is None or data.visible is None:
        raise BadInput("the online data hold no marker reports; start the run again")
    starts = data.state_offsets()
    runs = []
    for e in episodes:
        s0, length = int(starts[e]), int(data.episode_lengths[e]) + 1
        frames = data.markers[s0 : s0 + length].astype(np.float64)
        shown = np.maximum(np.arange(length) - latency, 0)  # the time each frame shows
        poses = data.grippers[s0 : s0 + length][shown].astype(np.float64)
        frames = np.where(layout.held[:, None], held_markers(layout, poses), frames)
        complete = data.visible[s0 : s0 + length].all(axis=1)
        runs += [frames[a:b] for a, b in _true_spans(complete) if b - a >= MIN_FRAMES]
    return runs


def _true_spans(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of every run of True in ``flags``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(int), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def update_marker_model(
    model: Any,
    data: Dataset,
    spec: Any,
    fit: Any,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> TrainResult:
    """Train the marker ``model`` on D (``spec``: the online spec) in place; ``cancel`` stops
    it between gradient steps."""
    layout = run_marker_layout(spec)
    latency = spec.task.observation.latency_steps
    train_idx, val_idx = split_episodes(data.n_episodes, fit.val_fraction)
    train = complete_runs(data, train_idx, layout, latency)
    if not train:
        raise BadInput(
            "no run of complete marker frames to learn from: lower --dropout or "
            "--occlusion-probability for training"
        )
    val = complete_runs(data, val_idx, layout, latency)
    # one cable, whose recordings grow with every update: one code (a model with cable codes)
    cables_val = [Cable(val, layout.held, ONLINE_CABLE)] if val else []
    cables = Cables([Cable(train, layout.held, ONLINE_CABLE)], cables_val)
    return fit_model(model, cables, fit, progress=progress, cancel=cancel)


def new_marker_model(spec: Any) -> Any:
    """A fresh marker model of the run's model kind, for its markers."""
    layout = run_marker_layout(spec)
    return build_marker_model(spec.model, len(layout), layout.held)
