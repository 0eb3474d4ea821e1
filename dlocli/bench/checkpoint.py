"""Mid-job checkpoints of the bench: a stopped job continues from its last evaluation point.

After each evaluation point, the job writes what it needs to continue from there into its
work directory (``<job>/resume``), and a job that finds one continues instead of starting
again. The continuation is exact: the learner's own state, the training env's episode
generator and the global random generators are all restored, so a job stopped and resumed
gives the rows an uninterrupted job gives (``tests/test_bench_resume.py``).

Layout of ``resume/``:

- ``point-<index>/``: one slot per checkpoint; ``progress.json`` (the rows so far, the wall
  time, the fingerprint) and ``generators.pkl`` there, and the learner's files
  (:meth:`BenchLearner.save_state`). A slot is written under a temporary name and renamed,
  then older slots are removed, so a job killed while checkpointing keeps the previous one.
- ``shared/``: what learners write once and keep growing (an SB3 replay buffer in chunks,
  each written once), so a checkpoint costs the new transitions, not the whole buffer.

A checkpoint whose fingerprint or package versions differ from the job's is ignored.
"""

from __future__ import annotations

import json
import pickle
import random
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dlocli.io import versions, write_bytes_atomic, write_json_atomic

if TYPE_CHECKING:
    from dlocli.bench.agents import BenchLearner

SLOT_PREFIX = "point-"


@dataclass
class Progress:
    """Where a job stood at a checkpoint: ``index`` of its last evaluated point, its rows,
    its learning wall time and how many training episodes the rows already account for."""

    index: int
    rows: list[dict[str, Any]]
    wall: float
    trained: int
    #: the transitions at which the job was continued after a stop, in order
    resumed_at: list[int] = field(default_factory=list)
    #: the job's time so far (learning and evaluating), over all its processes
    seconds: float = 0.0


def _generators() -> dict[str, Any]:
    import torch

    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
    }


def _set_generators(state: dict[str, Any]) -> None:
    import torch

    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])


def _index(slot: Path) -> int | None:
    number = slot.name[len(SLOT_PREFIX) :]
    return int(number) if number.isdigit() else None


class JobCheckpoint:
    """The checkpoints of one job in ``directory`` (its work directory's ``resume``)."""

    def __init__(self, directory: Path, fingerprint: str) -> None:
        self.directory = Path(directory)
        self.fingerprint = fingerprint
        self.shared = self.directory / "shared"

    def _slots(self) -> list[Path]:
        if not self.directory.is_dir():
            return []
        slots = [p for p in self.directory.glob(SLOT_PREFIX + "*") if _index(p) is not None]
        return sorted(slots, key=_index)

    def latest(self) -> tuple[Path, Progress] | None:
        """The newest checkpoint of this job's fingerprint and versions, if any."""
        for slot in reversed(self._slots()):
            try:
                saved = json.loads((slot / "progress.json").read_text())
            except (OSError, ValueError):
                continue
            if saved.get("fingerprint") != self.fingerprint or saved.get("versions") != versions():
                continue
            progress = Progress(saved["index"], saved["rows"], saved["wall"], saved["trained"])
            progress.resumed_at = saved.get("resumed_at", [])  # later fields: older files lack
            progress.seconds = saved.get("seconds", 0.0)
            return slot, progress
        return None

    def restore(self, learner: BenchLearner) -> Progress | None:
        """Put ``learner`` and the global generators back at the newest checkpoint; None (and
        ``learner`` untouched) if there is none."""
        found = self.latest()
        if found is None:
            return None
        slot, progress = found
        learner.load_state(slot, self.shared)
        with open(slot / "generators.pkl", "rb") as f:
            _set_generators(pickle.load(f))
        progress.resumed_at.append(learner.transitions)
        return progress

    def save(self, learner: BenchLearner, progress: Progress) -> bool:
        """Checkpoint the job after point ``progress.index``; False if the learner cannot
        be saved there (nothing is written then)."""
        slot = self.directory / f"{SLOT_PREFIX}{progress.index}"
        staging = self.directory / f".{slot.name}.tmp"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        self.shared.mkdir(exist_ok=True)
        if not learner.save_state(staging, self.shared):
            shutil.rmtree(staging)
            return False
        write_bytes_atomic(staging / "generators.pkl", pickle.dumps(_generators()))
        write_json_atomic(
            staging / "progress.json",
            {
                "fingerprint": self.fingerprint,
                "versions": versions(),
                "index": progress.index,
                "rows": progress.rows,
                "wall": progress.wall,
                "trained": progress.trained,
                "resumed_at": progress.resumed_at,
                "seconds": progress.seconds,
            },
        )
        shutil.rmtree(slot, ignore_errors=True)
        staging.rename(slot)
        for old in self._slots():
            if old != slot:
                shutil.rmtree(old, ignore_errors=True)
        return True

    def remove(self) -> None:
        """Delete every checkpoint (the job is finished: its result is its record)."""
        shutil.rmtree(self.directory, ignore_errors=True)
