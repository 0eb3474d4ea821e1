"""A model steps at its data's control period and is used only at it: a checkpoint records the
period, and `dlo control`, the planners, `dlo eval` and `dlo train --init-from` refuse another
in one line naming both rates and the fix, before any run directory is written; a checkpoint
from before the record is taken as it is (nothing to compare)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from dlocli.errors import BadInput

from tiny import dlo_import, run_dlo, write_cable

#: a marker model of 6 recorded markers, one held at each end, as `dlo control` observes them
OBSERVE = ["--observation", "markers", "--markers", "6", "--gripper-markers", "0"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A cable recorded at 100 Hz, imported as it is (data) and at 50 Hz (data50), and a tiny
    marker model trained on the 100 Hz import (model)."""
    root = tmp_path_factory.mktemp("rate")
    write_cable(root / "cable", n_train=3, n_eval=1)
    assert dlo_import(root / "cable", root / "data", "--held", "0,-1") == 0
    assert dlo_import(root / "cable", root / "data50", "--held", "0,-1", "--control-hz", "50") == 0
    assert run_dlo(["train", "--data", str(root / "data"), "--model", "mlp", "--hidden", "8",
                    "--update-steps", "2", "--rollout-steps", "2", "--eval-every", "2",
                    "--device", "cpu", "--out", str(root / "model")]) == 0  # fmt: skip
    return root


def control(goal: Path, checkpoint: Path, out: Path, *flags: str) -> int:
    argv = ["--goal", str(goal), "--checkpoint", str(checkpoint), *OBSERVE, "--steps", "2"]
    return run_dlo(["control", *argv, "--shapes", "near-rest", "--out", str(out), *flags])


def refused_in_one_line(capsys, *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert all(word in err for word in words), err
    return err


def test_a_trained_model_records_its_data_rate(recorded):
    payload = torch.load(recorded / "model/checkpoints/final.pt", weights_only=True)
    assert payload["control_dt"] == pytest.approx(0.01)


def test_control_refuses_a_model_of_another_rate(recorded, near_rest_goal, tmp_path, capsys):
    out = tmp_path / "control"
    assert control(near_rest_goal, recorded / "model", out) == 2
    refused_in_one_line(capsys, "100 Hz", "50 Hz", "--control-dt 0.01", "re-train")
    assert not out.exists()
    # at the model's rate it controls
    assert control(near_rest_goal, recorded / "model", out, "--control-dt", "0.01") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 2
    assert json.loads((out / "spec.json").read_text())["task"]["control_dt"] == 0.01


def test_a_checkpoint_without_its_rate_is_taken_as_it_is(recorded, near_rest_goal, tmp_path):
    payload = torch.load(recorded / "model/checkpoints/final.pt", weights_only=True)
    del payload["control_dt"]  # as checkpoints were written before they recorded it
    old = tmp_path / "old.pt"
    torch.save(payload, old)
    assert control(near_rest_goal, old, tmp_path / "control") == 0


def test_planners_refuse_a_model_of_another_rate(recorded):
    """What `dlo online`'s and `dlo bench`'s trials build: a planner through a model."""
    from dlocli.controllers.base import make_controller
    from dlocli.env.shape_env import make_env
    from dlocli.models.checkpoints import load_planning_model
    from dlocli.specs import BackendSpec, ObservationSpec, TaskSpec

    model = load_planning_model(recorded / "model")
    observation = ObservationSpec(kind="markers", markers=6, gripper_markers=0)
    for dt, refused in ((0.02, True), (0.01, False)):
        task = TaskSpec(shapes="near-rest", control_dt=dt, observation=observation)
        env = make_env(BackendSpec(), task, seed=0)
        try:
            if refused:
                with pytest.raises(BadInput, match="100 Hz.*50 Hz.*control_dt to 0.01"):
                    make_controller("mpc", env, model=model)
            else:
                make_controller("mpc", env, model=model)
        finally:
            env.close()


def test_eval_and_fine_tuning_refuse_data_of_another_rate(recorded, tmp_path, capsys):
    data50 = str(recorded / "data50")
    out = tmp_path / "eval"
    argv = ["eval", "--checkpoint", str(recorded / "model"), "--data", data50, "--out", str(out)]
    assert run_dlo(argv) == 2
    refused_in_one_line(capsys, "100 Hz", "50 Hz")
    assert not out.exists()
    out = tmp_path / "tuned"
    assert run_dlo(["train", "--init-from", str(recorded / "model"), "--data", data50,
                    "--update-steps", "2", "--rollout-steps", "2", "--device", "cpu",
                    "--out", str(out)]) == 2  # fmt: skip
    refused_in_one_line(capsys, "100 Hz", "50 Hz", "--init-from")
    assert not out.exists()
