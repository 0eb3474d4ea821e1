"""How much the real cables damp their swing, against the calibrated rods under the same
motion.

DEFORM's grippers never rest (the longest stretch with both grips below 2 cm/s is 0.32 s, on
DLO1; none on DLO2-4), so the free swing after a stop, as swing_decay.py measures it on a
rod, cannot be read off a recording. Instead every recording (train and eval), and its replay
on each calibrated rod, is reduced to the motion of the cable's middle (its central free
markers) relative to the midpoint of its grips, sideways (horizontal, across the grips'
chord) and in-plane (across the chord in the vertical plane), and measured alike on real
and simulated cables (the first second left out: the replayed rod starts at rest there):

- a forced damped oscillator fitted by least squares, q'' = -2 zeta omega q' - omega^2 q +
  gripper terms (the chord midpoint's acceleration, both end tangents, the chord's length
  and gravity across it) + a constant per recording: zeta and omega pooled over the
  recordings, the spread from 200 bootstrap draws of the recordings;
- the 1-2 Hz transmissibility: the middle's relative acceleration over the chord
  midpoint's, in the swing band;
- the overshoot after the grips slow down: at each local minimum of their speed below half
  the peak of the 0.3 s before, the middle's peak relative speed in the 0.3 s after over it;
- the RMS of the middle's relative motion below 1 Hz, at 1-2 Hz and above;
- for the replays, where their error lies (chord-frame components and frequency bands).

These readings of a driven cable are not the free swing's damping ratio; a rod replayed at
several damping times (CABLE-BACKEND@bending_damping=...) shows how they follow it.
Two stages, each backend's replays in its own MuJoCo (3 for "mujoco", 4 for "mujoco-flex"):

  python examples/calibration/real_swing.py replay DEFORM/DLO2 examples/calibration/DLO2.yaml \
      examples/calibration/results/DLO2-mujoco runs/real_swing [bending_damping=0.02]
  python examples/calibration/real_swing.py analyse DEFORM runs/real_swing \
      examples/calibration/results/real_swing.json     # and real_swing.md beside it
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from scipy.signal import savgol_filter, welch

from dlocli.calibration.fit import load_cable, replay_settings
from dlocli.calibration.replay import replay
from dlocli.calibration.spec import CalibrateSpec
from dlocli.io import write_json_atomic
from dlocli.registry import backends
from dlocli.specs import BackendSpec

RATE_HZ = 100.0
SKIP_S = 1.0  # the replayed rod starts at rest: its first second is its start transient
SMOOTH_S = 0.15  # Savitzky-Golay window of the derivatives (the swing's period is ~0.7 s)
SWING_BAND_HZ = (1.0, 2.0)
OVERSHOOT_S = 0.3
BANDS_HZ = {"below 1 Hz": (0.0, 1.0), "1-2 Hz": (1.0, 2.0), "above 2 Hz": (2.0, RATE_HZ)}
Z_AXIS = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- replays
def replay_run(
    source: Path, cable_yaml: Path, run: Path, out: Path, changes: dict[str, float]
) -> None:
    """Replay every recording of ``source`` on the calibrated rod of ``run`` (with the rod
    fields ``changes`` changed); save the simulated markers (T,V,3 each) to
    OUT/CABLE-BACKEND.npz (CABLE-BACKEND@FIELD=VALUE.npz with changes)."""
    fields = yaml.safe_load(cable_yaml.read_text())
    spec = CalibrateSpec.model_validate({**fields, "source": source})
    calibrated = yaml.safe_load((run / "calibrated.yaml").read_text())["backend"]
    calibrated["rod"].update(changes)
    backend_spec = BackendSpec.model_validate(calibrated)
    spec.backend.name = backend_spec.name
    cable = load_cable(spec)
    if abs(cable.backend.rod.length - backend_spec.rod.length) > 1e-9:
        raise SystemExit(f"{run}: its rod is not {cable_yaml}'s ({backend_spec.rod.length})")
    settings = replay_settings(spec, cable.held)
    backend = backends.get(backend_spec.name)(backend_spec, control_dt=1.0 / RATE_HZ)
    simulated, started = {}, time.time()
    try:
        for split, items in (("eval", cable.eval), ("train", cable.train)):
            for name, recording in items:
                result = replay(backend, recording, cable.arc, settings)
                if result.diverged_at is not None:
                    print(f"{name}: diverged at frame {result.diverged_at}; left out")
                    continue
                simulated[f"{split}/{name}"] = result.simulated.astype(np.float32)
    finally:
        backend.close()
    out.mkdir(parents=True, exist_ok=True)
    label = run.name + "".join(f"@{k}={v:g}" for k, v in changes.items())
    np.savez_compressed(out / f"{label}.npz", **simulated)
    print(f"{label}: {len(simulated)} replays in {time.time() - started:.0f} s")


# --------------------------------------------------------------------------- the swing's signals
def derivatives(x: np.ndarray, order: int) -> np.ndarray:
    window = round(SMOOTH_S * RATE_HZ) | 1
    return savgol_filter(x, window, 3, deriv=order, delta=1.0 / RATE_HZ, axis=0)


def swing_signals(markers: np.ndarray, held: np.ndarray) -> dict[str, np.ndarray]:
    """The middle's motion relative to the grips' midpoint, sideways and in-plane, and the
    gripper terms it is driven by, from the (T,V,3) markers; the first SKIP_S left out."""
    held_at = np.flatnonzero(held)
    free = np.flatnonzero(~held)
    left, right = held_at[held_at < free[0]], held_at[held_at > free[-1]]
    grip_a, grip_b = markers[:, left[-1]], markers[:, right[0]]
    half = len(free) // 2
    centre = free[half - 1 : half + 1] if len(free) % 2 == 0 else free[half : half + 1]
    middle = markers[:, centre].mean(1)
    base = 0.5 * (grip_a + grip_b)
    chord = grip_b - grip_a
    along = chord / np.linalg.norm(chord, axis=1, keepdims=True)
    sideways = np.cross(along, Z_AXIS)
    sideways /= np.linalg.norm(sideways, axis=1, keepdims=True)
    in_plane = np.cross(sideways, along)  # up, across the chord
    tangent_left = markers[:, left[-1]] - markers[:, left[0]]
    tangent_right = markers[:, right[-1]] - markers[:, right[0]]
    tangent_left /= np.linalg.norm(tangent_left, axis=1, keepdims=True)
    tangent_right /= np.linalg.norm(tangent_right, axis=1, keepdims=True)
    relative = middle - base
    velocity, acceleration = derivatives(relative, 1), derivatives(relative, 2)
    base_acceleration = derivatives(base, 2)
    grip_speed = 0.5 * (
        np.linalg.norm(derivatives(grip_a, 1), axis=1)
        + np.linalg.norm(derivatives(grip_b, 1), axis=1)
    )
    skip = round(SKIP_S * RATE_HZ)
    out = {"grip_speed": grip_speed, "relative_speed": np.linalg.norm(velocity, axis=1)}
    for name, axis in (("sideways", sideways), ("in_plane", in_plane)):
        dot = lambda v, axis=axis: np.einsum("ij,ij->i", v, axis)  # noqa: E731
        out[name] = np.stack(
            [
                dot(acceleration),
                dot(velocity),
                dot(relative),
                dot(base_acceleration),
                dot(tangent_left),
                dot(tangent_right),
                np.linalg.norm(chord, axis=1),
                axis[:, 2],  # gravity's share across the chord
            ],
            axis=1,
        )
    return {k: v[skip:] for k, v in out.items()}


# --------------------------------------------------------------------------- estimates
def oscillator(columns: list[np.ndarray]) -> dict[str, float]:
    """zeta and omega of q'' = -2 zeta omega q' - omega^2 q + gripper terms + a constant per
    recording, by least squares over the recordings' (T,8) signal columns."""
    # a constant per recording: each recording's columns about their means
    stacked = np.concatenate([c - c.mean(0) for c in columns])
    coef = np.linalg.lstsq(stacked[:, 1:], stacked[:, 0], rcond=None)[0]
    stiffness = -coef[1]
    if stiffness <= 0:
        return {"damping_ratio": math.nan, "swing_hz": math.nan}
    omega = math.sqrt(stiffness)
    return {"damping_ratio": -coef[0] / (2 * omega), "swing_hz": omega / (2 * math.pi)}


