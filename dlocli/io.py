"""Atomic writes and run directories: results are never left half-written or clobbered."""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dlocli.errors import BadInput

#: the lock file of a run directory (:mod:`dlocli.rundir`); it alone leaves a directory empty
LOCK_FILE = ".dlo.lock"
#: what dlo wrote in a run directory: its entries' paths, relative, as a JSON list
MANIFEST_FILE = ".dlo-written.json"


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success make it durable and rename it over
    ``path``. Every file dlo writes goes through here, so a full disk is one ``OSError``
    naming the file and never a truncated file in its place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp's 0600 would hide results from the group
    try:
        yield tmp_path
        _check_not_cut(tmp_path)
        _fsync(tmp_path)  # ENOSPC on delayed allocation surfaces here, not after the rename
        os.replace(tmp_path, path)
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from exc  # name the file we wrote
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _check_not_cut(path: Path) -> None:
    """OSError (EFBIG) if the file reached the process's file-size limit (``ulimit -f``): a
    write cut there can return without an error, leaving the file short."""
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and path.stat().st_size >= limit:
        raise OSError(errno.EFBIG, os.strerror(errno.EFBIG))  # cut at ``limit`` bytes


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _umask() -> int:
    """The process's umask (reading it means setting it; set straight back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: Path, data: bytes | memoryview) -> None:
    """Write ``data`` atomically with plain Python I/O.

    Libraries that write files themselves (HDF5, torch's zip writer) serialise into memory
    first and land here, so a full disk is one clean ``OSError`` (ENOSPC) rather than a
    native library failing mid-file (HDF5's close then segfaults)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)


def write_text_atomic(path: Path, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))  # durable, a full disk names the file


def write_json_atomic(path: Path, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2, default=str) + "\n")


def read_json(path: Path, expect: type = object) -> Any:
    """The JSON value in ``path`` (one that :func:`write_json_atomic` wrote); BadInput naming
    the file if it is not JSON, or not of type ``expect``."""
    try:
        value = json.loads(Path(path).read_bytes())
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise BadInput(
            f"{path} is damaged ({str(exc)[:80]}); restore it, or start a new run"
        ) from exc
    if not isinstance(value, expect):
        raise BadInput(
            f"{path} is damaged (it holds a {type(value).__name__}, not a {expect.__name__}); "
            "restore it, or start a new run"
        )
    return value


def prepare_run_dir(out: Path, overwrite: bool) -> Path:
    """Create the run directory; refuse an existing non-empty one unless ``overwrite``, and
    with ``overwrite`` one that holds anything dlo did not write there (its manifest).

    Nothing is deleted here: files are replaced atomically as the run writes them, so an
    interrupted run never leaves a half-emptied directory; a command may then remove what
    an earlier run of its own left, since everything there is dlo's.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out} is a file; pass a directory path")
    if out.is_dir() and run_dir_entries(out) and not overwrite:
        raise BadInput(f"--out {out} exists and is not empty; pass --overwrite or another --out")
    foreign = run_dir_entries(out) - written_by_dlo(out) if out.is_dir() else set()
    foreign = sorted(foreign, key=lambda entry: (-entry.count(os.sep), entry))  # files first
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        raise BadInput(
            f"--overwrite {out}: dlo did not write {foreign[0][:200]}{more} there and deletes "
            "only its own files; move them out or pass another --out"
        )
    out.mkdir(parents=True, exist_ok=True)
    return out


def remove_unwritten(out: Path, patterns: Iterable[str], written: set[Path]) -> None:
    """Delete what an earlier run left in ``out`` matching the glob ``patterns`` that this
    run did not write (``written``), files and folders: a run over an earlier one
    (``--overwrite``, where everything is dlo's: :func:`prepare_run_dir`) then holds its own
    outputs alone. Called once the run's outputs are written, so a stop never empties it."""
    for pattern in patterns:
        for path in sorted(out.glob(pattern)):
            if path in written:
                continue
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)


def run_dir_entries(run_dir: Path) -> set[str]:
    """Every file, folder and link under ``run_dir`` (relative paths; links not followed),
    but its lock and manifest."""
    found = set()
    for folder, dirs, files in os.walk(run_dir):
        relative = Path(folder).relative_to(run_dir)
        found.update(str(relative / name) for name in (*dirs, *files))
    return found - {LOCK_FILE, MANIFEST_FILE}


def written_by_dlo(run_dir: Path) -> set[str]:
    """The entries of ``run_dir`` its manifest says dlo wrote (none if it has no manifest)."""
    try:
        listed = json.loads((Path(run_dir) / MANIFEST_FILE).read_text())
    except (OSError, ValueError):
        return set()
    if not isinstance(listed, list):
        return set()
    return {entry for entry in listed if isinstance(entry, str)}


def record_written(run_dir: Path, before: set[str]) -> None:
    """Update ``run_dir``'s manifest after a run: what it listed and is still there, and what
    appeared since ``before`` (the entries when the run took the directory)."""
    now, listed = run_dir_entries(run_dir), written_by_dlo(run_dir)
    written = (listed & now) | (now - before)
    if written != listed:  # a refused run leaves a user's folder as it was
        write_json_atomic(Path(run_dir) / MANIFEST_FILE, sorted(written))


def adopt_written(run_dir: Path, tops: set[str]) -> None:
    """A resumed run takes over what it continues from: the entries of ``run_dir`` under the
    top-level names ``tops`` (its own layout) join the manifest. A run killed outright
    (SIGKILL, power loss) could not record them, and a later --overwrite would refuse them."""
    listed = written_by_dlo(run_dir)
    found = {e for e in run_dir_entries(run_dir) if Path(e).parts[0] in tops}
    if not found <= listed:
        write_json_atomic(Path(run_dir) / MANIFEST_FILE, sorted(listed | found))


def check_writable(path: Path, flag: str, overwrite: bool) -> None:
    """BadInput unless a file could be written at ``path``, and replacing an existing one
    only with ``overwrite`` (checked before the work starts, so a long run does not end on an
    unwritable output)."""
    path = Path(path)
    if path.is_dir():
        raise BadInput(f"{flag} {path} is a directory; pass a file path")
    if path.exists() and not overwrite:
        raise BadInput(f"{flag} {path} exists; pass --overwrite or another {flag}")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise BadInput(f"{flag} {path}: cannot write in {parent}; pass a path you can write to")


def versions() -> dict[str, str]:
    """Versions of the packages that determine results (for dataset and checkpoint metadata)."""
    from importlib.metadata import PackageNotFoundError, version

    found = {}
    for name in (
        "dlocli",
        "mujoco",
        "pybullet",
        "torch",
        "numpy",
        "gymnasium",
        "stable-baselines3",
    ):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            continue
    return found
