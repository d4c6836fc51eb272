"""ROS 2 MCAP sink: read back with mcap_ros2 and, independently, with rosbags' CDR deserializer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_sinks_mcap import (
    DATA,
    GRID,
    STAMP0,
    cell_of,
    expected_quaternion,
    make_frame,
    read_messages,
    write_frames,
)

from terrainmap.config import Config, GridConfig
from terrainmap.ros2defs import SCHEMAS
from terrainmap.sinks import open_mcap_sink
from terrainmap.sinks.mcap_ros2 import grid_map_message


def rosbags_store():
    store = get_typestore(Stores.EMPTY)
    for name, text in SCHEMAS.items():
        store.register(get_types_from_msg(text, name))
    return store


def read_with_rosbags(path: Path) -> dict[str, list]:
    """topic → [decoded] using rosbags' own CDR deserializer (no mcap_ros2 code involved)."""
    store = rosbags_store()
    topics: dict[str, list] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            topics.setdefault(channel.topic, []).append(store.deserialize_cdr(message.data, schema.name))
    return topics


@pytest.fixture(scope="module")
def ros_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("ros2") / "out.mcap"
    frames = [make_frame(i) for i in range(3)]
    write_frames(path, "ros2", frames)
    return path, frames, read_messages(path, DecoderFactory()), read_with_rosbags(path)


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def grid_map_cell(msg, layer: str, x: float, y: float) -> float:
    """Value at (x, y) by grid_map's own convention: index (0, 0) at the +x, +y corner, column-major."""
    info = msg.info
    i = math.floor((info.pose.position.x + info.length_x / 2 - x) / info.resolution)
    j = math.floor((info.pose.position.y + info.length_y / 2 - y) / info.resolution)
    array = msg.data[msg.layers.index(layer)]
    rows = array.layout.dim[1].size
    return float(np.asarray(array.data)[j * rows + i])


def test_grid_map_fields_and_values(ros_file):
    _path, frames, mcap_topics, rosbags_topics = ros_file
    m0, m1 = GRID.shape
    for k, (frame, result) in enumerate(frames):
        for msg in (mcap_topics["/terrainmap/grid_map"][k][2], rosbags_topics["/terrainmap/grid_map"][k]):
            assert msg.header.frame_id == "base_link" and stamp_ns(msg.header) == frame.stamp_ns
            assert (msg.info.resolution, msg.info.length_x, msg.info.length_y) == (0.5, 4.0, 3.0)
            p = msg.info.pose
            assert (p.position.x, p.position.y, p.position.z, p.orientation.w) == (4.0, 0.5, 0.0, 1.0)
            assert list(msg.layers) == ["elevation", "slope", "cost", "label", "valid"]
            assert list(msg.basic_layers) == ["elevation"]
            assert (msg.outer_start_index, msg.inner_start_index) == (0, 0)
            for name, array in zip(msg.layers, msg.data, strict=True):
                dims = [(d.label, d.size, d.stride) for d in array.layout.dim]
                assert dims == [("column_index", m1, m0 * m1), ("row_index", m0, m0)]
                data = np.asarray(array.data, np.float32).reshape(m1, m0)  # [j][i]
                layer = result.layers[name].astype(np.float32)
                if name in ("elevation", "slope"):  # none where the cell has no data
                    layer = np.where(result.layers["valid"], layer, np.nan)
                np.testing.assert_array_equal(data[::-1, ::-1].T, layer)


def test_grid_map_cell_at_known_position(ros_file):
    _path, frames, mcap_topics, _ = ros_file
    msg = mcap_topics["/terrainmap/grid_map"][0][2]
    layers = frames[0][1].layers
    slope = np.where(layers["valid"], layers["slope"], np.nan)  # as written
    for x, y in [(2.1, -0.9), (5.9, 1.9), (3.3, 1.2), (4.2, 0.4)]:
        np.testing.assert_equal(grid_map_cell(msg, "slope", x, y), slope[cell_of(GRID, x, y)])
    # the +x, +y corner cell is grid_map's first element
    np.testing.assert_equal(msg.data[1].data[0], slope[-1, -1])


def test_grid_map_layout_matches_a_real_grid_map_bag():
    """grid_map_ros' own output: dim[0] is column_index with length_y / resolution entries."""
    bag = DATA / "negative" / "grid_map_ros1.bag"
    if not bag.exists():
        pytest.skip(f"{bag} not available")
    with AnyReader([bag]) as reader:
        connection = next(c for c in reader.connections if c.msgtype == "grid_map_msgs/msg/GridMap")
        _, _, raw = next(reader.messages(connections=[connection]))
        real = reader.deserialize(raw, connection.msgtype)
    info = real.info
    grid = GridConfig(x_min_m=-info.length_x / 2, length_m=info.length_x, width_m=info.length_y,
                      cell_size_m=info.resolution)
    _, result = make_frame(0, grid=grid)
    ours = grid_map_message(result)
    real_dims = [(d.label, d.size, d.stride) for d in real.data[0].layout.dim]
    our_dims = [(d["label"], d["size"], d["stride"]) for d in ours["data"][0]["layout"]["dim"]]
    assert our_dims == real_dims
    assert ours["info"]["length_x"] == pytest.approx(info.length_x)


