"""Training an ensemble's members (:mod:`dlocli.models.ensemble`), in either view.

One mechanism serves both views: :func:`train_members` hands each member, as the state of
"the view of member i" (:func:`member_state`: the ensemble view's buffers, its normalisation
among them, member i's codes and, when it continues, member i's weights), to a worker that
rebuilds that one-network view and trains it exactly as a single network would be trained
in that view, from its own seed, and puts the trained weights back. So a fresh ensemble's
member i is exactly the network `dlo train --seed SEED+i` trains alone (its initial
weights, batches and noise or windows are that seed's). The members are independent, so on
CPU they train in parallel, one process per core (:class:`~dlocli.executors.LocalExecutor`);
on a GPU one after another.

- the marker view (:func:`fit_members`): rollout windows on recorded cables
  (:func:`~dlocli.models.marker_training._fit_markers`); with cable codes, each member learns
  its own (the view's column i);
- the rod view (:func:`fit_rod_members`): the paper's epochs
  (:func:`~dlocli.models.rod_training._train_model`).

The history is the members' mean at each validation (seconds: the slowest member's), its
last record's validation the ensemble's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.data import Dataset
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event
from dlocli.executors import LocalExecutor
from dlocli.models.base import DynamicsModel, build_model, resolve_device
from dlocli.models.ensemble import Ensemble
from dlocli.models.fitting import FitRecord, TrainResult
from dlocli.models.marker_model import SCALES, MarkerModel
from dlocli.models.marker_training import Cable, _fit_markers, validation_score
from dlocli.models.rod_training import _train_model, set_up, validation_loss
from dlocli.models.spec import FitSpec
from dlocli.threads import machine_cpus


def fit_members(
    model: MarkerModel,
    train: list[Cable],
    val: list[Cable],
    fit: FitSpec,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> list[FitRecord]:
    """Train every member of ``model``'s ensemble in place on recorded cables (see the module
    docstring); returns the validation history."""
    assert isinstance(model.network, Ensemble)
    fresh = not bool(model.fitted)  # else fine-tuning: the members start from their weights
    if fresh:  # one normalisation for all, as the view applies one
        model.fit_normalization([(e, c.held) for c in train for e in c.episodes])

    def call(index: int, own: FitSpec, events: Callback | None, stop: CancelToken | None) -> tuple:
        # copies: sending a tensor to a process moves its storage to shared memory, and a
        # numpy view of the old storage would be sent as whatever then lies there
        return (member_state(model, index, weights=not fresh), model.spec, model.n_segments,
                model.held.cpu().numpy().copy(), list(model.cable_keys), train, val, own,
                events, stop)  # fmt: skip

    results = train_members(model, _fit_member, call, fit, progress, cancel)
    _gather_codes(model, [codes for codes, _ in results])
    model.to(resolve_device(fit.device)).eval()
    return _merged([history for _, history in results], validation_score(model, val))


def fit_rod_members(
    model: DynamicsModel,
    dataset: Dataset,
    fit: FitSpec,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> TrainResult:
    """Train every member of the rod ``model``'s ensemble in place, each for ``fit.epochs``
    epochs on ``dataset``'s training split as a single rod model is (see the module
    docstring); the history's last validation is the ensemble's, on the validation split."""
    assert isinstance(model.network, Ensemble)
    fresh = not bool(model.fitted)  # else fine-tuning: the members start from their weights
    setup = set_up(model, dataset, fit, None)  # the split, and one normalisation for all

    def call(index: int, own: FitSpec, events: Callback | None, stop: CancelToken | None) -> tuple:
        return (member_state(model, index, weights=not fresh), model.spec, model.n_segments,
                dataset, own, events, stop)  # fmt: skip

    start = time.perf_counter()
    results = train_members(model, _fit_rod_member, call, fit, progress, cancel)
    elapsed = time.perf_counter() - start
    model.eval()
    history = _merged([history for _, history in results], validation_loss(model, setup.val))
    rows = len(setup.train["state"]) * len(history) * len(results)  # every member's epochs
    return TrainResult(
        history=history,
        train_episodes=setup.train_episodes,
        val_episodes=setup.val_episodes,
        transitions_per_s=rows / elapsed if elapsed > 0 else 0.0,
        best_val_loss=min((r.val_loss for r in history), default=math.nan),
    )


#: the arguments of the worker for member ``index`` under its own ``fit`` spec (its seed),
#: with the events and the cancel token it may see
MemberCall = Callable[[int, FitSpec, Callback | None, CancelToken | None], tuple]


def train_members(
    model: DynamicsModel | MarkerModel,
    worker: Callable[..., tuple[dict[str, torch.Tensor], Any, list[FitRecord]]],
    call: MemberCall,
    fit: FitSpec,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> list[tuple[Any, list[FitRecord]]]:
    """The one ensemble mechanism: ``worker(*call(i, fit with seed fit.seed + i, ...))``
    trains member i through its own view and returns (its network's weights, what else the
    view keeps of it, its history); the weights go back into member i. Returns, per member,
    what else was kept and the history. ``progress`` gets a Began and an Event per member
    done (and, where the members train in this process, their own events)."""
    count = len(model.network.members)  # type: ignore[union-attr]
    device = resolve_device(fit.device)
    jobs = min(count, machine_cpus()) if device.type == "cpu" else 1
    inline = jobs == 1  # this process: the member's own events and the cancel token reach it
    calls = [call(i, fit.model_copy(update={"seed": fit.seed + i}),
                  progress if inline else None, cancel if inline else None)
             for i in range(count)]  # fmt: skip
    if progress:
        progress(Began("member", 0, count))
    results: list[tuple[Any, list[FitRecord]]] = [(None, [])] * count
    executor = LocalExecutor(jobs, threads=max(1, machine_cpus() // jobs))
    try:
        for done, (index, result) in enumerate(executor.map(worker, calls), 1):
            if isinstance(result, BaseException):
                raise result
            state, kept, records = result
            model.network.members[index].load_state_dict(state)  # type: ignore[union-attr]
            results[index] = (kept, records)
            if cancel is not None:
                cancel.raise_if_cancelled()
            if progress:
                progress(Event("member", done, count, {
                    "val_loss": records[-1].val_loss if records else float("nan"),
                    "seconds": sum(r.seconds for r in records)}))  # fmt: skip
    finally:
        executor.close()
    return results


def member_state(
    model: DynamicsModel | MarkerModel, index: int, weights: bool = True
) -> dict[str, torch.Tensor]:
    """The state of the view of member ``index``: the ensemble view's buffers (normalisation,
    a marker view's mask), the member's own cable codes where the view has codes, and, with
    ``weights``, the member's weights."""
    state = {k: v.cpu().clone() for k, v in model.state_dict().items()
             if not k.startswith("network.")}  # fmt: skip
    codes = getattr(model, "codes", None)
    if codes is not None:  # the member's own codes
        state["codes"] = codes.detach()[:, index].cpu().clone()
    if not weights:
        return state
    member = model.network.members[index]  # type: ignore[union-attr]
    state.update({f"network.{k}": v.cpu().clone() for k, v in member.state_dict().items()})
    return state


