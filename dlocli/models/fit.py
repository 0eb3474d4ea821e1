"""The one training entry point: :func:`fit` trains a model on data as a schedule says, the
schedule chosen by the model's form and the spec:

- epochs (the paper's): passes over all the training transitions
  (:func:`dlocli.models.rod_training._train_model`);
- steps (an ``UpdateSpec`` with schedule "steps"): a fixed number of gradient steps with the
  newest episodes weighted in (:func:`dlocli.models.step_schedule._train_steps`);
- rollout windows (a marker model, recorded cables): gradient steps through k-step open-loop
  rollouts (:func:`dlocli.models.marker_training._fit_markers`); an ensemble's members each
  so, in parallel (:func:`dlocli.models.member_fits.fit_members`).

An ensemble's members train apart in either view (:mod:`dlocli.models.member_fits`): a rod
ensemble's each for the epochs; the online loop's updates (``UpdateSpec``), which continue
one optimiser's state from update to update, train one network and refuse an ensemble.

It is the only way in: those three are private to their modules.

Every schedule reports :class:`~dlocli.events.Event` to ``progress``, stops before
its next gradient step once ``cancel`` is cancelled, and returns a
:class:`~dlocli.models.fitting.TrainResult`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.models.base import ONE_NETWORK_ONLINE, DynamicsModel
from dlocli.models.cable_codes import cable_key
from dlocli.models.ensemble import Ensemble
from dlocli.models.fitting import TrainResult
from dlocli.models.marker_model import MarkerModel
from dlocli.models.marker_training import Cable, Cables, _fit_markers
from dlocli.models.member_fits import fit_members, fit_rod_members
from dlocli.models.rod_training import _train_model
from dlocli.models.spec import FitSpec, UpdateSpec
from dlocli.models.splits import split_episodes
from dlocli.models.step_schedule import _train_steps

#: why an ensemble's run (either view's) does not resume after an epoch or a validation
ENSEMBLE_DOES_NOT_RESUME = (
    "an ensemble's members train apart and it is saved once all are done, so its run does "
    "not resume after an epoch or a validation: train it again with --overwrite"
)


def fit(
    model: DynamicsModel | MarkerModel,
    data: Any,
    schedule: FitSpec,
    *,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
    recent_episodes: np.ndarray | None = None,
    **state: Any,
) -> TrainResult:
    """Train ``model`` in place on ``data`` (a rod :class:`~dlocli.data.Dataset`; for a marker
    model a marker dataset, or :class:`~dlocli.models.marker_training.Cables` already split)
    as ``schedule`` says (see the module docstring). The steps schedule weighs
    ``recent_episodes`` (those added since the previous update) in; the others train on all
    episodes alike. ``state`` is what the schedule continues from: epochs take
    ``optimizer_state``, ``on_validation``, ``start_epoch``, ``generator_state`` and ``best``;
    steps ``optimizer_state`` and ``on_validation``; rollout windows ``on_validation`` (each
    validation's record and :class:`~dlocli.models.marker_training.RolloutPoint`) and
    ``resume_from`` (such a point; one network only)."""
    if isinstance(model, MarkerModel):
        return _fit_windows(model, data, schedule, progress, cancel, **state)
    if isinstance(model.network, Ensemble):
        return _fit_rod_ensemble(model, data, schedule, progress, cancel, **state)
    if isinstance(schedule, UpdateSpec) and schedule.schedule == "steps":
        return _train_steps(model, data, schedule, progress=progress, cancel=cancel,
                            recent_episodes=recent_episodes, **state)  # fmt: skip
    return _train_model(model, data, schedule, progress=progress, cancel=cancel, **state)


def _fit_windows(
    model: MarkerModel,
    data: Any,
    schedule: FitSpec,
    progress: Callback | None,
    cancel: CancelToken | None,
    **state: Any,
) -> TrainResult:
    """Rollout windows on the train split of the marker dataset ``data``, ``val_fraction`` of
    its trajectories held out for validation (its eval split is never seen); on
    :class:`Cables` as they were split (the result then names no episodes). ``state``: see
    :func:`fit`; an ensemble takes none (BadInput)."""
    if isinstance(data, Cables):
        cables = data
        train_idx = val_idx = np.zeros(0, np.int64)
    else:
        episodes = data.episodes("train")
        train_idx, val_idx = split_episodes(len(episodes), schedule.val_fraction)
        # train and validation: one cable, one code
        key = cable_key(data.held, episodes) if model.spec.cable_code else None
        train = Cable([episodes[i] for i in train_idx], data.held, key)
        val = [Cable([episodes[i] for i in val_idx], data.held, key)] if len(val_idx) else []
        cables = Cables([train], val)
    if isinstance(model.network, Ensemble):
        if state.get("resume_from") is not None:
            raise BadInput(ENSEMBLE_DOES_NOT_RESUME)
        history = fit_members(model, cables.train, cables.val, schedule, progress, cancel)
    else:
        history = _fit_markers(model, cables.train, cables.val, schedule, progress, cancel,
                               **state)  # fmt: skip
    return TrainResult(
        history=history,
        train_episodes=train_idx,
        val_episodes=val_idx,
        steps=schedule.update_steps,
        best_val_loss=min((r.val_loss for r in history), default=math.nan),
    )


def _fit_rod_ensemble(
    model: DynamicsModel,
    data: Any,
    schedule: FitSpec,
    progress: Callback | None,
    cancel: CancelToken | None,
    **state: Any,
) -> TrainResult:
    """The members of a rod ensemble, each for the epochs (:func:`fit_rod_members`): they
    start afresh, so nothing the epochs would continue from (an optimiser's state, a finished
    epoch, a checkpoint per epoch) applies; BadInput for the online loop's updates."""
    if isinstance(schedule, UpdateSpec):
        raise BadInput(ONE_NETWORK_ONLINE.format(members=model.spec.members))
    if state.get("start_epoch") or state.get("generator_state") is not None:
        raise BadInput(ENSEMBLE_DOES_NOT_RESUME)
    return fit_rod_members(model, data, schedule, progress, cancel)
