"""Point-cloud frame sequences as ``.npz`` files: what a camera recorded, for the tracker.

One archive holds F frames:

- ``points`` (P,3) float: every frame's points, one frame after the other, world frame (m);
- ``counts`` (F,) int: how many points each frame has (they sum to P);
- ``times`` (F,) float: seconds, increasing;
- ``extrinsics`` (F,4,4) or (4,4) float: camera to world (a camera on a tripod: one);
- ``intrinsics`` (3,3) float, optional: the pinhole's, in pixels;
- ``held`` (F,H,3) float, optional: where the robot held the held markers (its grippers).

Read with ``allow_pickle=False``, each array's size checked from its header before it is
read. A file with NaN or infinite values, no points at all, or a first frame without points
is refused in one line.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlocli.errors import BadInput
from dlocli.io import atomic_path
from dlocli.limits import refuse_unless_fits
from dlocli.recorded_cables.formats import require_regular_file
from dlocli.tracking.camera import CloudFrame

REQUIRED = ("points", "counts", "times", "extrinsics")
OPTIONAL = ("intrinsics", "held")


@dataclass
class FrameSequence:
    """Frames read from a file, and the held markers' positions per frame if recorded."""

    frames: list[CloudFrame]
    held: np.ndarray | None


def save_frames(path: Path | str, frames: list[CloudFrame], held: np.ndarray | None = None):
    """Write ``frames`` (and ``held`` (F,H,3)) to ``path`` atomically."""
    arrays = {
        "points": np.concatenate([f.points for f in frames]).astype(np.float32),
        "counts": np.array([len(f.points) for f in frames], dtype=np.int64),
        "times": np.array([f.time for f in frames], dtype=np.float64),
        "extrinsics": np.stack([f.extrinsics for f in frames]),
        "intrinsics": frames[0].intrinsics,
    }
    if held is not None:
        arrays["held"] = np.asarray(held, dtype=np.float64)
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as out:
        np.savez_compressed(out, **arrays)


def load_frames(path: Path | str) -> FrameSequence:
    """The frames of a ``.npz`` sequence (module docstring), or BadInput naming the fault."""
    path = Path(path)
    arrays = _read_arrays(path)
    missing = [key for key in REQUIRED if key not in arrays]
    if missing:
        raise BadInput(
            f"{path} lacks {', '.join(missing)}; a frame sequence holds points, counts, "
            "times and extrinsics (dlocli.tracking.frames)"
        )
    points, counts, times = arrays["points"], arrays["counts"], arrays["times"]
    count = len(counts)
    _check_shape(path, "points", points, (None, 3))
    _check_shape(path, "counts", counts, (count,))
    _check_shape(path, "times", times, (count,))
    extrinsics = arrays["extrinsics"]
    if extrinsics.shape == (4, 4):
        extrinsics = np.broadcast_to(extrinsics, (count, 4, 4))
    _check_shape(path, "extrinsics", extrinsics, (count, 4, 4))
    intrinsics = arrays.get("intrinsics", np.eye(3))
    _check_shape(path, "intrinsics", intrinsics, (3, 3))
    held = arrays.get("held")
    if held is not None:
        _check_shape(path, "held", held, (count, None, 3))
    _check_values(path, arrays, counts, times)
    starts = np.concatenate([[0], np.cumsum(counts)])
    frames = [
        CloudFrame(
            points[starts[i] : starts[i + 1]].astype(np.float64),
            extrinsics[i].astype(np.float64),
            intrinsics.astype(np.float64),
            float(times[i]),
            np.full(int(counts[i]), -1, dtype=np.int32),
        )
        for i in range(count)
    ]
    return FrameSequence(frames, None if held is None else held.astype(np.float64))


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    require_regular_file(path, "a .npz frame file")
    arrays = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.namelist():
                key = member.removesuffix(".npy")
                if key in REQUIRED + OPTIONAL:
                    with archive.open(member) as f:
                        arrays[key] = _read_member(f, f"{path}:{key}")
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise BadInput(f"{path} is not a readable .npz archive ({str(exc)[:80]})") from exc
    return arrays


def _read_member(f, name: str) -> np.ndarray:
    """One array, its size checked from its header before it is read."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    if dtype.kind not in "fiu":
        raise BadInput(f"{name} holds {dtype} values; save numbers")
    refuse_unless_fits(name, 8.0 * float(np.prod(shape)), "record fewer frames per file")
    f.seek(0)
    return np.lib.format.read_array(f, allow_pickle=False)


def _check_shape(path: Path, key: str, array: np.ndarray, shape: tuple) -> None:
    fits = array.ndim == len(shape) and all(
        want is None or have == want for have, want in zip(array.shape, shape, strict=True)
    )
    if not fits:
        wanted = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise BadInput(f"{path}: {key} has shape {array.shape}, expected {wanted}")


def _check_values(path: Path, arrays: dict, counts: np.ndarray, times: np.ndarray) -> None:
    for key, array in arrays.items():
        if not np.isfinite(array).all():
            raise BadInput(f"{path}: {key} holds NaN or infinite values; drop those points")
    if counts.dtype.kind not in "iu" or (counts < 0).any() or counts.sum() != len(arrays["points"]):
        raise BadInput(
            f"{path}: counts must be whole numbers >= 0 summing to the "
            f"{len(arrays['points'])} points"
        )
    if len(counts) == 0 or counts.sum() == 0:
        raise BadInput(f"{path} holds no points; record the cable's clouds")
    if counts[0] == 0:
        raise BadInput(f"{path}: the first frame has no points; the tracker starts from it")
    if (np.diff(times) <= 0).any():
        raise BadInput(f"{path}: times must increase from frame to frame")
