"""Read DEFORM trajectory files (Chen et al., CoRL 2024, repository roahmlab/DEFORM).

Each ``.pkl`` is a pickled nested list of floats, shape (frames, 3, V): x/y/z in metres of V
markers along the cable. Pickles can run code when loaded, so they are read with an
unpickler that refuses every global: a plain list of floats loads, anything that names a
class or function is refused before it is built.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from dlocli.errors import BadInput

SPLITS = ("train", "eval")
MIN_MARKERS = 4  # two held at each end
HELD_PER_END = 2
MAX_FILE_BYTES = 256 * 2**20


class _NoGlobals(pickle.Unpickler):
    """An unpickler for plain data: every global (class, function) is refused."""

    def find_class(self, module: str, name: str) -> None:
        raise pickle.UnpicklingError(f"it names {module}.{name}")


def read_trajectory(path: Path) -> np.ndarray:
    """One recorded trajectory as (frames, V, 3) float64; BadInput on anything else."""
    path = Path(path)
    if path.stat().st_size > MAX_FILE_BYTES:
        raise BadInput(f"{path} is over {MAX_FILE_BYTES >> 20} MiB; not a trajectory file")
    try:
        with open(path, "rb") as f:
            data = _NoGlobals(f).load()
    except pickle.UnpicklingError as exc:
        raise BadInput(
            f"{path} refused: {exc} (only plain lists of numbers are loaded; code in a pickle "
            "is never run); pass the DEFORM data files"
        ) from exc
    except (EOFError, ValueError, TypeError, IndexError, KeyError, MemoryError) as exc:
        raise BadInput(
            f"{path} is not a readable pickle ({type(exc).__name__}); re-download it"
        ) from exc
    try:
        array = np.asarray(data, dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise BadInput(
            f"{path} is not a rectangular array of numbers; pass a (frames, 3, V) list"
        ) from exc
    if array.ndim != 3 or array.shape[1] != 3:
        raise BadInput(f"{path} has shape {array.shape}, expected (frames, 3, markers)")
    if array.shape[2] < MIN_MARKERS:
        raise BadInput(
            f"{path} has {array.shape[2]} markers; at least {MIN_MARKERS} are needed "
            f"({HELD_PER_END} held at each end)"
        )
    if array.shape[0] < 3:
        raise BadInput(f"{path} has {array.shape[0]} frames; at least 3 are needed")
    if not np.isfinite(array).all():
        raise BadInput(f"{path} contains NaN or inf positions; clean or drop that file")
    return array.transpose(0, 2, 1).copy()


def held_markers(n_markers: int) -> np.ndarray:
    """(V,) bool: the two markers at each end, which the grippers hold."""
    held = np.zeros(n_markers, dtype=bool)
    held[:HELD_PER_END] = held[-HELD_PER_END:] = True
    return held


def read_folder(folder: Path) -> dict[str, list[tuple[str, np.ndarray]]]:
    """``{split: [(file stem, (frames, V, 3)), ...]}`` from ``folder/train`` and
    ``folder/eval`` (sorted by name); every file must have the same marker count."""
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
    for split, files in found.items():
        out[split] = []
        for path in files:
            array = read_trajectory(path)
            counts.setdefault(array.shape[1], str(path))
            if len(counts) > 1:
                (a, first), (b, other) = list(counts.items())[:2]
                raise BadInput(
                    f"mixed marker counts: {first} has {a}, {other} has {b}; import one cable "
                    "per folder"
                )
            out[split].append((path.stem, array))
    return out
