"""The DEFORM benchmark protocol (Chen et al., CoRL 2024, Table 1) and our view of it.

Start from frame 1 (velocity = frame 1 - frame 0) and predict frames 2 ... T open loop: at
every step only the held markers are given (their recorded positions); every other marker
comes from the model's own previous prediction. Score: mean absolute error per coordinate
over all markers (held ones included) over the predicted frames, in centimetres. Our view:
mean Euclidean error of the free markers in millimetres at fixed horizons.
"""

from __future__ import annotations

import numpy as np

FIRST_PREDICTED = 2  # frames 0 and 1 are given
HORIZONS_S = (0.5, 1.0, 2.0, 5.0)


def deform_score_cm(predicted: np.ndarray, recorded: np.ndarray) -> float:
    """DEFORM's score of one rollout: (T, V, 3) predicted (frames 0-1 ignored) and recorded."""
    diff = predicted[FIRST_PREDICTED:] - recorded[FIRST_PREDICTED:]
    return float(np.abs(diff).mean() * 100.0)


def freeze(recorded: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Reference: the free markers stay where they are at frame 1; held markers exact."""
    out = np.repeat(recorded[1:2], len(recorded), axis=0)
    out[:, held] = recorded[:, held]
    return out


def straight_line(recorded: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Reference: the free markers evenly spaced on the line between the innermost held
    markers (vertices 1 and V-2 on a DEFORM cable); held markers exact."""
    inner = np.flatnonzero(held)
    left, right = inner[inner < len(held) // 2].max(), inner[inner >= len(held) // 2].min()
    frac = (np.arange(len(held)) - left) / (right - left)
    line = recorded[:, left : left + 1] + frac[None, :, None] * (
        recorded[:, right : right + 1] - recorded[:, left : left + 1]
    )
    return np.where(held[None, :, None], recorded, line)


REFERENCES = {"freeze": freeze, "straight_line": straight_line}


def horizon_errors_mm(
    predicted: np.ndarray, recorded: np.ndarray, held: np.ndarray, rate_hz: float
) -> dict[str, float]:
    """Mean Euclidean error of the free markers (mm) at each horizon after frame 1 (the
    last recorded frame stands for horizons beyond the recording)."""
    out = {}
    for h in HORIZONS_S:
        t = min(1 + int(round(h * rate_hz)), len(recorded) - 1)
        err = np.linalg.norm(predicted[t, ~held] - recorded[t, ~held], axis=-1)
        out[f"{h:g}s"] = float(err.mean() * 1000.0)
    return out


def error_by_frame_mm(predicted: np.ndarray, recorded: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(T,) mean Euclidean error of the free markers per frame, mm."""
    return np.linalg.norm(predicted[:, ~held] - recorded[:, ~held], axis=-1).mean(1) * 1000.0
