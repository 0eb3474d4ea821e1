"""Silent mistakes (issue 51): inputs and runs that used to end in exit 0 with a wrong result,
or deep inside with a message naming nothing the user gave, now say what went wrong."""

from __future__ import annotations

import csv
import json

import pytest

from dlocli.bridge.remote import CellLost
from dlocli.runs.control import ControlSpec, run_control
from dlocli.specs import TaskSpec


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
