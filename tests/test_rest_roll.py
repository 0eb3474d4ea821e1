"""The roll the rod rests best at: rest states from real episodes, the locally weighted map's
roll on the real MuJoCo rod settled at a range of rolls, the planner's servo turned by it, and
the rest states a checkpoint carries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import dlocli
from dlocli.backends.rotations import quat_from_rotvec, quat_multiply
from dlocli.controllers.held_end import roll_directions, servo_action, without
from dlocli.controllers.mpc import GradientMPC, MPCSpec
from dlocli.controllers.rest_roll import REST_WINDOW_S, RestMap, rest_states
from dlocli.data import Dataset
from dlocli.env.metrics import shape_error_mm
from dlocli.env.rollout import ActionSequence, rollout
from dlocli.env.shapes import drive_grippers
from dlocli.errors import BadInput
from dlocli.models import build_model
from dlocli.models.checkpoints import REST_STATES, load_model, save_checkpoint
from dlocli.models.spec import model_spec

from tiny import MUJOCO_ROD

RIGHT = np.array([False, True])
#: rolls (rad) of the right gripper the rod is settled at, and the goal's
ROLLS = np.linspace(-0.6, 0.6, 9)
GOAL_ROLL = 0.45
SETTLE_STEPS = 60


@pytest.fixture(scope="module")
def env():
    env = dlocli.make_env(MUJOCO_ROD, "single", seed=0)
    yield env
    env.close()


def rolled(poses: np.ndarray, angle: float) -> np.ndarray:
    """``poses`` (2, 7) with the right gripper turned by ``angle`` about its own x axis."""
    turned = np.array(poses, dtype=np.float64)
    turned[1, 3:] = quat_multiply(turned[1, 3:], quat_from_rotvec(np.array([angle, 0.0, 0.0])))
    return turned


def settle_at(env, base: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The grippers' poses (2, 7) and the rod's mean positions (N, 3) over the last rest
    window, the right gripper driven to ``base`` turned by ``angle`` and held still."""
    backend, task = env.backend, env.task_spec
    assert drive_grippers(backend, task, rolled(base, angle), RIGHT)
    window = int(round(REST_WINDOW_S / task.control_dt))
    still = np.zeros(env.action_space.shape)
    positions = []
    for _ in range(SETTLE_STEPS):
        env.step(still)
        positions.append(env.state_parts()["positions"])
    return backend.gripper_poses(), np.mean(positions[-window:], axis=0)


@pytest.fixture(scope="module")
def rested(env):
    """The real rod settled at each of ROLLS and at GOAL_ROLL from one start: rest states
    {"grippers", "positions"} over ROLLS, and the goal's shape."""
    env.reset(seed=2)
    base = env.backend.gripper_poses()
    found = [settle_at(env, base, angle) for angle in ROLLS]
    _, goal = settle_at(env, base, GOAL_ROLL)
    states = {
        "grippers": np.array([g for g, _ in found]),
        "positions": np.array([p for _, p in found]),
    }
    return base, states, goal


