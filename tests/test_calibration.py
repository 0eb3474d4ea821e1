"""`dlo calibrate`: replay of recorded held-marker motion on a simulated rod, CMA-ES fit of
its material, resume after a kill, refused inputs. The recordings are made by the simulator
itself (a rod of known stiffness), so the fit has a known answer; the real DEFORM data is
used when present."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import dlocli
from dlocli.calibration.fit import load_cable
from dlocli.calibration.replay import ReplaySettings, replay
from dlocli.calibration.spec import CalibrateSpec
from dlocli.data import protocol
from dlocli.env.observation import marker_layout
from dlocli.events import Event
from dlocli.io import written_by_dlo
from dlocli.recorded_cables import deform
from dlocli.registry import backends
from dlocli.runs.calibrate import run_calibration
from dlocli.specs import BackendSpec, ObservationSpec, RodSpec

from tiny import MUJOCO_ROD, file_digests, run_dlo

pytest.importorskip("cma")

DEFORM_DATA = Path(
    os.environ.get("DLOCLI_DEFORM_DATA", Path(__file__).parents[2] / "shared/data/deform")
)
LENGTH, MASS, RADIUS = 0.6, 0.018, 0.005
TRUE_E = 3e6
ARC = np.array([0.0, 0.03, 0.2, 0.4, 0.57, 0.6])
FRAMES, RATE = 120, 100.0
SETTINGS = ReplaySettings(approach_s=0.5, settle_s=0.5)


ROD_ARC = ARC - ARC[1]  # half-segment clamps: the grippers hold markers 1 and V-2
ROD = float(ROD_ARC[-2])


def _rod(young: float) -> BackendSpec:
    density = MASS / LENGTH / (np.pi * RADIUS**2)
    rod = RodSpec(length=ROD, n_segments=12, radius=RADIUS, density=density)
    return BackendSpec(rod=rod.model_copy(update={"young_bending": young}))


def _held_motion(seed: int) -> np.ndarray:
    """(T,V,3) end markers swinging smoothly, their neighbours 3 cm inwards, free markers
    on the chord (the replay replaces them)."""
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES)[:, None] / RATE
    phase = rng.uniform(0, 2 * np.pi, 4)
    left = np.hstack([0.05 * np.sin(3 * t + phase[0]), 0.04 * np.sin(2 * t + phase[1]), 0 * t])
    right = np.hstack([0.45 + 0.05 * np.sin(4 * t + phase[2]), 0 * t, 0.06 * np.sin(3 * t)])
    tilt = 0.4 * np.sin(2 * t + phase[3])
    inwards = np.hstack([np.cos(tilt), 0 * t, np.sin(tilt)])
    s = (ARC / LENGTH)[None, :, None]
    markers = left[:, None] + s * (right - left)[:, None]
    markers[:, 1] = left + 0.03 * inwards
    markers[:, -2] = right - 0.03 * np.hstack([np.ones_like(t), 0 * t, 0 * t])
    return markers


def _simulate(young: float, seed: int) -> np.ndarray:
    backend = backends.get(MUJOCO_ROD)(_rod(young), control_dt=1 / RATE)
    return replay(backend, _held_motion(seed), ROD_ARC, SETTINGS).simulated


def _write(folder: Path, recordings: dict[str, list[np.ndarray]]) -> Path:
    for split, items in recordings.items():
        (folder / split).mkdir(parents=True, exist_ok=True)
        for i, rec in enumerate(items):
            data = rec.transpose(0, 2, 1).tolist()  # DEFORM's (frames, 3, markers)
            (folder / split / f"{i}.pkl").write_bytes(pickle.dumps(data))
    return folder


@pytest.fixture(scope="module")
def cable(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of a rod of stiffness TRUE_E: two train motions, one eval motion."""
    folder = tmp_path_factory.mktemp("synthetic") / "CABLE"
    return _write(folder, {"train": [_simulate(TRUE_E, 0), _simulate(TRUE_E, 1)],
                           "eval": [_simulate(TRUE_E, 2)]})  # fmt: skip


