"""The one training loop (:func:`dlocli.models.fitting.fit_loop`) with a view of its own: a
plan and an objective are all a view writes to train through it, whatever its data."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import torch

from dlocli.cancel import CancelToken
from dlocli.errors import DloError
from dlocli.events import Began
from dlocli.models.fitting import (
    BatchDone,
    KeepBest,
    RolloutValidated,
    Round,
    Validated,
    fit_loop,
)


@dataclass
class LinePlan:
    """``rounds`` rounds of ``size`` batches of 8 points of the line y = 2x."""

    rounds_: int = 3
    size: int = 4
    unit: str = "step"
    start: int = 0
    kept: str = "nothing is saved"
    gen: torch.Generator | None = None
    k: int | None = None

    @property
    def total(self) -> int:
        return self.rounds_ * self.size

    def rounds(self) -> Iterator[Round]:
        for r in range(1, self.rounds_ + 1):
            batches = [torch.linspace(-1, 1, 8) + 0.1 * b for b in range(self.size)]
            yield Round(r * self.size, batches, self.size, self.k)


@dataclass
class LineObjective:
    """Squared error of a line through the origin; validation on x = 1 (or ``val``)."""

    model: torch.nn.Linear
    val: float | None = None
    clip: float | None = None
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None

    def loss(self, batch: torch.Tensor) -> torch.Tensor:
        pred = self.model(batch[:, None])[:, 0]
        return ((pred - 2 * batch) ** 2).mean()

    def validate(self) -> float:
        if self.val is not None:
            return self.val
        with torch.no_grad():
            return float((self.model(torch.ones(1, 1)) - 2) ** 2)

    def mean_loss(self, losses: list[torch.Tensor], sizes: list[int]) -> float:
        return float(sum(float(x) * n for x, n in zip(losses, sizes, strict=True)) / sum(sizes))


def _line() -> torch.nn.Linear:
    torch.manual_seed(0)
    return torch.nn.Linear(1, 1, bias=False)


def test_a_new_view_trains_through_the_one_loop():
    model = _line()
    events = []
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    history, rows = fit_loop(model, LineObjective(model), LinePlan(), optimizer,
                             KeepBest(keep=True), events.append)  # fmt: skip
    assert [r.count for r in history] == [4, 8, 12] and rows == 12 * 8
    assert history[-1].val_loss < history[0].val_loss and not model.training
    assert isinstance(events[0], Began) and events[0].total == 12
    assert any(isinstance(e, BatchDone) for e in events)
    validated = [e for e in events if isinstance(e, Validated)]
    assert [e.done for e in validated] == [4, 8, 12]
    assert not any(isinstance(e, RolloutValidated) for e in validated)


def test_a_view_with_rollout_windows_reports_its_k():
    model = _line()
    events = []
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    history, _ = fit_loop(model, LineObjective(model), LinePlan(k=5), optimizer, KeepBest(),
                          events.append)  # fmt: skip
    assert all(r.k == 5 for r in history)
    rollouts = [e for e in events if isinstance(e, RolloutValidated)]
    assert len(rollouts) == 3 and rollouts[0].values["k"] == 5
    assert rollouts[0].values["train_loss"] == history[0].train_loss


def test_clip_and_scheduler_are_the_views():
    model = _line()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: 0.5**s)
    objective = LineObjective(model, clip=1e-3, scheduler=scheduler)
    before = model.weight.item()
    fit_loop(model, objective, LinePlan(rounds_=1, size=1), optimizer, KeepBest())
    assert abs(model.weight.item() - before) <= 1e-3 + 1e-9  # one step, clipped
    assert optimizer.param_groups[0]["lr"] == 0.5  # stepped once


def test_the_best_validation_is_kept_and_a_nan_counts_as_worst():
    model = _line()
    start = model.weight.detach().clone()
    best = KeepBest(keep=True, nan_is_worst=True)
    best.observe(0, 1.0, model)  # the weights it starts from: the best there is
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    fit_loop(model, LineObjective(model, val=math.nan), LinePlan(), optimizer, best)
    assert torch.equal(model.weight, start) and best.count == 0
    stays = KeepBest()  # without nan_is_worst a NaN (no validation) keeps the latest weights
    assert stays.observe(1, math.nan, model)


def test_a_diverging_fit_is_refused_and_a_cancel_stops_it_first():
    model = _line()
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    nan = LineObjective(model)
    nan.loss = lambda batch: model(batch[:, None]).sum() * math.nan  # type: ignore[method-assign]
    with pytest.raises(DloError, match="diverged.*step 4 at lr 0.1"):
        fit_loop(model, nan, LinePlan(), optimizer, KeepBest())
    cancel = CancelToken()
    cancel.cancel()
    model = _line()
    before = model.weight.detach().clone()
    optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
    with pytest.raises(KeyboardInterrupt):  # the token's stop (Ctrl-C's by default)
        fit_loop(model, LineObjective(model), LinePlan(), optimizer, KeepBest(), cancel=cancel)
    assert torch.equal(model.weight, before)
