"""OUT/history.json of a calibration: every finished CMA-ES generation, read back on resume.

    {"generations": [{"candidates": [[x, ...] x population], "scores": [cm x population]},
                     ...],
     "seconds": fit time so far, "recordings": sha256 of the recordings}

A resume replays it into CMA-ES, so every field is checked first, each refusal one line
naming the file and the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

from dlocli.calibration.spec import CalibrateSpec
from dlocli.errors import BadInput
from dlocli.io import read_json
from dlocli.specs import validated


class _Generation(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid")

    candidates: list[list[FiniteFloat]]
    scores: list[FiniteFloat]


class _History(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid")

    generations: list[_Generation] = []
    seconds: FiniteFloat = Field(0.0, ge=0)
    recordings: str | None = None


def read_history(path: Path, spec: CalibrateSpec) -> dict[str, Any]:
    """The history in ``path`` as data; BadInput naming the field that is not of this run
    (population, parameter count, numbers)."""
    state = read_json(path, dict)
    history = validated(_History, state, f"--resume {spec.out}: {path.name}")
    n, size = spec.population, len(spec.parameters)
    for g, generation in enumerate(history.generations):
        candidates, scores = generation.candidates, generation.scores
        if len(candidates) != n or len(scores) != n or any(len(c) != size for c in candidates):
            raise BadInput(
                f"--resume {spec.out}: {path.name} generation {g} holds {len(candidates)} "
                f"candidates and {len(scores)} scores, not {n} of {size} parameters each (the "
                "run's population); restore it, or start a new run"
            )
    return history.model_dump(exclude_none=True)
