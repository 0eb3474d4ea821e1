"""Episodes from given gripper poses (``env.reset(options=...)``), and a recorded cable's
twin: the calibrated rod in the recorded cell, observed through the recorded markers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from dlocli.calibration.fit import Cable
from dlocli.calibration.twin import TwinSettings, goal_gap_mm, make_twin, write_twin_task
from dlocli.controllers.views import MarkerView
from dlocli.env.rollout import ActionSequence, rollout
from dlocli.env.shape_env import make_env
from dlocli.errors import BadInput, BadOption
from dlocli.models.base import valid_model_spec
from dlocli.models.marker_model import build_marker_model
from dlocli.recorded_cables import deform
from dlocli.specs import BackendSpec, EnvSpec, RodSpec, TaskSpec

from tiny import MUJOCO_ROD

QUICK = {"shapes": "near-rest", "episode_steps": 5, "reset_motion_steps": 15,
         "reset_settle_steps": 20}  # fmt: skip
FRAMES, RATE = 60, 100.0
ARC = np.array([0.0, 0.03, 0.15, 0.3, 0.45, 0.57, 0.6])  # a 0.6 m cable, held pairs 3 cm


def _poses_of_a_random_shape(env, seed: int) -> np.ndarray:
    env.reset(seed=seed)
    return env.backend.gripper_poses().copy()


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_an_episode_starts_and_ends_at_the_given_gripper_poses(backend: str) -> None:
    env = make_env(backend, "bimanual", seed=0, render_mode=None, **QUICK)
    try:
        start, goal = _poses_of_a_random_shape(env, 1), _poses_of_a_random_shape(env, 2)
        options = {"start_grippers": start, "goal_grippers": goal}
        env.reset(seed=3, options=options)
        assert np.abs(env.goal_gripper_poses[:, :3] - goal[:, :3]).max() < 1e-4
        assert np.abs(env.backend.gripper_poses()[:, :3] - start[:, :3]).max() < 1e-4
        first_goal = env.goal.copy()
        env.reset(seed=4, options=options)  # the poses decide; the seed does not
        assert np.abs(env.goal - first_goal).max() < 1e-9
        episode = rollout(env, ActionSequence(np.zeros((5, 12))), 5, options=options)
        assert np.abs(episode.grippers[0, :, :3] - start[:, :3]).max() < 1e-4
    finally:
        env.close()


def test_bad_reset_options_are_refused_in_one_line() -> None:
    env = make_env(MUJOCO_ROD, "bimanual", seed=0, render_mode=None, **QUICK)
    try:
        poses = _poses_of_a_random_shape(env, 1)
        far = poses.copy()
        far[1, 0] += 10.0
        cases = [({"start_pose": poses}, "not known"),
                 ({"goal_grippers": poses[:1]}, "(2, 7)"),
                 ({"goal_grippers": far}, "outside the task's workspace")]  # fmt: skip
        for options, message in cases:
            with pytest.raises(BadOption, match=message.replace("(", r"\(").replace(")", r"\)")):
                env.reset(seed=0, options=options)
    finally:
        env.close()


def _recording(seed: int) -> np.ndarray:
    """(T,V,3) markers of a slack cable whose ends swing: free markers on a sagging arc."""
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES)[:, None] / RATE
    phase = rng.uniform(0, 2 * np.pi, 2)
    left = np.hstack([0.03 * np.sin(3 * t + phase[0]), 0 * t, 0 * t])
    right = np.hstack([0.45 + 0.03 * np.sin(2 * t + phase[1]), 0 * t, 0.02 * np.sin(3 * t)])
    s = (ARC / ARC[-1])[None, :, None]
    markers = left[:, None] + s * (right - left)[:, None]
    markers[..., 2] -= 0.15 * np.sin(np.pi * s[..., 0])  # sag
    markers[:, 1] = left + 0.03 * np.array([1.0, 0.0, 0.0])
    markers[:, -2] = right - 0.03 * np.array([1.0, 0.0, 0.0])
    return markers


def test_the_twin_observes_the_recorded_markers_and_settles_at_recorded_poses() -> None:
    grip_arc = ARC - ARC[1]
    rod = RodSpec(length=float(grip_arc[-2]), n_segments=12, radius=0.005, density=500.0)
    backend = BackendSpec(rod=rod)
    recordings = [("0", _recording(0)), ("1", _recording(1))]
    cable = Cable(recordings, recordings, grip_arc, backend, deform.held_markers(len(ARC)))
    twin = make_twin(cable, backend, RATE, TwinSettings(episode_steps=5, noise_mm=2.0))
    env = make_env(twin.spec.backend, task=twin.spec.task, seed=0, render_mode=None)
    try:
        held = deform.held_markers(len(ARC))
        assert np.array_equal(env.marker_layout.held, held)
        # a marker model trained on the recordings' markers plans on the twin as it is
        spec = valid_model_spec({"name": "mlp", "hidden": 16, "layers": 1})
        MarkerView(env, build_marker_model(spec, len(ARC), held), device=None)
        recording = recordings[0][1]
        env.reset(seed=0, options=twin.options(recording, 10, 50))
        goal = env.goal_markers() - twin.offset
        # the held markers: the grips exactly, the outer ones along the held pair
        assert np.abs(goal[held] - recording[50, held]).max() < 2e-3
        gap = goal_gap_mm(env, recording[50], twin)
        assert 0 < gap < 100  # the twin's settled sag is not the drawn arc
        assert env.task_spec.control_dt == pytest.approx(1 / RATE)
    finally:
        env.close()


def test_a_twin_task_file_draws_starts_and_goals_from_recorded_poses(tmp_path: Path) -> None:
    """`write_twin_task`: a --spec file any command takes; its episodes start at recorded
    gripper poses, and a bad poses file is one BadInput naming it."""
    grip_arc = ARC - ARC[1]
    rod = RodSpec(length=float(grip_arc[-2]), n_segments=12, radius=0.005, density=500.0)
    backend = BackendSpec(rod=rod)
    recordings = [("0", _recording(0))]
    cable = Cable(recordings, recordings, grip_arc, backend, deform.held_markers(len(ARC)))
    twin = make_twin(cable, backend, RATE, TwinSettings(episode_steps=5))
    path = write_twin_task(twin, [recordings[0][1]], tmp_path / "twin")
    spec = EnvSpec.model_validate(yaml.safe_load(path.read_text()))
    assert spec.task.shapes == "recorded"
    poses = np.load(tmp_path / "twin" / "poses.npy")
    assert poses.shape == (FRAMES // 10, 2, 7)
    env = make_env(spec.backend, task=spec.task, seed=0, render_mode=None)
    try:
        env.reset(seed=1)
        reached = env.backend.gripper_poses()[:, :3]
        assert np.abs(poses[:, :, :3] - reached).max(axis=(1, 2)).min() < 1e-4
    finally:
        env.close()
    np.save(tmp_path / "bad.npy", poses[:, :1])
    bad = spec.task.model_copy(update={"recorded_poses": tmp_path / "bad.npy"})
    with pytest.raises(BadInput, match="bad.npy holds no \\(K, 2, 7\\) array"):
        make_env(spec.backend, task=bad, seed=0, render_mode=None)
    with pytest.raises(ValueError, match="give both or neither"):
        TaskSpec(shapes="recorded")
