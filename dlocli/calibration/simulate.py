"""Simulated marker data of a (calibrated) rod under held-marker motion like a recording's.

A simulated trajectory takes the held markers' motion of one recorded train trajectory,
moved rigidly: rotated about the vertical through its centre by a uniform random angle,
mirrored (y -> -y about its centre) with probability 1/2, and played backwards with
probability 1/2. The rod replays that motion (:func:`replay`); its simulated markers, held
ones included, are the data. Physics has no preferred heading and no arrow of time in the
boundary motion, so each draw is motion the real grippers could have made, but none that
they made.
"""

from __future__ import annotations

import numpy as np

from dlocli.backends.base import Backend
from dlocli.calibration.replay import ReplaySettings, replay
from dlocli.events import Callback, Event


def moved_rigidly(recording: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A (T,V,3) recording rotated about the vertical, perhaps mirrored and reversed."""
    centre = recording.reshape(-1, 3).mean(0)
    angle = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if rng.random() < 0.5:
        turn = turn @ np.diag([1.0, -1.0, 1.0])
    moved = (recording - centre) @ turn.T + centre
    return moved[::-1].copy() if rng.random() < 0.5 else moved


def simulate_markers(
    backend: Backend,
    recordings: list[np.ndarray],
    arc: np.ndarray,
    count: int,
    seed: int,
    settings: ReplaySettings,
    progress: Callback | None = None,
) -> tuple[list[np.ndarray], int]:
    """``count`` simulated (T,V,3) trajectories (recording i mod n drives draw i) and the
    number of draws dropped because the simulation diverged; ``progress`` gets an Event
    after each draw."""
    rng = np.random.default_rng(seed)
    out, dropped = [], 0
    for i in range(count):
        result = replay(backend, moved_rigidly(recordings[i % len(recordings)], rng), arc, settings)
        if result.diverged_at is None:
            out.append(result.simulated)
        else:
            dropped += 1
        if progress is not None:
            progress(Event("draw", i + 1, count))
    return out, dropped
