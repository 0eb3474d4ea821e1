"""Goal files: reading and writing one, and refusing goals the rod cannot take."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dlocli.backends.base import Backend
from dlocli.errors import BadInput
from dlocli.io import atomic_path


def load_goal(path: Path, n_segments: int) -> np.ndarray:
    """Read a goal file: .npy, float (N,3), finite. BadInput naming the expected format."""
    path = Path(path)
    expected = f"expected a .npy file holding a float array of shape ({n_segments}, 3) in metres"
    if path.suffix != ".npy":
        raise BadInput(f"goal {path} is not a .npy file; {expected}")
    if not path.is_file():
        raise BadInput(f"goal {path} does not exist; {expected} (make one with `dlo goal`)")
    try:
        # memory-mapped: a header that claims terabytes is refused by its shape, not allocated
        goal = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file
        # numpy's own text (an allow_pickle hint for a text file) would mislead
        raise BadInput(f"goal {path} could not be read as a .npy array; {expected}") from exc
    if not isinstance(goal, np.ndarray):
        raise BadInput(f"goal {path} is an .npz archive, not one array; {expected}")
    if goal.dtype.kind not in "fiu" or goal.shape != (n_segments, 3):  # complex: refused
        raise BadInput(f"goal {path} has dtype {goal.dtype} and shape {goal.shape}; {expected}")
    if not np.all(np.isfinite(goal)):
        raise BadInput(f"goal {path} contains NaN or inf; {expected}")
    return goal.astype(np.float64)


def check_goal_reachable(
    goal: np.ndarray, backend: Backend, limits_margin: float = 0.2, name: str = "goal"
) -> None:
    """Refuse goals the rod cannot take: segments too far apart or outside the workspace;
    ``name`` says which goal in the message (its file)."""
    length = backend.rod.length
    # the reach first: a goal inside it has gaps that cannot overflow
    low = backend.limits.low - limits_margin - length
    high = backend.limits.high + limits_margin
    if np.any(goal < low) or np.any(goal > high):
        low_m = np.round(backend.limits.low, 2).tolist()
        high_m = np.round(backend.limits.high, 2).tolist()
        raise BadInput(f"{name} lies outside the grippers' reach (workspace {low_m}..{high_m} m)")
    seg = length / backend.n_segments
    gaps = np.linalg.norm(np.diff(goal, axis=0), axis=1)
    if np.any(gaps > 1.5 * seg) or np.any(gaps < 0.5 * seg):
        raise BadInput(
            f"{name}: segments {gaps.min():.3f}-{gaps.max():.3f} m apart but the rod's segments "
            f"are {seg:.3f} m long; the rod cannot take this shape (make one with `dlo goal`)"
        )


def save_goal(goal: np.ndarray, path: Path | str) -> None:
    """Write the goal .npy atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, goal)