def band_power(x: np.ndarray) -> float:
    frequencies, power = welch(x, fs=RATE_HZ, nperseg=len(x), window="hann")
    band = (frequencies >= SWING_BAND_HZ[0]) & (frequencies <= SWING_BAND_HZ[1])
    return float(power[band].sum())


def band_rms(signals: list[np.ndarray]) -> dict[str, float]:
    """RMS (mm) of the signals' parts in each of BANDS_HZ, pooled over recordings."""
    power = np.zeros(len(BANDS_HZ))
    for x in signals:
        spectrum = np.abs(np.fft.rfft(x - x.mean())) ** 2 * 2 / len(x) ** 2
        frequencies = np.fft.rfftfreq(len(x), 1.0 / RATE_HZ)
        power += [
            spectrum[(frequencies > lo) & (frequencies <= hi)].sum() for lo, hi in BANDS_HZ.values()
        ]
    return {
        k: round(float(np.sqrt(p / len(signals))) * 1e3, 3)
        for k, p in zip(BANDS_HZ, power, strict=True)
    }


def transmissibility(columns: list[np.ndarray]) -> float:
    """Swing-band power of the middle's relative acceleration over the grips' midpoint's."""
    return math.sqrt(
        sum(band_power(c[:, 0]) for c in columns) / sum(band_power(c[:, 3]) for c in columns)
    )