def _spec_file(tmp_path: Path, **fields: object) -> Path:
    spec = {
        "cable_length": LENGTH, "cable_mass": MASS, "rod_length": ROD, "rate_hz": RATE,
        "backend": {"name": MUJOCO_ROD, "rod": {"n_segments": 12, "radius": RADIUS}},
        "parameters": ["young_bending"], "approach_s": SETTINGS.approach_s,
        "settle_s": SETTINGS.settle_s, "train_trajectories": 1, "population": 4,
        "generations": 3, "sigma0": 0.1, "workers": 2, **fields,
    }  # fmt: skip
    CalibrateSpec.model_validate(spec)
    path = tmp_path / "calibrate.json"
    path.write_text(json.dumps(spec))
    return path


def _calibrate(*argv: str) -> int:
    return run_dlo(["calibrate", *argv, "--json"])


def test_replay_of_the_simulators_own_recording_is_exact(cable: Path) -> None:
    recorded = deform.read_trajectory(cable / "train/0.pkl")
    again = _simulate(TRUE_E, 0)
    assert np.abs(again - recorded).max() < 1e-6  # deterministic
    held = deform.held_markers(len(ARC))
    softer = replay(backends.get(MUJOCO_ROD)(_rod(TRUE_E / 3), control_dt=1 / RATE),
                    recorded, ROD_ARC, SETTINGS)  # fmt: skip
    freeze = protocol.deform_score_cm(protocol.freeze(recorded, held), recorded)
    assert 0 < softer.score_cm < freeze
    assert softer.held_error_mm < 2.0  # the grippers follow the recorded held markers


