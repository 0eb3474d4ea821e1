"""The online loop's model update (paper Algorithm 1): :func:`update_model` after each
iteration's trials, and :func:`train_like_online`, the offline model trained as long. Both
train through :func:`dlocli.models.fit.fit`, under the schedule of the run's ``fit`` spec.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.events import Callback
from dlocli.models.base import DynamicsModel
from dlocli.models.fit import fit as fit_model
from dlocli.models.fitting import TrainResult
from dlocli.models.spec import UpdateSpec


def update_model(
    model: DynamicsModel,
    dataset: Dataset,
    fit: UpdateSpec,
    *,
    recent_episodes: np.ndarray | None = None,
    cancel: CancelToken | None = None,
    **options: Any,
) -> TrainResult:
    """Train ``model`` in place as ``fit.schedule`` says (:func:`dlocli.models.fit.fit`, which
    the steps schedule weighs ``recent_episodes`` in); ``options``: ``optimizer_state``,
    ``progress``, ``on_validation``. ``cancel`` stops it between gradient steps (the online
    loop hands it the process's stop signals)."""
    return fit_model(model, dataset, fit, cancel=cancel, recent_episodes=recent_episodes, **options)


def train_like_online(
    model: DynamicsModel,
    dataset: Dataset,
    fit: UpdateSpec,
    updates: int,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> TrainResult:
    """Train a fresh ``model`` on all of ``dataset`` as long as the online loop's model had
    trained after ``updates`` updates under ``fit.schedule`` (paper Fig. 7's offline model):
    E·updates epochs ("epochs"), or update_steps·updates steps with nothing weighted ("steps",
    so the offline comparison stays affordable where the paper's schedule is not); ``cancel``
    as :func:`update_model`'s."""
    return update_model(model, dataset, fit.times(updates), progress=progress, cancel=cancel)
