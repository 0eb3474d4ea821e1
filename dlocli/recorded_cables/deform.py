"""Read DEFORM trajectory files (Chen et al., CoRL 2024, repository roahmlab/DEFORM).

Each ``.pkl`` is a pickled nested list of floats, shape (frames, 3, V): x/y/z in metres of V
markers along the cable. Pickles can run code when loaded, so they are read by
:mod:`~dlocli.recorded_cables.plain_pickle`: a plain list of numbers loads, anything that names a
class or function, reuses an object or does not fit the memory budget is refused before it
is built. Only regular files are opened (a FIFO named ``x.pkl`` would block the read).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np

from dlocli.data import DATASET_FILE, MarkerDataset, load_dataset
from dlocli.errors import BadInput
from dlocli.recorded_cables.plain_pickle import load_plain
from dlocli.recorded_cables.spec import DEFAULT_MEMORY_MIB

SPLITS = ("train", "eval")
MIN_MARKERS = 4  # two held at each end
HELD_PER_END = 2
#: memory the numbers of the recordings read so far keep per float64 byte: the arrays, the
#: dataset's float32 copy and the image of its file
KEPT_PER_BYTE = 2
DEFAULT_BUDGET = DEFAULT_MEMORY_MIB * 2**20


def read_trajectory(path: Path, budget_bytes: int = DEFAULT_BUDGET) -> np.ndarray:
    """One recorded trajectory as (frames, V, 3) float64, read within ``budget_bytes`` of
    memory; BadInput on anything else."""
    path = Path(path)
    data = load_plain(_read_regular(path, budget_bytes), str(path), budget_bytes)
    try:
        array = np.asarray(data, dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise BadInput(
            f"{path} is not a rectangular array of numbers; pass a (frames, 3, V) list"
        ) from exc
    return checked(array, str(path))


def checked(array: np.ndarray, name: str) -> np.ndarray:
    """``array`` (frames, 3, V) of file ``name`` as (frames, V, 3) float64; BadInput unless it
    has that shape, enough markers and frames, and finite numbers."""
    if array.ndim != 3 or array.shape[1] != 3:
        raise BadInput(f"{name} has shape {array.shape}, expected (frames, 3, markers)")
    if array.shape[2] < MIN_MARKERS:
        raise BadInput(
            f"{name} has {array.shape[2]} markers; at least {MIN_MARKERS} are needed "
            f"({HELD_PER_END} held at each end)"
        )
    if array.shape[0] < 3:
        raise BadInput(f"{name} has {array.shape[0]} frames; at least 3 are needed")
    if not np.isfinite(array).all():
        raise BadInput(f"{name} contains NaN or inf positions; clean or drop that file")
    return array.transpose(0, 2, 1).astype(np.float64)


def _read_regular(path: Path, limit: int) -> bytes:
    """The bytes of ``path``, a regular file of at most ``limit`` bytes; BadInput otherwise.
    Opened without blocking and checked once open, so a FIFO or device never stalls it."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise BadInput(f"{path} cannot be read ({exc.strerror}); pass readable files") from exc
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise BadInput(f"{path} is not a regular file (a FIFO, device or socket); pass files")
        data = f.read(limit + 1)  # no more than the budget, whatever the file claims or becomes
    if len(data) > limit:
        raise BadInput(
            f"{path} is over the budget's {limit / 2**20:.0f} MiB left; raise --max-memory-mib "
            "or import fewer files"
        )
    return data


def held_markers(n_markers: int) -> np.ndarray:
    """(V,) bool: the two markers at each end, which the grippers hold."""
    held = np.zeros(n_markers, dtype=bool)
    held[:HELD_PER_END] = held[-HELD_PER_END:] = True
    return held


def read_folder(
    folder: Path, budget_bytes: int = DEFAULT_BUDGET
) -> dict[str, list[tuple[str, np.ndarray]]]:
    """``{split: [(file stem, (frames, V, 3)), ...]}`` from ``folder/train`` and
    ``folder/eval`` (sorted by name), read within ``budget_bytes`` of memory; every file must
    have the same marker count."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BadInput(
            f"{folder} is not a folder; pass a DEFORM cable folder holding train/ and eval/"
        )
    found = {s: sorted((folder / s).glob("*.pkl")) for s in SPLITS if (folder / s).is_dir()}
    if not found.get("train"):
        raise BadInput(
            f"{folder}/train holds no .pkl files; pass a DEFORM cable folder (e.g. DLO1)"
        )
    out: dict[str, list[tuple[str, np.ndarray]]] = {}
    counts: dict[int, str] = {}
    for path in (p for files in found.values() for p in files):
        _require_utf8_name(path)
    kept = 0
    for split, files in found.items():
        out[split] = []
        for path in files:
            array = read_trajectory(path, max(0, budget_bytes - kept))
            kept += KEPT_PER_BYTE * array.nbytes
            counts.setdefault(array.shape[1], str(path))
            if len(counts) > 1:
                (a, first), (b, other) = list(counts.items())[:2]
                raise BadInput(
                    f"mixed marker counts: {first} has {a}, {other} has {b}; import one cable "
                    "per folder"
                )
            out[split].append((path.stem, array))
    return out


def _require_utf8_name(path: Path) -> None:
    """The file's name becomes an episode name in the dataset (UTF-8 text)."""
    try:
        path.name.encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise BadInput(f"{shown}: the file name is not valid UTF-8; rename the file") from None


def read_recordings(
    folder: Path, budget_bytes: int = DEFAULT_BUDGET
) -> tuple[dict[str, list[tuple[str, np.ndarray]]], np.ndarray]:
    """:func:`read_folder`'s recordings and the (V,) held markers (DEFORM's two per end); or,
    from a `dlo import` run directory (``folder/dataset.h5``, no ``train/``), its dataset's
    episodes (any format it imported, in metres) and its held markers (``--held``)."""
    data = imported(folder)
    if data is not None:
        return _episodes(data), np.asarray(data.held, dtype=bool)
    found = read_folder(folder, budget_bytes)
    return found, held_markers(next(iter(found.values()))[0][1].shape[1])


def imported(folder: Path | None) -> MarkerDataset | None:
    """The marker dataset of the `dlo import` run directory ``folder``; None if it is not one
    (a cable folder holds train/)."""
    if folder is None or (Path(folder) / "train").exists():
        return None
    if not (Path(folder) / DATASET_FILE).is_file():
        return None
    data = load_dataset(Path(folder))
    if not isinstance(data, MarkerDataset):
        raise BadInput(f"{folder} holds a rod dataset; pass a `dlo import` run or a cable folder")
    return data


def _episodes(data: MarkerDataset) -> dict[str, list[tuple[str, np.ndarray]]]:
    """``{split: [(name, (frames, V, 3) float64), ...]}`` of a marker dataset."""
    return {
        split: [
            (name, episode.astype(np.float64))
            for name, episode in zip(data.episode_names(split), data.episodes(split), strict=True)
        ]
        for split in SPLITS
        if data.episode_names(split)
    }
