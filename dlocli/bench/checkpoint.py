"""Mid-job checkpoints of the bench: a stopped job continues from its last evaluation point.

After each evaluation point, the job writes what it needs to continue from there into its
work directory (``<job>/resume``), and a job that finds one continues instead of starting
again. The continuation is exact: the learner's own state, the training env's episode
generator and the global random generators are all restored, so a job stopped and resumed
gives the rows an uninterrupted job gives (``tests/test_bench_resume.py``).

Layout of ``resume/``:

- ``point-<index>/``: one slot per checkpoint; ``progress.json`` (the rows so far, the wall
  time, the fingerprint) and ``generators.json`` there, and the learner's files
  (:meth:`BenchLearner.save_state`). A slot is written under a temporary name and renamed,
  then older slots are removed, so a job killed while checkpointing keeps the previous one.
- ``shared/``: what learners write once and keep growing (an SB3 replay buffer in chunks,
  each written once), so a checkpoint costs the new transitions, not the whole buffer.

A checkpoint whose fingerprint, package versions or format differ from the job's is ignored.
Nothing in a checkpoint is unpickled (JSON, ``.npz`` without objects, ``weights_only`` torch
files, SB3 zips read without their pickled entries): a bench folder is made to be shared.
"""

from __future__ import annotations

import json
import random
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dlocli.io import read_json, versions, write_json_atomic

if TYPE_CHECKING:
    from dlocli.bench.agents import BenchLearner

SLOT_PREFIX = "point-"
#: the layout of a slot; 2: no pickles (slots of format 1 held pickled generators and learners)
CHECKPOINT_FORMAT = 2


@dataclass
class Standing:
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
    """The global generators' states as JSON data."""
    import torch

    version, mt_state, gauss = random.getstate()
    numpy_state = np.random.get_state(legacy=False)
    numpy_state["state"]["key"] = numpy_state["state"]["key"].tolist()
    return {
        "python": [version, list(mt_state), gauss],
        "numpy": numpy_state,
        "torch": torch.get_rng_state().tolist(),
    }


def _set_generators(state: dict[str, Any]) -> None:
    import torch

    version, mt_state, gauss = state["python"]
    random.setstate((version, tuple(mt_state), gauss))
    numpy_state = state["numpy"]
    key = np.asarray(numpy_state["state"]["key"], dtype=np.uint32)
    np.random.set_state({**numpy_state, "state": {**numpy_state["state"], "key": key}})
    torch.set_rng_state(torch.tensor(state["torch"], dtype=torch.uint8))


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

    def latest(self) -> tuple[Path, Standing] | None:
        """The newest checkpoint of this job's fingerprint and versions, if any."""
        for slot in reversed(self._slots()):
            try:
                saved = json.loads((slot / "progress.json").read_text())
            except (OSError, ValueError):
                continue
            if (
                saved.get("format") != CHECKPOINT_FORMAT
                or saved.get("fingerprint") != self.fingerprint
                or saved.get("versions") != versions()
            ):
                continue
            progress = Standing(saved["index"], saved["rows"], saved["wall"], saved["trained"])
            progress.resumed_at = saved.get("resumed_at", [])  # later fields: older files lack
            progress.seconds = saved.get("seconds", 0.0)
            return slot, progress
        return None

    def restore(self, learner: BenchLearner) -> Standing | None:
        """Put ``learner`` and the global generators back at the newest checkpoint; None (and
        ``learner`` untouched) if there is none."""
        found = self.latest()
        if found is None:
            return None
        slot, progress = found
        learner.load_state(slot, self.shared)
        _set_generators(read_json(slot / "generators.json"))
        progress.resumed_at.append(learner.transitions)
        return progress

    def save(self, learner: BenchLearner, progress: Standing) -> bool:
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
        write_json_atomic(staging / "generators.json", _generators())
        write_json_atomic(
            staging / "progress.json",
            {
                "format": CHECKPOINT_FORMAT,
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
