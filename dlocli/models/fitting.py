"""The one training loop of every view: a plan yields rounds of mini-batches (an epoch's,
``eval_every`` gradient steps', or rollout windows'), each ended by a validation; the view's
:class:`Objective` says what a batch's loss is and how it validates, so the loop itself (Adam
steps, divergence, validation records, progress, cancel, keeping the best) is written once.
:class:`KeepBest` tracks the best validation, stops early and restores the best weights where
the plan asks it to.

The rod view's objective is :class:`dlocli.models.rod_training.RodObjective` (one-step loss with
input noise, paper Sec. IV-C), under the epochs plan of :mod:`dlocli.models.rod_training` (the
paper's schedule) or the steps plan of :mod:`dlocli.models.step_schedule`; the marker view's is
:class:`dlocli.models.marker_training.RolloutObjective` (k-step open-loop rollouts) under its
own steps plan. :func:`dlocli.models.fit.fit` picks them.

Every fit reports its progress as :class:`~dlocli.events.Event` (its start, a batch done, a
validation) and is stopped through the :class:`~dlocli.cancel.CancelToken` it is given,
checked every step.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.errors import DloError
from dlocli.events import Began, Callback, Event

Unit = Literal["epoch", "step"]


# ---------------------------------------------------------------------- records and events
@dataclass
class FitRecord:
    """One validation: after ``count`` epochs or gradient steps (``unit``), the mean training
    loss since the previous one, the validation loss, and the seconds in between; a fit
    through rollout windows also records their length ``k`` then (and its losses are cm)."""

    unit: Unit
    count: int
    train_loss: float
    val_loss: float
    seconds: float
    k: int | None = None

    def as_row(self) -> dict[str, float]:
        """``{unit: count, "train_loss", "val_loss", "seconds"}`` (metrics.csv, checkpoints)."""
        return {self.unit: self.count, "train_loss": self.train_loss,
                "val_loss": self.val_loss, "seconds": self.seconds}  # fmt: skip

    @classmethod
    def from_row(cls, row: dict[str, Any]) -> FitRecord:
        unit: Unit = "step" if "step" in row else "epoch"
        k = row.get("k")  # a fit through rollout windows records it
        return cls(unit, int(row[unit]), row["train_loss"], row["val_loss"], row["seconds"],
                   None if k is None else int(k))  # fmt: skip


class BatchDone(Event):
    """Progress within a round: ``done`` of ``total`` mini-batches (unit "batch"); ``values``
    holds the round's count of epochs or steps when it ends (key: its unit) and the ``loss``."""


class Validated(Event):
    """A round ended: ``done`` of ``total`` epochs or steps (``unit``); ``values``: its
    ``val_loss`` and ``stopped_early`` (True: the fit stops here, ``val_loss`` is the best's)."""


class RolloutValidated(Validated):
    """A validation of a fit through k-step rollouts (marker models): ``val_loss`` is the
    benchmark score of whole rollouts (cm); ``values`` also hold the rollout length ``k`` and
    ``train_loss``, the mean k-step rollout loss (cm) since the previous validation."""


#: the random generator a plan draws from: torch's (the rod view's) or numpy's (rollout windows)
Generator = torch.Generator | np.random.Generator

#: called after each validation with its record, the optimizer and the random generator
OnValidation = Callable[[FitRecord, torch.optim.Optimizer, Generator], None]


@dataclass
class TrainResult:
    """What a fit returns: its validations, the optimiser's state, the split, the speed; for
    the steps schedule also the gradient steps taken, the step whose weights were kept (0: the
    weights it started from) and the share of sampled training rows from the recent episodes."""

    history: list[FitRecord] = field(default_factory=list)
    optimizer_state: dict[str, Any] = field(default_factory=dict)
    train_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    val_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    transitions_per_s: float = 0.0
    steps: int = 0
    best_step: int | None = None
    best_val_loss: float = math.nan
    recent_share: float = math.nan

    @property
    def val_loss(self) -> float:
        """The validation loss of the weights the model ends with."""
        if self.best_step is not None:
            return self.best_val_loss
        return self.history[-1].val_loss if self.history else math.nan


# ---------------------------------------------------------------------- keeping the best
@dataclass
class KeepBest:
    """The lowest validation loss so far and the count it came at (a NaN counts as lower:
    without validation the latest weights stand; with ``nan_is_worst``, a NaN is a rollout
    that blew up on validation data and counts as the highest). With ``keep``, the weights
    (and Adam's state) that had it, restored at the end; with ``patience``, a stop after that
    many validations in a row without a lower loss (0: never)."""

    val_loss: float = math.inf
    count: int = 0
    patience: int = 0
    keep: bool = False
    stale: int = 0
    saved: dict[str, Any] | None = None
    nan_is_worst: bool = False

    def start(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None) -> None:
        """Hold the starting weights as the best so far (at ``val_loss``, count 0)."""
        if self.keep:
            self.saved = _snapshot(model, optimizer)

    def observe(
        self,
        count: int,
        val_loss: float,
        model: torch.nn.Module,
        optimizer: torch.optim.Optimizer | None = None,
    ) -> bool:
        """Take a validation; True if it is the best so far."""
        if self.nan_is_worst and math.isnan(val_loss):
            val_loss = math.inf
        if val_loss >= self.val_loss:
            self.stale += 1
            return False
        self.val_loss, self.count, self.stale = val_loss, count, 0
        if self.keep:
            self.saved = _snapshot(model, optimizer)
        return True

    @property
    def stop(self) -> bool:
        return self.patience > 0 and self.stale >= self.patience

    def restore(
        self, count: int, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None = None
    ) -> None:
        """Back to the best weights (and Adam state, where it was held with them), unless
        they are those at ``count``."""
        if self.saved is None or self.count == count:
            return
        model.load_state_dict(self.saved["model"])
        if optimizer is not None and self.saved["optimizer"] is not None:
            optimizer.load_state_dict(self.saved["optimizer"])