def test_calibration_recovers_the_stiffness(cable: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert _calibrate("--spec", str(_spec_file(tmp_path)), "--source", str(cable),
                      "--out", str(out)) == 0  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    fitted = report["parameters"]["young_bending"]
    train = deform.read_trajectory(cable / f"{report['train_recordings'][0]}.pkl")
    # the margin: how much worse a rod half or twice as stiff replays the same recording
    # (markers placed as the calibration places them)
    arc = load_cable(CalibrateSpec.model_validate_json((out / "spec.json").read_text())).arc
    neighbours = [
        replay(backends.get(MUJOCO_ROD)(_rod(e), control_dt=1 / RATE), train, arc, SETTINGS)
        for e in (TRUE_E / 2, TRUE_E * 2)
    ]
    assert report["train_best_cm"] < min(r.score_cm for r in neighbours)
    assert TRUE_E / 2 < fitted < TRUE_E * 2
    assert report["eval_calibrated_cm"] < report["eval_default_cm"]
    calibrated = yaml.safe_load((out / "calibrated.yaml").read_text())
    assert calibrated["backend"]["rod"]["young_bending"] == fitted
    # the recordings' rate and markers: two held at each end, the outer ones on the grippers
    assert calibrated["task"]["control_dt"] == pytest.approx(1 / RATE)
    observation = ObservationSpec(kind="markers", **calibrated["task"]["observation"])
    layout = marker_layout(observation, ROD, 12, (True, True))
    assert layout.held.tolist() == deform.held_markers(len(ARC)).tolist()
    assert layout.on_gripper.tolist() == [True, False, False, False, False, True]
    assert np.allclose(layout.arc, arc, atol=1e-5)  # where the replays read them off the rod
    _rehearse_on(out / "calibrated.yaml", BackendSpec.model_validate(calibrated["backend"]))


def _rehearse_on(spec_file: Path, rod: BackendSpec) -> None:
    """The calibrated rod is a task: every simulating command's spec takes the file, and a
    short control episode runs on it."""
    from dlocli.bench.spec import BenchSpec
    from dlocli.runs.control import ControlSpec
    from dlocli.runs.online import OnlineSpec
    from dlocli.specs import resolve_spec

    for command in (OnlineSpec, ControlSpec, BenchSpec):
        assert resolve_spec(command, spec_file, {}).backend == rod
    out = spec_file.parent.parent / "rehearsal"  # outside the calibration run (an input)
    assert run_dlo(["goal", "--spec", str(spec_file), "--shapes", "near-rest",
                    "--out", str(out / "goal.npy"), "--json"]) == 0  # fmt: skip
    argv = [
        "control",
        "--spec",
        str(spec_file),
        "--goal",
        str(out / "goal.npy"),
        "--controller",
        "random",
        "--steps",
        "3",
        "--shapes",
        "near-rest",
        "--observation",
        "markers",
        "--out",
        str(out / "control"),
    ]
    assert run_dlo([*argv, "--json"]) == 0
    summary = json.loads((out / "control" / "summary.json").read_text())
    assert summary["steps"] == 3 and not summary["diverged"]


@pytest.mark.slow
def test_a_killed_calibration_resumes_where_it_stopped(cable: Path, tmp_path: Path) -> None:
    spec = _spec_file(tmp_path, generations=3)
    reference = tmp_path / "reference"
    assert _calibrate("--spec", str(spec), "--source", str(cable), "--out", str(reference)) == 0
    killed = tmp_path / "killed"
    copied = tmp_path / "cable"
    shutil.copytree(cable, copied)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])}
    cmd = [sys.executable, "-m", "dlocli", "calibrate", "--spec", str(spec), "--source",
           str(copied), "--out", str(killed), "--json"]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    history = killed / "history.json"
    deadline = time.monotonic() + 300
    while not history.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = json.loads(history.read_text())["generations"]
    assert 1 <= len(done) < 3 and not (killed / "report.json").exists()
    recording = sorted((copied / "train").glob("*.pkl"))[0]
    original = recording.read_bytes()
    frames = np.array(pickle.loads(original))
    recording.write_bytes(pickle.dumps((frames + 1e-3).tolist()))
    kept = file_digests(killed)
    assert _calibrate("--resume", str(killed)) == 2  # another cable's data: refused
    assert file_digests(killed) == kept
    recording.write_bytes(original)
    assert _calibrate("--resume", str(killed)) == 0
    assert {"history.json", "spec.json"} <= written_by_dlo(killed)  # --overwrite may clear it
    resumed = json.loads(history.read_text())["generations"]
    expected = json.loads((reference / "history.json").read_text())["generations"]
    assert resumed[: len(done)] == done  # finished generations kept, not re-run
    assert np.allclose([g["scores"] for g in resumed], [g["scores"] for g in expected])
    assert np.allclose([g["candidates"] for g in resumed], [g["candidates"] for g in expected])


def test_calibration_reports_through_the_one_callback(cable: Path, tmp_path: Path) -> None:
    """Its progress, as Events counting up: each generation's replays of its candidates, the
    generation with the best train score so far, then the eval replays."""
    fields = json.loads(_spec_file(tmp_path, generations=2, workers=1).read_text())
    spec = CalibrateSpec.model_validate({**fields, "source": cable, "out": tmp_path / "run"})
    events: list = []
    summary = run_calibration(spec, overwrite=False, progress=events.append)
    assert events and all(isinstance(e, Event) for e in events)
    generations = [e for e in events if e.unit == "generation"]
    assert [(e.done, e.total) for e in generations] == [(1, 2), (2, 2)]
    best = [e.values["best_cm"] for e in generations]
    assert best[1] <= best[0] and best[1] == pytest.approx(summary["train_best_cm"], abs=1e-3)
    replays = [e for e in events if e.unit == "replay"]
    calls = replays[0].total
    assert [e.done for e in replays] == [*range(1, calls + 1)] * 2  # afresh each generation
    evals = [e for e in events if e.unit == "eval"]
    assert [e.done for e in evals] == [*range(1, evals[0].total + 1)] and events[-1] is evals[-1]


