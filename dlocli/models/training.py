"""Model training by epochs, the paper's schedule: :func:`_train_model`, reached through
:func:`dlocli.models.fit.fit`. The loop itself is :mod:`dlocli.models.fitting`'s, shared with
the online loop's fixed-cost update (:mod:`dlocli.models.update_steps`); ``dlo train``'s run
is :mod:`dlocli.runs.train`.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.events import Callback
from dlocli.models.base import DynamicsModel
from dlocli.models.fitting import (  # noqa: F401 (the training API, also from here)
    FitRecord,
    KeepBest,
    OnValidation,
    Round,
    TrainResult,
    Validated,
    fit_loop,
    mirror_applies,
    set_up,
    transition_tensors,
    validation_loss,
)
from dlocli.models.spec import FitSpec
from dlocli.models.splits import split_episodes  # noqa: F401 (also imported from here)


@dataclass
class EpochPlan:
    """Epochs ``start + 1 .. fit.epochs``: each a pass over the training rows in shuffled
    mini-batches (a permutation drawn from ``gen``), then a validation on all of ``val``."""

    fit: FitSpec
    n_train: int
    val: dict[str, torch.Tensor]
    gen: torch.Generator
    device: torch.device
    start: int = 0
    unit: str = "epoch"
    kept: str = "the last finite epoch is saved"

    @property
    def total(self) -> int:
        return self.fit.epochs

    def rounds(self) -> Iterator[Round]:
        size = self.fit.batch_size
        for epoch in range(self.start + 1, self.fit.epochs + 1):
            order = torch.randperm(self.n_train, generator=self.gen).to(self.device)
            batches = [order[b : b + size] for b in range(0, self.n_train, size)]
            yield Round(epoch, batches, len(batches))


def _train_model(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    *,
    optimizer_state: dict[str, Any] | None = None,
    progress: Callback | None = None,
    on_validation: OnValidation | None = None,
    start_epoch: int = 0,
    generator_state: torch.Tensor | None = None,
    best: KeepBest | None = None,
    cancel: CancelToken | None = None,
) -> TrainResult:
    """Train ``model`` in place for ``fit.epochs`` epochs on ``dataset``'s training split
    (with ``fit.mirror``, also on its transitions' mirrored twins; validation stays on the
    recorded data); the model ends with the last epoch's weights.

    The model moves to ``fit.device`` and comes back in eval mode. Its normalisation is
    fitted on the training data if it was never fitted (a continued model keeps its own).
    ``optimizer_state`` resumes Adam's moments (from a previous :class:`TrainResult` or
    checkpoint). ``progress`` gets a Began, a :class:`~dlocli.models.fitting.BatchDone` every few
    steps and a :class:`Validated` after each epoch; ``on_validation`` each epoch's
    :class:`FitRecord`, the optimizer and the random generator (for checkpoints), after
    ``best`` (the lowest validation loss so far) has seen it. ``start_epoch`` epochs are
    taken as done: given the generator state saved after them, the remaining epochs are
    those an uninterrupted run would train. ``cancel``: stop before the next gradient step
    once it is cancelled (none: run to the end).
    """
    setup = set_up(model, dataset, fit, optimizer_state)
    gen = torch.Generator(device="cpu").manual_seed(fit.seed)
    if generator_state is not None:
        gen.set_state(generator_state)
    device = setup.train["state"].device
    plan = EpochPlan(fit, len(setup.train["state"]), setup.val, gen, device, start_epoch)
    start = time.perf_counter()
    history, rows = fit_loop(model, setup, fit, plan, gen, best or KeepBest(), progress,
                             on_validation, cancel)  # fmt: skip
    elapsed = time.perf_counter() - start
    return TrainResult(
        history=history,
        optimizer_state=copy.deepcopy(setup.optimizer.state_dict()),  # not the live one
        train_episodes=setup.train_episodes,
        val_episodes=setup.val_episodes,
        transitions_per_s=rows / elapsed if elapsed > 0 else 0.0,
    )
