"""Run directories are owned: one process writes a run directory at a time, and a resumed
run checks that its spec and its input files are the ones it started with.

The lock is ``OUT/.dlo.lock``, an advisory ``flock`` held for the whole run; the file holds
the PID of the process that took it. The operating system drops the lock when that process
dies however it dies, so a stale lock file from a killed run is simply taken over.
Several readers may share a directory (a bench resumed by several processes, each running
its own jobs, see :mod:`dlocli.bench.run`); a writer excludes everyone.

``OUT/fingerprints.json`` records the SHA-256 of ``spec.json`` and of every input file the
spec names (datasets, checkpoints, goal files). ``--resume`` refuses a run whose spec or
inputs changed since, unless told ``--accept-changes``; then the new fingerprints are
recorded and the change is the user's.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dlocli.errors import BadInput
from dlocli.io import LOCK_FILE, write_json_atomic

try:  # POSIX; elsewhere runs are not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

FINGERPRINTS_FILE = "fingerprints.json"
#: spec fields that name what a run writes, not what it reads
OUTPUT_FIELDS = frozenset({"out", "video", "plot"})

#: locks this process holds: resolved directory -> [file descriptor, holders]
_held: dict[Path, list[int]] = {}


class InUse(BadInput):
    """The run directory's lock is held by another process (``holder``: its PID)."""

    def __init__(self, run_dir: Path, holder: str) -> None:
        super().__init__(
            f"{run_dir} is in use by another dlo process (PID {holder}); wait for it to end "
            "or pass another --out"
        )
        self.holder = holder


@contextmanager
def owned(run_dir: Path, *, shared: bool = False) -> Iterator[Path]:
    """Hold ``run_dir``'s lock (creating the directory) while the block runs; BadInput naming
    the holder's PID if another process holds it. Re-entrant within one process."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise BadInput(f"--out {run_dir} is a file; pass a directory path")
    created = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    key = run_dir.resolve()
    if key in _held:
        _held[key][1] += 1
    else:
        _held[key] = [_acquire(run_dir, shared), 1]
    try:
        yield run_dir
    finally:
        _held[key][1] -= 1
        if _held[key][1] == 0:
            if not shared:
                _remove_if_unused(run_dir, created)
            os.close(_held.pop(key)[0])  # closing the descriptor releases the lock


def _remove_if_unused(run_dir: Path, created: bool) -> None:
    """A run refused before it wrote anything leaves no lock file (nor the directory it
    created). Unlinked while still locked: a process that opened the old file sees that it
    is no longer the lock (:func:`_acquire`)."""
    if [p.name for p in run_dir.iterdir()] != [LOCK_FILE]:
        return
    (run_dir / LOCK_FILE).unlink(missing_ok=True)
    if created:
        with contextlib.suppress(OSError):  # something appeared meanwhile: it stays
            run_dir.rmdir()


def _acquire(run_dir: Path, shared: bool) -> int:
    path = run_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    if fcntl is None:  # pragma: no cover
        return fd
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise InUse(run_dir, holder) from None
    if not _is_current(fd, path):  # its holder removed it before releasing: take the new one
        os.close(fd)
        run_dir.mkdir(parents=True, exist_ok=True)
        return _acquire(run_dir, shared)
    if not shared:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def _is_current(fd: int, path: Path) -> bool:
    """Whether ``fd`` is still the file at ``path``."""
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


# ----------------------------------------------------------------------------- fingerprints
def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def input_files(spec: Any) -> dict[str, Path]:
    """The files a spec reads, by dotted field name (a run directory given as a dataset
    stands for its ``dataset.h5``)."""
    found: dict[str, Path] = {}

    def walk(node: Any, prefix: str) -> None:
        for name in type(node).model_fields:
            value = getattr(node, name)
            if hasattr(type(value), "model_fields"):
                walk(value, f"{prefix}{name}.")
            elif isinstance(value, Path) and name not in OUTPUT_FIELDS:
                path = value / "dataset.h5" if value.is_dir() else value
                if path.is_file():
                    found[prefix + name] = path

    walk(spec, "")
    return found


def fingerprints(run_dir: Path, spec: Any) -> dict[str, Any]:
    return {
        "spec.json": file_digest(Path(run_dir) / "spec.json"),
        "inputs": {
            name: {"path": str(path), "sha256": file_digest(path)}
            for name, path in input_files(spec).items()
        },
    }


def record_fingerprints(run_dir: Path, spec: Any) -> None:
    """Record what the run in ``run_dir`` starts from (call after writing spec.json)."""
    write_json_atomic(Path(run_dir) / FINGERPRINTS_FILE, fingerprints(run_dir, spec))


def check_fingerprints(run_dir: Path, spec: Any, accept_changes: bool = False) -> None:
    """BadInput if ``spec.json`` or an input file changed since the run started (a run older
    than fingerprints is trusted and gets them); with ``accept_changes`` record the new ones."""
    path = Path(run_dir) / FINGERPRINTS_FILE
    if path.is_file() and not accept_changes:
        recorded = json.loads(path.read_text())
        now = fingerprints(run_dir, spec)
        changed = [
            name
            for name in ("spec.json", *sorted({*recorded["inputs"], *now["inputs"]}))
            if _entry(recorded, name) != _entry(now, name)
        ]
        if changed:
            raise BadInput(
                f"--resume {run_dir}: {', '.join(changed)} changed since the run started; "
                "restore it, start a new run, or pass --accept-changes to continue anyway"
            )
    record_fingerprints(run_dir, spec)


def _entry(prints: dict[str, Any], name: str) -> Any:
    if name == "spec.json":
        return prints["spec.json"]
    entry = prints["inputs"].get(name)
    return entry and entry["sha256"]