def _snapshot(model: torch.nn.Module, optimizer: torch.optim.Optimizer | None) -> dict[str, Any]:
    return {
        "model": copy.deepcopy(model.state_dict()),
        "optimizer": None if optimizer is None else copy.deepcopy(optimizer.state_dict()),
    }


# ---------------------------------------------------------------------- the loop
@dataclass
class Round:
    """The mini-batches between two validations: ``size`` of them (an iterator may draw each
    as it is asked for), after which ``count`` epochs or steps are done. A plan whose rounds
    can end early (a time budget) updates ``count`` as its batches are drawn; a fit through
    rollout windows sets ``k``, the length of the round's last windows."""

    count: int
    batches: Iterable[Any]
    size: int
    k: int | None = None


class Plan(Protocol):
    """What a schedule tells the loop: its unit, its length (and the count it starts at), its
    rounds, what stays of the model if the loss diverges, and the generator of its random
    draws (handed to ``on_validation`` for checkpoints; None: the plan has none to resume)."""

    unit: Unit
    total: int
    start: int
    kept: str
    gen: Generator | None

    def rounds(self) -> Iterator[Round]: ...


class Objective(Protocol):
    """What a view trains on: the loss of one of its batches (with its graph; a view may refuse
    a non-finite one at once), the validation loss of the model as it is (NaN: no validation
    data), and the round's training loss from its batches' losses and sizes. ``clip``: the
    gradient norm every step is clipped to (None: no clipping); ``scheduler``: stepped after
    every optimizer step (None: a constant learning rate)."""

    clip: float | None
    scheduler: torch.optim.lr_scheduler.LRScheduler | None

    def loss(self, batch: Any) -> torch.Tensor: ...

    def validate(self) -> float: ...

    def mean_loss(self, losses: list[torch.Tensor], sizes: list[int]) -> float: ...


def fit_loop(
    model: torch.nn.Module,
    objective: Objective,
    plan: Plan,
    optimizer: torch.optim.Optimizer,
    best: KeepBest,
    progress: Callback | None = None,
    on_validation: OnValidation | None = None,
    cancel: CancelToken | None = None,
) -> tuple[list[FitRecord], int]:
    """Train ``model`` round by round as ``plan`` says, each batch's loss from ``objective``,
    validating after each round; stop when ``best`` says so and end (in eval mode) with the
    weights it keeps, or raise ``cancel``'s stop before any gradient step once it is
    cancelled. Returns the records and the training rows (batch sizes) processed."""
    history: list[FitRecord] = []
    rows, count = 0, 0
    if progress is not None:
        progress(Began(plan.unit, plan.start, plan.total))
    for each in plan.rounds():
        t0 = time.perf_counter()
        model.train()
        losses, sizes = [], []
        for b, batch in enumerate(each.batches, 1):
            loss = _step(model, objective, optimizer, batch, cancel)
            losses.append(loss)
            sizes.append(len(batch))
            if progress is not None and (b % 10 == 1 or b == each.size):
                values = {plan.unit: each.count, "loss": loss.item()}
                progress(BatchDone("batch", b, each.size, values))
        count = each.count
        rows += sum(sizes)
        train_loss = objective.mean_loss(losses, sizes)
        if not math.isfinite(train_loss):  # the model is lost; never save it as a result
            raise DloError(
                f"training diverged: the loss became {train_loss} in {plan.unit} {count} at lr "
                f"{optimizer.defaults['lr']:g}; start again with a lower --lr ({plan.kept})"
            )
        val_loss = objective.validate()
        seconds = time.perf_counter() - t0
        record = FitRecord(plan.unit, count, train_loss, val_loss, seconds, each.k)
        history.append(record)
        best.observe(count, val_loss, model, optimizer)
        if progress is not None:
            progress(_validated(record, plan.total))
        if on_validation is not None and plan.gen is not None:
            on_validation(record, optimizer, plan.gen)
        if best.stop:
            if progress is not None:  # the bar ends full, at the count reached
                values = {"val_loss": best.val_loss, "stopped_early": True}
                progress(Validated(plan.unit, count, count, values))
            break
    best.restore(count, model, optimizer)
    model.eval()
    return history, rows


def _step(
    model: torch.nn.Module,
    objective: Objective,
    optimizer: torch.optim.Optimizer,
    batch: Any,
    cancel: CancelToken | None,
) -> torch.Tensor:
    """One Adam step on ``batch``; its loss (detached). A cancelled ``cancel`` raises its stop
    before the step."""
    if cancel is not None:
        cancel.raise_if_cancelled()
    loss = objective.loss(batch)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if objective.clip is not None:
        torch.nn.utils.clip_grad_norm_(model.parameters(), objective.clip)
    optimizer.step()
    if objective.scheduler is not None:
        objective.scheduler.step()
    return loss.detach()


def _validated(record: FitRecord, total: int) -> Validated:
    """The event of a validation: a :class:`RolloutValidated` for a fit through rollout
    windows (its record has ``k``)."""
    values: dict[str, Any] = {
        "val_loss": record.val_loss,
        "train_loss": record.train_loss,
        "stopped_early": False,
    }
    if record.k is None:
        return Validated(record.unit, record.count, total, values)
    values["k"] = record.k
    return RolloutValidated(record.unit, record.count, total, values)
