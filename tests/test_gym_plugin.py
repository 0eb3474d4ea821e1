"""The Gymnasium face of dlocli: ids made by name, validated keyword arguments, one episode
length, the observation layout and Gymnasium's render convention."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest

import dlocli  # noqa: F401  (registers the ids)
from dlocli.backends import runnable_backends
from dlocli.env.registration import DEFAULT_EPISODE_STEPS, gym_id, gym_ids
from dlocli.errors import BadOption, UnknownName, UnknownOption
from dlocli.specs import TaskSpec, default_backend

#: the Gymnasium id of the MuJoCo rod the installed MuJoCo runs, single gripper
DEFAULT_ID = gym_id(default_backend(), "single")

FAST = {"shapes": "near-rest", "reset_motion_steps": 5, "reset_settle_steps": 5}
#: the ids whose backend runs here (one MuJoCo rod per MuJoCo major version)
RUNNABLE_IDS = sorted(i for i, (b, _) in gym_ids().items() if b in runnable_backends())


def test_ids_cover_every_backend_and_task():
    from dlocli.registry import backends, tasks

    ids = gym_ids()
    assert len(ids) == len(backends.names()) * len(tasks.names())
    assert ids["dlocli/MujocoSingle-v0"] == ("mujoco", "single")
    for env_id in ids:
        assert gym.spec(env_id).max_episode_steps == DEFAULT_EPISODE_STEPS
    assert TaskSpec.model_fields["episode_steps"].default == DEFAULT_EPISODE_STEPS


def test_gym_make_every_id_in_a_process_that_imports_only_gymnasium():
    code = textwrap.dedent(
        f"""
        import sys
        import gymnasium as gym
        assert "dlocli" not in sys.modules
        for env_id in {RUNNABLE_IDS!r}:
            env = gym.make("dlocli:" + env_id, **{FAST!r})
            assert env.spec.id == env_id and env.spec.max_episode_steps == 200, env.spec
            obs, info = env.reset(seed=0)
            assert env.observation_space.contains(obs)
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert -1.5 <= reward <= 0 and not truncated
            env.close()
        try:
            gym.make({DEFAULT_ID!r}, episode_step=50)
        except TypeError as exc:
            print(exc)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "got an unexpected keyword argument 'episode_step'" in out.stdout
    assert "did you mean 'episode_steps'" in out.stdout
    assert "valid ones: backend, task, goal, seed, render_mode" in out.stdout
    assert "shapes" in out.stdout and "max_linear_velocity" in out.stdout


@pytest.mark.filterwarnings("ignore:.*not in the possible render_modes")
@pytest.mark.parametrize(
    "kwargs,error,match",
    [
        ({"goals": "random"}, UnknownOption, "keyword argument 'goals'.*valid ones: backend"),
        ({"name": "bimanual"}, UnknownOption, "unexpected keyword argument 'name'"),
        ({"goal": "randm"}, BadOption, "'fixed' or 'random'.*did you mean 'random'"),
        ({"episode_steps": 0}, BadOption, "episode_steps"),
        ({"shapes": "circle"}, BadOption, "shapes"),
        ({"max_linear_velocity": -1.0}, BadOption, "max_linear_velocity"),
        ({"seed": -1}, BadOption, "seed"),
        ({"render_mode": "depth"}, BadOption, "render_mode"),
        ({"backend": "mujoko"}, UnknownName, "did you mean 'mujoco'"),
    ],
)
def test_bad_keywords_are_refused(kwargs, error, match):
    with pytest.raises(error, match=f"(?i){match}"):
        gym.make(DEFAULT_ID, **kwargs)
    assert issubclass(UnknownOption, TypeError) and issubclass(BadOption, ValueError)