def test_bad_inputs_get_one_line_and_exit_2(
    cable: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flat = tmp_path / "FLAT"
    (flat / "train").mkdir(parents=True)
    (flat / "train/0.pkl").write_bytes(pickle.dumps(np.zeros((50, 2, 6)).tolist()))
    pair = shutil.copytree(cable, tmp_path / "PAIR")  # the right end's two markers meet
    frames = np.array(pickle.loads((pair / "eval/0.pkl").read_bytes()))  # (T, 3, V)
    frames[7, :, -2] = frames[7, :, -1]
    (pair / "eval/0.pkl").write_bytes(pickle.dumps(frames.tolist()))
    spec = _spec_file(tmp_path)
    out = tmp_path / "out"
    cases = [
        (["--source", str(flat)], "expected (frames, 3, markers)"),
        (["--source", str(pair)], "PAIR/eval/0: its right end markers 4 and 5 coincide in frame 7"),
        (["--source", str(cable), "--rod-length", "0.3"], "shorter than the grip markers"),
        (["--source", str(cable), "--cable-length", "0.4"], "pass the cable's real length"),
    ]
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    before = file_digests(existing)
    for argv, message in cases:
        capsys.readouterr()
        assert _calibrate("--spec", str(spec), *argv, "--out", str(out)) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
        assert not out.exists()
        assert _calibrate("--spec", str(spec), *argv, "--out", str(existing), "--overwrite") == 2
        assert file_digests(existing) == before


@pytest.mark.skipif(not (DEFORM_DATA / "DLO3/eval").is_dir(), reason="DEFORM data not present")
def test_a_real_cable_replays_better_than_freezing() -> None:
    spec = CalibrateSpec(source=DEFORM_DATA / "DLO3", cable_length=0.998, cable_mass=0.0968)
    cable = load_cable(spec)
    recording = cable.eval[0][1][:150]
    backend = backends.get(MUJOCO_ROD)(cable.backend, control_dt=0.01)
    result = replay(backend, recording, cable.arc, ReplaySettings())
    held = deform.held_markers(recording.shape[1])
    freeze = protocol.deform_score_cm(protocol.freeze(recording, held), recording)
    assert result.diverged_at is None and result.score_cm < freeze


def test_simulated_markers_train_a_model_that_fine_tunes(cable: Path, tmp_path: Path) -> None:
    """Simulated data of the rod is a marker dataset `dlo train` takes; --init-from starts a
    marker model from that checkpoint (its weights and normalization)."""
    from dlocli.calibration.simulate import simulate_markers
    from dlocli.data import MarkerDataset
    from dlocli.models.checkpoints import load_marker_model

    recordings = [deform.read_trajectory(cable / f"train/{i}.pkl") for i in range(2)]
    backend = backends.get(MUJOCO_ROD)(_rod(TRUE_E), control_dt=1 / RATE)
    sims, dropped = simulate_markers(backend, recordings, ROD_ARC, 3, 0, SETTINGS)
    assert dropped == 0 and len(sims) == 3
    for sim, rec in zip(sims, [recordings[0], recordings[1], recordings[0]], strict=True):
        # a rigid move of the recorded held motion: the end markers' separations are kept
        span = np.linalg.norm(sim[:, -1] - sim[:, 0], axis=-1)
        recorded_span = np.linalg.norm(rec[:, -1] - rec[:, 0], axis=-1)
        assert np.abs(np.sort(span) - np.sort(recorded_span)).max() < 5e-3
    held = deform.held_markers(len(ARC))
    named = {"train": [(f"sim{i}", s) for i, s in enumerate(sims)]}
    MarkerDataset.from_trajectories(named, held, {"rate_hz": RATE}).save(tmp_path / "sim.h5")
    common = ["--model", "mlp", "--rollout-steps", "8", "--device", "cpu", "--json"]
    assert run_dlo(["train", "--data", str(tmp_path / "sim.h5"), "--update-steps", "20",
                    "--lr", "3e-3", "--out", str(tmp_path / "sim"), *common]) == 0  # fmt: skip
    assert run_dlo(["import", "--source", str(cable), "--out", str(tmp_path / "real"),
                    "--json"]) == 0  # fmt: skip
    assert run_dlo(["train", "--data", str(tmp_path / "real"), "--update-steps", "1",
                    "--lr", "1e-12", "--init-from", str(tmp_path / "sim"),
                    "--out", str(tmp_path / "tuned"), *common]) == 0  # fmt: skip
    start = load_marker_model(tmp_path / "sim").state_dict()
    tuned = load_marker_model(tmp_path / "tuned").state_dict()
    for name, value in start.items():
        assert torch.allclose(value.float(), tuned[name].float(), atol=1e-6), name


def test_the_grips_are_the_innermost_held_markers_of_each_end() -> None:
    """Half-segment clamps bend at the grip: the gripper holds the rod where the cable
    leaves it, the innermost held marker of its end; rigid clamps hold the end markers."""
    from dlocli.calibration.replay import grip_markers

    deform_layout = deform.held_markers(12)
    assert grip_markers(deform_layout, "half-segment") == (1, 10)
    assert grip_markers(deform_layout, "rigid") == (0, 11)
    one_per_end = np.array([True] + [False] * 4 + [True])
    assert grip_markers(one_per_end, "half-segment") == (0, 5)


def test_an_import_run_is_calibrated_with_its_held_markers(cable: Path, tmp_path: Path) -> None:
    assert run_dlo(["import", "--source", str(cable), "--held", "0,-1", "--out",
                    str(tmp_path / "imported"), "--json"]) == 0  # fmt: skip
    spec = CalibrateSpec(
        source=tmp_path / "imported", cable_length=LENGTH, cable_mass=MASS, rod_length=LENGTH
    )
    held = load_cable(spec).held
    assert held.tolist() == [True] + [False] * (len(ARC) - 2) + [True]
    arc = load_cable(spec).arc
    assert arc[0] == 0.0 and arc[-1] == pytest.approx(load_cable(spec).backend.rod.length)


def test_a_fitted_flex_rod_says_the_twist_damping_it_has() -> None:
    """MuJoCo's flex damping damps twist with the bending time, so a calibration that fits
    the bending time above the default twist time writes the twist time the rod has (the
    same physics, no warning on every use); the composite cable keeps what it was given."""
    flex, cable = backends.facts("mujoco-flex"), backends.facts("mujoco")
    rod = RodSpec(bending_damping=0.3, twist_damping=0.05)
    assert flex.effective_rod(rod).twist_damping == 0.3
    assert flex.effective_rod(RodSpec(twist_damping=0.01)).twist_damping == 0.05  # default
    for kept in (RodSpec(bending_damping=0.3, twist_damping=0.5), RodSpec(twist_damping=None)):
        assert flex.effective_rod(kept) == kept
    assert cable.effective_rod(rod) == rod


@pytest.mark.skipif(MUJOCO_ROD != "mujoco-flex", reason="the flex rod needs MuJoCo 4")
def test_the_flex_rods_effective_twist_damping_is_the_same_physics() -> None:
    asked = RodSpec(bending_damping=0.3, twist_damping=0.05)
    said = backends.facts("mujoco-flex").effective_rod(asked)
    paths = []
    for rod, warns in ((asked, True), (said, False)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            env = dlocli.make_env(BackendSpec(name="mujoco-flex", rod=rod), seed=0)
        assert any("twist_damping" in str(w.message) for w in caught) == warns
        try:
            env.reset(seed=0)
            actions = np.random.default_rng(0).uniform(-1, 1, (20, *env.action_space.shape))
            paths.append([env.step(a)[0] for a in actions])
        finally:
            env.close()
    np.testing.assert_array_equal(np.array(paths[0]), np.array(paths[1]))
