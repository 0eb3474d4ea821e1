"""Recording formats `dlo import` reads, one reader per file suffix (:data:`READERS`).

A cable folder holds ``train/`` and ``eval/``; each file in them is read by the reader of its
suffix and gives one or more trajectories, (frames, V, 3) float64 in the recording's units:

- ``.pkl``: DEFORM's pickled (frames, 3, V) lists (:mod:`~dlocli.recorded_cables.deform`).
- ``.npy``: one array, (frames, 3, V) as DEFORM stores it or (frames, V, 3); with V >= 4 the
  two never look alike. Loaded memory-mapped with ``allow_pickle=False``.
- ``.npz``: one such array per key; a file of one key is named by its stem, otherwise each
  trajectory is ``stem.key``.
- ``.h5`` / ``.hdf5``: one such array per dataset (every group visited), named likewise.
- ``.csv``: motion capture, one trajectory per file (:func:`read_csv`), at its frame times.
- a folder: a ROS 2 bag, one trajectory (:mod:`~dlocli.recorded_cables.rosbag`), at its stamps.

Each array's shape and type are read before its numbers, and refused past the memory budget.
"""

from __future__ import annotations

import csv
import io
import math
import os
import stat
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlocli.cancel import CancelToken
from dlocli.errors import BadInput
from dlocli.events import Began, Callback, Event, ignore
from dlocli.recorded_cables import deform

#: a reader: (file, memory budget in bytes, --fill-gaps) -> trajectories
Reader = Callable[[Path, int, int], list["Trajectory"]]


@dataclass
class Trajectory:
    name: str
    positions: np.ndarray  # (frames, V, 3)
    gaps: int = 0  # (frame, marker) cells the file left empty, filled by interpolation
    times: np.ndarray | None = None  # (frames,) seconds, when the file has timestamps


def read_folder(
    folder: Path,
    budget_bytes: int,
    fill_gaps: int = 0,
    bags: Reader | None = None,
    progress: Callback | None = None,
    cancel: CancelToken | None = None,
) -> dict[str, list[Trajectory]]:
    """``{split: [Trajectory, ...]}`` from ``folder/train`` and ``folder/eval`` (files sorted
    by name, any suffix of :data:`READERS`; a folder in them is read by ``bags``), read within
    ``budget_bytes`` of memory; every trajectory must have the same marker count.

    ``progress`` gets a Began of the files (unit "recording") once all are checked, then an
    Event as each is read (``values``: its ``split`` and ``file``); ``cancel`` is checked
    before each file."""
    progress, cancel = progress or ignore, cancel or CancelToken()
    folder = Path(folder)
    if not folder.is_dir():
        raise BadInput(f"{folder} is not a folder; pass a cable folder holding train/ and eval/")
    found = {
        s: sorted(p for p in (folder / s).iterdir() if not p.name.startswith("."))
        for s in deform.SPLITS
        if (folder / s).is_dir()
    }
    if not found.get("train"):
        raise BadInput(f"{folder}/train holds no recordings; pass a cable folder (e.g. DLO1)")
    for path in (p for files in found.values() for p in files):
        deform._require_utf8_name(path)
        if path.is_dir():
            _require_bag(path, bags)
        elif path.suffix.lower() not in READERS:
            raise BadInput(
                f"{path}: unknown suffix {path.suffix or '(none)'!r}; recordings are "
                f"{', '.join(READERS)} files (move other files out of the folder)"
            )
    out: dict[str, list[Trajectory]] = {}
    counts: dict[int, str] = {}
    kept, done, total = 0, 0, sum(len(files) for files in found.values())
    progress(Began("recording", 0, total))
    for split, files in found.items():
        out[split] = []
        for path in files:
            cancel.raise_if_cancelled()
            read = bags if path.is_dir() and bags else READERS[path.suffix.lower()]
            for item in read(path, max(0, budget_bytes - kept), fill_gaps):
                kept += deform.KEPT_PER_BYTE * item.positions.nbytes
                counts.setdefault(item.positions.shape[1], f"{path} ({item.name})")
                if len(counts) > 1:
                    (a, first), (b, other) = list(counts.items())[:2]
                    raise BadInput(
                        f"mixed marker counts: {first} has {a}, {other} has {b}; import one "
                        "cable per folder"
                    )
                out[split].append(item)
            done += 1
            progress(Event("recording", done, total, {"split": split, "file": path.name}))
    return out


