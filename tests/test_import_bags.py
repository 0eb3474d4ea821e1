"""`dlo import` reads ROS 2 bags (PoseArray, MarkerArray, PointCloud2 on a named topic) as it
reads DEFORM's pickles: the same recording gives the same dataset; a bad bag is one line."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dlocli.data import MarkerDataset, load_dataset

from tiny import dlo_import, swinging_cable

pytest.importorskip("rosbags")
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TYPES = get_typestore(Stores.ROS2_HUMBLE)
SPLITS = {"train": 3, "eval": 2}
TOPIC = "/cable/markers"
START_NS = 1_700_000_000 * 10**9  # an epoch stamp, as a real recorder writes


def _header(stamp_ns: int) -> object:
    time = TYPES.types["builtin_interfaces/msg/Time"]
    return TYPES.types["std_msgs/msg/Header"](
        stamp=time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="world"
    )


def _pose(xyz: np.ndarray) -> object:
    t = TYPES.types
    point = t["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))
    rotation = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    return t["geometry_msgs/msg/Pose"](position=point, orientation=rotation)


def pose_array(frame: np.ndarray, stamp_ns: int) -> object:
    """(V, 3) as a PoseArray."""
    return TYPES.types["geometry_msgs/msg/PoseArray"](
        header=_header(stamp_ns), poses=[_pose(p) for p in frame]
    )


def marker_array(frame: np.ndarray, stamp_ns: int) -> object:
    """(V, 3) as a MarkerArray, written in reverse id order (the reader orders by id)."""
    t = TYPES.types
    marker = t["visualization_msgs/msg/Marker"]
    zero = t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    scale = t["geometry_msgs/msg/Vector3"](x=0.01, y=0.01, z=0.01)
    color = t["std_msgs/msg/ColorRGBA"](r=1.0, g=0.0, b=0.0, a=1.0)
    items = [
        marker(header=_header(stamp_ns), ns="cable", id=i, type=2, action=0, pose=_pose(p),
               scale=scale, color=color, lifetime=zero, frame_locked=False, points=[],
               colors=[], texture_resource="", texture=t["sensor_msgs/msg/CompressedImage"](
                   header=_header(0), format="", data=np.zeros(0, np.uint8)),
               uv_coordinates=[], text="", mesh_resource="", mesh_file=t[
                   "visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
               mesh_use_embedded_materials=False)
        for i, p in enumerate(frame)
    ][::-1]  # fmt: skip
    return t["visualization_msgs/msg/MarkerArray"](markers=items)


def point_cloud(frame: np.ndarray, stamp_ns: int) -> object:
    """(V, 3) as an unordered PointCloud2 of float32 x, y, z and a padding byte field."""
    t = TYPES.types
    field = t["sensor_msgs/msg/PointField"]
    fields = [field(name=a, offset=4 * i, datatype=7, count=1) for i, a in enumerate("xyz")]
    points = np.zeros(len(frame), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4")])
    points["x"], points["y"], points["z"] = frame.T
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(stamp_ns), height=1, width=len(frame), fields=fields, is_bigendian=False,
        point_step=16, row_step=16 * len(frame), data=points.view(np.uint8), is_dense=True,
    )  # fmt: skip


MESSAGES = {
    "geometry_msgs/msg/PoseArray": pose_array,
    "visualization_msgs/msg/MarkerArray": marker_array,
    "sensor_msgs/msg/PointCloud2": point_cloud,
}


def write_bag(
    path: Path,
    frames: np.ndarray,
    msgtype: str = "geometry_msgs/msg/PoseArray",
    rate_hz: float = 100.0,
    storage: StoragePlugin = StoragePlugin.SQLITE3,
    topic: str = TOPIC,
    stamps_ns: list[int] | None = None,
    received_ns: list[int] | None = None,
    header_stamps: bool = True,
) -> Path:
    """A ROS 2 bag folder of ``frames`` (frames, V, 3), one message per frame on ``topic``,
    stamped at ``rate_hz`` (or ``stamps_ns``; 0 without ``header_stamps``) and received 2 ms
    later (or at ``received_ns``), plus an unrelated topic."""
    stamps = stamps_ns or [START_NS + round(k * 1e9 / rate_hz) for k in range(len(frames))]
    received = received_ns or [stamp + 2_000_000 for stamp in stamps]
    with Writer(path, version=9, storage_plugin=storage) as bag:
        markers = bag.add_connection(topic, msgtype, typestore=TYPES)
        other = bag.add_connection("/status", "std_msgs/msg/String", typestore=TYPES)
        for frame, stamp, time in zip(frames, stamps, received, strict=True):
            message = MESSAGES[msgtype](frame, stamp if header_stamps else 0)
            bag.write(markers, time, TYPES.serialize_cdr(message, msgtype))
        text = TYPES.types["std_msgs/msg/String"](data="ok")
        bag.write(other, stamps[0], TYPES.serialize_cdr(text, "std_msgs/msg/String"))
    return path


def write_bags(root: Path, msgtype: str, storage: StoragePlugin = StoragePlugin.SQLITE3) -> Path:
    """The recordings of tiny.write_cable, one bag folder per trajectory."""
    for split, n in SPLITS.items():
        (root / split).mkdir(parents=True)
        for i in range(n):
            frames = swinging_cable(i + (100 if split == "eval" else 0)).transpose(0, 2, 1)
            write_bag(root / split / str(i), frames, msgtype, storage=storage)
    return root


@pytest.fixture
def reference(deform_reference: MarkerDataset) -> MarkerDataset:
    return deform_reference


@pytest.mark.parametrize(
    ("msgtype", "storage"),
    [("geometry_msgs/msg/PoseArray", StoragePlugin.SQLITE3),
     ("visualization_msgs/msg/MarkerArray", StoragePlugin.MCAP),
     ("sensor_msgs/msg/PointCloud2", StoragePlugin.SQLITE3)],
)  # fmt: skip
def test_a_bag_round_trips_to_the_deform_dataset(
    msgtype: str, storage: StoragePlugin, tmp_path: Path, reference: MarkerDataset, capsys
) -> None:
    source = write_bags(tmp_path / "CABLE", msgtype, storage)
    assert dlo_import(source, tmp_path / "out", "--topic", TOPIC) == 0
    assert json.loads(capsys.readouterr().out)["rate_hz"] == 100.0
    data = load_dataset(tmp_path / "out")
    tolerance = 1e-6 if msgtype.endswith("PointCloud2") else 0  # float32 points
    np.testing.assert_allclose(data.positions, reference.positions, atol=tolerance, rtol=0)
    for name in ("held", "split", "episode_lengths", "names"):
        np.testing.assert_array_equal(getattr(data, name), getattr(reference, name))
    assert data.rate_hz == reference.rate_hz


def test_unset_header_stamps_fall_back_to_the_receive_times(
    tmp_path: Path, reference: MarkerDataset
) -> None:
    for split, n in SPLITS.items():
        (tmp_path / "C" / split).mkdir(parents=True)
        for i in range(n):
            frames = swinging_cable(i + (100 if split == "eval" else 0)).transpose(0, 2, 1)
            late = [START_NS + k * 10**7 + (k % 2) * 10**6 for k in range(len(frames))]
            write_bag(tmp_path / "C" / split / str(i), frames, received_ns=late)
    # the headers at 100 Hz exactly, the receive times 0 or 1 ms late: the headers are read
    assert dlo_import(tmp_path / "C", tmp_path / "out") == 0
    np.testing.assert_array_equal(load_dataset(tmp_path / "out").positions, reference.positions)
    # no header stamps: the receive times are, jittered by 1 ms (reported, resampled)
    write_bag(tmp_path / "C" / "train" / "9", frames, received_ns=late, header_stamps=False)
    assert dlo_import(tmp_path / "C", tmp_path / "o2", "--control-hz", "100") == 0
    data = load_dataset(tmp_path / "o2")
    assert data.episode_names("train")[-1] == "9" and len(data.episodes("train")[-1]) == 40
    np.testing.assert_allclose(data.episodes("train")[-1], frames, atol=0.01)


def test_the_only_markers_topic_needs_no_flag(tmp_path: Path) -> None:
    source = write_bags(tmp_path / "C", "geometry_msgs/msg/PoseArray")
    assert dlo_import(source, tmp_path / "out") == 0


def _one_bag(edit: Callable[[Path, np.ndarray], None]) -> Callable[[Path], None]:
    return lambda train: edit(train / "bad", swinging_cable(7).transpose(0, 2, 1))


def _nan_gap(path: Path, frames: np.ndarray) -> None:
    frames = frames.copy()
    frames[10:12, 2] = np.nan
    write_bag(path, frames)


def _ragged(path: Path, frames: np.ndarray) -> None:
    with Writer(path, version=9) as bag:
        c = bag.add_connection(TOPIC, "geometry_msgs/msg/PoseArray", typestore=TYPES)
        for k, frame in enumerate(frames):
            message = pose_array(frame[: 5 if k == 3 else None], START_NS + k * 10**7)
            bag.write(c, START_NS, TYPES.serialize_cdr(message, "geometry_msgs/msg/PoseArray"))


def _text_topic(path: Path) -> None:
    with Writer(path, version=9) as bag:
        c = bag.add_connection(TOPIC, "std_msgs/msg/String", typestore=TYPES)
        text = TYPES.types["std_msgs/msg/String"](data="not markers")
        bag.write(c, START_NS, TYPES.serialize_cdr(text, "std_msgs/msg/String"))


def _corrupt(path: Path, frames: np.ndarray) -> None:
    write_bag(path, frames)
    next(path.glob("*.db3")).write_bytes(b"not sqlite" * 10)


BAD: dict[str, tuple[Callable[[Path], None], str]] = {
    "topic of another type": (
        _one_bag(lambda p, f: write_bag(p, f, topic="/x")),
        "no topic '/cable/markers'",
    ),
    "unsupported type": (_one_bag(lambda p, f: _text_topic(p)), "carries std_msgs/msg/String"),
    "stamps repeat": (
        _one_bag(lambda p, f: write_bag(p, f, stamps_ns=[START_NS] * len(f))),
        "not after the one before",
    ),
    "marker count changes": (_one_bag(_ragged), "frames of 5 and 6 markers"),
    "NaN gap": (_one_bag(_nan_gap), "--fill-gaps 2"),
    "two messages": (_one_bag(lambda p, f: write_bag(p, f[:2])), "at least 3"),
    "corrupt storage": (_one_bag(_corrupt), "not a readable ROS 2 bag"),
    "bad metadata": (
        lambda t: ((t / "bad").mkdir(), (t / "bad" / "metadata.yaml").write_text("[")),
        "not a readable ROS 2 bag",
    ),
    "a plain folder": (lambda t: (t / "notes").mkdir(), "not a ROS 2 bag"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_bags_get_one_line_and_nothing_is_written(tmp_path: Path, capsys, case) -> None:
    make, words = BAD[case]
    source = write_bags(tmp_path / "C", "geometry_msgs/msg/PoseArray")
    make(source / "train")
    out = tmp_path / "out"
    assert dlo_import(source, out, "--topic", TOPIC) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    assert not out.exists()


def test_a_bag_with_several_marker_topics_asks_for_one(tmp_path: Path, capsys) -> None:
    source = write_bags(tmp_path / "C", "geometry_msgs/msg/PoseArray")
    frames = swinging_cable(3).transpose(0, 2, 1)
    with Writer(source / "eval" / "two", version=9) as bag:
        for topic in ("/a", "/b"):
            c = bag.add_connection(topic, "geometry_msgs/msg/PoseArray", typestore=TYPES)
            message = pose_array(frames[0], START_NS)
            bag.write(c, START_NS, TYPES.serialize_cdr(message, "geometry_msgs/msg/PoseArray"))
    assert dlo_import(source, tmp_path / "out") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pass --topic" in err and "/a" in err, err


def test_a_nan_gap_is_filled_when_asked(tmp_path: Path, capsys) -> None:
    source = write_bags(tmp_path / "C", "geometry_msgs/msg/PoseArray")
    _one_bag(_nan_gap)(source / "train")
    assert dlo_import(source, tmp_path / "out", "--fill-gaps", "2") == 0
    assert json.loads(capsys.readouterr().out)["gaps_filled"] == {"train/bad": 2}