def test_costmap_is_the_cost_layer_as_an_occupancy_grid(ros_file):
    """nav_msgs/OccupancyGrid: row-major from the (x_min, y_min) corner, 0..100, −1 unknown."""
    _path, frames, mcap_topics, rosbags_topics = ros_file
    m0, m1 = GRID.shape
    for k, (frame, result) in enumerate(frames):
        cost = result.layers["cost"]
        for msg in (mcap_topics["/terrainmap/costmap"][k][2], rosbags_topics["/terrainmap/costmap"][k]):
            assert msg.header.frame_id == "base_link" and stamp_ns(msg.header) == frame.stamp_ns
            info = msg.info
            assert (info.resolution, info.width, info.height) == (0.5, m0, m1)
            assert (info.origin.position.x, info.origin.position.y, info.origin.orientation.w) == (2.0, -1.0, 1.0)
            data = np.asarray(msg.data, np.int8)
            assert data.size == m0 * m1
            for x, y in [(2.1, -0.9), (5.9, 1.9), (3.3, 1.2), (4.2, -0.4)]:
                ix, iy = cell_of(GRID, x, y)
                index = math.floor((y - info.origin.position.y) / info.resolution) * info.width + math.floor(
                    (x - info.origin.position.x) / info.resolution
                )
                expected = -1 if np.isnan(cost[ix, iy]) else round(100 * float(cost[ix, iy]))
                assert data[index] == expected
            assert (data.reshape(m1, m0)[1] == -1).all()  # the row of unknown cost (iy = 1)


def test_no_costmap_without_a_cost_layer(tmp_path):
    path = tmp_path / "out.mcap"
    write_frames(path, "ros2", [make_frame(0, cost=False)])
    topics = read_messages(path, DecoderFactory())
    assert "/terrainmap/grid_map" in topics and "/terrainmap/costmap" not in topics


def test_point_cloud2(ros_file):
    _path, frames, mcap_topics, rosbags_topics = ros_file
    for k, (_frame, result) in enumerate(frames):
        for msg in (mcap_topics["/terrainmap/points"][k][2], rosbags_topics["/terrainmap/points"][k]):
            fields = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
            # the label UINT32 (6), as PCL's PointXYZL has it: pcl::fromROSMsg matches name and datatype
            assert fields == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("label", 12, 6, 1)]
            n = len(result.points_vehicle)
            assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, n, 16, 16 * n)
            assert not msg.is_bigendian and msg.is_dense
            raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(n, 16)
            np.testing.assert_array_equal(raw[:, :12].copy().view("<f4"), result.points_vehicle)
            np.testing.assert_array_equal(raw[:, 12:].copy().view("<u4")[:, 0], result.point_labels)


def test_marker_array(ros_file):
    _path, frames, mcap_topics, rosbags_topics = ros_file
    for k, (frame, result) in enumerate(frames):
        for msg in (mcap_topics["/terrainmap/obstacles"][k][2], rosbags_topics["/terrainmap/obstacles"][k]):
            first, *markers = msg.markers
            assert first.action == 3  # DELETEALL
            shown = [o for o in result.obstacles if o.confirmed]  # a tentative track is no obstacle yet
            assert len(markers) == 2 * (len(shown) + len(result.occupied))
            namespaces = [("obstacles", "obstacle_labels")] * len(shown) + [("occupied", "occupied_labels")] * len(
                result.occupied)
            for cube, text, obstacle, (ns, labels) in zip(markers[::2], markers[1::2], shown + result.occupied,
                                                          namespaces, strict=True):
                assert (cube.type, cube.action, cube.ns, text.type, text.ns) == (1, 0, ns, 9, labels)
                assert cube.header.frame_id == "base_link" and stamp_ns(cube.header) == frame.stamp_ns
                np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y, cube.pose.position.z],
                                           obstacle.center_m)
                np.testing.assert_allclose([cube.scale.x, cube.scale.y, cube.scale.z], obstacle.size_m)
                assert 2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w) == pytest.approx(obstacle.yaw_rad)
                if ns == "obstacles":
                    assert text.text == f"{obstacle.track_id} {obstacle.kind} {obstacle.height_m:.2f} m"
                assert text.pose.position.z > cube.pose.position.z and text.pose.orientation.w == 1.0
            if len(shown) == 2:
                assert [m.id for m in markers] == [7, 7, 8, 8, 0, 0, 1, 1]  # the track ids, then n
                assert [m.text for m in markers[5::2]] == ["part of 7", "11 unseen"]


