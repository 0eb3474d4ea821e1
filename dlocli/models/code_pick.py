"""Picking a new cable's code: which of a coded model's codes predicts its recordings best.

A model with cable codes (:mod:`dlocli.models.cable_codes`) knows a code per training cable
and gives a cable it never saw their mean, which is no cable's. Given a few recordings of the
new cable, each candidate (every training cable's code, and the mean) rolls them out as the
benchmark does (:func:`~dlocli.models.marker_training.predict_episodes`, from frame 1, the
held markers given) and is scored by the benchmark's score; the lowest mean score is the
pick. No gradient step: a candidate costs one batched open-loop rollout per recording length.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlocli.data import MarkerDataset, load_dataset
from dlocli.data.protocol import deform_score_cm, freeze
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event
from dlocli.models.cable_codes import cable_key
from dlocli.models.marker_model import MarkerModel
from dlocli.models.marker_training import predict_episodes
from dlocli.specs import MAX_SPEC_BYTES

#: the candidate that is no training cable's code: their mean
MEAN_CODE = "mean code"
#: how many runs back a checkpoint's training cables are looked for (fine-tunes of fine-tunes)
NAME_DEPTH = 4


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


def cable_names(checkpoint: Path, keys: list[str]) -> list[str]:
    """A name per code row: "NAME's code" where the checkpoint's run (or a run it was
    fine-tuned from) names a dataset, still readable, whose train recordings have that row's
    key (NAME: its folder or file name), else "cable i's code"."""
    found: dict[str, str] = {}
    for path in _run_datasets(Path(checkpoint), NAME_DEPTH):
        try:
            data = load_dataset(path)
        except (BadInput, OSError):
            continue
        if isinstance(data, MarkerDataset):
            label = path.parent.name if path.name == "dataset.h5" else path.stem
            found.setdefault(cable_key(data.held, data.episodes("train")), label or str(path))
    return [f"{found.get(k, f'cable {i}')}'s code" for i, k in enumerate(keys)]


def _run_datasets(checkpoint: Path, depth: int) -> list[Path]:
    """The datasets the run of ``checkpoint`` (a run directory, or its checkpoints/*.pt)
    names in its spec.json (``data``), then those of the run it started from (``init_from``
    or ``checkpoint``), ``depth`` runs back at most."""
    run = checkpoint if checkpoint.is_dir() else checkpoint.parent.parent
    try:
        if (run / "spec.json").stat().st_size > MAX_SPEC_BYTES:
            return []
        saved = json.loads((run / "spec.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    if not isinstance(saved, dict):
        return []
    data = saved.get("data")
    paths = [Path(p) for p in (data if isinstance(data, list) else [data]) if isinstance(p, str)]
    source = saved.get("init_from") or saved.get("checkpoint")
    if depth > 1 and isinstance(source, str):
        paths += _run_datasets(Path(source), depth - 1)
    return paths
