"""The online loop's fixed-cost model update (``FitSpec.schedule == "steps"``): a set number
of gradient steps on mini-batches drawn from all the data with the newest episodes weighted
in, stopped early on (a capped subset of) the validation split, the best weights kept. Its cost
does not grow with the dataset, unlike the paper's E epochs over all of it
(:func:`dlocli.models.training.train_model`); both share the set-up, the gradient step and the
validation of :mod:`dlocli.models.training`.
"""

from __future__ import annotations

import copy
import math
import time
from typing import Any

import numpy as np
import torch

from dlocli.data import Dataset
from dlocli.models.base import DynamicsModel
from dlocli.models.spec import FitSpec
from dlocli.models.training import (
    OnEpoch,
    Progress,
    TrainResult,
    _check_finite,
    _gradient_step,
    _set_up,
    train_model,
    validation_loss,
)


def train_steps(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    *,
    recent_episodes: np.ndarray | None = None,
    optimizer_state: dict[str, Any] | None = None,
    progress: Progress | None = None,
    on_eval: OnEpoch | None = None,
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

    Set-up as :func:`train_model`. Every random draw comes from one generator seeded with
    ``fit.seed``, so the result is a function of the seed, the data and the starting weights
    and optimizer state. ``progress`` gets ``{"epoch": step, "epochs": fit.update_steps,
    "val_loss", "unit": "step"}`` after each validation (epoch-like events: the online
    command's bar counts steps); ``on_eval`` gets each validation's record ``{"step",
    "train_loss", "val_loss", "seconds"}``, the optimizer and the generator.
    """
    setup = _set_up(model, dataset, fit, optimizer_state)
    train, optimizer = setup.train, setup.optimizer
    n_train = len(train["state"])
    gen = torch.Generator(device="cpu").manual_seed(fit.seed)
    val = _val_subset(setup.val, fit.val_transitions, gen)
    has_val = len(val["state"]) > 0
    recent = recent_rows(dataset, setup.train_episodes, recent_episodes, setup.mirror)
    is_recent = torch.zeros(n_train, dtype=torch.bool)
    is_recent[recent] = True
    result = TrainResult(train_episodes=setup.train_episodes, val_episodes=setup.val_episodes)
    best = {"step": 0, "val_loss": validation_loss(model, val)}
    if has_val:
        best.update(_snapshot(model, optimizer))
    device = train["state"].device
    start = t0 = time.perf_counter()
    total, hits, since, stale, step = torch.zeros((), device=device), 0, 0, 0, 0
    model.train()
    while step < fit.update_steps:
        step += 1
        idx = sample_batch(n_train, recent, fit, gen)
        hits += int(is_recent[idx].sum())
        total += _gradient_step(model, optimizer, train, idx.to(device), fit, gen)
        since += 1
        if step % fit.eval_every and step < fit.update_steps:
            continue
        train_loss = float(total) / since
        _check_finite(train_loss, f"step {step}", fit, "the model it started from is kept")
        record = {"step": step, "train_loss": train_loss, "val_loss": validation_loss(model, val),
                  "seconds": time.perf_counter() - t0}  # fmt: skip
        result.history.append(record)
        if progress is not None:
            progress({"epoch": step, "epochs": fit.update_steps, "val_loss": record["val_loss"],
                      "unit": "step"})  # fmt: skip
        if on_eval is not None:
            on_eval(record, optimizer, gen)
        total, since, t0 = torch.zeros((), device=device), 0, time.perf_counter()
        if record["val_loss"] < best["val_loss"]:
            best, stale = {"step": step, "val_loss": record["val_loss"]}, 0
            best.update(_snapshot(model, optimizer))
        elif has_val:
            stale += 1
            if fit.patience and stale >= fit.patience:
                if progress is not None:  # the bar ends full, at the steps taken
                    progress({"epoch": step, "epochs": step, "val_loss": best["val_loss"],
                              "unit": "step", "stopped_early": True})  # fmt: skip
                break
    if has_val and best["step"] != step:
        model.load_state_dict(best["model"])
        optimizer.load_state_dict(best["optimizer"])
    model.eval()
    elapsed = time.perf_counter() - start
    result.optimizer_state = copy.deepcopy(optimizer.state_dict())
    result.steps = step
    if has_val:
        result.best_step, result.best_val_loss = int(best["step"]), float(best["val_loss"])
    result.recent_share = hits / (step * fit.batch_size) if step else math.nan
    result.transitions_per_s = step * fit.batch_size / elapsed if elapsed > 0 else 0.0
    return result


def sample_batch(n: int, recent: torch.Tensor, fit: FitSpec, gen: torch.Generator) -> torch.Tensor:
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
    """The rows of :func:`transition_tensors` ``(dataset, train_episodes, mirror=mirror)``
    that come from an episode in ``recent`` (with ``mirror``, their twins too)."""
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


def _snapshot(model: DynamicsModel, optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    return {
        "model": copy.deepcopy(model.state_dict()),
        "optimizer": copy.deepcopy(optimizer.state_dict()),
    }


def train_like_online(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    updates: int,
    progress: Progress | None = None,
) -> TrainResult:
    """Train a fresh ``model`` on all of ``dataset`` as long as the online loop's model had
    trained after ``updates`` updates under ``fit.schedule`` (paper Fig. 7's offline model):
    E·updates epochs ("epochs"), or update_steps·updates steps with nothing weighted ("steps",
    so the offline comparison stays affordable where the paper's schedule is not)."""
    if fit.schedule == "steps":
        fit = fit.model_copy(update={"update_steps": fit.update_steps * updates})
        return train_steps(model, dataset, fit, progress=progress)
    fit = fit.model_copy(update={"epochs": fit.epochs * updates})
    return train_model(model, dataset, fit, progress=progress)
