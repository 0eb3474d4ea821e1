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

A run refused (a :class:`~dlocli.errors.DloError`) before its first result, having written
only its start files (``spec.json``, ``fingerprints.json``) and empty folders, is undone:
a directory it created is removed, lock file and created parents included; one that existed
gets its start files back as they were and loses only the lock file the run added.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dlocli.errors import BadInput, DloError
from dlocli.io import (
    LOCK_FILE,
    read_json,
    record_written,
    run_dir_entries,
    write_bytes_atomic,
    write_json_atomic,
)

try:  # POSIX; elsewhere runs are not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

FINGERPRINTS_FILE = "fingerprints.json"
#: what a run writes before its first result (a run refused with only these is undone)
START_FILES = frozenset({"spec.json", FINGERPRINTS_FILE})
#: a start file larger than this is not dlo's (nor kept in memory to be put back)
MAX_START_BYTES = 1 << 24
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
    created = _first_missing(run_dir)
    had_lock = os.path.lexists(run_dir / LOCK_FILE)
    run_dir.mkdir(parents=True, exist_ok=True)
    key = run_dir.resolve()
    outermost = key not in _held
    found = None
    if outermost:
        _held[key] = [_acquire(run_dir, shared), 1]
        try:
            found = _Found(run_dir, created, had_lock)
        except BaseException:
            os.close(_held.pop(key)[0])
            raise
    else:
        _held[key][1] += 1
    refused = False
    try:
        yield run_dir
    except DloError:
        refused = True
        raise
    finally:
        _held[key][1] -= 1
        if found is not None:
            _record_and_release(found, key, shared, refused)


class _Found:
    """What a run directory held when a run took it: its entries, the signature of each file
    (a file replaced atomically gets a new inode) and the bytes of its start files."""

    def __init__(self, run_dir: Path, created: Path | None, had_lock: bool) -> None:
        self.run_dir, self.created, self.had_lock = run_dir, created, had_lock
        self.entries = run_dir_entries(run_dir)
        self.signatures = _signatures(run_dir, self.entries)
        self.start_bytes = {
            name: (run_dir / name).read_bytes()
            for name, (mode, _, size, _) in self.signatures.items()
            if name in START_FILES and stat.S_ISREG(mode) and size <= MAX_START_BYTES
        }

    def undo(self) -> bool:
        """Put the directory back as it was found if the run wrote nothing but start files
        and folders left empty; True if so (then the lock file it added is gone too)."""
        now = run_dir_entries(self.run_dir)
        signatures = _signatures(self.run_dir, now)
        changed = {e for e in now | self.entries if signatures.get(e) != self.signatures.get(e)}
        new_folders = {e for e in now - self.entries if stat.S_ISDIR(signatures[e][0])}
        files = changed - new_folders  # a file in a new folder is itself new: a result
        if self.entries - now or not files <= START_FILES:
            return False
        if any(name in self.entries and name not in self.start_bytes for name in files):
            return False  # a start file that was a link or a folder: not ours to rewrite
        for name in files:
            if name in self.start_bytes:
                write_bytes_atomic(self.run_dir / name, self.start_bytes[name])
            else:
                (self.run_dir / name).unlink()
        for folder in sorted(new_folders, key=lambda e: -e.count(os.sep)):  # deepest first
            (self.run_dir / folder).rmdir()
        _remove_created(self.run_dir, self.created, self.had_lock)
        return True


