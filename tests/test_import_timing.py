"""`dlo import` reads frame times (a CSV's time column, a bag's stamps, else --rate-hz) and
resamples to --control-hz; irregular times and gaps are reported, long gaps refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dlocli.data import load_dataset

from tiny import dlo_import

MARKERS = 6
FREQUENCY_HZ, AMPLITUDE_M = 1.3, 0.05


def motion(t: np.ndarray) -> np.ndarray:
    """(len(t), V, 3): a cable whose markers swing sinusoidally, in metres."""
    s = np.linspace(0, 1, MARKERS)[None, :]
    wave = AMPLITUDE_M * np.sin(2 * np.pi * FREQUENCY_HZ * t[:, None] + 3 * s)
    return np.stack([0.8 * s + wave, 0.1 * wave, 0.5 - 0.2 * np.sin(np.pi * s) + wave * s], -1)


def write_csv(path: Path, times: np.ndarray) -> Path:
    """The motion at ``times`` (s) as a motion-capture CSV with a time column."""
    header = ["frame", "time"] + [f"m{j}_{a}" for j in range(MARKERS) for a in "xyz"]
    rows = [",".join(header)]
    for k, (t, frame) in enumerate(zip(times, motion(times), strict=True)):
        rows.append(",".join([str(k), f"{t:.6f}", *(f"{x:.9f}" for x in frame.ravel())]))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path


def test_120_hz_resampled_to_100_hz_follows_the_motion(tmp_path: Path, capsys) -> None:
    write_csv(tmp_path / "C" / "train" / "a.csv", np.arange(61) / 120.0)  # 0.5 s
    assert dlo_import(tmp_path / "C", tmp_path / "out", "--control-hz", "100") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rate_hz"] == 100.0 and summary["resampled_from_hz"] == [120.0]
    data = load_dataset(tmp_path / "out")
    assert data.rate_hz == 100.0
    frames = data.episodes("train")[0]
    truth = motion(np.arange(51) / 100.0)
    assert frames.shape == truth.shape
    # linear interpolation errs by at most h^2/8 max|f''|, plus the CSV's and float32 digits
    bound = (1 / 120) ** 2 / 8 * AMPLITUDE_M * (2 * np.pi * FREQUENCY_HZ) ** 2 + 1e-6
    error = np.abs(frames - truth).max()
    assert error <= bound, (error, bound)
    unresampled = np.abs(motion(np.arange(51) / 120.0) - truth).max()  # 120 Hz read as 100
    assert unresampled > 100 * bound


def test_uniform_times_keep_the_frames_and_give_the_rate(tmp_path: Path, capsys) -> None:
    times = np.arange(40) / 120.0
    write_csv(tmp_path / "C" / "train" / "a.csv", times)
    assert dlo_import(tmp_path / "C", tmp_path / "out") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rate_hz"] == 120.0 and "resampled_from_hz" not in summary
    assert "irregular_timestamps" not in summary
    frames = load_dataset(tmp_path / "out").episodes("train")[0]
    np.testing.assert_allclose(frames, motion(times), atol=1e-6)


def test_jittered_times_are_reported_and_resampled(tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(0)
    times = np.arange(60) / 100.0 + rng.uniform(-0.002, 0.002, 60) * (np.arange(60) % 7 == 3)
    write_csv(tmp_path / "C" / "train" / "a.csv", times)
    assert dlo_import(tmp_path / "C", tmp_path / "out") == 0
    summary = json.loads(capsys.readouterr().out)
    report = summary["irregular_timestamps"]["train/a"]
    steps = np.diff(np.round(times, 6))
    off = np.abs(steps - np.median(steps)) > 0.01 * np.median(steps)
    assert report == {"intervals": int(off.sum()), "longest_gap_s": pytest.approx(steps.max())}
    # the mean interval: off by at most the two end frames' jitter over the span
    assert summary["rate_hz"] == pytest.approx(100.0, rel=2 * 0.002 / (times[-1] - times[0]))


def test_missing_frames_are_refused_unless_filled(tmp_path: Path, capsys) -> None:
    times = np.delete(np.arange(50) / 100.0, [20, 21, 22])  # 3 frames missed
    write_csv(tmp_path / "C" / "train" / "a.csv", times)
    out = tmp_path / "out"
    assert dlo_import(tmp_path / "C", out) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "3 frames missed" in err and "--fill-gaps 3" in err
    assert not out.exists()
    assert dlo_import(tmp_path / "C", out, "--fill-gaps", "3") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["irregular_timestamps"]["train/a"] == {
        "intervals": 1, "longest_gap_s": pytest.approx(0.04)
    }  # fmt: skip
    frames = load_dataset(out).episodes("train")[0]
    assert len(frames) == 50
    np.testing.assert_allclose(frames, motion(np.arange(50) / 100.0), atol=2e-3)


def test_arrays_at_a_stated_rate_are_resampled_too(tmp_path: Path, capsys) -> None:
    (tmp_path / "C" / "train").mkdir(parents=True)
    np.save(tmp_path / "C" / "train" / "a.npy", motion(np.arange(61) / 120.0))
    flags = ("--rate-hz", "120", "--control-hz", "50")
    assert dlo_import(tmp_path / "C", tmp_path / "out", *flags) == 0
    frames = load_dataset(tmp_path / "out").episodes("train")[0]
    truth = motion(np.arange(26) / 50.0)
    assert frames.shape == truth.shape
    assert np.abs(frames - truth).max() < 1e-3


def _two_rates(root: Path) -> Path:
    write_csv(root / "train" / "a.csv", np.arange(40) / 100.0)
    write_csv(root / "eval" / "b.csv", np.arange(48) / 120.0)
    return root


BAD = {
    "rates differ": (_two_rates, (), "pass --control-hz"),
    "--rate-hz contradicts": (
        lambda r: write_csv(r / "train" / "a.csv", np.arange(40) / 120.0),
        ("--rate-hz", "100"),
        "its timestamps say 120 Hz",
    ),
    "time goes back": (
        lambda r: write_csv(r / "train" / "a.csv", np.r_[0:20, 5, 21:40] / 100),
        (),
        "not after the one before",
    ),
    "too few frames": (
        lambda r: write_csv(r / "train" / "a.csv", np.arange(4) / 100.0),
        ("--control-hz", "20"),
        "at least 3",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_times_get_one_line_and_nothing_is_written(tmp_path: Path, capsys, case) -> None:
    make, flags, words = BAD[case]
    make(tmp_path / "C")
    out = tmp_path / "out"
    assert dlo_import(tmp_path / "C", out, *flags) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    assert not out.exists()


def test_different_rates_resample_to_one_control_rate(tmp_path: Path) -> None:
    _two_rates(tmp_path / "C")
    assert dlo_import(tmp_path / "C", tmp_path / "out", "--control-hz", "100") == 0
    data = load_dataset(tmp_path / "out")
    assert [len(e) for e in data.episodes()] == [40, 40]