def test_keywords_take_effect():
    env = gym.make(DEFAULT_ID, episode_steps=5, goal="random", seed=3, **FAST)
    try:
        assert env.spec.max_episode_steps == 5
        env.reset(seed=0)
        first = env.unwrapped.goal.copy()
        for t in range(1, 6):
            *_, truncated, info = env.step(env.action_space.sample())
            assert truncated == (t == 5) and info["t"] == t
        env.reset(seed=1)
        assert np.abs(env.unwrapped.goal - first).max() > 1e-3  # a new goal per episode
        assert env.unwrapped.task_spec.shapes == "near-rest"
        assert env.unwrapped.seed_value == 3
    finally:
        env.close()


def test_one_episode_length_whichever_keyword_sets_it():
    env = gym.make("dlocli/PybulletSingle-v0", max_episode_steps=4, **FAST)
    try:  # Gymnasium's own keyword sets the task's episode length too
        assert env.spec.max_episode_steps == 4
        assert env.unwrapped.task_spec.episode_steps == 4
        remade = gym.make(env.spec)
        assert remade.spec.max_episode_steps == 4
        assert remade.unwrapped.task_spec.episode_steps == 4
        remade.close()
    finally:
        env.close()
    with pytest.raises(ValueError, match="disagree"):
        gym.make("dlocli/PybulletSingle-v0", max_episode_steps=4, episode_steps=6, **FAST)


@pytest.mark.parametrize("velocity", [True, False])
def test_observation_slices_match_the_observation(velocity):
    env = gym.make(gym_id(default_backend(), "bimanual"), observe_velocity=velocity, **FAST)
    try:
        base = env.unwrapped
        obs, _ = env.reset(seed=0)
        obs, *_ = env.step(np.ones(12, dtype=np.float32))
        slices, shapes = base.observation_slices, base.observation_shapes
        n = base.n_segments
        expected = {"positions": (n, 3), "quaternions": (n, 4), "grippers": (2, 7), "goal": (n, 3)}
        if velocity:
            expected["velocities"] = (n, 7)
        assert shapes == expected and list(slices) == list(expected)
        assert sum(s.stop - s.start for s in slices.values()) == obs.shape[0]
        assert obs.shape[0] == (354 if velocity else 214)

        def part(name):
            return obs[slices[name]].reshape(shapes[name])

        np.testing.assert_allclose(part("goal"), base.goal, atol=1e-6)
        np.testing.assert_allclose(part("positions"), base.backend.segment_positions(), atol=1e-6)
        quat = base.backend.segment_quaternions()
        np.testing.assert_allclose(part("quaternions"), quat, atol=1e-6)
        np.testing.assert_allclose(part("grippers"), base.backend.gripper_poses(), atol=1e-6)
        if velocity:
            assert np.abs(part("velocities")).max() > 0  # the grippers moved
        for name, value in base.split_observation(obs).items():
            np.testing.assert_array_equal(value, part(name))
    finally:
        env.close()


def test_render_follows_gymnasiums_convention():
    from gymnasium.utils.env_checker import check_env

    env = gym.make(DEFAULT_ID, **FAST)
    try:
        env.reset(seed=0)
        assert env.render_mode is None and env.render() is None
    finally:
        env.close()
    env = gym.make(DEFAULT_ID, render_mode="rgb_array", episode_steps=20, **FAST)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
        check_env(env.unwrapped, skip_render_check=False)  # unwrapped, as Gymnasium advises
    finally:
        env.close()


@pytest.mark.parametrize("env_id", RUNNABLE_IDS)
def test_torchrl_gymenv_builds_every_id_and_passes_its_spec_check(env_id):
    """TorchRL's GymEnv passes ``frameskip`` and retries without it on Python's own
    "unexpected keyword argument" TypeError; its spec check then steps the env."""
    pytest.importorskip("torchrl")
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv("dlocli:" + env_id, episode_steps=5, **FAST)
    try:
        check_env_specs(env, seed=0)
        assert env.rollout(3).batch_size == (3,)
    finally:
        env.close()
