"""Picking a new cable's code: which of a coded model's codes predicts its recordings best.

A model with cable codes (:mod:`dlocli.models.cable_codes`) knows a code per training cable
and gives a cable it never saw their mean, which is no cable's. Given a few recordings of the
new cable, each candidate (every training cable's code, and the mean) rolls them out as the
benchmark does (:func:`~dlocli.models.marker_training.predict_episodes`, from frame 1, the
held markers given) and is scored by the benchmark's score; the lowest mean score is the
pick. No gradient step: a candidate costs one batched open-loop rollout per recording length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlocli.data.protocol import deform_score_cm, freeze
from dlocli.events import Began, Callback, Event
from dlocli.models.marker_training import predict_episodes
from dlocli.models.markers import MarkerModel

#: the candidate that is no training cable's code: their mean
MEAN_CODE = "mean code"


@dataclass
class Candidate:
    """A code the new cable may get: its name, its row of the model's codes (None: the mean)
    and its benchmark score (cm) on each recording read."""

    name: str
    row: int | None
    scores_cm: list[float]

    @property
    def mean_cm(self) -> float:
        return float(np.mean(self.scores_cm))


def score_candidates(
    model: MarkerModel,
    episodes: list[np.ndarray],
    held: np.ndarray,
    names: list[str],
    progress: Callback | None = None,
) -> list[Candidate]:
    """Every candidate code of ``model`` scored on ``episodes`` (each (T+1, V, 3)) of a cable
    with the held mask ``held``: the mean code first, then each training cable's (row i named
    ``names[i]``). ``progress`` gets a Began, then an Event per candidate scored (its
    ``name`` and ``score_cm``). The model's code in use is left as it was."""
    chosen = model.cable
    candidates = [Candidate(MEAN_CODE, None, [])]
    candidates += [Candidate(name, row, []) for row, name in enumerate(names)]
    if progress:
        progress(Began("candidate", 0, len(candidates)))
    try:
        for done, candidate in enumerate(candidates, 1):
            model.cable = candidate.row
            predicted = predict_episodes(model, episodes, held)
            candidate.scores_cm = [deform_score_cm(p, e)
                                   for p, e in zip(predicted, episodes, strict=True)]  # fmt: skip
            if progress:
                values = {"name": candidate.name, "score_cm": candidate.mean_cm}
                progress(Event("candidate", done, len(candidates), values))
    finally:
        model.cable = chosen
    return candidates


def best(candidates: list[Candidate]) -> Candidate:
    """The candidate of the lowest mean score (the first of equals; a NaN score never wins)."""
    finite = [c for c in candidates if np.isfinite(c.mean_cm)]
    return min(finite or candidates, key=lambda c: c.mean_cm)


def freeze_cm(episodes: list[np.ndarray], held: np.ndarray) -> list[float]:
    """The reference: each recording's score with its free markers frozen at frame 1."""
    return [deform_score_cm(freeze(e, held), e) for e in episodes]
