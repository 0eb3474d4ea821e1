"""Frame times of a recording and its resampling to the control rate.

A recording with timestamps (a CSV's ``time`` column, a ROS 2 bag) is read at its own times;
one without is at ``--rate-hz``. Its rate is uniform when every interval is within
:data:`ON_TIME` of the median one: then it is kept frame for frame (DEFORM's pickles stay
bit-identical). A longer interval is a gap of frames the recorder missed (refused past
``--fill-gaps`` frames), a shorter or jittered one an irregular interval; both are reported.
``--control-hz`` (default: the recording's own rate) resamples every recording by linear
interpolation onto a uniform clock from its first frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dlocli.errors import BadInput
from dlocli.recorded_cables import deform
from dlocli.recorded_cables.spec import DEFAULT_RATE_HZ, ImportSpec

#: how far (a fraction of the median interval) an interval may be from it and be on time
ON_TIME = 0.01
#: an interval this many times the median one or longer skips frames
GAP = 1.5
#: significant digits of a rate read from timestamps (they are rounded by the recorder)
RATE_DIGITS = 6


@dataclass
class Clock:
    """What a recording's frame times say."""

    rate_hz: float  # its frame rate: the mean one, over the intervals that skip no frame
    uniform: bool
    irregular: int = 0  # intervals off the median by more than ON_TIME
    longest_gap_s: float = 0.0  # the longest interval
    missing: int = 0  # frames missed in the longest interval


def clock(times: np.ndarray, name: str) -> Clock:
    """The clock of frame times (s); BadInput unless finite and increasing."""
    steps = np.diff(times)
    if not np.isfinite(times).all():
        raise BadInput(f"{name}: a frame time is NaN or infinite; write finite seconds")
    if (steps <= 0).any():
        frame = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise BadInput(
            f"{name}: frame {frame}'s time {times[frame]:.6g} s is not after the one before; "
            "write the frames in time order, each at its own time"
        )
    median = float(np.median(steps))
    off = np.abs(steps - median) > ON_TIME * median
    if not off.any():
        mean = (len(times) - 1) / float(times[-1] - times[0])
        return Clock(_rounded(mean), uniform=True, longest_gap_s=float(steps.max()))
    # the nominal interval: the mean of those that skip no frame (jitter averages out)
    nominal = float(steps[steps < GAP * median].mean())
    return Clock(
        _rounded(1.0 / nominal),
        uniform=False,
        irregular=int(off.sum()),
        longest_gap_s=float(steps.max()),
        missing=max(0, int(round(steps.max() / nominal)) - 1),
    )


def _rounded(rate: float) -> float:
    return float(f"{rate:.{RATE_DIGITS}g}")


def resample(positions: np.ndarray, times: np.ndarray, rate_hz: float) -> np.ndarray:
    """(frames, V, 3) at ``times`` -> at ``times[0] + k / rate_hz`` up to the last time,
    each coordinate interpolated linearly between the frames around it."""
    span = float(times[-1] - times[0])
    grid = times[0] + np.arange(int(np.floor(span * rate_hz * (1 + 1e-9))) + 1) / rate_hz
    flat = positions.reshape(len(positions), -1)
    out = np.empty((len(grid), flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.interp(grid, times, flat[:, j])
    return out.reshape(len(grid), *positions.shape[1:])


def to_control_rate(
    read: dict[str, list[Any]], spec: ImportSpec, budget_bytes: int
) -> tuple[dict[str, list[tuple[str, np.ndarray]]], float, dict[str, Any]]:
    """``{split: [(name, (frames, V, 3)), ...]}`` at the control rate from the recordings
    ``read`` (:class:`~dlocli.recorded_cables.formats.Trajectory`), that rate, and the report for
    the summary; BadInput for bad times, gaps past ``spec.fill_gaps`` or rates that differ
    without ``spec.control_hz``."""
    clocks = {}
    for split, items in read.items():
        for t in items:
            clocks[f"{split}/{t.name}"] = _checked_clock(t, spec, f"{spec.source}/{split}")
    rates = sorted({c.rate_hz for c in clocks.values()})
    target = spec.control_hz
    if target is None:
        if rates[-1] > rates[0] * (1 + ON_TIME):
            first, other = (next(n for n, c in clocks.items() if c.rate_hz == r) for r in rates)
            raise BadInput(
                f"recordings at different rates ({first} {rates[0]:g} Hz, {other} "
                f"{rates[-1]:g} Hz); pass --control-hz to resample them all to one"
            )
        target = rates[0]
    out: dict[str, list[tuple[str, np.ndarray]]] = {}
    kept, resampled = 0, False
    for split, items in read.items():
        out[split] = []
        for t in items:
            key = f"{split}/{t.name}"
            c = clocks[key]
            array = t.positions
            as_recorded = c.uniform and spec.control_hz in (None, c.rate_hz)
            if not as_recorded:
                times = t.times if t.times is not None else np.arange(len(array)) / c.rate_hz
                array = _resampled(array, times, target, key, budget_bytes - kept)
                resampled = True
            kept += deform.KEPT_PER_BYTE * array.nbytes
            out[split].append((t.name, array))
    report: dict[str, Any] = {"rate_hz": target}
    if resampled:
        report["resampled_from_hz"] = rates
    irregular = {
        n: {"intervals": c.irregular, "longest_gap_s": round(c.longest_gap_s, 6)}
        for n, c in clocks.items()
        if not c.uniform
    }
    if irregular:
        report["irregular_timestamps"] = irregular
    return out, target, report


def _checked_clock(t: Any, spec: ImportSpec, where: str) -> Clock:
    name = f"{where}/{t.name}"
    if t.times is None:
        return Clock(spec.rate_hz or DEFAULT_RATE_HZ, uniform=True)
    c = clock(t.times, name)
    if spec.rate_hz is not None and abs(c.rate_hz - spec.rate_hz) > ON_TIME * spec.rate_hz:
        raise BadInput(
            f"{name}: its timestamps say {c.rate_hz:g} Hz, --rate-hz {spec.rate_hz:g}; drop "
            "--rate-hz (recordings with timestamps are read at their own times)"
        )
    if c.missing > spec.fill_gaps:
        raise BadInput(
            f"{name} has {c.irregular} irregular frame intervals, the longest "
            f"{c.longest_gap_s:.4g} s ({c.missing} frames missed); pass --fill-gaps "
            f"{c.missing} to interpolate across"
        )
    return c


def _resampled(
    array: np.ndarray, times: np.ndarray, rate_hz: float, name: str, budget: int
) -> np.ndarray:
    frames = int(np.floor(float(times[-1] - times[0]) * rate_hz * (1 + 1e-9))) + 1
    needed = deform.KEPT_PER_BYTE * 8 * frames * array.shape[1] * 3
    if needed > budget:
        raise BadInput(
            f"{name} resampled to {rate_hz:g} Hz would take {needed / 2**20:.0f} MiB, over "
            "the budget left; lower --control-hz or raise --max-memory-mib"
        )
    if frames < 3:
        raise BadInput(
            f"{name} has {frames} frames at {rate_hz:g} Hz; at least 3 are needed (raise "
            "--control-hz or record longer)"
        )
    return resample(array, times, rate_hz)
