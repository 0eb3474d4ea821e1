"""The one fit loop of the rod models, whatever counts the training: a plan yields rounds of
mini-batches (an epoch's, or ``eval_every`` gradient steps'), each ended by a validation;
:class:`KeepBest` tracks the best validation, stops early and restores the best weights
where the plan asks it to. :func:`dlocli.models.training._train_model` plans epochs (the
paper's schedule), :func:`dlocli.models.step_schedule._train_steps` gradient steps.

Every model is fitted with Adam on the mean squared error of the normalised state change,
with Gaussian noise on the input state (paper Sec. IV-C), on a train/validation split by
trajectory that stays the same as the dataset grows (so continued training in the online
loop never validates on what it trained on).

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
from dlocli.data import Dataset
from dlocli.errors import BadInput, DloError
from dlocli.events import Began, Callback, Event
from dlocli.models.base import DynamicsModel, resolve_device
from dlocli.models.mirror import with_mirrored
from dlocli.models.spec import FitSpec
from dlocli.models.splits import split_episodes

EVAL_BATCH = 1024
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
        return cls(unit, int(row[unit]), row["train_loss"], row["val_loss"], row["seconds"])


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


#: called after each validation with its record, the optimizer and the random generator
OnValidation = Callable[[FitRecord, torch.optim.Optimizer, torch.Generator], None]


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
    without validation the latest weights stand). With ``keep``, the weights (and Adam's
    state) that had it, restored at the end; with ``patience``, a stop after that many
    validations in a row without a lower loss (0: never)."""

    val_loss: float = math.inf
    count: int = 0
    patience: int = 0
    keep: bool = False
    stale: int = 0
    saved: dict[str, Any] | None = None

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
        """Back to the best weights (and Adam state), unless they are those at ``count``."""
        if self.saved is None or self.count == count:
            return
        model.load_state_dict(self.saved["model"])
        if optimizer is not None:
            optimizer.load_state_dict(self.saved["optimizer"])


def _snapshot(model: torch.nn.Module, optimizer: torch.optim.Optimizer | None) -> dict[str, Any]:
    return {
        "model": copy.deepcopy(model.state_dict()),
        "optimizer": None if optimizer is None else copy.deepcopy(optimizer.state_dict()),
    }


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


# ---------------------------------------------------------------------- a step, a validation
def gradient_step(
    model: DynamicsModel,
    optimizer: torch.optim.Optimizer,
    data: dict[str, torch.Tensor],
    idx: torch.Tensor,
    fit: FitSpec,
    gen: torch.Generator,
    cancel: CancelToken | None = None,
) -> torch.Tensor:
    """One Adam step on the rows ``idx`` of ``data``, with input noise from ``gen``; the
    batch's loss (detached). A cancelled ``cancel`` raises its stop before the step."""
    if cancel is not None:
        cancel.raise_if_cancelled()
    state = data["state"][idx]
    noise = None
    if fit.input_noise > 0:  # in units of the one-step change, expressed in state units
        scale = fit.input_noise * model.delta_std / model.state_std
        noise = torch.randn(state.shape, generator=gen).to(state.device) * scale
    loss = model.loss(
        state, data["action"][idx], data["next_state"][idx], noise, data["previous_state"][idx]
    )
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.detach()


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


# ---------------------------------------------------------------------- the loop
@dataclass
class Round:
    """The mini-batches between two validations: ``size`` of them (row indices; an iterator
    may draw each as it is asked for), after which ``count`` epochs or steps are done."""

    count: int
    batches: Iterable[torch.Tensor]
    size: int


class Plan(Protocol):
    """What a schedule tells the loop: its unit, its length (and the count it starts at),
    its validation data, its rounds, and what stays of the model if the loss diverges."""

    unit: Unit
    total: int
    start: int
    val: dict[str, torch.Tensor]
    kept: str

    def rounds(self) -> Iterator[Round]: ...


def fit_loop(
    model: DynamicsModel,
    setup: Setup,
    fit: FitSpec,
    plan: Plan,
    gen: torch.Generator,
    best: KeepBest,
    progress: Callback | None = None,
    on_validation: OnValidation | None = None,
    cancel: CancelToken | None = None,
) -> tuple[list[FitRecord], int]:
    """Train ``model`` round by round as ``plan`` says, validating after each round; stop
    when ``best`` says so and end with the weights it keeps, or raise ``cancel``'s stop before
    any gradient step once it is cancelled. Returns the records and the training rows
    processed."""
    history: list[FitRecord] = []
    optimizer, rows, count = setup.optimizer, 0, 0
    if progress is not None:
        progress(Began(plan.unit, plan.start, plan.total))
    for each in plan.rounds():
        count, t0 = each.count, time.perf_counter()
        model.train()
        total, seen = torch.zeros((), device=setup.train["state"].device), 0
        for b, idx in enumerate(each.batches, 1):
            loss = gradient_step(model, optimizer, setup.train, idx, fit, gen, cancel)
            total += loss * len(idx)
            seen += len(idx)
            if progress is not None and (b % 10 == 1 or b == each.size):
                progress(BatchDone("batch", b, each.size, {plan.unit: count, "loss": loss.item()}))
        rows += seen
        train_loss = float(total) / seen
        if not math.isfinite(train_loss):  # the model is lost; never save it as a result
            raise DloError(
                f"training diverged: the loss became {train_loss} in {plan.unit} {count} at lr "
                f"{fit.lr:g}; start again with a lower --lr ({plan.kept})"
            )
        val_loss = validation_loss(model, plan.val)
        record = FitRecord(plan.unit, count, train_loss, val_loss, time.perf_counter() - t0)
        history.append(record)
        best.observe(count, val_loss, model, optimizer)
        if progress is not None:
            progress(Validated(plan.unit, count, plan.total, _validated(val_loss)))
        if on_validation is not None:
            on_validation(record, optimizer, gen)
        if best.stop:
            if progress is not None:  # the bar ends full, at the count reached
                progress(Validated(plan.unit, count, count, _validated(best.val_loss, True)))
            break
    best.restore(count, model, optimizer)
    model.eval()
    return history, rows


def _validated(val_loss: float, stopped_early: bool = False) -> dict[str, Any]:
    """The numbers of a :class:`Validated`."""
    return {"val_loss": val_loss, "stopped_early": stopped_early}