def _require_bag(path: Path, bags: Reader | None) -> None:
    """BadInput unless the folder ``path`` is a ROS 2 bag (its metadata.yaml) and bags are
    read."""
    if not (path / "metadata.yaml").is_file():
        raise BadInput(
            f"{path} is a folder without metadata.yaml, not a ROS 2 bag; recordings are "
            f"{', '.join(READERS)} files or bag folders (move other folders out)"
        )
    if bags is None:
        raise BadInput(f"{path} is a ROS 2 bag; import it with `dlo import`")


def held_mask(n_markers: int, held: list[int] | None) -> np.ndarray:
    """(V,) bool from marker indices (negative from the far end); None: DEFORM's two at each
    end. BadInput unless the indices exist and some are held in each half of the cable."""
    if held is None:
        return deform.held_markers(n_markers)
    mask = np.zeros(n_markers, dtype=bool)
    for i in held:
        if not -n_markers <= i < n_markers:
            raise BadInput(
                f"--held names marker {i}, but the recordings have {n_markers} markers "
                f"(0 to {n_markers - 1}, or -1 for the last)"
            )
        mask[i] = True
    half = n_markers // 2
    if mask.all():
        raise BadInput("--held names every marker; leave the free markers out of it")
    if not (mask[:half].any() and mask[half:].any()):
        raise BadInput(
            f"--held {','.join(map(str, held))} holds no marker in one half of the cable; name "
            "the markers each gripper holds (e.g. --held 0,-1)"
        )
    return mask