def overshoots(signals: list[dict[str, np.ndarray]]) -> list[float]:
    """At each slow-down of the grips (a local minimum of their speed under half the peak of
    the OVERSHOOT_S before), the middle's peak relative speed in the OVERSHOOT_S after over
    that gripper peak."""
    window = round(OVERSHOOT_S * RATE_HZ)
    found = []
    for s in signals:
        speed, relative = s["grip_speed"], s["relative_speed"]
        for t in range(window, len(speed) - window):
            if speed[t] <= speed[t - 1] and speed[t] < speed[t + 1]:
                before = speed[t - window : t].max()
                if speed[t] < 0.5 * before and before > 0.05:
                    found.append(float(relative[t : t + window].max() / before))
    return found


def spread(values: list[float]) -> list[float]:
    return [round(float(v), 4) for v in np.nanpercentile(values, [16, 50, 84])]


def describe(signals: list[dict[str, np.ndarray]], seed: int = 0) -> dict[str, object]:
    """Every measure of one cable (real or a replay) over its recordings; spreads are the
    16/50/84th percentiles of 200 bootstrap draws of the recordings."""
    rng = np.random.default_rng(seed)
    out: dict[str, object] = {"recordings": len(signals)}
    for part in ("sideways", "in_plane"):
        columns = [s[part] for s in signals]
        fit = oscillator(columns)
        draws = [
            oscillator([columns[i] for i in rng.integers(len(columns), size=len(columns))])
            for _ in range(200)
        ]
        out[part] = {
            "damping_ratio": round(fit["damping_ratio"], 4),
            "damping_ratio_spread": spread([d["damping_ratio"] for d in draws]),
            "swing_hz": round(fit["swing_hz"], 3),
            "transmissibility": round(transmissibility(columns), 4),
            "relative_rms_mm": band_rms([c[:, 2] for c in columns]),
        }
    ratios = overshoots(signals)
    out["overshoot"] = {"events": len(ratios), "median_and_spread": spread(ratios)}
    return out


