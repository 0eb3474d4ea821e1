"""`dlo collect`, `dlo goal`, `dlo list`: outputs, the dataset round trip, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.data import load_dataset

from tiny import MUJOCO_ROD

runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, list(args))


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_collect_json_and_reader(tmp_path, backend):
    out = tmp_path / backend
    res = run(
        "collect",
        "--random",
        "--backend",
        backend,
        "--episodes",
        "2",
        "--steps",
        "15",
        "--out",
        str(out),
        "--json",
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert {"episodes", "transitions", "seconds", "path"} <= summary.keys()
    assert summary["episodes"] == 2 and summary["transitions"] == 30
    data = load_dataset(out)
    assert data.n_episodes == 2 and data.n_transitions == 30
    assert data.attrs["backend"] == backend and data.attrs["rod"]["young_bending"] == 1e7
    t = data.transitions()
    assert t["state"].shape == (30, 20, 7) and t["action"].shape == (30, 2, 6)
    assert np.all(t["action"][:, 0] == 0), "single task: the left gripper never moves"
    assert np.all(np.abs(t["action"]) <= 1)
    saved = json.loads((out / "spec.json").read_text())
    assert saved["backend"]["name"] == backend and saved["episodes"] == 2


def test_workers_give_identical_data(tmp_path):
    common = ["collect", "--episodes", "3", "--steps", "10", "--seed", "4", "--json"]
    assert run(*common, "--out", str(tmp_path / "w1")).exit_code == 0
    assert run(*common, "--workers", "2", "--out", str(tmp_path / "w2")).exit_code == 0
    a, b = load_dataset(tmp_path / "w1"), load_dataset(tmp_path / "w2")
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.actions, b.actions)


def test_goal_command(tmp_path):
    out = tmp_path / "shape.npy"
    res = run("goal", "--out", str(out), "--seed", "3", "--json")
    assert res.exit_code == 0, res.output
    goal = np.load(out)
    assert goal.shape == (20, 3) and np.all(np.isfinite(goal))
    again = tmp_path / "again.npy"
    run("goal", "--out", str(again), "--seed", "3")
    np.testing.assert_array_equal(goal, np.load(again))
    assert run("goal", "--out", str(out), "--seed", "3").exit_code == 2, "no silent overwrite"


def test_list():
    res = run("list", "--json")
    assert res.exit_code == 0
    listed = json.loads(res.stdout)
    assert {"mujoco", "pybullet"} <= listed["backends"].keys()


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--backend", "mujoko"], "valid backends: mujoco, mujoco-flex, pybullet"),
        (["--task", "tri"], "valid tasks"),
        (["--episodes", "0"], "episodes"),
        (["--steps", "-3"], "steps"),
        (["--workers", "0"], "workers"),
    ],
)
def test_collect_bad_input_exit_2(tmp_path, args, needle):
    res = run("collect", "--out", str(tmp_path / "x"), *args)
    assert res.exit_code == 2
    assert needle in res.output
    assert "Traceback" not in res.output


def test_bad_spec_files_exit_2(tmp_path):
    missing = run("collect", "--spec", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o"))
    assert missing.exit_code == 2 and "does not exist" in missing.output
    corrupt = tmp_path / "bad.yaml"
    corrupt.write_text("episodes: [1,\n")
    assert run("collect", "--spec", str(corrupt), "--out", str(tmp_path / "o")).exit_code == 2
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("episodez: 3\n")
    res = run("collect", "--spec", str(unknown), "--out", str(tmp_path / "o"))
    assert res.exit_code == 2 and "episodez" in res.output


def test_non_empty_out_is_refused_and_kept(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    res = run("collect", "--episodes", "1", "--steps", "5", "--out", str(out))
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert (out / "precious.txt").read_text() == "keep me"
    assert not (out / "dataset.h5").exists()


def test_spec_file_then_flags(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("episodes: 5\ntask: {name: bimanual, episode_steps: 7}\n")
    out = tmp_path / "run"
    res = run("collect", "--spec", str(spec), "--episodes", "1", "--out", str(out), "--json")
    assert res.exit_code == 0, res.output
    saved = json.loads((out / "spec.json").read_text())
    assert (
        saved["episodes"] == 1
        and saved["task"]["episode_steps"] == 7
        and saved["task"]["name"] == "bimanual"
    )
    assert load_dataset(out).actions[:, 0].any(), "bimanual moves the left gripper too"


def test_ctrl_c_leaves_complete_dataset_or_nothing(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "interrupted"
    cmd = [
        sys.executable,
        "-m",
        "dlocli.cli",
        "collect",
        "--episodes",
        "100000",  # far more than 2 s can collect on any machine: the stop must cut it short
        "--steps",
        "20",
        "--out",
        str(out),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while not list(out.glob("episodes/episode_*.h5")):  # the first episode is saved
        assert proc.poll() is None and time.time() < deadline
        time.sleep(0.05)
    time.sleep(0.5)  # (not earlier: Ctrl-C inside `import mujoco` breaks the import itself)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()
    assert not list(out.glob("*.tmp")), "no half-written files"
    data = load_dataset(out)  # the finished episodes, assembled
    assert 0 < data.n_episodes < 100000 and data.n_transitions == 20 * data.n_episodes
