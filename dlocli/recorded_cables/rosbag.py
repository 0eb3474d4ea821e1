"""ROS 2 bags of tracked cable markers (the ``ros`` extra: rosbags, a pure-Python reader).

A bag folder (rosbag2, sqlite3 or mcap storage) inside ``train/`` or ``eval/`` is one
trajectory, named by the folder. Every message on the markers' topic is a frame:

- ``geometry_msgs/msg/PoseArray``: the poses' positions, in order;
- ``visualization_msgs/msg/MarkerArray``: each marker's pose position, ordered by marker id;
- ``sensor_msgs/msg/PointCloud2``: the points' x, y, z (float32 or float64 fields), in order.

A frame's time is its header stamp (a MarkerArray's: its first marker's), or the time the
bag received it where the stamp is zero; frames are taken in stamp order. A NaN coordinate is
a gap, filled like a CSV's empty cell (``--fill-gaps``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dlocli.errors import BadInput
from dlocli.extras import require
from dlocli.recorded_cables.formats import Reader, Trajectory, filled, from_array

POSE_ARRAY = "geometry_msgs/msg/PoseArray"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
#: PointField datatypes of coordinates read, as numpy types
CLOUD_TYPES = {7: "f4", 8: "f8"}  # FLOAT32, FLOAT64
#: what the markers' topic may carry, as errors name it
MARKER_MESSAGES = "tracked markers (PoseArray, MarkerArray or PointCloud2 messages)"


def reader(topic: str | None) -> Reader:
    """The reader of bag folders for ``--topic`` (None: a bag's only markers topic)."""
    return lambda path, budget, fill_gaps: [read_bag(path, budget, fill_gaps, topic)]


def read_bag(path: Path, budget: int, fill_gaps: int, topic: str | None) -> Trajectory:
    require("ros", "importing a ROS 2 bag", "convert it to CSV or .npz")
    size = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    if 2 * size > budget:  # the messages, decoded one at a time, and their numbers kept
        raise BadInput(
            f"{path} holds {size / 2**20:.0f} MiB, over half the budget's "
            f"{budget / 2**20:.0f} MiB left; raise --max-memory-mib or import fewer bags"
        )
    frames, stamps = read_topic(path, topic, tuple(FRAMES), MARKER_MESSAGES)
    return _trajectory(path, frames, stamps, fill_gaps)


def read_topic(
    path: Path, topic: str | None, types: tuple[str, ...], kinds: str
) -> tuple[list[np.ndarray], list[int]]:
    """Each message's points on ``topic`` (None: the bag's only topic of ``types``, message
    types named ``kinds`` in errors) and its stamp in ns (the time the bag received it where
    the stamp is zero); BadInput for a bag that cannot be read or a topic of another type."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    points, stamps = [], []
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as bag:
            connections = _connections(bag.connections, topic, path, types, kinds)
            for connection, received, raw in bag.messages(connections=connections):
                message = bag.deserialize(raw, connection.msgtype)
                frame, stamp = FRAMES[connection.msgtype](message, path)
                points.append(frame)
                stamps.append(stamp if stamp else received)
    except BadInput:
        raise
    except Exception as exc:  # a third-party parser of the file: any failure is the file's
        raise BadInput(f"{path} is not a readable ROS 2 bag ({str(exc)[:80]})") from exc
    return points, stamps


def _connections(
    connections: list[Any], topic: str | None, path: Path, types: tuple[str, ...], kinds: str
) -> list[Any]:
    """The connections of the chosen topic; BadInput naming the bag's topics otherwise."""
    listed = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in connections}))[:200]
    if topic is None:
        topics = {c.topic for c in connections if c.msgtype in types}
        if len(topics) != 1:
            raise BadInput(
                f"{path} has {len(topics)} topics of {kinds} among {listed or 'none'}; pass "
                "--topic NAME"
            )
        topic = topics.pop()
    chosen = [c for c in connections if c.topic == topic]
    if not chosen:
        raise BadInput(f"{path} has no topic {topic!r}; its topics: {listed or 'none'}")
    if any(c.msgtype not in types for c in chosen):
        raise BadInput(
            f"{path}: topic {topic} carries {chosen[0].msgtype}; pass a topic of {kinds}"
        )
    return chosen