def test_tf_static_once_and_stamps(ros_file):
    _path, _frames, mcap_topics, rosbags_topics = ros_file
    assert "/tf" not in mcap_topics and len(mcap_topics["/tf_static"]) == 1
    for msg in (mcap_topics["/tf_static"][0][2], rosbags_topics["/tf_static"][0]):
        (tf,) = msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "left_optical")
        t, r = tf.transform.translation, tf.transform.rotation
        assert (t.x, t.y, t.z) == (0.2, -0.1, 1.6)
        np.testing.assert_allclose([r.x, r.y, r.z, r.w], expected_quaternion(), atol=1e-12)
    for entries in mcap_topics.values():
        for log_time, publish_time, msg in entries:
            header = msg.transforms[0].header if hasattr(msg, "transforms") else (
                msg.markers[0].header if hasattr(msg, "markers") else msg.header)
            assert log_time == publish_time == stamp_ns(header)
    assert mcap_topics["/terrainmap/grid_map"][2][0] == STAMP0 + 200_000_000


def channel_qos(path: Path) -> dict[str, tuple[int, int, int]]:
    """topic → (reliability, durability, depth) of its offered QoS, parsed by rosbags (as rosbag2 would)."""
    from rosbags.rosbag2.metadata import parse_qos

    with open(path, "rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    profiles = {c.topic: parse_qos(c.metadata["offered_qos_profiles"]) for c in channels}
    return {topic: (p.reliability.value, p.durability.value, p.depth) for topic, (p,) in profiles.items()}


def test_channels_offer_qos_for_ros2_bag_play_with_static_topics_latched(ros_file, tmp_path):
    estimated = tmp_path / "estimated.mcap"  # its camera pose goes on /tf
    write_frames(estimated, "ros2", [make_frame(0, source="estimated")])
    qos = {**channel_qos(ros_file[0]), "/tf": channel_qos(estimated)["/tf"]}
    assert {"/tf_static", "/terrainmap/costmap", "/terrainmap/grid_map", "/terrainmap/points"} <= set(qos)
    for topic, (reliability, durability, depth) in qos.items():
        latched = topic in ("/tf_static", "/terrainmap/costmap")
        depth_wanted = 1 if latched else 100 if topic == "/tf" else 10  # /tf: as tf2's TransformBroadcaster
        assert (reliability, durability, depth) == (1, 1 if latched else 2, depth_wanted), topic  # 1 = reliable; 1 transient local, 2 volatile


def test_schemas_registered_once_with_short_dependency_names(ros_file):
    path = ros_file[0]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    names = sorted(s.name for s in summary.schemas.values())
    assert names == sorted(set(names))
    assert all(b"/msg/" not in s.data for s in summary.schemas.values())
    assert all(s.encoding == "ros2msg" for s in summary.schemas.values())


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_full_size_frames_are_written_whole(tmp_path, flavor):
    """Frames of 300k points at the paper's grid size: every point reaches the file (x, y, z
    float32 and a uint8 label, at least 13 bytes each). The cost per frame: `terrainmap bench`."""
    frames = [make_frame(i, grid=GridConfig(), points=300_000) for i in range(3)]
    path = tmp_path / "full.mcap"
    with open_mcap_sink(path, flavor, config=Config(), compression="lz4") as sink:
        for frame, result in frames:
            sink.write(frame, result)
    with open(path, "rb") as f:
        clouds = [m for _s, _c, m in make_reader(f).iter_messages(topics=["/terrainmap/points"])]
    assert len(clouds) == 3 and all(len(m.data) >= 300_000 * 13 for m in clouds)


def test_a_cloud_with_a_point_that_is_not_finite_is_not_dense(tmp_path):
    """PointCloud2's ``is_dense`` says every point is finite: a result built with a NaN point
    (a library caller's) must not claim it."""
    frame, result = make_frame(0, points=5)
    result.points_vehicle[3, 2] = np.nan
    path = tmp_path / "nan.mcap"
    write_frames(path, "ros2", [(frame, result)])
    ((_, _, cloud),) = read_messages(path, DecoderFactory())["/terrainmap/points"]
    assert cloud.width == 5 and not cloud.is_dense
    assert np.isnan(np.frombuffer(bytes(cloud.data), np.uint8).reshape(5, 16)[3, 8:12].copy().view("<f4")[0])
