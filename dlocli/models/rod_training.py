"""The rod view's side of training (:mod:`dlocli.models.fitting` runs the loop): its split
into training and validation transitions, their tensors, the set-up of a fit,
:class:`RodObjective`, the loss every rod model is fitted on, and the paper's schedule by
epochs, :func:`_train_model` (the online loop's fixed-cost schedule is
:mod:`dlocli.models.step_schedule`'s). Both are reached through :func:`dlocli.models.fit.fit`;
``dlo train``'s run is :mod:`dlocli.runs.train`.

Every rod model is fitted with Adam on the mean squared error of the normalised state change,
with Gaussian noise on the input state (paper Sec. IV-C), on a train/validation split by
trajectory that stays the same as the dataset grows (so continued training in the online
loop never validates on what it trained on).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.errors import BadInput
from dlocli.events import Callback
from dlocli.models.base import DynamicsModel, resolve_device
from dlocli.models.fitting import KeepBest, OnValidation, Round, TrainResult, fit_loop
from dlocli.models.mirror import with_mirrored
from dlocli.models.spec import FitSpec
from dlocli.models.splits import split_episodes

EVAL_BATCH = 1024


# ---------------------------------------------------------------------- split and tensors
def transition_tensors(
    dataset: Dataset, episodes: np.ndarray, device: torch.device, mirror: bool = False
) -> dict[str, torch.Tensor]:
    """``previous_state``, ``state`` (M,N,7), ``action`` (M,2,6), ``next_state`` (M,N,7)
    float32 on ``device``, for the transitions whose previous state is recorded (t >= 1);
    with ``mirror``, followed by their mirrored twins (2M rows, :mod:`dlocli.models.mirror`)."""
    arrays = dataset.transitions(episodes, skip_first=True)
    if mirror:
        arrays = with_mirrored(arrays)
    return {
        k: torch.as_tensor(arrays[k], dtype=torch.float32, device=device)
        for k in ("previous_state", "state", "action", "next_state")
    }


def mirror_applies(dataset: Dataset) -> bool:
    """Whether ``dataset``'s transitions have valid mirrored twins: both rod ends held (a free
    right end's twin would be a rod with a free left end, which no backend simulates)."""
    spec = dataset.attrs.get("spec")
    backend = spec.get("backend") if isinstance(spec, dict) else None
    return not (isinstance(backend, dict) and backend.get("held_ends") == "left")


@dataclass
class Setup:
    """What every fit trains with: the split, its tensors and the optimizer."""

    train_episodes: np.ndarray
    val_episodes: np.ndarray
    train: dict[str, torch.Tensor]
    val: dict[str, torch.Tensor]
    optimizer: torch.optim.Optimizer
    mirror: bool  # whether the training rows include the mirrored twins


def set_up(
    model: DynamicsModel, dataset: Dataset, fit: FitSpec, optimizer_state: dict[str, Any] | None
) -> Setup:
    """Move ``model`` to ``fit.device``, split ``dataset``, fit the normalisation of a model
    that never had one, and make Adam (resuming ``optimizer_state``, at ``fit.lr``)."""
    if dataset.n_segments != model.n_segments:
        raise BadInput(
            f"dataset has {dataset.n_segments} segments but the model {model.n_segments}; "
            "train a new model or use a matching dataset"
        )
    device = resolve_device(fit.device)
    model.to(device)
    train_eps, val_eps = split_episodes(dataset.n_episodes, fit.val_fraction)
    mirror = fit.mirror and mirror_applies(dataset)
    train = transition_tensors(dataset, train_eps, device, mirror=mirror)
    val = transition_tensors(dataset, val_eps, device)  # the recorded data only
    if len(train["state"]) == 0:
        raise BadInput("the training split has no transitions; collect more episodes")
    if not bool(model.fitted):
        arrays = dataset.transitions(train_eps)
        model.fit_normalization(with_mirrored(arrays) if mirror else arrays)
    model.requires_grad_(True)  # a loaded model comes frozen for planning
    optimizer = torch.optim.Adam(model.parameters(), lr=fit.lr)
    if optimizer_state:
        optimizer.load_state_dict(copy.deepcopy(optimizer_state))  # the caller's stays as is
        for group in optimizer.param_groups:
            group["lr"] = fit.lr
    return Setup(train_eps, val_eps, train, val, optimizer, mirror)


# ---------------------------------------------------------------------- the objective
@torch.no_grad()
def validation_loss(model: DynamicsModel, data: dict[str, torch.Tensor]) -> float:
    """Mean normalised-delta MSE on ``data`` without input noise (NaN if it is empty)."""
    n = len(data["state"])
    if n == 0:
        return math.nan
    was_training = model.training
    model.eval()
    total = 0.0
    for i in range(0, n, EVAL_BATCH):
        sl = slice(i, i + EVAL_BATCH)
        batch = data["state"][sl]
        loss = model.loss(
            batch, data["action"][sl], data["next_state"][sl], previous=data["previous_state"][sl]
        )
        total += float(loss) * len(batch)
    model.train(was_training)
    return total / n


@dataclass
class RodObjective:
    """The rod view's :class:`~dlocli.models.fitting.Objective`: a batch is row indices of
    ``train``, its loss the normalised-delta MSE with input noise drawn from ``gen``; the
    validation loss is on all of ``val``; a round's training loss is the mean over its rows
    (accumulated on the device, read once per round). No clipping, a constant rate."""

    model: DynamicsModel
    train: dict[str, torch.Tensor]
    val: dict[str, torch.Tensor]
    fit: FitSpec
    gen: torch.Generator
    clip: float | None = None
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None

    def loss(self, batch: torch.Tensor) -> torch.Tensor:
        data, model, fit = self.train, self.model, self.fit
        state = data["state"][batch]
        noise = None
        if fit.input_noise > 0:  # in units of the one-step change, expressed in state units
            scale = fit.input_noise * model.delta_std / model.state_std
            noise = torch.randn(state.shape, generator=self.gen).to(state.device) * scale
        return model.loss(state, data["action"][batch], data["next_state"][batch], noise,
                          data["previous_state"][batch])  # fmt: skip

    def validate(self) -> float:
        return validation_loss(self.model, self.val)

    def mean_loss(self, losses: list[torch.Tensor], sizes: list[int]) -> float:
        total = torch.zeros((), device=self.train["state"].device)
        for loss, size in zip(losses, sizes, strict=True):
            total += loss * size
        return float(total) / sum(sizes)


# ---------------------------------------------------------------------- epochs
@dataclass
class EpochPlan:
    """Epochs ``start + 1 .. fit.epochs``: each a pass over the training rows in shuffled
    mini-batches (a permutation drawn from ``gen``), then a validation."""

    fit: FitSpec
    n_train: int
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
    plan = EpochPlan(fit, len(setup.train["state"]), gen, device, start_epoch)
    objective = RodObjective(model, setup.train, setup.val, fit, gen)
    start = time.perf_counter()
    history, rows = fit_loop(model, objective, plan, setup.optimizer, best or KeepBest(),
                             progress, on_validation, cancel)  # fmt: skip
    elapsed = time.perf_counter() - start
    return TrainResult(
        history=history,
        optimizer_state=copy.deepcopy(setup.optimizer.state_dict()),  # not the live one
        train_episodes=setup.train_episodes,
        val_episodes=setup.val_episodes,
        transitions_per_s=rows / elapsed if elapsed > 0 else 0.0,
    )
