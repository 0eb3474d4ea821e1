"""`dlo track` on ROS 2 bags of PointCloud2 clouds (the 'ros' extra), recorded by the
simulated depth camera on a real MuJoCo cable: the tracked markers against the true ones;
a topic of another type, or a bag without the camera's position, one line and exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from dlocli.data import load_dataset
from dlocli.env.observation import marker_layout
from dlocli.env.shape_env import make_env
from dlocli.specs import ObservationSpec, TaskSpec
from dlocli.tracking.camera import DepthCamera
from dlocli.tracking.measure import policy_action, true_markers
from dlocli.tracking.spec import CameraSpec

from tiny import MUJOCO_ROD, run_dlo

pytest.importorskip("rosbags")
from test_import_bags import write_bag  # noqa: E402

STEPS = 30  # control steps per episode: 16 clouds at 25 per second


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """train/ bags of seeds 0 and 1, each one's true markers, and the camera's position."""
    root = tmp_path_factory.mktemp("bags")
    env = make_env(MUJOCO_ROD, TaskSpec(name="single", goal="random"), seed=0, render_mode=None)
    layout = marker_layout(ObservationSpec(gripper_markers=0), 1.0, 20, (True, True))
    camera = DepthCamera(CameraSpec(), env.backend.rod.length)
    truth = {}
    (root / "train").mkdir()
    for seed in (0, 1):
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        clouds, markers = [], []
        for step in range(STEPS + 1):
            if step % 2 == 0:
                clouds.append(camera.capture(env.backend, rng).points)
                markers.append(true_markers(env, layout))
            if step < STEPS:
                env.step(policy_action(env, "oracle", rng))
        write_bag(root / "train" / f"seed{seed}", clouds, "sensor_msgs/msg/PointCloud2",
                  rate_hz=25.0, topic="/camera/cable")  # fmt: skip
        truth[f"seed{seed}"] = np.stack(markers)
    env.close()
    return root, truth, ",".join(f"{v:g}" for v in camera.origin)


def test_dlo_track_reads_point_cloud_bags(bags, tmp_path):
    root, truth, position = bags
    out = tmp_path / "tracked"
    assert run_dlo(["track", "--source", str(root), "--camera-position", position,
                    "--gripper-markers", "0", "--out", str(out)]) == 0  # fmt: skip
    data = load_dataset(out)
    assert data.n_markers == 10 and data.rate_hz == pytest.approx(25.0)
    for name, episode in zip(data.episode_names(), data.episodes(), strict=True):
        true = truth[name]
        error = np.linalg.norm(episode - true, axis=-1)[:, 1:-1].mean()
        still = np.linalg.norm(true[:1] - true, axis=-1)[:, 1:-1].mean()
        assert error < min(25e-3, 0.5 * still), name


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--topic", "/status"], "carries std_msgs/msg/String"),
        (["--topic", "/nothing"], "has no topic '/nothing'"),
        ([], "--camera-position"),
    ],
)
def test_bad_bag_input_is_one_line_exit_2(bags, tmp_path, capsys, flags, words):
    root, _, position = bags
    camera = [] if not flags else ["--camera-position", position]
    out = tmp_path / "out"
    argv = ["track", "--source", str(root), "--gripper-markers", "0", "--out", str(out)]
    capsys.readouterr()
    assert run_dlo([*argv, *camera, *flags]) == 2
    error = capsys.readouterr().err.strip()
    assert words in error and "\n" not in error and not out.exists()