def test_rest_states_are_each_start_and_each_end_the_grippers_stood_still_through(env):
    steps = env.task_spec.episode_steps
    still = rollout(env, ActionSequence(np.zeros((steps, 6))), seed=1)
    rng = np.random.default_rng(0)
    moving = rollout(env, ActionSequence(rng.uniform(-1, 1, (steps, 6))), seed=2)
    data = Dataset.from_episodes([still, moving])
    found = rest_states(data, RIGHT, 0.02)
    window = int(round(REST_WINDOW_S / 0.02))
    np.testing.assert_allclose(found["grippers"], np.stack(
        [still.grippers[0], still.grippers[-1], moving.grippers[0]]), atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(found["positions"], np.stack(
        [still.positions[0], still.positions[-window:].mean(0), moving.positions[0]]),
        atol=1e-6)  # fmt: skip
    assert found["grippers"].dtype == np.float32


def test_the_map_turns_the_roll_towards_where_the_rod_rested_at_the_goal(rested):
    """From the rest states of the rod settled at nine rolls, a start rested at one of them
    is told to turn most of the way to the goal's roll, and the rest shape there is nearer
    the goal than where it stands."""
    base, states, goal = rested
    rest_map = RestMap(states["grippers"], states["positions"], RIGHT)
    for start in (0, 2):  # rolls -0.6 and -0.3
        offsets = rest_map.roll_offsets(states["grippers"][start], goal)
        assert offsets is not None and offsets.shape == (1,)
        wrong = GOAL_ROLL - ROLLS[start]
        assert abs(ROLLS[start] + offsets[0] - GOAL_ROLL) < 0.35 * wrong, offsets
    # the rolled rod's rest shapes differ from the goal's by millimetres: the roll shows
    errors = [float(shape_error_mm(p, goal)) for p in states["positions"]]
    assert errors[0] > 1.0 and int(np.argmin(errors)) in (7, 8)


def test_the_map_says_nothing_far_from_its_rest_states_or_for_another_shape(rested):
    base, states, goal = rested
    rest_map = RestMap(states["grippers"], states["positions"], RIGHT)
    far = np.array(states["grippers"][0], dtype=np.float64)
    far[1, :3] += [0.1, 0.0, 0.0]
    assert rest_map.roll_offsets(far, goal) is None
    assert rest_map.roll_offsets(states["grippers"][0], goal[:10]) is None


def tiny_model(rest: dict[str, np.ndarray] | None) -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model(model_spec({"hidden": 16, "edge_layers": 1, "node_layers": 1,
                                    "lstm_layers": 1}), 20).eval()  # fmt: skip
    model.rest_states = rest
    return model


def test_the_planner_pulls_the_roll_where_the_rest_states_say(env, rested):
    """rest_roll: the servo's action the plan is pulled to turns the roll towards the map's
    roll (at most at the largest rate), all else the servo's; off, the roll is not pulled."""
    base, states, goal = rested
    env.reset(seed=2)
    assert drive_grippers(env.backend, env.task_spec, rolled(base, ROLLS[2]), RIGHT)
    obs, *_ = env.step(np.zeros(env.action_space.shape))
    grippers = env.split_observation(obs)["grippers"]
    offsets = RestMap(states["grippers"], states["positions"], RIGHT).roll_offsets(grippers, goal)
    assert offsets is not None and offsets[0] > 0.1
    servo = servo_action(env, env.task, obs)
    rolls = roll_directions(env.task, grippers)
    on = GradientMPC(env, tiny_model(states), MPCSpec(servo_cost=1e-3, rest_roll=True))
    off = GradientMPC(env, tiny_model(states), MPCSpec(servo_cost=1e-3, rest_roll=False))
    for planner in (on, off):
        planner.reset(goal)
        planner.act(obs)
    pulled = on._servo.numpy()
    assert on._servo_read is None  # the roll too is pulled
    np.testing.assert_allclose(pulled @ rolls[0], 1.0, atol=1e-5)  # far off: the largest rate
    np.testing.assert_allclose(pulled @ without(rolls), servo @ without(rolls), atol=1e-5)
    assert off._servo_read is not None
    np.testing.assert_allclose(off._servo.numpy(), servo, atol=1e-5)
    # without rest states the option changes nothing
    bare = GradientMPC(env, tiny_model(None), MPCSpec(servo_cost=1e-3, rest_roll=True))
    bare.reset(goal)
    bare.act(obs)
    assert bare._servo_read is not None


def held_states(states: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {name: torch.from_numpy(array.astype(np.float32)) for name, array in states.items()}


def test_a_checkpoint_carries_its_rest_states(rested, tmp_path):
    _, states, _ = rested
    held = held_states(states)
    path = save_checkpoint(tiny_model(None), tmp_path / "model.pt", {REST_STATES: held})
    loaded = load_model(path)
    for name, array in states.items():
        np.testing.assert_allclose(loaded.rest_states[name], array, atol=1e-6)
    assert load_model(save_checkpoint(tiny_model(None), tmp_path / "bare.pt")).rest_states is None


@pytest.mark.parametrize("breaking", ["nan", "inf", "pose of 6", "counts differ", "a string",
                                      "no positions", "a list"])  # fmt: skip
def test_broken_rest_states_are_refused_in_one_line(rested, tmp_path, breaking):
    _, states, _ = rested
    held: object = held_states(states)
    grippers, positions = held["grippers"].clone(), held["positions"].clone()
    if breaking == "nan":
        positions[0, 0, 0] = float("nan")
    elif breaking == "inf":
        grippers[1, 1, 3] = float("inf")
    elif breaking == "pose of 6":
        grippers = grippers[:, :, :6]
    elif breaking == "counts differ":
        positions = positions[:-1]
    held = {"grippers": grippers, "positions": positions}
    if breaking == "a string":
        held = {"grippers": "rest", "positions": positions}
    elif breaking == "no positions":
        held = {"grippers": grippers}
    elif breaking == "a list":
        held = [grippers, positions]
    path = save_checkpoint(tiny_model(None), tmp_path / "broken.pt", {REST_STATES: held})
    with pytest.raises(BadInput, match="unreadable rest states") as refused:
        load_model(path)
    assert "\n" not in str(refused.value)