# ----------------------------------------------------------------------------- arrays
def require_regular_file(path: Path, wanted: str = "readable files") -> None:
    """BadInput unless ``path`` is a regular file (a FIFO would block the read); the
    message asks for ``wanted``."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise BadInput(f"{path} cannot be read ({exc.strerror}); pass {wanted}") from exc
    if not stat.S_ISREG(mode):
        raise BadInput(f"{path} is not a regular file (a FIFO, device or socket); pass {wanted}")


def _fits(name: str, shape: tuple[int, ...], dtype: np.dtype, budget: int) -> None:
    """BadInput unless an array of numbers of ``shape`` fits the budget as float64 copies."""
    if dtype.kind not in "fiu":
        raise BadInput(f"{name} holds {dtype}, not numbers; store float positions")
    needed = 2 * 8 * math.prod(shape)  # the float64 array and its transposed copy
    if needed > budget:
        raise BadInput(
            f"{name} would take {needed / 2**20:.0f} MiB to read (shape {shape}), over the "
            f"budget's {budget / 2**20:.0f} MiB left; raise --max-memory-mib or import fewer files"
        )


def from_array(array: np.ndarray, name: str) -> np.ndarray:
    """(frames, 3, V) or (frames, V, 3) -> checked (frames, V, 3) float64."""
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[1] != 3 and array.shape[2] == 3:
        array = array.transpose(0, 2, 1)
    if array.ndim != 3 or array.shape[1] != 3:
        raise BadInput(
            f"{name} has shape {array.shape}, expected (frames, 3, markers) or (frames, markers, 3)"
        )
    return deform.checked(np.asarray(array, dtype=np.float64), name)


def _named(path: Path, key: str, many: bool) -> str:
    return f"{path.stem}.{key}" if many else path.stem


def read_pkl(path: Path, budget: int, fill_gaps: int) -> list[Trajectory]:
    return [Trajectory(path.stem, deform.read_trajectory(path, budget))]


def read_npy(path: Path, budget: int, fill_gaps: int) -> list[Trajectory]:
    require_regular_file(path)
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise BadInput(f"{path} is not a readable .npy array ({str(exc)[:80]})") from exc
    _fits(str(path), array.shape, array.dtype, budget)
    return [Trajectory(path.stem, from_array(array, str(path)))]


def read_npz(path: Path, budget: int, fill_gaps: int) -> list[Trajectory]:
    require_regular_file(path)
    out: list[Trajectory] = []
    try:
        with zipfile.ZipFile(path) as archive:
            members = [m for m in archive.namelist() if m.endswith(".npy")]
            if not members:
                raise BadInput(f"{path} holds no arrays; save one array per trajectory")
            for member in members:
                name = f"{path}:{member[:-4]}"
                with archive.open(member) as f:
                    version = np.lib.format.read_magic(f)
                    header = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = header(f)
                    _fits(name, shape, dtype, budget)
                    budget -= deform.KEPT_PER_BYTE * 8 * math.prod(shape)
                    f.seek(0)
                    array = np.lib.format.read_array(f, allow_pickle=False)
                key = _named(path, member[:-4], len(members) > 1)
                out.append(Trajectory(key, from_array(array, name)))
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise BadInput(f"{path} is not a readable .npz archive ({str(exc)[:80]})") from exc
    return out


def read_h5(path: Path, budget: int, fill_gaps: int) -> list[Trajectory]:
    import h5py

    require_regular_file(path)
    try:
        with h5py.File(path, "r") as f:
            keys: list[str] = []
            f.visititems(lambda k, v: keys.append(k) if isinstance(v, h5py.Dataset) else None)
            if not keys:
                raise BadInput(f"{path} holds no datasets; store one array per trajectory")
            out = []
            for key in keys:
                name = f"{path}:{key}"
                _fits(name, f[key].shape, f[key].dtype, budget)
                budget -= deform.KEPT_PER_BYTE * 8 * math.prod(f[key].shape)
                positions = from_array(f[key][()], name)
                out.append(Trajectory(_named(path, key, len(keys) > 1), positions))
    except OSError as exc:
        raise BadInput(f"{path} is not a readable HDF5 file ({str(exc)[:80]})") from exc
    return out


# ----------------------------------------------------------------------------- csv
#: leading columns a motion-capture export may have, skipped
INDEX_COLUMNS = ("frame", "time")
AXES = ("_x", "_y", "_z")


def read_csv(path: Path, budget: int, fill_gaps: int) -> list[Trajectory]:
    """A motion-capture CSV: a header ``frame,time,m0_x,m0_y,m0_z,m1_x,...`` (both
    optional; ``frame`` is ignored, ``time`` is each frame's time in seconds, else frames are
    at --rate-hz), then one row per frame in time order. Each marker is three columns
    ``NAME_x,NAME_y,NAME_z``; the marker order is the column order. An empty cell is a gap:
    that marker is missing in that frame."""
    # the text and its decoded copy, then 8 bytes per cell (>= 2 bytes of text) as parsed
    # rows (with their overhead) and again as stacked: about 16 times the text at worst
    text = deform._read_regular(path, budget // 16)
    try:
        reader = csv.reader(io.StringIO(text.decode("utf-8-sig")))
        header = [h.strip().lower() for h in next(reader, [])]
        if not header:
            raise BadInput(
                f"{path} is empty; write a header frame,time,m0_x,m0_y,m0_z,... and rows"
            )
        skip = _index_columns(header)
        triples = _markers(header[skip:], path)
        clock = header.index("time") if "time" in header[:skip] else None
        parsed, times = [], []
        for row in reader:
            parsed.append(_row(row, len(header), skip, path, reader.line_num))
            if clock is not None:
                times.append(_time(row[clock], path, reader.line_num, clock))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise BadInput(f"{path} is not a UTF-8 CSV file ({str(exc)[:60]})") from exc
    values = np.array(parsed, dtype=np.float64).reshape(len(parsed), 3 * triples)
    del parsed, text
    positions = values.reshape(len(values), triples, 3)
    missing = np.isnan(positions).any(axis=2)  # (frames, V)
    gaps = int(missing.sum())
    if gaps:
        positions = filled(positions, missing, fill_gaps, path)
    stamps = np.array(times) if clock is not None else None
    return [Trajectory(path.stem, from_array(positions, str(path)), gaps, stamps)]


def _index_columns(header: list[str]) -> int:
    """How many leading columns are frame numbers or times."""
    skip = 0
    while skip < len(header) and header[skip] in INDEX_COLUMNS:
        skip += 1
    return skip


def _markers(columns: list[str], path: Path) -> int:
    """The number of markers of the coordinate columns; BadInput unless NAME_x,NAME_y,NAME_z
    triples."""
    triples = [columns[i : i + 3] for i in range(0, len(columns), 3)]
    if not triples or any(
        len(t) != 3 or [c[-2:] for c in t] != list(AXES) or len({c[:-2] for c in t}) != 1
        for t in triples
    ):
        raise BadInput(
            f"{path}: header {','.join(columns)[:80]!r} is not frame,time,m0_x,m0_y,m0_z,"
            "m1_x,... (three columns NAME_x,NAME_y,NAME_z per marker)"
        )
    return len(triples)


def _row(row: list[str], width: int, skip: int, path: Path, line: int) -> np.ndarray:
    """One frame's coordinates (NaN for an empty cell); BadInput for a ragged row or text."""
    if len(row) != width:
        raise BadInput(
            f"{path} line {line} has {len(row)} cells, the header {width}; write every row "
            "in full (an empty cell is a gap)"
        )
    return np.array(
        [
            _number(c, path, line, j + skip) if c.strip() else np.nan
            for j, c in enumerate(row[skip:])
        ]
    )