def _trajectory(path: Path, frames: list[np.ndarray], stamps: list[int], fill: int) -> Trajectory:
    """The bag's frames in stamp order as a checked trajectory."""
    if len(frames) < 3:
        raise BadInput(f"{path} has {len(frames)} messages on the topic; at least 3 are needed")
    counts = sorted({len(f) for f in frames})
    if len(counts) > 1:
        raise BadInput(
            f"{path}: frames of {counts[0]} and {counts[-1]} markers; track the same markers "
            "in every frame (NaN for one not seen)"
        )
    order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
    stamps_ns = np.array(stamps, dtype=np.int64)[order]
    positions = np.stack(frames)[order]
    missing = np.isnan(positions).any(axis=2)
    gaps = int(missing.sum())
    if gaps:
        positions = filled(positions, missing, fill, path)
    times = (stamps_ns - stamps_ns[0]) / 1e9  # from the first frame: float64 keeps the ns
    return Trajectory(path.name, from_array(positions, str(path)), gaps, times)


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _poses(message: Any, path: Path) -> tuple[np.ndarray, int]:
    points = [(p.position.x, p.position.y, p.position.z) for p in message.poses]
    return np.array(points, dtype=np.float64).reshape(-1, 3), _stamp_ns(message.header)


def _markers(message: Any, path: Path) -> tuple[np.ndarray, int]:
    markers = sorted(message.markers, key=lambda m: m.id)
    if not markers:
        raise BadInput(f"{path}: a MarkerArray holds no markers; publish every tracked marker")
    ids = [m.id for m in markers]
    if len(set(ids)) != len(ids):
        raise BadInput(f"{path}: a MarkerArray holds two markers of one id; give each its own")
    points = [(m.pose.position.x, m.pose.position.y, m.pose.position.z) for m in markers]
    return np.array(points, dtype=np.float64), _stamp_ns(markers[0].header)


def _cloud(message: Any, path: Path) -> tuple[np.ndarray, int]:
    fields = {f.name: f for f in message.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise BadInput(f"{path}: a PointCloud2 lacks an x, y or z field; publish point coordinates")
    for axis in "xyz":
        if fields[axis].datatype not in CLOUD_TYPES:
            raise BadInput(
                f"{path}: PointCloud2 field {axis} is of datatype {fields[axis].datatype}, not "
                "FLOAT32 (7) or FLOAT64 (8)"
            )
    order = ">" if message.is_bigendian else "<"
    layout = np.dtype({
        "names": list("xyz"),
        "formats": [order + CLOUD_TYPES[fields[a].datatype] for a in "xyz"],
        "offsets": [fields[a].offset for a in "xyz"],
        "itemsize": message.point_step,
    })  # fmt: skip
    width, height, row = int(message.width), int(message.height), int(message.row_step)
    data = np.asarray(message.data, dtype=np.uint8)
    if width * message.point_step > row or data.size < height * row:
        raise BadInput(f"{path}: a PointCloud2's data is shorter than its width and height say")
    rows = data[: height * row].reshape(height, row)[:, : width * message.point_step]
    points = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=layout)
    xyz = np.stack([points[a] for a in "xyz"], axis=1).astype(np.float64)
    return xyz, _stamp_ns(message.header)


#: message type -> (message, bag) -> (markers (V, 3), header stamp in ns, 0 if unset)
FRAMES: dict[str, Callable[[Any, Path], tuple[np.ndarray, int]]] = {
    POSE_ARRAY: _poses,
    MARKER_ARRAY: _markers,
    POINT_CLOUD: _cloud,
}
