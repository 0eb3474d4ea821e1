"""Random-action data collection (``dlo collect --random``), in one or several processes.

Every episode's randomness comes from ``(seed, episode index)`` only, so any number of
workers produce the same dataset as one worker, and a resumed run the same dataset as an
uninterrupted one. The episodes are :func:`dlocli.env.rollout.random_episode`.

Run directory (every file written atomically)::

    spec.json                         resolved CollectSpec
    episodes/episode_EEEEEE.h5        one file per finished episode (a one-episode dataset),
                                      written as soon as the episode ends
    episodes/progress.json            {"seconds": collecting time of the episodes kept so far}
    dataset.h5                        all episodes in index order (format: :mod:`dlocli.data.rod`)
    summary.json                      episodes, transitions, diverged_episodes, seconds, ...

``episodes/`` exists from the start of a run until its end: ``dataset.h5`` and then
``summary.json`` are written from the part files, and only then is ``episodes/`` removed.
So a run directory without ``episodes/`` but with ``summary.json`` is finished. On Ctrl-C
(KeyboardInterrupt) ``dataset.h5`` is written from the finished episodes and ``episodes/``
is kept, so the run can still be resumed; a killed run keeps every finished episode.

Resume (``dlo collect --resume RUN``): the episodes whose part file exists are kept (left-
over temporary files are deleted, unreadable parts are collected again), the missing ones
are collected, and ``dataset.h5`` is assembled; ``seconds`` adds up over the resumed parts.
Resuming a finished run only returns its summary.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from dlocli.cancel import CancelToken
from dlocli.data import DATASET_FILE, Dataset, Episode, load_dataset
from dlocli.env.rollout import random_episode, stream_seed
from dlocli.env.shape_env import DLOShapeEnv, make_env_from_spec
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.io import adopt_written, prepare_run_dir, versions, write_json_atomic
from dlocli.limits import refuse_oversized_dataset
from dlocli.processes import start_worker
from dlocli.resume import resumed_run_spec
from dlocli.rundir import FINGERPRINTS_FILE, check_fingerprints, owned, record_fingerprints
from dlocli.runs.checks import check_registered
from dlocli.specs import CollectSpec, EnvSpec

PARTS_DIR = "episodes"
PROGRESS_FILE = "progress.json"
SUMMARY_FILE = "summary.json"
_PART = re.compile(r"episode_(\d+)\.h5")

# One env per worker process, built once (the goal is derived from the spec's seed, so every
# worker has the same fixed goal).
_worker_env: DLOShapeEnv | None = None
_worker_spec: CollectSpec | None = None


def _init_worker(
    spec_json: str, parent: int | None = None, cancel: CancelToken | None = None
) -> None:
    """The env of this process; a pool worker's is not cancelled (its own signals end it)."""
    global _worker_env, _worker_spec
    if parent is not None:  # a pool worker: one thread, and an end with the collecting process
        start_worker(parent, threads=1)
    _worker_spec = CollectSpec.model_validate_json(spec_json)
    _worker_env = make_env_from_spec(_worker_spec, cancel=cancel)


def _collect_one(episode: int) -> Episode:
    assert _worker_env is not None and _worker_spec is not None
    seed = _worker_spec.seed
    return random_episode(_worker_env, stream_seed(seed, episode), [seed, episode, 7])


def _episodes(
    spec: CollectSpec, indices: list[int], cancel: CancelToken | None = None
) -> Iterator[tuple[int, Episode]]:
    """Yield ``(index, episode)`` for ``indices`` in their order, from this process or a pool."""
    if not indices:
        return
    if spec.workers == 1:
        _init_worker(spec.model_dump_json(), cancel=cancel)
        for e in indices:
            yield e, _collect_one(e)
        return
    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    ctx = mp.get_context(method)
    with ctx.Pool(
        min(spec.workers, len(indices)), _init_worker, (spec.model_dump_json(), os.getpid())
    ) as pool:
        yield from zip(indices, pool.imap(_collect_one, indices, chunksize=1), strict=True)


