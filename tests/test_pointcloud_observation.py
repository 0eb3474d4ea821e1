"""The pointcloud observation (issue 54, part 3): the env's markers found by the tracker in
the simulated depth camera's clouds, on real MuJoCo and PyBullet rods, against the true
markers; `dlo online` learning a marker model from them and `dlo control` planning through
it; bad camera settings refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from dlocli.env.observation import markers_of_state
from dlocli.env.rollout import random_episode
from dlocli.env.shape_env import make_env
from dlocli.errors import BadInput

from tiny import MUJOCO_ROD, run_dlo

CLOUD = {"kind": "pointcloud"}
TINY_ONLINE = ["online", "--observation", "pointcloud", "--iters", "2", "--trials", "2",
               "--steps", "15", "--initial-episodes", "2", "--hidden", "8", "--update-steps",
               "12", "--rollout-steps", "3", "--shapes", "near-rest", "--seed", "3"]  # fmt: skip


def true_markers(env) -> np.ndarray:
    b = env.backend
    return markers_of_state(env.marker_layout, b.segment_positions(), b.segment_quaternions(),
                            b.gripper_poses())  # fmt: skip


@pytest.mark.parametrize("backend", [MUJOCO_ROD, "pybullet"])
def test_the_env_reports_the_tracked_markers_and_keeps_the_true_state(backend):
    full = make_env(backend, "single", seed=2, render_mode=None, goal="random",
                    episode_steps=60)  # fmt: skip
    cloud = make_env(backend, "single", seed=2, render_mode=None, goal="random",
                     episode_steps=60, observation=CLOUD)  # fmt: skip
    try:
        check_env(cloud, skip_render_check=True)
        a, b = random_episode(full, 5, 10), random_episode(cloud, 5, 10)
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.goal, b.goal)
        assert b.markers.shape == (61, 12, 3) and np.isfinite(b.markers).all()
        cloud.reset(seed=4)
        errors, moved, start = [], [], true_markers(cloud)
        for _ in range(50):
            obs, *_ = cloud.step(np.full(6, 0.5))
            truth, layout = true_markers(cloud), cloud.marker_layout
            seen = cloud.split_observation(obs)["markers"]
            errors.append(np.linalg.norm(seen - truth, axis=1)[~layout.held].mean())
            moved.append(np.linalg.norm(start - truth, axis=1)[~layout.held].mean())
        # the reports lag the truth by up to a frame (25 per second at 50 control steps)
        assert np.mean(errors) < min(8e-3, 0.3 * np.mean(moved))
    finally:
        full.close()
        cloud.close()


def test_a_camera_that_misses_the_cable_and_marker_faults_are_refused():
    away = {**CLOUD, "camera": {"look_at": (0.0, -3.0, 1.1)}}
    env = make_env(MUJOCO_ROD, "single", seed=0, render_mode=None, observation=away)
    try:
        with pytest.raises(BadInput, match="does not see the cable"):
            env.reset(seed=0)
    finally:
        env.close()
    with pytest.raises(BadInput) as caught:
        make_env(MUJOCO_ROD, "single", render_mode=None, observation={**CLOUD, "noise_mm": 2.0})
    assert "camera.noise_mm" in str(caught.value) and "\n" not in str(caught.value)


@pytest.fixture(scope="module")
def cloud_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("online") / "run"
    assert run_dlo([*TINY_ONLINE, "--out", str(out)]) == 0
    return out


def test_online_and_control_through_the_camera(cloud_run, near_rest_goal, tmp_path):
    summary = json.loads((cloud_run / "summary.json").read_text())
    assert summary["iterations_done"] == 2
    out = tmp_path / "control"
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint",
            str(cloud_run / "checkpoints" / "iter_02.pt"), "--observation", "pointcloud",
            "--steps", "8", "--shapes", "near-rest", "--out", str(out)]  # fmt: skip
    assert run_dlo(argv) == 0
    control = json.loads((out / "summary.json").read_text())
    assert control["steps"] == 8
    # in simulation the run says how far the tracked markers were from the true ones
    assert 0 < control["tracking_error_mm"] < 50, control


def test_a_bridged_camera_run_equals_the_in_process_one(cloud_run, near_rest_goal, tmp_path):
    """`dlo serve --camera`: the cell's camera takes the clouds (the controller sends each
    episode's noise seed), the controller tracks them: the same run as in this process."""
    pytest.importorskip("zmq")
    from cells import served, step_errors

    here, there, blind = tmp_path / "here", tmp_path / "there", tmp_path / "blind"
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint",
            str(cloud_run / "checkpoints" / "iter_02.pt"), "--observation", "pointcloud",
            "--steps", "8", "--shapes", "near-rest"]  # fmt: skip
    assert run_dlo([*argv, "--out", str(here)]) == 0
    with served("--camera") as address:
        assert run_dlo([*argv, "--out", str(there), "--cell", address]) == 0
    with served() as address:  # a cell without a camera: one line, nothing written
        assert run_dlo([*argv, "--out", str(blind), "--cell", address]) == 2
    assert not blind.exists()
    assert step_errors(there) == step_errors(here)
    assert len(step_errors(here)) == 8
    summaries = [json.loads((run / "summary.json").read_text()) for run in (here, there)]
    assert summaries[0]["tracking_error_mm"] == summaries[1]["tracking_error_mm"]


def test_a_camera_run_records_its_clouds_and_the_tracked_markers(cloud_run, near_rest_goal,
                                                                 tmp_path):  # fmt: skip
    """--record with the pointcloud observation: the camera's cloud and the markers the
    tracker found in it at every step, read back with Rerun's RRD reader."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    recording, run = tmp_path / "camera.rrd", tmp_path / "run"
    argv = ["control", "--goal", str(near_rest_goal), "--checkpoint",
            str(cloud_run / "checkpoints" / "iter_02.pt"), "--observation", "pointcloud",
            "--steps", "4", "--shapes", "near-rest", "--out", str(run), "--record",
            str(recording)]  # fmt: skip
    assert run_dlo(argv) == 0
    steps: dict[str, list[int]] = {}
    points: list[int] = []
    for chunk in RrdReader(recording).stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        steps.setdefault(chunk.entity_path, []).extend(batch.column("step").to_pylist())
        if chunk.entity_path == "/world/camera/cloud":
            column = [c for c in batch.column_names if c.endswith("positions")][0]
            points += [len(row) for row in batch.column(column).to_pylist()]
    acted_on = list(range(4))  # the observations the controller acted on: the reset's and 3
    assert sorted(steps["/world/camera/cloud"]) == acted_on
    assert sorted(steps["/world/markers/seen"]) == acted_on
    assert sorted(steps["/world/rod"]) == list(range(5))
    assert min(points) > 10  # the default camera sees the cable: dozens of points a frame
