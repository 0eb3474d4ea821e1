"""The safety envelope: each limit holds on both backends, and every clip is counted."""

from __future__ import annotations

import numpy as np
import pytest

import dlocli
from dlocli.backends.base import GripperLimits
from dlocli.env.envelope import Envelope
from dlocli.errors import BadInput
from dlocli.specs import EnvelopeSpec

from tiny import MUJOCO_ROD

BACKENDS = [MUJOCO_ROD, "pybullet"]
DT = 0.02


def _env(backend: str, task: str = "single", speed: float = 0.1, **envelope: object):
    env = dlocli.make_env(backend, task, seed=0, episode_steps=60, shapes="near-rest",
                          max_linear_velocity=speed, envelope=EnvelopeSpec(**envelope))  # fmt: skip
    env.reset(seed=1)
    return env


def _drive(env, action: np.ndarray, steps: int) -> np.ndarray:
    """(steps + 1, 2, 7) gripper poses under a constant ``action``."""
    poses = [env.backend.gripper_poses()]
    for _ in range(steps):
        env.step(action)
        poses.append(env.backend.gripper_poses())
    return np.array(poses)


@pytest.mark.parametrize("backend", BACKENDS)
def test_speed_is_held_to_its_limit(backend):
    env = _env(backend, max_linear_speed=0.05, max_angular_speed=0.2)
    poses = _drive(env, np.ones(6), 5)
    speeds = np.linalg.norm(np.diff(poses[:, 1, :3], axis=0), axis=1) / DT
    assert speeds.max() == pytest.approx(0.05, rel=1e-9)  # the full command, cut to the limit
    assert env.envelope.summary()["clipped_speed"] == 5
    env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_acceleration_is_held_to_its_limit(backend):
    env = _env(backend, max_linear_acceleration=1.0)
    poses = _drive(env, np.r_[np.ones(3), np.zeros(3)], 12)
    velocities = np.diff(poses[:, 1, :3], axis=0) / DT
    changes = np.linalg.norm(np.diff(np.vstack([np.zeros(3), velocities]), axis=0), axis=1) / DT
    assert changes.max() <= 1.0 + 1e-6
    assert changes[0] == pytest.approx(1.0, rel=1e-6)  # from rest: the limit, not the command
    # the command (0.1 m/s on each axis: 0.173 m/s) takes 8 clipped steps of 0.02 m/s, then one
    assert np.linalg.norm(velocities[-1]) == pytest.approx(np.sqrt(3) * 0.1, rel=1e-6)
    assert env.envelope.summary()["clipped_acceleration"] == 8
    env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_gripper_stays_in_its_own_box(backend):
    start = _env(backend).backend.gripper_poses()[1, :3]
    box = {"right_low": tuple(start - 0.05), "right_high": tuple(start + [0.01, 0.05, 0.05])}
    env = _env(backend, **box)
    poses = _drive(env, np.r_[1.0, 0, 0, 0, 0, 0], 20)  # +x: 0.2 m asked, 1 cm allowed
    assert poses[:, 1, 0].max() == pytest.approx(start[0] + 0.01, abs=1e-9)
    assert env.envelope.summary()["clipped_gripper_workspace"] >= 15
    env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_tasks_separation_clips_are_counted(backend):
    env = _env(backend, "bimanual")
    length = env.backend.rod.length
    outwards = np.r_[-1.0, 0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0]  # the grippers pull apart
    poses = _drive(env, outwards, 40)  # from ~0.82 rod lengths apart, 8 mm a step
    separation = np.linalg.norm(poses[:, 1, :3] - poses[:, 0, :3], axis=1)
    assert separation.max() <= 0.95 * length + 1e-9
    assert env.envelope.summary()["clipped_separation"] >= 5
    env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_tasks_workspace_clips_are_counted(backend):
    env = _env(backend, speed=1.0)
    length = env.backend.rod.length
    poses = _drive(env, np.r_[0, 0, 1.0, 0, 0, 0], 60)  # 1.2 m up: past the top
    assert poses[:, 1, 2].max() == pytest.approx(1.4 * length)  # the workspace's top
    assert env.envelope.summary()["clipped_workspace"] >= 5
    env.close()


def test_no_envelope_changes_nothing_and_counts_nothing_within_the_limits():
    plain, enveloped = _env(MUJOCO_ROD), _env(MUJOCO_ROD, max_linear_speed=2.0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        action = rng.uniform(-0.5, 0.5, 6)
        a, b = plain.step(action)[0], enveloped.step(action)[0]
        assert np.array_equal(a, b)
    assert sum(enveloped.envelope.summary().values()) == 0
    plain.close()
    enveloped.close()


def test_an_envelope_that_excludes_the_start_is_refused():
    with pytest.raises(BadInput, match="outside its envelope box"):
        _env(MUJOCO_ROD, right_low=(2.0, 2.0, 2.0), right_high=(3.0, 3.0, 3.0))


@pytest.mark.parametrize(
    "fields, problem",
    [({"left_low": (0.0, 0.0, 0.0)}, "give both"),
     ({"right_low": (0.0, 0.0, 1.0), "right_high": (1.0, 1.0, 0.5)}, "below"),
     ({"max_linear_speed": -1.0}, "greater than 0")],
)  # fmt: skip
def test_bad_envelopes_are_refused(fields, problem):
    with pytest.raises(ValueError, match=problem):
        EnvelopeSpec(**fields)


def test_lost_tracking_stops_the_grippers_after_the_stated_time():
    envelope = Envelope(EnvelopeSpec(stop_after_lost_s=0.05), GripperLimits.default(1.0),
                        np.array([False, True]), DT)  # fmt: skip
    poses = np.zeros((2, 7))
    poses[:, 2], poses[:, 3], poses[1, 0] = 0.8, 1.0, 0.45
    command = np.tile([0.05, 0.0, 0.0, 0.0, 0.0, 0.1], (2, 1))
    sent = [envelope.apply(command, poses, tracked) for tracked in
            [True, False, False, False, True, False]]  # fmt: skip
    moving = [bool(np.any(twist)) for twist in sent]
    # lost for 0.02, 0.04, 0.06 s: the third is past 0.05 s; tracked again, it moves at once
    assert moving == [True, True, True, False, True, True]
    assert envelope.summary()["clipped_tracking_lost"] == 1