def _time(cell: str, path: Path, line: int, column: int) -> float:
    try:
        value = float(cell)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise BadInput(
            f"{path} line {line}, column {column + 1}: time {cell[:20]!r} is not a number of "
            "seconds; write every frame's time or drop the time column"
        )
    return value


def _number(cell: str, path: Path, line: int, column: int) -> float:
    try:
        value = float(cell)
    except ValueError:
        raise BadInput(
            f"{path} line {line}, column {column + 1}: {cell[:20]!r} is not a number; leave "
            "the cell empty for a gap"
        ) from None
    if not math.isfinite(value):
        raise BadInput(
            f"{path} line {line}, column {column + 1}: {cell[:20]!r} is not a finite "
            "number; leave the cell empty for a gap"
        )
    return value


def filled(positions: np.ndarray, missing: np.ndarray, fill_gaps: int, path: Path) -> np.ndarray:
    """Each marker's gaps interpolated linearly between the frames around them; BadInput for
    a gap longer than ``fill_gaps`` frames or at the first or last frame."""
    gaps, longest, edge = int(missing.sum()), 0, False
    runs = []
    for v in range(missing.shape[1]):
        frames = np.flatnonzero(missing[:, v])
        for run in np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1) if len(frames) else []:
            longest = max(longest, len(run))
            edge |= run[0] == 0 or run[-1] == len(missing) - 1
            runs.append((v, run))
    if edge or longest > fill_gaps:
        why = "one at the first or last frame, which cannot be interpolated" if edge else ""
        hint = "trim the recording" if edge else f"pass --fill-gaps {longest} to interpolate them"
        raise BadInput(
            f"{path} has {gaps} gaps (a marker missing in a frame), the longest "
            f"{longest} frames{'; ' + why if why else ''}; {hint}"
        )
    out = positions.copy()
    for v, run in runs:
        a, b = run[0] - 1, run[-1] + 1
        w = ((run - a) / (b - a))[:, None]
        out[run, v] = (1 - w) * positions[a, v] + w * positions[b, v]
    return out


#: suffix -> reader; a new format is one function and one entry here
READERS: dict[str, Reader] = {
    ".pkl": read_pkl, ".npy": read_npy, ".npz": read_npz,
    ".h5": read_h5, ".hdf5": read_h5, ".csv": read_csv,
}  # fmt: skip