def dataset_attrs(spec: EnvSpec) -> dict[str, Any]:
    return {
        "spec": spec.model_dump(mode="json"),
        "backend": spec.backend.name,
        "task": spec.task.name,
        "rod": spec.backend.rod.model_dump(mode="json"),
        "versions": versions(),
        "max_linear_velocity": spec.task.max_linear_velocity,
        "max_angular_velocity": spec.task.max_angular_velocity,
    }


def part_path(out: Path, episode: int) -> Path:
    """The part file of episode ``episode`` in run directory ``out``."""
    return Path(out) / PARTS_DIR / f"episode_{episode:06d}.h5"


def resumed_spec(run_dir: Path, overrides: dict[str, Any]) -> CollectSpec:
    """`dlo collect --resume RUN`: the spec of the run in ``run_dir`` (pass it to
    :func:`collect_random` with ``resume=True``); flags that contradict it are refused
    (``--workers`` may change: the data do not depend on it)."""
    return resumed_run_spec(
        CollectSpec, run_dir, overrides, "a collect", "dlo collect", free=frozenset({"workers"})
    )


def collect_random(
    spec: CollectSpec,
    overwrite: bool = False,
    progress: Callback | None = None,
    resume: bool = False,
    accept_changes: bool = False,
    cancel: CancelToken | None = None,
) -> dict[str, Any]:
    """Collect ``spec.episodes`` random episodes into ``spec.out/dataset.h5``; return a summary.

    Each finished episode is written at once as its own part file (see the module docstring);
    with ``resume`` the parts already in ``spec.out`` are kept and only the missing episodes
    are collected (a changed spec.json is refused unless ``accept_changes``). On
    KeyboardInterrupt the finished episodes are assembled into ``dataset.h5`` (atomically)
    before re-raising. ``progress`` gets a Began (unit "episode", ``done``: the episodes kept
    from a stopped run), then an Event after each finished episode; ``cancel`` stops it
    between episodes (and this process's env between its physics steps).
    """
    check_registered(spec)
    refuse_oversized_dataset(spec.episodes, spec.task.episode_steps, spec.backend.rod.n_segments)
    with owned(spec.out):
        if resume:
            check_fingerprints(spec.out, spec, accept_changes)
        return _collect(spec, overwrite, progress or ignore, resume, cancel or CancelToken())


def random_dataset(spec: CollectSpec, cancel: CancelToken | None = None) -> Dataset:
    """The dataset `dlo collect --random` would write for ``spec``, held in memory (nothing is
    written; ``spec.out`` is not read): ``spec.episodes`` random-action episodes, in
    ``spec.workers`` processes; ``cancel`` stops this process's env between physics steps."""
    refuse_oversized_dataset(spec.episodes, spec.task.episode_steps, spec.backend.rod.n_segments)
    episodes = [episode for _, episode in _episodes(spec, list(range(spec.episodes)), cancel)]
    return Dataset.from_episodes(episodes, dataset_attrs(spec))


def _collect(
    spec: CollectSpec, overwrite: bool, progress: Callback, resume: bool, cancel: CancelToken
) -> dict[str, Any]:
    out = Path(spec.out)
    parts = out / PARTS_DIR
    if resume:
        # a run killed outright could not record its files as dlo's (--overwrite clears them)
        adopt_written(out, {"spec.json", FINGERPRINTS_FILE, PARTS_DIR, DATASET_FILE, SUMMARY_FILE})
        finished = _finished_summary(out)
        if finished is not None:
            return finished
        done = _resume_parts(spec, out)
    else:
        out = prepare_run_dir(out, overwrite)
        shutil.rmtree(parts, ignore_errors=True)  # --overwrite: an earlier run's episodes
        parts.mkdir()  # no progress file yet: a run refused before its first episode is undone
        write_json_atomic(out / "spec.json", spec.model_dump(mode="json"))
        record_fingerprints(out, spec)
        done = set()
    earlier = _progress_seconds(parts)
    start = time.perf_counter()
    missing = [e for e in range(spec.episodes) if e not in done]
    attrs = dataset_attrs(spec)
    n_done = len(done)
    progress(Began("episode", n_done, spec.episodes))
    try:
        for e, episode in _episodes(spec, missing, cancel):
            cancel.raise_if_cancelled()
            Dataset.from_episodes([episode], attrs).save(part_path(out, e))
            n_done += 1
            seconds = earlier + time.perf_counter() - start
            write_json_atomic(parts / PROGRESS_FILE, {"seconds": round(seconds, 3)})
            progress(Event("episode", n_done, spec.episodes))
    except KeyboardInterrupt:
        if _part_indices(parts):
            _assemble(out, attrs).save(out / DATASET_FILE)
        raise
    data = _assemble(out, attrs)
    data.save(out / DATASET_FILE)
    seconds = earlier + time.perf_counter() - start
    transitions = data.n_transitions
    summary = {
        "episodes": data.n_episodes,
        "transitions": transitions,
        "diverged_episodes": int(data.diverged.sum()),
        "seconds": round(seconds, 3),
        "transitions_per_s": round(transitions / seconds, 1) if seconds > 0 else None,
        "workers": spec.workers,
        "path": str(out / DATASET_FILE),
    }
    write_json_atomic(out / SUMMARY_FILE, summary)
    shutil.rmtree(parts)
    return summary


