"""Field-by-field checks of a dataset file as loaded (formats: :mod:`dlocli.data.rod`,
:mod:`dlocli.data.markers`).

Each check takes the file's arrays by name (and its attributes), skips a field the file does
not hold (a marker dataset has positions only), and raises BadInput naming the field, what
it holds and the fix. :func:`check_fields` runs them all, after the arrays were found to be
finite numbers of consistent shapes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dlocli.errors import BadInput

#: largest distance from the origin (m) of a stored position: far beyond any workspace or
#: recording room; more is a unit error or corruption
MAX_POSITION = 100.0
#: how far a stored quaternion's norm may be from 1 (float32 rounding over a long episode)
QUATERNION_NORM_TOLERANCE = 1e-3
#: how far a stored action may be beyond [-1, 1] (float32 rounding)
ACTION_TOLERANCE = 1e-5


def check_fields(
    arrays: dict[str, np.ndarray], attrs: dict[str, Any], path: Path, newest_version: int
) -> None:
    """BadInput on the first field that breaks the format."""
    check_format_version(attrs, path, newest_version)
    check_episode_lengths(arrays, path)
    check_per_episode_fields(arrays, path)
    check_grippers(arrays, path)
    check_unit_quaternions(arrays, path)
    check_actions_in_range(arrays, path)
    check_positions_bounded(arrays, path)
    check_observed_markers(arrays, path)


def check_format_version(attrs: dict[str, Any], path: Path, newest_version: int) -> None:
    version = attrs.get("format_version")
    if not isinstance(version, int) or not 1 <= version <= newest_version:
        raise BadInput(
            f"dataset {path}: format_version {str(version)[:40]} is not one this dlocli reads "
            f"(1 to {newest_version}); upgrade dlocli or re-collect it"
        )


def check_episode_lengths(arrays: dict[str, np.ndarray], path: Path) -> None:
    lengths = arrays["episode_lengths"]
    if lengths.ndim != 1 or lengths.dtype.kind not in "iu":
        raise BadInput(f"dataset {path}: episode_lengths must be integers (E,); re-collect it")
    if len(lengths) == 0:
        raise BadInput(f"dataset {path} holds no episodes; collect at least one")
    # an episode whose physics diverged on its first step is stored with no transition
    diverged = arrays.get("diverged")
    may_be_empty = (
        diverged.astype(bool) if diverged is not None and diverged.shape == lengths.shape else False
    )
    bad = (lengths < 0) | ((lengths == 0) & ~may_be_empty)
    if bad.any():
        raise BadInput(
            f"dataset {path}: episode_lengths holds {int(lengths[bad][0])}; every episode "
            "needs at least one transition (none only if it diverged); re-collect it"
        )


def check_per_episode_fields(arrays: dict[str, np.ndarray], path: Path) -> None:
    """One reward per transition, one ``diverged`` flag and one goal per episode."""
    lengths = arrays["episode_lengths"]
    expected = {"rewards": int(lengths.sum()), "diverged": len(lengths), "goals": len(lengths)}
    for name, rows in expected.items():
        if name in arrays and len(arrays[name]) != rows:
            raise BadInput(
                f"dataset {path}: {name} has {len(arrays[name])} rows, not {rows}; re-collect it"
            )


def check_grippers(arrays: dict[str, np.ndarray], path: Path) -> None:
    if "grippers" in arrays and arrays["grippers"].shape[1:] != (2, 7):
        raise BadInput(
            f"dataset {path}: grippers rows are {arrays['grippers'].shape[1:]}, not (2, 7) "
            "(position and quaternion of each gripper); re-collect it"
        )


def check_unit_quaternions(arrays: dict[str, np.ndarray], path: Path) -> None:
    if "quaternions" not in arrays:
        return
    norms = np.linalg.norm(arrays["quaternions"].astype(np.float64), axis=-1)
    worst = float(np.abs(norms - 1).max(initial=0.0))
    if worst > QUATERNION_NORM_TOLERANCE:
        raise BadInput(
            f"dataset {path}: quaternions are not unit (a norm is {worst:.3g} off 1, more than "
            f"{QUATERNION_NORM_TOLERANCE}); re-collect it"
        )


def check_actions_in_range(arrays: dict[str, np.ndarray], path: Path) -> None:
    if "actions" not in arrays:
        return
    largest = float(np.abs(arrays["actions"]).max(initial=0.0))
    if largest > 1 + ACTION_TOLERANCE:
        raise BadInput(
            f"dataset {path}: actions reach {largest:.3g}, outside [-1, 1] (commands are "
            "scaled to the maximum velocities); re-collect it"
        )


def check_positions_bounded(arrays: dict[str, np.ndarray], path: Path) -> None:
    for name in ("positions", "goals"):
        if name in arrays:
            largest = float(np.abs(arrays[name].astype(np.float64)).max(initial=0.0))
            if largest > MAX_POSITION:
                raise BadInput(
                    f"dataset {path}: {name} reach {largest:.3g} m from the origin, more than "
                    f"{MAX_POSITION:g} m (positions are in metres); re-collect it"
                )


def check_observed_markers(arrays: dict[str, np.ndarray], path: Path) -> None:
    """The markers observation's optional arrays: both or neither, (S, M, 3) finite
    positions and (S, M) flags, one row per state."""
    markers, visible = arrays.get("markers"), arrays.get("visible")
    if markers is None and visible is None:
        return
    states = len(arrays["positions"])
    ok = (
        markers is not None and visible is not None
        and markers.ndim == 3 and markers.shape[0] == states and markers.shape[2] == 3
        and markers.dtype.kind == "f" and bool(np.isfinite(markers).all())
        and visible.shape == markers.shape[:2] and visible.dtype.kind == "b"
    )  # fmt: skip
    if not ok:
        raise BadInput(
            f"dataset {path}: markers and visible must be (S, M, 3) finite positions and "
            "(S, M) flags, one row per state; re-collect it"
        )