def residual_band_fraction(real: list[np.ndarray], sim: list[np.ndarray]) -> float:
    """Share of the sideways residual's (simulated minus real relative displacement) power
    that lies in the swing band."""
    band = total = 0.0
    for r, s in zip(real, sim, strict=True):
        residual = s[:, 2] - r[:, 2]
        frequencies, power = welch(residual, fs=RATE_HZ, nperseg=len(residual))
        inside = (frequencies >= SWING_BAND_HZ[0]) & (frequencies <= SWING_BAND_HZ[1])
        band += power[inside].sum()
        total += power[1:].sum()
    return round(float(band / total), 4)


def chord_frame(markers: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(T,3,3) unit axes per frame: along the grips' chord, sideways, in-plane."""
    held_at, free = np.flatnonzero(held), np.flatnonzero(~held)
    chord = markers[:, held_at[held_at > free[-1]][0]] - markers[:, held_at[held_at < free[0]][-1]]
    along = chord / np.linalg.norm(chord, axis=1, keepdims=True)
    sideways = np.cross(along, Z_AXIS)
    sideways /= np.linalg.norm(sideways, axis=1, keepdims=True)
    return np.stack([along, sideways, np.cross(sideways, along)], axis=1)


def residual_parts(real: list[np.ndarray], sim: list[np.ndarray], held: np.ndarray) -> dict:
    """Where a rod's replay error lies: the DEFORM score (cm) of the first SKIP_S and of the
    rest; after SKIP_S, the free markers' mean absolute error (cm) along the chord, sideways
    and in-plane, and the error's RMS (mm) in frequency bands."""
    skip = round(SKIP_S * RATE_HZ)
    free = ~held
    start, rest, parts, bands = [], [], [], []
    for r, s in zip(real, sim, strict=True):
        error = s[:, free] - r[:, free]
        start.append(np.abs(error[2:skip]).sum() / (skip - 2) / r[0].size)
        rest.append(np.abs(error[skip:]).sum() / (len(r) - skip) / r[0].size)
        local = np.einsum("tij,tfj->tfi", chord_frame(r, held)[skip:], error[skip:])
        parts.append(np.abs(local).mean((0, 1)))
        spectrum = np.fft.rfft(error[skip:] - error[skip:].mean(0), axis=0)
        frequencies = np.fft.rfftfreq(len(error) - skip, 1.0 / RATE_HZ)
        power = (np.abs(spectrum) ** 2).sum((1, 2)) / (len(error) - skip) ** 2 / free.sum()
        bands.append(
            [power[(frequencies > lo) & (frequencies <= hi)].sum() for lo, hi in BANDS_HZ.values()]
        )
    return {
        "score_first_second_cm": round(float(np.mean(start)) * 100, 4),
        "score_after_cm": round(float(np.mean(rest)) * 100, 4),
        "mean_abs_error_cm": {
            k: round(float(v) * 100, 4)
            for k, v in zip(("along", "sideways", "in_plane"), np.mean(parts, 0), strict=True)
        },
        "rms_mm": {
            k: round(float(np.sqrt(2 * v)) * 1e3, 3)
            for k, v in zip(BANDS_HZ, np.mean(bands, 0), strict=True)
        },
    }


def rest_stretches(markers: list[np.ndarray], held: np.ndarray) -> dict[str, object]:
    """How still the grips ever are: both grips' speeds (m/s, per frame) and the longest run
    of frames with both below 1, 2 and 5 cm/s."""
    held_at, free = np.flatnonzero(held), np.flatnonzero(~held)
    grips = [held_at[held_at < free[0]][-1], held_at[held_at > free[-1]][0]]
    speeds, longest = [], {0.01: 0, 0.02: 0, 0.05: 0}
    for rec in markers:
        speed = np.linalg.norm(np.diff(rec[:, grips], axis=0), axis=-1).max(1) * RATE_HZ
        speeds.append(speed)
        for limit in longest:
            run = best = 0
            for slow in speed < limit:
                run = run + 1 if slow else 0
                best = max(best, run)
            longest[limit] = max(longest[limit], best)
    return {
        "faster_grip_speed_m_s_percentiles_5_25_50": [
            round(float(v), 3) for v in np.percentile(np.concatenate(speeds), [5, 25, 50])
        ],
        "longest_still_s": {f"below {k * 100:g} cm/s": v / RATE_HZ for k, v in longest.items()},
    }


def analyse(deform: Path, replays: Path, out: Path, cables: list[str]) -> None:
    from dlocli.recorded_cables import deform as deform_format

    found: dict[str, object] = {}
    for cable in cables or sorted(p.name for p in deform.iterdir() if p.name.startswith("DLO")):
        recordings, held = deform_format.read_recordings(deform / cable)
        markers = {
            f"{split}/{name}": rec for split, items in recordings.items() for name, rec in items
        }
        real = {name: swing_signals(rec, held) for name, rec in markers.items()}
        entry: dict[str, object] = {
            "grips": rest_stretches(list(markers.values()), held),
            "real": describe(list(real.values())),
        }
        for run in sorted(replays.glob(f"{cable}-*.npz")):
            simulated = np.load(run)
            names = [n for n in real if n in simulated.files]
            sim = {n: swing_signals(simulated[n], held) for n in names}
            backend = run.stem[len(cable) + 1 :]
            entry[backend] = describe(list(sim.values()))
            if len(names) < len(real):  # some replays diverged: real on the same recordings
                entry[backend]["real_on_same_recordings"] = describe([real[n] for n in names])
            entry[backend]["residual_swing_band_fraction"] = residual_band_fraction(
                [real[n]["sideways"] for n in names], [sim[n]["sideways"] for n in names]
            )
            entry[backend]["error"] = residual_parts(
                [markers[n] for n in names], [simulated[n] for n in names], held
            )
        found[cable] = entry
        print(cable, "done", flush=True)
    write_json_atomic(out, found)
    out.with_suffix(".md").write_text(table(found, out.parent))


def rest_swing(results: Path, cable: str, source: str) -> str:
    """The rod's free swing damping ratio after a stop (swing_decay.py's), where measured."""
    backend, _, change = source.partition("@")
    name = f"{cable}-{backend}" + (f" {change}" if change else "")
    for path in results.glob("swing_*.json"):
        measured = json.loads(path.read_text())
        if name in measured:
            return f"{measured[name]['damping_ratio']:.3f}"
    return ""


def table(found: dict[str, dict], results: Path) -> str:
    """Markdown: per cable, the real recordings and each rod replaying them."""
    lines = [
        "| cable | motion of | sideways damping ratio, driven fit (16-84%) | swing Hz "
        "| 1-2 Hz transmissibility | overshoot after slow-downs | middle's 1-2 Hz sideways "
        "RMS (mm) | rod's free swing damping ratio | replay score after 1 s (cm) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for cable, entry in found.items():
        for source, v in entry.items():
            if source == "grips":
                continue
            side = v["sideways"]
            low, _, high = side["damping_ratio_spread"]
            error = v.get("error", {}).get("score_after_cm", "")
            lines.append(
                f"| {cable} | {source} | {side['damping_ratio']:.3f} ({low:.3f}-{high:.3f}) "
                f"| {side['swing_hz']:.2f} | {side['transmissibility']:.2f} "
                f"| {v['overshoot']['median_and_spread'][1]:.2f} "
                f"| {side['relative_rms_mm']['1-2 Hz']:.0f} "
                f"| {rest_swing(results, cable, source) if source != 'real' else ''} | {error} |"
            )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    if sys.argv[1] == "replay":
        changes = {k: float(v) for k, v in (a.split("=") for a in sys.argv[6:])}
        replay_run(*(Path(a) for a in sys.argv[2:6]), changes)
    else:
        analyse(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), sys.argv[5:])
