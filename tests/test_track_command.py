"""`dlo track`: point clouds recorded by the simulated depth camera on a real MuJoCo cable
(.npz frame sequences) into a marker dataset that `dlo train` reads, the tracked markers
against the simulator's true ones; bad recordings refused in one line, exit 2."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dlocli.data import MarkerDataset, load_dataset
from dlocli.env.shape_env import make_env
from dlocli.specs import TaskSpec
from dlocli.tracking.camera import DepthCamera
from dlocli.tracking.frames import save_frames
from dlocli.tracking.measure import env_layout, policy_action, robot_held, true_markers
from dlocli.tracking.spec import CameraSpec

from tiny import MUJOCO_ROD, file_digests, run_dlo

STEPS = 30  # control steps per episode: 16 frames at 25 per second


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """train/ (seeds 0, 1) and eval/ (seed 2) recordings, and each one's true markers."""
    root = tmp_path_factory.mktemp("clouds")
    env = make_env(MUJOCO_ROD, TaskSpec(name="single", goal="random"), seed=0, render_mode=None)
    layout = env_layout(env)
    camera = DepthCamera(CameraSpec(), env.backend.rod.length)
    truth = {}
    for split, seed in (("train", 0), ("train", 1), ("eval", 2)):
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        frames, held, markers = [], [], []
        for step in range(STEPS + 1):
            if step % 2 == 0:
                frames.append(camera.capture(env.backend, rng, time=step * 0.02))
                held.append(robot_held(env, layout))
                markers.append(true_markers(env, layout))
            if step < STEPS:
                env.step(policy_action(env, "oracle", rng))
        (root / split).mkdir(exist_ok=True)
        save_frames(root / split / f"seed{seed}.npz", frames, np.stack(held))
        truth[f"seed{seed}"] = np.stack(markers)
    env.close()
    return root, truth


def test_dlo_track_makes_a_marker_dataset_that_dlo_train_reads(recorded, tmp_path):
    source, truth = recorded
    out = tmp_path / "tracked"
    assert run_dlo(["track", "--source", str(source), "--out", str(out), "--json"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train_episodes"] == 2 and summary["eval_episodes"] == 1
    assert summary["rate_hz"] == pytest.approx(25.0)
    data = load_dataset(out)
    assert isinstance(data, MarkerDataset) and data.n_markers == 12
    assert data.held.tolist() == [True, True] + [False] * 8 + [True, True]
    names = data.episode_names("train") + data.episode_names("eval")
    for name, episode in zip(names, data.episodes("train") + data.episodes("eval"), strict=True):
        error = np.linalg.norm(episode - truth[name], axis=-1)[:, ~data.held]
        assert error.mean() < 6e-3, name
    model = tmp_path / "model"
    assert run_dlo(["train", "--data", str(out), "--out", str(model), "--update-steps", "4",
                    "--rollout-steps", "2", "--hidden", "8", "--device", "cpu",
                    "--json"]) == 0  # fmt: skip
    assert json.loads((model / "summary.json").read_text())["form"] == "markers"


def test_bad_recordings_are_one_line_and_exit_2(recorded, tmp_path, capsys):
    source, _ = recorded
    good = dict(np.load(source / "train" / "seed0.npz"))
    nan = {**good, "points": good["points"].copy()}
    nan["points"][0, 2] = np.nan
    cases = {
        "NaN": ({"a.npz": nan}, []),
        "no points": (
            {"a.npz": {**good, "points": np.zeros((0, 3)), "counts": 0 * good["counts"]}}, []
        ),
        "records no held positions": ({"a.npz": {k: v for k, v in good.items() if k != "held"}},
                                      []),
        "held records 1 markers": ({"a.npz": {**good, "held": good["held"][:, :1]}}, []),
        "holds no .npz": ({}, []),
        "frame rates differ": (
            {"a.npz": good, "b.npz": {**good, "times": 2 * good["times"]}}, []
        ),
    }  # fmt: skip
    for words, (files, extra) in cases.items():
        folder = tmp_path / words.replace(" ", "_")
        folder.mkdir()
        for name, arrays in files.items():
            np.savez(folder / name, **arrays)
        out = tmp_path / f"out_{folder.name}"
        capsys.readouterr()
        assert run_dlo(["track", "--source", str(folder), "--out", str(out), *extra]) == 2
        error = capsys.readouterr().err.strip()
        assert words in error and "\n" not in error and "Traceback" not in error, words
        assert not out.exists(), words


def test_an_out_inside_the_source_is_refused_in_one_line(recorded, tmp_path, capsys):
    """`--out src/train/tracked.npz` would land a dataset among the recordings and break the
    next track of src: refused as `dlo import` refuses it, one line, exit 2, src unchanged."""
    source = tmp_path / "src"
    shutil.copytree(recorded[0], source)
    before = file_digests(source)
    assert run_dlo(["track", "--source", str(source),
                    "--out", str(source / "train" / "tracked.npz")]) == 2  # fmt: skip
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "lies inside or holds --source" in lines[0], lines
    assert file_digests(source) == before


def test_without_the_robots_poses_the_cable_is_ordered_from_its_cloud(recorded, tmp_path):
    """Recordings without held positions: the markers on the cable only (--gripper-markers
    0), the chain's ends found in the cloud; the grippers hide the cable's ends, so the
    margin is wider, but the tracked cable is far nearer the truth than standing still."""
    source, truth = recorded
    folder = tmp_path / "no_held"
    folder.mkdir()
    for path in (source / "train").glob("*.npz"):
        arrays = dict(np.load(path))
        del arrays["held"]
        np.savez(folder / path.name, **arrays)
    out = tmp_path / "tracked"
    assert run_dlo(["track", "--source", str(folder), "--out", str(out),
                    "--gripper-markers", "0"]) == 0  # fmt: skip
    data = load_dataset(out)
    assert data.n_markers == 10 and data.held.tolist() == [True] + [False] * 8 + [True]
    for name, episode in zip(data.episode_names(), data.episodes(), strict=True):
        true = truth[name][:, 1:-1]  # the gripper markers dropped
        error = np.linalg.norm(episode - true, axis=-1)[:, 1:-1].mean()
        still = np.linalg.norm(true[:1] - true, axis=-1)[:, 1:-1].mean()
        assert error < min(25e-3, 0.5 * still), name
