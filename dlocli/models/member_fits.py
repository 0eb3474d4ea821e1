"""Training an ensemble's members (:mod:`dlocli.models.ensemble`) on recorded cables.

Each member is trained exactly as a single network would be
(:func:`~dlocli.models.marker_training._fit_markers`), seen through its own marker view with
the ensemble's normalisation, from its own seed: a fresh ensemble's member i is exactly the
network `dlo train --seed SEED+i` trains alone (its initial weights, windows and
augmentations are that seed's). The members are independent, so on CPU they train in
parallel, one process per core (:class:`~dlocli.executors.LocalExecutor`); on a GPU one after
another. With cable codes, each member learns its own (the view's column i). The history is
the members' mean at each validation (seconds: the slowest member's), its last record's
validation the ensemble's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dlocli.cancel import CancelToken
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event
from dlocli.executors import LocalExecutor
from dlocli.models.base import resolve_device
from dlocli.models.ensemble import Ensemble
from dlocli.models.fitting import FitRecord
from dlocli.models.marker_training import Cable, _fit_markers, validation_score
from dlocli.models.markers import SCALES, MarkerModel
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
    """Train every member of ``model``'s ensemble in place (see the module docstring);
    returns the validation history. ``progress`` gets a Began and an Event per member done."""
    assert isinstance(model.network, Ensemble)
    device = resolve_device(fit.device)
    fresh = not bool(model.fitted)  # else fine-tuning: the members start from their weights
    if fresh:  # one normalisation for all, as the view applies one
        model.fit_normalization([(e, c.held) for c in train for e in c.episodes])
    count = len(model.network.members)
    jobs = min(count, machine_cpus()) if device.type == "cpu" else 1
    inline = jobs == 1  # this process: the member's own events and the cancel token reach it
    # copies: sending a tensor to a process moves its storage to shared memory, and a numpy
    # view of the old storage would be sent as whatever then lies there
    calls = [(member_state(model, i, weights=not fresh), model.spec, model.n_segments,
              model.held.cpu().numpy().copy(), list(model.cable_keys), train, val,
              fit.model_copy(update={"seed": fit.seed + i}),
              progress if inline else None, cancel if inline else None)
             for i in range(count)]  # fmt: skip
    if progress:
        progress(Began("member", 0, count))
    histories: list[list[FitRecord]] = [[] for _ in range(count)]
    codes: list[tuple[list[str], torch.Tensor | None]] = [([], None)] * count
    executor = LocalExecutor(jobs, threads=max(1, machine_cpus() // jobs))
    try:
        for done, (index, result) in enumerate(executor.map(_fit_member, calls), 1):
            if isinstance(result, BaseException):
                raise result
            state, codes[index], histories[index] = result
            model.network.members[index].load_state_dict(state)
            if cancel is not None:
                cancel.raise_if_cancelled()
            if progress:
                records = histories[index]
                progress(Event("member", done, count, {
                    "val_loss": records[-1].val_loss if records else float("nan"),
                    "seconds": sum(r.seconds for r in records)}))  # fmt: skip
    finally:
        executor.close()
    _gather_codes(model, codes)
    model.to(device).eval()
    return _merged(histories, validation_score(model, val))


def member_state(model: MarkerModel, index: int, weights: bool = True) -> dict[str, torch.Tensor]:
    """The state of member ``index`` seen through its own marker view: the ensemble view's
    buffers (mask, normalisation) and, with ``weights``, the member's weights."""
    state = {k: v.cpu().clone() for k, v in model.state_dict().items()
             if not k.startswith("network.")}  # fmt: skip
    if model.codes is not None:  # the member's own codes
        state["codes"] = model.codes.detach()[:, index].cpu().clone()
    if not weights:
        return state
    member = model.network.members[index]  # type: ignore[union-attr]
    state.update({f"network.{k}": v.cpu().clone() for k, v in member.state_dict().items()})
    return state


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
