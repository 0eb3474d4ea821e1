"""The env's observation: its parts in order, their shapes and bounds, for the full and the
markers observation (:mod:`dlocli.env.observation`)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from dlocli.specs import TaskSpec

#: bound of every position in the observation (metres); a diverged rod is clipped to it
POSITION_BOUND = 10.0
#: bound of every velocity component in the observation (m/s, 1/s)
VELOCITY_BOUND = 100.0


def observation_layout(
    n: int, velocity: bool = False, markers: int | None = None
) -> dict[str, tuple[int, ...]]:
    """The parts of the flat observation, in order, with their shapes (N = ``n`` segments);
    with ``markers`` = M, those of the markers observation (:mod:`dlocli.env.observation`)."""
    if markers is not None:
        layout = {"markers": (markers, 3), "visible": (markers, 1), "grippers": (2, 7),
                  "goal": (markers, 3)}  # fmt: skip
        if velocity:
            layout["velocities"] = (markers, 3)
        return layout
    layout = {"positions": (n, 3), "quaternions": (n, 4), "grippers": (2, 7), "goal": (n, 3)}
    if velocity:
        layout["velocities"] = (n, 7)
    return layout


def observed_markers(task: TaskSpec) -> int | None:
    """M with the task's markers observation, None with the full one."""
    observation = task.observation
    return observation.marker_count() if observation.reports_markers else None


#: bound of each column of every part of the observation (rows repeat it)
_ROW_BOUNDS = {
    "positions": [POSITION_BOUND] * 3,
    "quaternions": [1.0] * 4,
    "grippers": [POSITION_BOUND] * 3 + [1.0] * 4,
    "goal": [POSITION_BOUND] * 3,
    "velocities": [VELOCITY_BOUND] * 7,
    "markers": [POSITION_BOUND] * 3,
    "visible": [1.0],
}


def observation_space(n: int, velocity: bool = False, markers: int | None = None) -> gym.spaces.Box:
    """Positions within +-POSITION_BOUND m, quaternion components within [-1, 1], velocity
    components (if observed) within +-VELOCITY_BOUND, visibility flags within [0, 1]."""
    layout = observation_layout(n, velocity, markers)
    # a row's bounds are the first columns of its part's (markers' velocities: 3 of 7)
    rows = {k: _ROW_BOUNDS[k][: shape[1]] for k, shape in layout.items()}
    high = np.concatenate([np.tile(rows[k], shape[0]) for k, shape in layout.items()])
    flags = np.concatenate(
        [np.full(int(np.prod(shape)), k == "visible") for k, shape in layout.items()]
    )
    low = np.where(flags, 0.0, -high)
    return gym.spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)


def observation_slices(layout: dict[str, tuple[int, ...]]) -> dict[str, slice]:
    """Where each part of ``layout`` lies in the flat observation."""
    slices, start = {}, 0
    for name, shape in layout.items():
        size = int(np.prod(shape))
        slices[name] = slice(start, start + size)
        start += size
    return slices
