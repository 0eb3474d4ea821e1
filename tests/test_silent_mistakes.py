"""Silent mistakes (issue 51): inputs and runs that used to end in exit 0 with a wrong result,
or deep inside with a message naming nothing the user gave, now say what went wrong."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from dlocli.bridge.remote import CellLost
from dlocli.env.shape_env import make_env
from dlocli.errors import BadOption
from dlocli.events import Event
from dlocli.runs.control import ControlSpec, run_control
from dlocli.specs import TaskSpec

from tiny import MUJOCO_ROD, file_digests, run_dlo


def _one_line(argv: list[str], capsys, root: Path) -> str:
    """The one error line of `dlo argv` (exit 2), which left every file under ``root`` as
    it was."""
    before = file_digests(root)
    code = run_dlo(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    assert file_digests(root) == before
    return lines[0]


# --------------------------------------------------------------------- separation limits
@pytest.mark.parametrize(
    ("task", "limits"),
    [("single", {"min_separation": 0.92}),
     ("bimanual", {"min_separation": 0.3, "max_separation": 0.7})],
    ids=["min-above-rest", "max-below-rest"],
)  # fmt: skip
def test_goal_refuses_separation_limits_that_exclude_the_rest_separation(
    task, limits, tmp_path, capsys
):
    """The grippers start every shape at rest, 0.9 rod lengths apart: limits without it held
    them there and `dlo goal` wrote the rest shape as a goal breaking them, exit 0."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({"task": limits}))
    out = tmp_path / "goal.npy"
    argv = ["goal", "--spec", str(spec), "--task", task, "--out", str(out)]
    line = _one_line(argv, capsys, tmp_path)
    assert "min_separation" in line and "max_separation" in line and "0.9" in line, line
    assert not out.exists()
    np.save(out, np.zeros((20, 3)))  # an existing goal stays as it was
    _one_line([*argv, "--overwrite"], capsys, tmp_path)


def test_separation_limits_around_the_rest_separation_give_goals_inside_them():
    env = make_env(MUJOCO_ROD, "bimanual", seed=0, render_mode=None, min_separation=0.5,
                   max_separation=0.92)  # fmt: skip
    try:
        poses = env.goal_gripper_poses
        separation = np.linalg.norm(poses[1, :3] - poses[0, :3]) / env.backend.rod.length
        assert 0.5 - 1e-9 <= separation <= 0.92 + 1e-9 and abs(separation - 0.9) > 0.01
    finally:
        env.close()


# --------------------------------------------------------------------- a stopped run's reward
def test_a_stopped_control_run_sums_the_rewards_of_the_steps_it_ran(near_rest_goal, tmp_path):
    """A run whose cell stops answering after 4 of 200 steps: its summary's cumulative reward
    is metrics.csv's, not that plus 196 steps at the divergence clip, and it says it stopped."""
    out = tmp_path / "run"
    task = TaskSpec(goal_file=near_rest_goal, shapes="near-rest", episode_steps=200)
    spec = ControlSpec(task=task, controller="random", out=out, seed=1)

    def lose_the_cell(event: Event) -> None:
        if event.done == 4:  # what a cell that stops answering raises inside the loop
            raise CellLost("the cell stopped answering")

    with pytest.raises(CellLost):
        run_control(spec, lose_the_cell)
    summary = json.loads((out / "summary.json").read_text())
    with open(out / "metrics.csv", newline="") as f:
        rewards = [float(row["reward"]) for row in csv.DictReader(f)]
    assert len(rewards) == summary["steps"] == 4
    assert summary["diverged"] is False and "stopped answering" in summary["stopped"]
    assert summary["cumulative_reward"] == pytest.approx(sum(rewards), abs=1e-3)
    assert summary["cumulative_reward"] > -1.5 * 4  # each step's reward lies in [-1.5, 0]


# --------------------------------------------------------------------- given orientations
QUICK = {"shapes": "near-rest", "episode_steps": 5, "reset_motion_steps": 5,
         "reset_settle_steps": 5}  # fmt: skip
#: (id, the right gripper's orientation, words the error holds)
BAD_QUATERNIONS = [
    ("zero", [0.0, 0.0, 0.0, 0.0], "norm 0"),
    ("huge", [1e200, 0.0, 0.0, 0.0], "norm inf"),
    ("scaled", [2.0, 0.0, 0.0, 0.0], "norm 2"),
    ("nan", [np.nan, 0.0, 0.0, 0.0], "finite (2, 7)"),
]


@pytest.fixture(scope="module")
def bimanual_env():
    env = make_env(MUJOCO_ROD, "bimanual", seed=0, render_mode=None, **QUICK)
    yield env
    env.close()


@pytest.mark.parametrize(("case", "quaternion", "words"), BAD_QUATERNIONS,
                         ids=[c[0] for c in BAD_QUATERNIONS])  # fmt: skip
@pytest.mark.parametrize("option", ["start_grippers", "goal_grippers"])
def test_a_reset_option_without_unit_quaternions_is_refused_naming_it(
    bimanual_env, option, case, quaternion, words
):
    poses = bimanual_env.backend.rest_gripper_poses()
    poses[1, 3:] = quaternion
    with pytest.raises(BadOption) as refused:
        bimanual_env.reset(seed=0, options={option: poses})
    message = str(refused.value)
    assert option in message and words in message and "\n" not in message, message
    if case != "nan":
        assert "right gripper" in message and "unit quaternion w x y z" in message, message


def test_a_near_unit_quaternion_is_normalised(bimanual_env):
    """A recording's rounding (norm 1.005) is no mistake: the gripper turns to the rotation."""
    poses = bimanual_env.backend.rest_gripper_poses()
    turned = np.array([np.cos(0.05), 0.0, 0.0, np.sin(0.05)])  # 0.1 rad about z: 10 steps
    poses[1, 3:] = 1.005 * turned
    bimanual_env.reset(seed=0, options={"start_grippers": poses})
    reached = bimanual_env.backend.gripper_poses()[1, 3:]
    assert np.abs(reached - turned).max() < 1e-4


@pytest.mark.parametrize(("case", "quaternion", "words"), BAD_QUATERNIONS[:3],
                         ids=[c[0] for c in BAD_QUATERNIONS[:3]])  # fmt: skip
def test_recorded_poses_without_unit_quaternions_are_refused_naming_file_and_row(
    case, quaternion, words, tmp_path, capsys
):
    poses = np.stack([make_env_rest_poses()] * 3)
    poses[2, 1, 3:] = quaternion
    recorded = tmp_path / "poses.npy"
    np.save(recorded, poses)
    spec = tmp_path / "spec.yaml"
    task = {"name": "bimanual", "shapes": "recorded", "recorded_poses": str(recorded)}
    spec.write_text(yaml.safe_dump({"task": task}))
    argv = ["goal", "--spec", str(spec), "--out", str(tmp_path / "goal.npy")]
    line = _one_line(argv, capsys, tmp_path)
    assert f"recorded_poses {recorded}: row 2: the right gripper's" in line, line
    assert words in line and "unit quaternion w x y z" in line, line
    assert not (tmp_path / "goal.npy").exists()


def make_env_rest_poses() -> np.ndarray:
    """(2, 7) the grippers' rest poses of the default rod."""
    env = make_env(MUJOCO_ROD, "bimanual", seed=0, render_mode=None, **QUICK)
    try:
        return env.backend.rest_gripper_poses()
    finally:
        env.close()
