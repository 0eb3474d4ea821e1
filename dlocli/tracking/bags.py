"""ROS 2 bags of a depth camera's cable clouds (``sensor_msgs/msg/PointCloud2``), for
`dlo track` (the ``ros`` extra: rosbags, a pure-Python reader).

A bag folder is one episode; every message on the clouds' topic is a frame: its points'
x, y, z, taken in the world frame (transform the clouds there first: the tracker reads no
tf), at its header stamp (or the time the bag received it where the stamp is zero), in
stamp order. Points with a NaN coordinate (an organised cloud's pixels without depth) are
left out. The camera's position is given: the tracker moves each point away from it, from
the cable's surface to its axis.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dlocli.errors import BadInput
from dlocli.extras import require
from dlocli.recorded_cables.rosbag import POINT_CLOUD, read_topic
from dlocli.tracking.camera import CloudFrame
from dlocli.tracking.frames import FrameSequence

#: what the clouds' topic carries, as errors name it
CLOUD_MESSAGES = "the cable's clouds (sensor_msgs/msg/PointCloud2 messages)"


def is_bag(path: Path) -> bool:
    """Whether ``path`` is a rosbag2 folder (it holds a metadata.yaml)."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def read_cloud_bag(
    path: Path, topic: str | None, camera_position: np.ndarray, budget: int
) -> FrameSequence:
    """The frames of one bag; BadInput naming the fault (a topic of another type, ...)."""
    require("ros", "reading a ROS 2 bag", "save the clouds as .npz frame sequences")
    size = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    if 4 * size > budget:  # the messages, decoded one at a time, and their points kept
        raise BadInput(f"{path} holds {size / 2**20:.0f} MiB, too large to track at once")
    frames, stamps = read_topic(path, topic, (POINT_CLOUD,), CLOUD_MESSAGES)
    clouds = [points[np.isfinite(points).all(axis=1)] for points in frames]
    return _sequence(path, clouds, stamps, camera_position)


def _sequence(
    path: Path, clouds: list[np.ndarray], stamps: list[int], camera_position: np.ndarray
) -> FrameSequence:
    if len(clouds) < 2:
        raise BadInput(f"{path} has {len(clouds)} clouds on the topic; an episode needs 2")
    order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
    stamps_ns = np.array(stamps, dtype=np.int64)[order]
    if (np.diff(stamps_ns) <= 0).any():
        raise BadInput(f"{path}: two clouds share a stamp; record each frame once")
    if not len(clouds[order[0]]):
        raise BadInput(f"{path}: the first cloud has no points; the tracker starts from it")
    extrinsics = np.eye(4)
    extrinsics[:3, 3] = camera_position
    times = (stamps_ns - stamps_ns[0]) / 1e9
    frames = [
        CloudFrame(clouds[i], extrinsics, np.eye(3), float(t),
                   np.full(len(clouds[i]), -1, dtype=np.int32))
        for i, t in zip(order, times, strict=True)
    ]  # fmt: skip
    return FrameSequence(frames, None)