def _fit_rod_member(
    state: dict[str, torch.Tensor],
    spec: Any,
    n_segments: int,
    dataset: Dataset,
    fit: FitSpec,
    progress: Callback | None,
    cancel: CancelToken | None,
) -> tuple[dict[str, torch.Tensor], None, list[FitRecord]]:
    """One member trained through its own rod view: (its network's weights, nothing else,
    its history). Given no weights, it starts as `dlo train` builds the network alone from
    ``fit.seed``."""
    torch.manual_seed(fit.seed)
    view = build_model(spec.model_copy(update={"members": 1}), n_segments)
    view.load_state_dict(state, strict=any(k.startswith("network.") for k in state))
    result = _train_model(view, dataset, fit, progress=progress, cancel=cancel)
    weights = {k: v.cpu() for k, v in view.network.state_dict().items()}
    return weights, None, result.history


def _fit_member(
    state: dict[str, torch.Tensor],
    spec: Any,
    n_markers: int,
    held: np.ndarray,
    cable_keys: list[str],
    train: list[Cable],
    val: list[Cable],
    fit: FitSpec,
    progress: Callback | None,
    cancel: CancelToken | None,
) -> tuple[dict[str, torch.Tensor], tuple[list[str], torch.Tensor | None], list[FitRecord]]:
    """One member trained through its own view: (its network's weights, its cable keys and
    codes, its history). Given no weights, it starts as the network alone would from
    ``fit.seed``."""
    torch.manual_seed(fit.seed)
    view = MarkerModel(spec.model_copy(update={"members": 1}), n_markers, held)
    view.add_cables(cable_keys)  # the codes' rows, before their values load
    view.load_state_dict(state, strict=any(k.startswith("network.") for k in state))
    rows = _fit_markers(view, train, val, fit, progress, cancel)
    codes = None if view.codes is None else view.codes.detach().cpu()
    weights = {k: v.cpu() for k, v in view.network.state_dict().items()}
    return weights, (list(view.cable_keys), codes), rows