# ----------------------------------------------------------------------------- parts
def _part_indices(parts: Path) -> list[int]:
    """Indices of the part files in ``parts``, sorted (temporary files are not parts)."""
    if not parts.is_dir():
        return []
    found = (_PART.fullmatch(p.name) for p in parts.iterdir())
    return sorted(int(m.group(1)) for m in found if m)


def _assemble(out: Path, attrs: dict[str, Any]) -> Dataset:
    """One dataset of all part files in ``out``, in episode order."""
    loaded = [load_dataset(part_path(out, e)) for e in _part_indices(out / PARTS_DIR)]
    if not loaded:
        raise BadInput(f"{out / PARTS_DIR} holds no episodes to assemble")
    data = loaded[0].concat(*loaded[1:])
    data.attrs = attrs
    return data


def _progress_seconds(parts: Path) -> float:
    """Collecting time of the episodes kept so far (0 if not recorded)."""
    try:
        return float(json.loads((parts / PROGRESS_FILE).read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0.0


def _finished_summary(out: Path) -> dict[str, Any] | None:
    """The summary of a finished run in ``out`` (no parts left, dataset and summary written)."""
    summary = out / SUMMARY_FILE
    if (out / PARTS_DIR).exists() or not summary.is_file() or not (out / DATASET_FILE).is_file():
        return None
    try:
        data = json.loads(summary.read_text())
    except ValueError:
        return None
    return data if isinstance(data, dict) else None


def _resume_parts(spec: CollectSpec, out: Path) -> set[int]:
    """Make ``out/episodes`` ready to continue; return the indices of the episodes kept.

    Temporary files of interrupted writes are deleted, and so are parts that cannot be read.
    A run from before part files, stopped with its finished episodes in ``dataset.h5``, has
    them split into parts.
    """
    parts = out / PARTS_DIR
    for tmp in [*parts.glob(".*.tmp"), *out.glob(f".{DATASET_FILE}.*.tmp")]:
        tmp.unlink(missing_ok=True)
    if not parts.is_dir():
        parts.mkdir()
        if (out / DATASET_FILE).is_file():
            _split_into_parts(spec, out)
    kept = set()
    for e in _part_indices(parts):
        path = part_path(out, e)
        try:
            ok = e < spec.episodes and load_dataset(path).n_episodes == 1
        except BadInput:
            ok = False
        if ok:
            kept.add(e)
        else:
            path.unlink()
    return kept


def _split_into_parts(spec: CollectSpec, out: Path) -> None:
    """The episodes of an older run's partial ``dataset.h5`` (episodes 0..k-1) as parts."""
    try:
        data = load_dataset(out / DATASET_FILE)
    except BadInput:
        return  # unreadable: those episodes are collected again
    attrs = dataset_attrs(spec)
    for e in range(min(data.n_episodes, spec.episodes)):
        Dataset.from_episodes([data.episode(e)], attrs).save(part_path(out, e))