def _signatures(run_dir: Path, entries: set[str]) -> dict[str, tuple[int, int, int, int]]:
    """(mode, inode, size, mtime) of each entry, links not followed; directories by mode only
    (their times change with what is written inside)."""
    found = {}
    for entry in entries:
        with contextlib.suppress(FileNotFoundError):
            info = os.lstat(run_dir / entry)
            if stat.S_ISDIR(info.st_mode):
                found[entry] = (info.st_mode, 0, 0, 0)
            else:
                found[entry] = (info.st_mode, info.st_ino, info.st_size, info.st_mtime_ns)
    return found


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (what ``mkdir -p`` creates)."""
    missing = None
    for folder in (path, *path.parents):
        if os.path.lexists(folder):
            break
        missing = folder
    return missing


def _remove_created(run_dir: Path, created: Path | None, had_lock: bool) -> None:
    """Remove the lock file unless it was there before, then the folders from ``run_dir`` up
    to ``created`` that this run made, as long as they are empty."""
    if not had_lock:
        (run_dir / LOCK_FILE).unlink(missing_ok=True)
    if created is None:
        return
    for folder in (run_dir, *run_dir.parents):  # ``created`` is one of them
        try:
            folder.rmdir()
        except OSError:  # something appeared meanwhile: it stays
            return
        if folder == created:
            return


def _record_and_release(found: _Found, key: Path, shared: bool, refused: bool) -> None:
    try:
        undone = refused and not shared and found.undo()
        if not undone and (shared or not _remove_if_unused(found)):
            record_written(found.run_dir, found.entries)
    except OSError:
        pass  # a full disk: unrecorded files are refused by --overwrite, never deleted
    finally:
        os.close(_held.pop(key)[0])  # closing the descriptor releases the lock


def _remove_if_unused(found: _Found) -> bool:
    """A run that wrote nothing leaves no lock file (nor the directory it created); True if
    so. Unlinked while still locked: a process that opened the old file sees that it is no
    longer the lock (:func:`_acquire`)."""
    if [p.name for p in found.run_dir.iterdir()] != [LOCK_FILE]:
        return False
    # the folders above stay: a bench's job locks share theirs with other processes
    _remove_created(found.run_dir, found.run_dir if found.created else None, had_lock=False)
    return True


def _acquire(run_dir: Path, shared: bool) -> int:
    path = run_dir / LOCK_FILE
    fd = _open_lock_file(path)
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


def _open_lock_file(path: Path) -> int:
    """The lock file, created if missing; BadInput if it is a link or not a plain file of its
    own (writing the PID there would change the file it stands for)."""
    nofollow = getattr(os, "O_NOFOLLOW", 0)
    refusal = BadInput(
        f"{path} is not a lock file dlo made (a link or a special file); remove it and run again"
    )
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | nofollow | os.O_NONBLOCK, 0o666)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENXIO, errno.EMLINK):
            raise refusal from exc
        raise
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
        os.close(fd)
        raise refusal
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


def _path_fields(spec: Any, outputs: bool = False) -> Iterator[tuple[str, Path]]:
    """(dotted name, path) of every path field of ``spec`` that it reads, or with ``outputs``
    that it writes."""

    def walk(node: Any, prefix: str) -> Iterator[tuple[str, Path]]:
        for name in type(node).model_fields:
            value = getattr(node, name)
            if hasattr(type(value), "model_fields"):
                yield from walk(value, f"{prefix}{name}.")
            elif isinstance(value, Path) and (name in OUTPUT_FIELDS) == outputs:
                yield prefix + name, value
            elif isinstance(value, list) and (name in OUTPUT_FIELDS) == outputs:
                # several paths: the first keeps the field's own name (as when it held one)
                paths = [v for v in value if isinstance(v, Path)]
                for k, path in enumerate(paths):
                    yield prefix + name + (f".{k}" if k else ""), path

    return walk(spec, "")


def input_files(spec: Any) -> dict[str, Path]:
    """The files a spec reads, by dotted field name (a run directory given as a dataset
    stands for its ``dataset.h5``)."""
    found: dict[str, Path] = {}
    for name, value in _path_fields(spec):
        path = value / "dataset.h5" if value.is_dir() else value
        if path.is_file():
            found[name] = path
    return found


def resolved(path: Path, field: str) -> Path:
    """``path`` made absolute with its links followed; BadInput naming ``field`` (the spec's
    dotted field) if the links loop (Python raises RuntimeError or OSError ELOOP, by version)."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno != errno.ELOOP:
            raise
        raise BadInput(
            f"{field} {path}: its symbolic links loop; pass a path that resolves"
        ) from None


def refuse_outputs_in_inputs(spec: Any) -> None:
    """BadInput if something ``spec`` writes would land in the run directory of something it
    reads (``dlo train --data D --out D``), or in a folder it reads (recordings, a policy,
    keys): that run's results would be replaced, or the folder's next reader would find the
    output among its inputs; or if a path of the spec's runs into a loop of links."""
    roots: dict[str, tuple[Path, str]] = {}
    for name, path in _path_fields(spec):
        if run := _run_of(path, name):
            roots[name] = (run, f"the run that {name} comes from")
        elif path.is_dir() and name != "source":  # recordings: see refuse_out_by_source
            flag = "--" + name.rstrip("0123456789").rstrip(".").rsplit(".", 1)[-1]
            roots[name] = (resolved(path, name), f"the folder {flag.replace('_', '-')} reads")
    for output, path in _path_fields(spec, outputs=True):
        target = resolved(path, output)
        for root, what in roots.values():
            if target == root or root in target.parents:
                raise BadInput(
                    f"--{output.replace('_', '-')} {path} lies inside {root}, {what}; write "
                    "to another path, outside the inputs"
                )


def refuse_out_by_source(spec: Any) -> None:
    """BadInput if ``spec.out`` lies inside ``spec.source``, a folder of recordings (`dlo
    import`, `dlo track`, `dlo calibrate`): the output would land among the recordings the
    next run reads; or holds it (--overwrite would put the recordings at stake)."""
    refuse_out_among(spec.out, [spec.source])


def refuse_out_among(out: Path, sources: list[Path]) -> None:
    """:func:`refuse_out_by_source` for a run that reads several folders of recordings."""
    where = resolved(out, "--out")
    for source in sources:
        folder = resolved(source, "--source")
        if where == folder or folder in where.parents or where in folder.parents:
            raise BadInput(
                f"--out {out} lies inside or holds --source {source}; write to a folder "
                "apart from the recordings"
            )


def _run_of(path: Path, field: str) -> Path | None:
    """The run directory ``path`` is or lies in (one holding a spec.json), if any."""
    path = resolved(path, field)
    for folder in (path, *path.parents) if path.is_dir() else path.parents:
        if (folder / "spec.json").is_file():
            return folder
    return None


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
        recorded = read_json(path, dict)
        now = fingerprints(run_dir, spec)
        try:
            changed = [
                name
                for name in ("spec.json", *sorted({*recorded["inputs"], *now["inputs"]}))
                if _entry(recorded, name) != _entry(now, name)
            ]
        except (KeyError, TypeError, AttributeError) as exc:
            raise BadInput(
                f"--resume {run_dir}: {path.name} is damaged; pass --accept-changes to record "
                "the current spec and inputs, or start a new run"
            ) from exc
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
