"""DLOShapeEnv on every backend and task: Gymnasium's and SB3's checkers, reward, resets."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import dlocli
from dlocli.backends import runnable_backends
from dlocli.env.registration import gym_id
from dlocli.errors import BadInput, UnknownName
from dlocli.specs import default_backend

#: the Gymnasium id of the MuJoCo rod the installed MuJoCo runs, single gripper
DEFAULT_ID = gym_id(default_backend(), "single")

CASES = [(b, t) for b in runnable_backends() for t in ("single", "bimanual")]


@pytest.fixture(scope="module")
def envs():
    cache = {}
    yield cache
    for env in cache.values():
        env.close()


def get_env(envs, backend, task):
    if (backend, task) not in envs:
        envs[(backend, task)] = dlocli.make_env(
            backend=backend, task=task, seed=0, episode_steps=20
        )
    return envs[(backend, task)]


@pytest.mark.parametrize("backend,task", CASES)
def test_gymnasium_env_checker(envs, backend, task):
    from gymnasium.utils.env_checker import check_env

    check_env(get_env(envs, backend, task), skip_render_check=False)


@pytest.mark.parametrize("backend,task", CASES)
def test_sb3_env_checker(envs, backend, task):
    from stable_baselines3.common.env_checker import check_env

    check_env(get_env(envs, backend, task), warn=False)


@pytest.mark.parametrize("backend,task", CASES)
def test_episode_reward_and_truncation(envs, backend, task):
    env = get_env(envs, backend, task)
    obs, info = env.reset(seed=3)
    assert env.action_space.shape == ((6,) if task == "single" else (12,))
    parts = env.split_observation(obs)
    np.testing.assert_allclose(parts["goal"], env.goal, atol=1e-6)
    truncated, t = False, 0
    while not truncated:
        obs, r, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated and -1.5 <= r <= 0.0
        expected = -min(np.linalg.norm(env.split_observation(obs)["positions"] - env.goal), 1.5)
        assert r == pytest.approx(expected, abs=1e-4)
        positions = env.split_observation(obs)["positions"]
        assert info["shape_error_mm"] == pytest.approx(
            1000 * np.linalg.norm(positions - env.goal, axis=-1).mean(), rel=1e-4, abs=1e-3
        )
        t += 1
    assert t == 20


def test_single_task_keeps_left_gripper_static(envs):
    env = get_env(envs, runnable_backends()[0], "single")
    env.reset(seed=1)
    left = env.backend.gripper_poses()[0].copy()
    for _ in range(10):
        env.step(np.ones(6, dtype=np.float32))
    np.testing.assert_allclose(env.backend.gripper_poses()[0], left)


def test_reset_distribution_is_seeded_and_varied(envs):
    env = get_env(envs, runnable_backends()[0], "single")
    a, _ = env.reset(seed=5)
    b, _ = env.reset(seed=5)
    c, _ = env.reset(seed=6)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_random_goals_change_per_episode():
    from dlocli.specs import TaskSpec

    env = dlocli.make_env(task=TaskSpec(goal="random", episode_steps=5), seed=0)
    env.reset(seed=0)
    g0 = env.goal.copy()
    env.reset(seed=1)
    assert np.abs(env.goal - g0).max() > 1e-3
    env.close()


def test_gym_ids_are_registered():
    assert DEFAULT_ID in gym.registry
    env = gym.make(DEFAULT_ID, episode_steps=5)
    env.reset(seed=0)
    env.close()


def test_bad_names_and_goals(tmp_path):
    with pytest.raises(UnknownName, match="valid backends: mujoco, mujoco-flex, pybullet"):
        dlocli.make_env(backend="mujoko")
    bad = tmp_path / "goal.npy"
    np.save(bad, np.zeros((5, 3)))
    with pytest.raises(BadInput, match=r"shape \(5, 3\)"):
        dlocli.make_env(goal=bad)
    far = tmp_path / "far.npy"
    np.save(far, np.stack([np.linspace(10, 11, 20), np.zeros(20), np.zeros(20)], axis=1) * 0.95)
    with pytest.raises(BadInput):
        dlocli.make_env(goal=far)


def test_a_cancelled_token_stops_the_env_at_its_next_step():
    """Stops reach the env as the token it is handed (the commands hand the process's stop
    signals): a step after the cancellation raises the stop, once."""
    from dlocli.cancel import CancelToken

    token = CancelToken()
    env = dlocli.make_env(task="single", seed=0, episode_steps=5, cancel=token)
    try:
        env.reset(seed=0)
        still = np.zeros(env.action_space.shape, dtype=np.float32)
        env.step(still)
        token.cancel()
        with pytest.raises(KeyboardInterrupt):
            env.step(still)
        assert token.reason is None, "the stop is raised once"
        assert env.step(still)[0].shape == env.observation_space.shape
    finally:
        env.close()
