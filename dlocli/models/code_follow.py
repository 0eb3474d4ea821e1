"""Following a cable's code while it moves: a coded model's code re-picked during control.

A model with cable codes (:mod:`dlocli.models.cable_codes`) plans a cable it never trained on
with the mean code, which is no cable's. While the cable moves under control, its own motion
tells more: every ``every`` control steps, the last ``window`` observed frames of its
markers are one recording to :func:`~dlocli.models.code_pick.score_candidates` (the pick of
`dlo adapt`): each trained cable's code and their mean predict it open loop from its start,
the held markers given, and the lowest score is the code planned with from then on. No
gradient step: a pick costs one open-loop rollout of the window per candidate.

A tracker's markers are noisy, and a rollout starts from its first two frames' velocity: the
window's first :data:`START_FRAMES` frames are fitted by a line per coordinate of each free
marker, and the rollout starts from the fit's last two frames (the held markers are where the
robot's grippers put them: no noise).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from dlocli.models.code_pick import MEAN_CODE, best, score_candidates
from dlocli.models.marker_model import MarkerModel

#: frames at the window's start fitted by a line, the rollout's start (0.08 s at 100 Hz)
START_FRAMES = 8
#: the fewest frames a pick reads: the fitted start and as many predicted frames
MIN_WINDOW = 2 * START_FRAMES


@dataclass
class Pick:
    """A re-pick at control step ``step``: the code chosen (its name and row, None the mean),
    every candidate's score (cm) on the window, the frames read and how long it took."""

    step: int
    name: str
    row: int | None
    scores_cm: dict[str, float]
    frames: int
    ms: float

    def summary(self) -> dict[str, object]:
        """The pick as the control run's summary lists it."""
        scores = {k: (round(v, 4) if np.isfinite(v) else None) for k, v in self.scores_cm.items()}
        return {"step": self.step, "code": self.name, "scores_cm": scores,
                "frames": self.frames, "ms": round(self.ms, 1)}  # fmt: skip


class CodeFollower:
    """Re-picks ``model``'s code (:attr:`MarkerModel.cable`) from the frames it is shown:
    the mean code first, then every ``every`` steps the candidate (each trained cable's code,
    ``names[i]`` for row i, and their mean) that best predicts the last ``window`` frames."""

    def __init__(self, model: MarkerModel, names: list[str], every: int, window: int) -> None:
        if window < MIN_WINDOW:
            raise ValueError(f"window {window} < {MIN_WINDOW} frames")
        self.model, self.names, self.every = model, names, every
        self.frames: deque[np.ndarray] = deque(maxlen=window)
        self.picks: list[Pick] = []
        self.reset()

    def reset(self) -> None:
        """A new episode: the mean code, no frames seen."""
        self.frames.clear()
        self.picks = []
        self.model.cable = None
        self.current = MEAN_CODE

    def observe(self, step: int, frame: np.ndarray) -> Pick | None:
        """Keep the markers (V, 3) observed at control step ``step``; at every ``every``-th
        step with at least :data:`MIN_WINDOW` frames kept, re-pick (returned), else None."""
        self.frames.append(np.asarray(frame, dtype=np.float64))
        if step == 0 or step % self.every or len(self.frames) < MIN_WINDOW:
            return None
        return self.repick(step)

    def repick(self, step: int) -> Pick:
        """Score every candidate on the frames kept and plan with the best from now on."""
        began = time.perf_counter()
        held = self.model.held.cpu().numpy()
        window = smoothed_start(np.stack(self.frames), held)
        candidates = score_candidates(self.model, [window], held, self.names)
        chosen = best(candidates)
        self.model.cable, self.current = chosen.row, chosen.name
        scores = {c.name: c.mean_cm for c in candidates}
        pick = Pick(step, chosen.name, chosen.row, scores, len(self.frames),
                    1000.0 * (time.perf_counter() - began))  # fmt: skip
        self.picks.append(pick)
        return pick


def smoothed_start(frames: np.ndarray, held: np.ndarray, count: int = START_FRAMES) -> np.ndarray:
    """``frames`` (T, V, 3) from frame ``count - 2`` on, its first two frames' free markers
    replaced by a least-squares line through the first ``count`` frames (T >= count + 1):
    a start whose velocity the tracker's noise does not swamp."""
    t = np.arange(count, dtype=np.float64)
    design = np.stack([np.ones(count), t], 1)  # (count, 2)
    first = frames[:count].reshape(count, -1)
    coefficients, *_ = np.linalg.lstsq(design, first, rcond=None)
    fitted = (design[-2:] @ coefficients).reshape(2, *frames.shape[1:])
    out = frames[count - 2 :].copy()
    out[:2, ~held] = fitted[:, ~held]
    return out
