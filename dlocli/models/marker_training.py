"""Training marker-form models through k-step open-loop rollouts.

One-step training (the paper's, with input noise) does not hold a 500-step open-loop
rollout: small errors feed back and grow. Here every gradient step rolls the model out
``k`` steps from recorded starts, with only the held markers given, and takes the mean
absolute error of the free markers over the rollout (the benchmark's L1 score). ``k`` grows
geometrically from ``fit.rollout_start`` to ``fit.rollout_steps`` over the first
``fit.rollout_ramp`` of the steps; the learning rate decays on a cosine to zero. Windows are
augmented by the cable's end-to-end mirror (marker order reversed, ``fit.mirror``) and a
random rotation about the vertical axis (gravity keeps its direction). Validation rolls the
held-out training trajectories out whole, by the benchmark's score, every ``eval_every``
steps; the best weights are kept. After each validation the fit can hand out a
:class:`RolloutPoint`, all it needs to go on from there as if never stopped (`dlo train
--resume`).

On CPU the rollouts run through the fused operations of :mod:`dlocli.models.marker_steps`
(and the MLP's whole rollout as one, :mod:`dlocli.models.marker_mlp_rollout`): the same
loss and gradients, ~5x the rollout steps per second for the MLP recipe, ~1.3x for the
in-bilstm and attention ones, whose networks' own arithmetic bounds them
(``benchmarks/results/training_throughput.txt``); elsewhere plain PyTorch.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data.protocol import deform_score_cm
from dlocli.errors import BadInput, DloError
from dlocli.events import Callback
from dlocli.models.base import resolve_device
from dlocli.models.cable_codes import cable_key
from dlocli.models.fitting import FitRecord, KeepBest, Round, Unit, fit_loop
from dlocli.models.marker_model import MarkerModel
from dlocli.models.spec import FitSpec

CM = 0.01


def rollout_length(fit: FitSpec, step: int) -> int:
    """k at gradient step ``step``: geometric from rollout_start to rollout_steps over the
    first rollout_ramp of the steps, then rollout_steps."""
    end = max(1, int(fit.rollout_ramp * fit.update_steps))
    start = min(fit.rollout_start, fit.rollout_steps)
    frac = min(1.0, step / end)
    return int(round(start * (fit.rollout_steps / start) ** frac))


@dataclass
class Cable:
    """Episodes (each (T+1, V, 3)) of one cable and its held-marker mask (V,); ``key``: what
    picks its code in a model with cable codes (default: the key of these episodes)."""

    episodes: list[np.ndarray]
    held: np.ndarray
    key: str | None = None

    def code_key(self) -> str:
        return self.key or cable_key(self.held, self.episodes)

    def mask(self, device: torch.device) -> torch.Tensor:
        return torch.as_tensor(self.held, dtype=torch.bool, device=device)


@dataclass
class Cables:
    """Cables already split for a rollout fit: those it trains on and those it validates on
    (what :func:`dlocli.models.fit.fit` takes for a marker model besides a marker dataset)."""

    train: list[Cable]
    val: list[Cable]


class WindowSampler:
    """Random k-step windows (x_{t-1}, x_t, x_{t+1..t+k}), each batch from one cable (drawn
    in proportion to its episodes)."""

    def __init__(self, cables: list[Cable], fit: FitSpec, device: torch.device) -> None:
        self.cables = cables
        self.episodes = [[torch.as_tensor(e, dtype=torch.float32, device=device)
                          for e in c.episodes] for c in cables]  # fmt: skip
        counts = np.array([len(c.episodes) for c in cables], dtype=float)
        self.weights = counts / counts.sum()
        # the mirror reverses the marker order: valid where the held markers are symmetric
        self.mirror = [fit.mirror and bool((c.held == c.held[::-1]).all()) for c in cables]
        self.rng = np.random.default_rng(fit.seed)
        self.device = device

    def sample(self, batch: int, k: int) -> tuple[torch.Tensor, torch.Tensor, int]:
        """(B, k + 2, V, 3) frames t-1 .. t+k, augmented, the cable's held mask and the
        cable's index in ``cables``."""
        c = int(self.rng.choice(len(self.cables), p=self.weights))
        episodes = self.episodes[c]
        lengths = np.array([len(e) for e in episodes])
        eps = self.rng.integers(len(episodes), size=batch)
        k = int(min(k, lengths[eps].min() - 2))
        starts = self.rng.integers(1, lengths[eps] - k)
        pairs = zip(eps, starts, strict=True)
        win = torch.stack([episodes[e][s - 1 : s + k + 1] for e, s in pairs])
        if self.mirror[c]:
            flip = torch.as_tensor(self.rng.random(batch) < 0.5, device=self.device)
            win = torch.where(flip[:, None, None, None], win.flip(2), win)
        return rotate_about_vertical(win, self.rng), self.cables[c].mask(self.device), c


