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
from dlocli.runs.control import ControlSpec, run_control
from dlocli.specs import TaskSpec

from tiny import file_digests, run_dlo


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
    env = make_env("mujoco", "bimanual", seed=0, render_mode=None, min_separation=0.5,
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

    def lose_the_cell(record: dict[str, float]) -> None:
        if record["step"] == 4:  # what a cell that stops answering raises inside the loop
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
