"""The held-end servo (no model) and the planners' pull towards it: its targets from the goal's
held ends, its control of the real MuJoCo rod against doing nothing from the same starts, and
the planner's servo term."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import dlocli
from dlocli.backends.rotations import quat_from_rotvec, quat_multiply, quat_to_matrix
from dlocli.controllers.base import make_controller, references
from dlocli.controllers.held_end import (
    end_tangent,
    roll_directions,
    servo_action,
    servo_targets,
    without,
)
from dlocli.controllers.mpc import GradientMPC, MPCSpec
from dlocli.env.metrics import shape_error_mm
from dlocli.env.rollout import rollout
from dlocli.models import build_model
from dlocli.models.spec import model_spec

from tiny import MUJOCO_ROD

RIGHT = np.array([False, True])


def bent_rod() -> tuple[np.ndarray, np.ndarray]:
    """Twenty points along a sagging arc and the two grippers holding its ends, each gripper's
    x axis along the rod where it holds it (pointing out of the rod)."""
    s = np.linspace(0.0, 1.0, 20)
    points = np.stack([s - 0.5, 0.1 * np.sin(np.pi * s), 1.0 - 0.3 * np.sin(np.pi * s)], 1)
    grippers = np.zeros((2, 7))
    for k, (held, inward) in enumerate(((0, 1), (19, -1))):
        out = -end_tangent(points, held, inward)
        turn = quat_from_rotvec(np.cross([1.0, 0, 0], out / np.linalg.norm(out)))
        grippers[k, 3:] = turn / np.linalg.norm(turn)
        grippers[k, :3] = points[held] - 0.02 * quat_to_matrix(grippers[k, 3:])[:, 0]
    return points, grippers


def test_at_the_goal_the_grippers_stay():
    points, grippers = bent_rod()
    targets = servo_targets(points, points, grippers, RIGHT)
    np.testing.assert_allclose(targets, grippers, atol=1e-12)


def test_a_goal_moved_rigidly_about_the_held_end_moves_the_gripper_alike():
    """The goal is the rod turned about its right held point (across the rod there, so no
    roll) and shifted: the target is the gripper moved the same way; the left one stays."""
    points, grippers = bent_rod()
    tangent = end_tangent(points, 19, -1)
    axis = np.cross(tangent, [0.0, 0.0, 1.0])
    turn = quat_from_rotvec(0.3 * axis / np.linalg.norm(axis))
    shift = np.array([0.05, -0.02, 0.03])
    rotation = quat_to_matrix(turn)
    goal = (points - points[19]) @ rotation.T + points[19] + shift
    targets = servo_targets(points, goal, grippers, RIGHT)
    np.testing.assert_allclose(targets[0], grippers[0])
    moved = (grippers[1, :3] - points[19]) @ rotation.T + points[19] + shift
    np.testing.assert_allclose(targets[1, :3], moved, atol=1e-9)
    np.testing.assert_allclose(
        quat_to_matrix(targets[1, 3:]), quat_to_matrix(quat_multiply(turn, grippers[1, 3:])),
        atol=1e-9,
    )  # fmt: skip


@pytest.mark.parametrize("hide", ["too few", "all hidden", "tangent hidden"])
def test_no_target_where_the_held_end_cannot_be_read(hide):
    points, grippers = bent_rod()
    if hide == "too few":
        points = points[:5]
    elif hide == "all hidden":
        points = np.full_like(points, np.nan)
    else:
        points = points.copy()
        points[17] = np.nan
    assert servo_targets(points, points, grippers, RIGHT) is None


def test_held_end_is_a_reference_after_doing_nothing_and_random():
    assert list(references())[:3] == ["zero", "random", "held-end"]


@pytest.fixture(scope="module")
def env():
    env = dlocli.make_env(MUJOCO_ROD, "single", seed=0)
    yield env
    env.close()


@pytest.mark.parametrize("seed", [3, 4])
def test_the_servo_closes_most_of_the_error_on_the_rod(env, seed):
    """On the default task (a goal the rod rests in, both ends held) the servo ends far nearer
    the goal than doing nothing from the same start: it closed 94-98% of the error over 40
    trials of the default rod (docs: benchmarks); 75% here leaves room for another CPU."""
    finals = {}
    for name in ("held-end", "zero"):
        episode = rollout(env, make_controller(name, env, seed=0), seed)
        error = shape_error_mm(episode.positions, episode.goal)
        finals[name] = float(error[-1])
    assert finals["held-end"] < 0.25 * finals["zero"]


def test_servo_cost_adds_each_actions_distance_from_the_servo_but_the_roll(env):
    """servo_cost w appends sqrt(w) x (action - the servo's action), the grippers' roll
    projected out, for every planned action after the paper's terms; a large w brings the
    plan nearer the servo's action than the paper's cost does (the roll, left to the model,
    may take the plan to the action bounds, so not onto it)."""
    torch.manual_seed(0)  # the untrained model's weights: the same whatever ran before
    model = build_model(model_spec({"hidden": 16, "edge_layers": 1, "node_layers": 1,
                                    "lstm_layers": 1}), 20).eval()  # fmt: skip
    obs, _ = env.reset(seed=5)
    pulled = GradientMPC(env, model, MPCSpec(servo_cost=100.0, iterations=5))
    paper = GradientMPC(env, model, MPCSpec(servo_cost=0.0))
    for mpc in (pulled, paper):
        mpc.reset(env.goal)
    action, unpulled = pulled.act(obs), paper.act(obs)
    servo = servo_action(env, env.task, obs)
    assert servo is not None and np.abs(servo).max() > 0.1
    read = without(roll_directions(env.task, env.split_observation(obs)["grippers"]))
    roll = np.eye(6) - read  # the right gripper's turn about its own x axis, alone
    assert np.linalg.matrix_rank(roll, tol=1e-6) == 1
    np.testing.assert_allclose(roll[:3], 0.0, atol=1e-12)  # no linear part
    near, far = (np.linalg.norm((a - servo) @ read) for a in (action, unpulled))
    assert near < 0.5 * far
    state = pulled.state_tensor(obs)
    plan = torch.linspace(-0.6, 0.6, 30).view(1, 5, 6)
    with torch.no_grad():
        ours, theirs = pulled.residuals(state, plan, None), paper.residuals(state, plan, None)
        rolled = pulled.residuals(state, plan + torch.as_tensor(roll[5], dtype=torch.float32),
                                  None)  # fmt: skip
    servo_t, read_t = (torch.as_tensor(a, dtype=torch.float32) for a in (servo, read))
    extra = 10.0 * ((plan - servo_t) @ read_t).flatten(1)
    torch.testing.assert_close(ours[:, : theirs.shape[1]], theirs)
    torch.testing.assert_close(ours[:, theirs.shape[1] :], extra)
    # a turn about the roll axis leaves the servo's term as it was
    torch.testing.assert_close(rolled[:, -extra.shape[1] :], extra, atol=1e-5, rtol=0)


def test_roll_search_pulls_towards_the_roll_the_model_predicts_nearest_the_goal(env):
    """roll_search S: the pull's target is the servo's action with the moving gripper's roll
    turned at one of ROLL_RATES, the one whose predicted positions after the horizon and S
    still steps lie nearest the goal; the pull then covers the roll too."""
    from dlocli.controllers.planning import ROLL_RATES

    torch.manual_seed(0)
    model = build_model(model_spec({"hidden": 16, "edge_layers": 1, "node_layers": 1,
                                    "lstm_layers": 1}), 20).eval()  # fmt: skip
    obs, _ = env.reset(seed=5)
    planner = GradientMPC(env, model, MPCSpec(servo_cost=1.0, roll_search=3, horizon=2))
    planner.reset(env.goal)
    planner.act(obs)
    servo = torch.as_tensor(servo_action(env, env.task, obs), dtype=torch.float32)
    (roll,) = torch.as_tensor(roll_directions(env.task, env.split_observation(obs)["grippers"]),
                              dtype=torch.float32)  # fmt: skip
    candidates = torch.stack([(servo + r * roll).clamp(-1, 1) for r in ROLL_RATES])
    chosen = int(torch.cdist(planner._servo[None], candidates).argmin())
    torch.testing.assert_close(planner._servo, candidates[chosen], atol=1e-5, rtol=0)
    assert planner._servo_read is None
    plans = torch.cat([candidates[:, None].expand(-1, 2, -1), torch.zeros(3, 3, 6)], dim=1)
    with torch.no_grad():
        predicted = planner.view.predict(planner._observed, env.task.to_grippers(plans), None)
    miss = (predicted[:, -1] - planner._goal).square().sum(dim=(1, 2))
    assert miss[chosen] == miss.min()
    no_search = GradientMPC(env, model, MPCSpec(servo_cost=1.0, horizon=2))
    no_search.reset(env.goal)
    no_search.act(obs)
    assert no_search._servo_read is not None
    torch.testing.assert_close(no_search._servo, servo)


def test_servo_above_hands_the_grippers_to_the_servo_while_the_model_misses(env):
    """servo_above_mm: the planner keeps the average of its one-step prediction error's mean
    distance; above the threshold the servo's action goes out (and is what the next step's
    error is measured against), below it the plan's, with or without the pull. An untrained
    model misses by far more than a micrometre and by far less than a metre."""
    torch.manual_seed(0)
    model = build_model(model_spec({"hidden": 16, "edge_layers": 1, "node_layers": 1,
                                    "lstm_layers": 1}), 20).eval()  # fmt: skip
    for threshold, serves, pull in ((1e-3, True, 1e-3), (1e3, False, 1e-3), (1e-3, True, 0.0)):
        obs, _ = env.reset(seed=5)
        planner = GradientMPC(env, model, MPCSpec(servo_cost=pull, servo_above_mm=threshold))
        plain = GradientMPC(env, model, MPCSpec(servo_cost=pull))
        for mpc in (planner, plain):
            mpc.reset(env.goal)
        first = planner.act(obs)
        np.testing.assert_allclose(first, plain.act(obs), atol=1e-6)  # no error measured yet
        assert planner._miss is None and "served" not in planner.last_stats
        expected = planner._expected.clone()
        obs, *_ = env.step(first)
        action = planner.act(obs)
        observed = planner._observed[0, :, :3]
        miss = float((observed - expected).norm(dim=-1).mean())
        assert planner._miss == pytest.approx(miss, rel=1e-6)
        assert 1e-6 < miss < 1.0
        servo = servo_action(env, env.task, obs)
        assert servo is not None
        if serves:
            np.testing.assert_allclose(action, servo, atol=1e-6)
            assert planner.last_stats["served"] == 1.0
        else:
            assert "served" not in planner.last_stats
            np.testing.assert_allclose(action, planner.plan[0].numpy(), atol=1e-6)
        assert planner._disturbance is None  # the disturbance option stays off
