"""Schedule "steps", the online loop's fixed-cost update: a set number of gradient steps on
mini-batches drawn from all the data with the newest episodes weighted in, stopped early on
(a capped subset of) the validation split, the best weights kept. Its cost does not grow with
the dataset, unlike the paper's E epochs over all of it
(:func:`dlocli.models.rod_training._train_model`). Both run :mod:`dlocli.models.fitting`'s loop
with the rod view's :class:`~dlocli.models.rod_training.RodObjective`;
:func:`dlocli.models.fit.fit` picks the schedule.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.events import Callback
from dlocli.models.base import DynamicsModel
from dlocli.models.fitting import KeepBest, OnValidation, Round, TrainResult, fit_loop
from dlocli.models.rod_training import RodObjective, set_up, validation_loss
from dlocli.models.spec import UpdateSpec


@dataclass
class StepPlan:
    """``fit.update_steps`` gradient steps in rounds of ``fit.eval_every``, each mini-batch
    drawn from ``gen`` when the loop asks for it (:func:`sample_batch`); counts the rows
    drawn from the recent episodes."""

    fit: UpdateSpec
    n_train: int
    recent: torch.Tensor
    gen: torch.Generator
    device: torch.device
    start: int = 0
    unit: str = "step"
    kept: str = "the model it started from is kept"
    hits: int = 0
    steps: int = 0

    def __post_init__(self) -> None:
        self.is_recent = torch.zeros(self.n_train, dtype=torch.bool)
        self.is_recent[self.recent] = True

    @property
    def total(self) -> int:
        return self.fit.update_steps

    def rounds(self) -> Iterator[Round]:
        total, every = self.fit.update_steps, self.fit.eval_every
        for first in range(0, total, every):
            size = min(every, total - first)
            yield Round(first + size, self._batches(size), size)

    def _batches(self, size: int) -> Iterator[torch.Tensor]:
        for _ in range(size):
            idx = sample_batch(self.n_train, self.recent, self.fit, self.gen)
            self.hits += int(self.is_recent[idx].sum())
            self.steps += 1
            yield idx.to(self.device)


def _train_steps(
    model: DynamicsModel,
    dataset: Dataset,
    fit: UpdateSpec,
    *,
    recent_episodes: np.ndarray | None = None,
    optimizer_state: dict | None = None,
    progress: Callback | None = None,
    on_validation: OnValidation | None = None,
    cancel: CancelToken | None = None,
) -> TrainResult:
    """Train ``model`` in place for at most ``fit.update_steps`` Adam steps (schedule
    "steps"): a cost per call that does not grow with ``dataset``.

    Each mini-batch of ``fit.batch_size`` training transitions is drawn with replacement from
    the whole training split, ``fit.recent_fraction`` of it from the transitions of
    ``recent_episodes`` (the data added since the previous update; when they are none or all
    of the training split, nothing is weighted). Every ``fit.eval_every`` steps (and after the
    last) the loss on a fixed random subset of at most ``fit.val_transitions`` validation
    transitions is measured; after ``fit.patience`` validations in a row without a lower loss
    than the best so far (the starting weights' included), training stops. The best weights
    and their Adam state are restored. Without a validation split every step runs and the
    last weights are kept.

    Set-up as :func:`~dlocli.models.rod_training._train_model`. Every random draw comes from one
    generator seeded with ``fit.seed``, so the result is a function of the seed, the data and
    the starting weights and optimizer state. ``progress`` gets a Began, then a
    :class:`~dlocli.models.fitting.Validated` (unit "step") after each validation;
    ``on_validation`` each validation's :class:`~dlocli.models.fitting.FitRecord`, the optimizer
    and the generator; ``cancel`` stops it before the next gradient step once cancelled.
    """
    setup = set_up(model, dataset, fit, optimizer_state)
    n_train = len(setup.train["state"])
    gen = torch.Generator(device="cpu").manual_seed(fit.seed)
    val = _val_subset(setup.val, fit.val_transitions, gen)
    has_val = len(val["state"]) > 0
    recent = recent_rows(dataset, setup.train_episodes, recent_episodes, setup.mirror)
    plan = StepPlan(fit, n_train, recent, gen, setup.train["state"].device)
    objective = RodObjective(model, setup.train, val, fit, gen)
    best = KeepBest(validation_loss(model, val), patience=fit.patience, keep=has_val)
    best.start(model, setup.optimizer)
    start = time.perf_counter()
    history, _ = fit_loop(model, objective, plan, setup.optimizer, best, progress,
                          on_validation, cancel)  # fmt: skip
    elapsed = time.perf_counter() - start
    step = plan.steps
    return TrainResult(
        history=history,
        optimizer_state=copy.deepcopy(setup.optimizer.state_dict()),
        train_episodes=setup.train_episodes,
        val_episodes=setup.val_episodes,
        transitions_per_s=step * fit.batch_size / elapsed if elapsed > 0 else 0.0,
        steps=step,
        best_step=best.count if has_val else None,
        best_val_loss=float(best.val_loss) if has_val else math.nan,
        recent_share=plan.hits / (step * fit.batch_size) if step else math.nan,
    )


def sample_batch(
    n: int, recent: torch.Tensor, fit: UpdateSpec, gen: torch.Generator
) -> torch.Tensor:
    """Row indices (CPU) of one mini-batch of ``fit.batch_size`` drawn with replacement:
    ``round(fit.recent_fraction * batch_size)`` of them from ``recent``, when it holds some but
    not all of the ``n`` rows, the rest from all ``n``."""
    k = round(fit.recent_fraction * fit.batch_size) if 0 < len(recent) < n else 0
    rows = torch.randint(n, (fit.batch_size - k,), generator=gen)
    if k == 0:
        return rows
    return torch.cat([recent[torch.randint(len(recent), (k,), generator=gen)], rows])


def recent_rows(
    dataset: Dataset, train_episodes: np.ndarray, recent: np.ndarray | None, mirror: bool
) -> torch.Tensor:
    """The rows of :func:`~dlocli.models.rod_training.transition_tensors` ``(dataset,
    train_episodes, mirror=mirror)`` that come from an episode in ``recent`` (with ``mirror``,
    their twins too)."""
    if recent is None:
        return torch.zeros(0, dtype=torch.long)
    per_episode = np.maximum(dataset.episode_lengths[train_episodes].astype(np.int64) - 1, 0)
    mask = np.repeat(np.isin(train_episodes, recent), per_episode)
    if mirror:
        mask = np.concatenate([mask, mask])
    return torch.as_tensor(np.flatnonzero(mask), dtype=torch.long)


def _val_subset(
    val: dict[str, torch.Tensor], most: int, gen: torch.Generator
) -> dict[str, torch.Tensor]:
    """At most ``most`` rows of ``val``, drawn once (in their order)."""
    n = len(val["state"])
    if n <= most:
        return val
    keep = torch.randperm(n, generator=gen)[:most].sort().values.to(val["state"].device)
    return {k: v[keep] for k, v in val.items()}