def rotate_about_vertical(win: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """Each window turned by its own random angle about the z axis (gravity unchanged)."""
    angle = torch.as_tensor(rng.uniform(0, 2 * math.pi, len(win)), dtype=win.dtype,
                            device=win.device)  # fmt: skip
    c, s = torch.cos(angle)[:, None, None], torch.sin(angle)[:, None, None]
    x, y = win[..., 0], win[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, win[..., 2]], -1)


def rollout_loss(model: MarkerModel, windows: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
    """Mean absolute error (cm) of the free markers over the open-loop rollout."""
    pred = model.rollout(windows[:, 1], windows[:, 0], windows[:, 2:], held)
    return (pred[:, :, ~held] - windows[:, 2:, ~held]).abs().mean() / CM


@torch.no_grad()
def predict_episodes(
    model: MarkerModel, episodes: list[np.ndarray], held: np.ndarray | None = None
) -> list[np.ndarray]:
    """The benchmark's open-loop rollout of every episode from frame 1 (frames 0-1 copied),
    batched over episodes of equal length."""
    mask = None if held is None else torch.as_tensor(held, dtype=torch.bool, device=model.device)
    out: list[np.ndarray] = [np.empty(0)] * len(episodes)
    by_length: dict[int, list[int]] = {}
    for i, e in enumerate(episodes):
        by_length.setdefault(len(e), []).append(i)
    for idx in by_length.values():
        rec = torch.as_tensor(np.stack([episodes[i] for i in idx]), dtype=torch.float32,
                              device=model.device)  # fmt: skip
        rolled = model.rollout(rec[:, 1], rec[:, 0], rec[:, 2:], mask)
        pred = torch.cat([rec[:, :2], rolled], 1)
        for j, i in enumerate(idx):
            out[i] = pred[j].double().cpu().numpy()
    return out


def scores_cm(model: MarkerModel, cable: Cable) -> list[float]:
    """The benchmark score (cm) of every episode of ``cable``."""
    if model.spec.cable_code:
        model.use_cable(cable.code_key())
    preds = predict_episodes(model, cable.episodes, cable.held)
    return [deform_score_cm(p, e) for p, e in zip(preds, cable.episodes, strict=True)]


def validation_score(model: MarkerModel, cables: list[Cable]) -> float:
    """The mean benchmark score over every validation episode (NaN: none)."""
    scores = [s for c in cables for s in scores_cm(model, c)]
    return float(np.mean(scores)) if scores else math.nan


@dataclass
class Windows:
    """One batch of a rollout fit: gradient step ``step``'s windows (B, k + 2, V, 3) of cable
    ``cable`` (its index in the fit's cables) and that cable's held mask."""

    step: int
    k: int
    windows: torch.Tensor
    held: torch.Tensor
    cable: int

    def __len__(self) -> int:
        return len(self.windows)


@dataclass
class WindowPlan:
    """``fit.update_steps`` gradient steps in rounds of ``fit.eval_every`` (and the last),
    each on windows of :func:`rollout_length` steps from ``sampler``; with ``budget``, the
    first step after which that many seconds since ``began`` have passed ends the last
    round."""

    fit: FitSpec
    sampler: WindowSampler
    began: float
    budget: float | None = None
    unit: Unit = "step"
    start: int = 0
    kept: str = "nothing is saved"
    gen: np.random.Generator | None = None
    step: int = 0
    ended: bool = False

    @property
    def total(self) -> int:
        return self.fit.update_steps

    def rounds(self) -> Iterator[Round]:
        every = self.fit.eval_every
        while self.step < self.total and not self.ended:
            size = min(every - self.step % every, self.total - self.step)
            each = Round(self.step + size, [], size)
            each.batches = self._windows(each)
            yield each

    def _windows(self, each: Round) -> Iterator[Windows]:
        for _ in range(each.size):
            self.step += 1
            each.count = self.step
            each.k = rollout_length(self.fit, self.step)
            windows, held, cable = self.sampler.sample(self.fit.batch_size, each.k)
            yield Windows(self.step, each.k, windows, held, cable)
            if self.budget is not None and time.perf_counter() - self.began >= self.budget:
                self.ended = True
                return


@dataclass
class RolloutObjective:
    """The marker view's :class:`~dlocli.models.fitting.Objective`: a batch is
    :class:`Windows`, its loss :func:`rollout_loss` (cm; a non-finite one is refused at once,
    before it reaches Adam's moments); the validation loss is the benchmark score of
    ``val``'s whole episodes (:func:`validation_score`); a round's training loss is the mean
    of its steps'. Gradients are clipped to norm 1, the rate decays on ``scheduler``."""

    model: MarkerModel
    val: list[Cable]
    rows: list[int]
    scheduler: torch.optim.lr_scheduler.LRScheduler | None
    clip: float | None = 1.0

    def loss(self, batch: Windows) -> torch.Tensor:
        self.model.cable = self.rows[batch.cable] if self.rows else None
        loss = rollout_loss(self.model, batch.windows, batch.held)
        if not math.isfinite(loss.item()):
            raise DloError(f"training diverged (loss {loss.item()}) at step {batch.step}; "
                           "lower --lr")  # fmt: skip
        return loss

    def validate(self) -> float:
        self.model.eval()
        score = validation_score(self.model, self.val)
        self.model.train()
        return score

    def mean_loss(self, losses: list[torch.Tensor], sizes: list[int]) -> float:
        return float(np.mean([loss.item() for loss in losses]))


@dataclass
class RolloutPoint:
    """Where a rollout fit stands after a validation: the gradient steps done, Adam's state,
    the random states its windows (numpy's, the sampler's) and torch draw from, the best
    validation so far (its loss, step, the validations since, and the weights and Adam state
    that had it) and the validation records so far (a fine-tune's starting point first). A
    fit resumed from it trains on as the uninterrupted one would, to the same bits."""

    step: int
    optimizer: dict[str, Any]
    sampler: dict[str, Any]
    torch_rng: torch.Tensor
    best: dict[str, Any]
    history: list[FitRecord] = field(default_factory=list)

    def as_payload(self) -> dict[str, Any]:
        """The checkpoint entries that hold it (what ``torch.load(weights_only=True)`` reads)."""
        rows = [{**r.as_row(), "k": r.k} for r in self.history]
        return {"step": self.step, "optimizer": self.optimizer, "sampler_rng": self.sampler,
                "torch_rng": self.torch_rng, "best": self.best, "history": rows}  # fmt: skip

    @classmethod
    def from_payload(cls, payload: dict[str, Any]) -> RolloutPoint | None:
        """The point a checkpoint's payload holds (None: it holds none)."""
        step, rows, best = payload.get("step"), payload.get("history"), payload.get("best")
        rng, sampler = payload.get("torch_rng"), payload.get("sampler_rng")
        optimizer = payload.get("optimizer")
        if not (isinstance(step, int) and isinstance(rows, list) and isinstance(best, dict)
                and torch.is_tensor(rng) and isinstance(sampler, dict)
                and isinstance(optimizer, dict)):  # fmt: skip
            return None
        history = [FitRecord.from_row(row) for row in rows]
        return cls(step, optimizer, sampler, rng, best, history)


#: called after each validation of a rollout fit with its record and where the fit stands
OnRolloutValidation = Callable[[FitRecord, RolloutPoint], None]


def _fit_markers(
    model: MarkerModel,
    train: list[Cable],
    val: list[Cable],
    fit: FitSpec,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
    *,
    on_validation: OnRolloutValidation | None = None,
    resume_from: RolloutPoint | None = None,
) -> list[FitRecord]:
    """Train ``model`` in place on one or more cables (see the module docstring) through
    :mod:`dlocli.models.fitting`'s loop; returns the validation history (a fine-tune's
    starting point first, as step 0). The model ends in eval mode with the best validated
    weights. ``progress`` gets a Began, then batches and a
    :class:`~dlocli.models.fitting.RolloutValidated` after each validation; ``cancel`` stops
    the fit before the next gradient step once cancelled. A spec with ``seconds`` (`dlo
    adapt`'s) also ends the fit, validated, once that many seconds have passed.
    ``on_validation`` gets each validation's record and the :class:`RolloutPoint` after it;
    ``resume_from`` such a point (with the model as it was then) continues the fit from there
    (its history then holds the records before it too)."""
    device = resolve_device(fit.device)
    torch.manual_seed(fit.seed)
    if not bool(model.fitted):
        model.fit_normalization([(e, c.held) for c in train for e in c.episodes])
    model.to(device).train().requires_grad_(True)
    sampler = WindowSampler(train, fit, device)
    rows = model.add_cables([c.code_key() for c in train]) if model.spec.cable_code else []
    if getattr(fit, "fine_tune", "all") == "code":  # the codes alone learn
        if model.codes is None:
            raise BadInput("fine_tune='code' needs a model with cable codes (cable_code > 0)")
        model.requires_grad_(False)
        model.codes.requires_grad_(True)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=fit.lr)
    done = 0 if resume_from is None else resume_from.step
    if resume_from is not None:
        optimizer.load_state_dict(resume_from.optimizer)
        sampler.rng.bit_generator.state = resume_from.sampler
    total = fit.update_steps
    schedule = torch.optim.lr_scheduler.LambdaLR(  # resumed: the rate at step ``done``
        optimizer, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, total) / total)), done - 1
    )
    history: list[FitRecord] = [] if resume_from is None else list(resume_from.history)
    best = KeepBest(keep=True, nan_is_worst=bool(val))
    start = time.perf_counter()
    if resume_from is not None:
        _resume_best(best, resume_from.best)
        torch.set_rng_state(resume_from.torch_rng)
    elif getattr(fit, "init_from", None) is not None and val:  # `dlo train --init-from`
        history.append(_starting_point(model, val, best))  # fine-tuning keeps it if no better
    plan = WindowPlan(fit, sampler, start, getattr(fit, "seconds", None),  # `dlo adapt --seconds`
                      start=done, gen=sampler.rng, step=done)  # fmt: skip
    objective = RolloutObjective(model, val, rows, schedule)
    records = list(history)

    def point_after(record: FitRecord, optimizer: torch.optim.Optimizer, gen: Any) -> None:
        records.append(record)
        if on_validation is not None:  # Adam's live state: the hook saves it at once
            on_validation(record, RolloutPoint(
                record.count, optimizer.state_dict(), gen.bit_generator.state,
                torch.get_rng_state(), {"val_loss": best.val_loss, "count": best.count,
                "stale": best.stale, "saved": best.saved}, list(records)))  # fmt: skip

    hook = point_after if on_validation is not None else None
    rounds, _ = fit_loop(model, objective, plan, optimizer, best, progress, hook, cancel)
    return history + rounds


def _resume_best(best: KeepBest, held: dict[str, Any]) -> None:
    """``best`` as a :class:`RolloutPoint` holds it."""
    best.val_loss, best.count = float(held["val_loss"]), int(held["count"])
    best.stale, best.saved = int(held["stale"]), held["saved"]


def _starting_point(model: MarkerModel, val: list[Cable], best: KeepBest) -> FitRecord:
    """The validation of the weights a fine-tune starts from, as step 0 of its history and a
    candidate of ``best``: fine-tuning never leaves the model worse on validation."""
    model.eval()
    score = validation_score(model, val)
    model.train()
    best.observe(0, score, model)
    return FitRecord("step", 0, math.nan, score, 0.0, k=0)