def _gather_codes(model: MarkerModel, codes: list[tuple[list[str], torch.Tensor | None]]) -> None:
    """The members' codes (cables, D) as the ensemble view's (cables, members, D); every
    member trained on the same cables, so their keys agree."""
    keys, first = codes[0]
    if first is None:
        return
    model.add_cables(keys)
    model.codes.data = torch.stack([c for _, c in codes], 1).to(model.codes.device)  # type: ignore[misc, union-attr]


def _merged(histories: list[list[FitRecord]], ensemble_score: float) -> list[FitRecord]:
    """The members' mean at each validation (seconds: the slowest member's); the last
    record's validation score is the ensemble's."""
    merged = []
    for records in zip(*histories, strict=True):
        first = records[0]
        merged.append(FitRecord(
            first.unit, first.count,
            float(np.mean([r.train_loss for r in records])),
            float(np.mean([r.val_loss for r in records])),
            max(r.seconds for r in records), first.k,
        ))  # fmt: skip
    if merged:
        merged[-1].val_loss = ensemble_score
    return merged


def joined(models: list[MarkerModel]) -> MarkerModel:
    """Networks trained apart (one spec, one cable layout, one normalisation, the same
    cables) as the ensemble of them: what `--members` gives when they were trained with seeds
    S, S+1, ... (on other machines, say); BadInput where they differ."""
    if len(models) < 2:
        raise BadInput(f"an ensemble joins two or more networks, not {len(models)}")
    first = models[0]
    spec = first.spec.model_copy(update={"members": 1})
    for model in models:
        _check_joinable(first, model, spec)
    ensemble = MarkerModel(spec.model_copy(update={"members": len(models)}), first.n_segments,
                           first.held.cpu().numpy())  # fmt: skip
    state = {k: v for k, v in first.state_dict().items()
             if not k.startswith("network.") and k != "codes"}  # fmt: skip
    ensemble.load_state_dict(state, strict=False)
    for member, model in zip(ensemble.network.members, models, strict=True):  # type: ignore[union-attr]
        member.load_state_dict(model.network.state_dict())
    _gather_codes(ensemble, [(list(m.cable_keys), None if m.codes is None else m.codes.detach())
                             for m in models])  # fmt: skip
    return ensemble.to(first.device).eval()


def _check_joinable(first: MarkerModel, model: MarkerModel, spec: Any) -> None:
    if model.spec.model_copy(update={"members": 1}) != spec or model.spec.members != 1:
        raise BadInput(
            "networks of different specs, or ensembles, do not join: give single "
            "networks trained with one spec"
        )
    if not torch.equal(model.held.cpu(), first.held.cpu()):
        raise BadInput("networks of different cable layouts (held markers) do not join")
    if model.cable_keys != first.cable_keys:
        raise BadInput("networks trained on different cables do not join: their codes differ")
    for name in SCALES:
        if not torch.allclose(getattr(model, name), getattr(first, name)):
            raise BadInput(f"networks with different normalisations ({name}) do not join")
