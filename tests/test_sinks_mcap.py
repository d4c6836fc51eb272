"""MCAP sinks: write synthetic frames, read them back with independent decoders, compare every field."""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory
from scipy.spatial.transform import Rotation

import terrainmap
from terrainmap.config import Config, GridConfig
from terrainmap.errors import ConfigError, InputError, TerrainmapError
from terrainmap.grid import HeightGrid, cell_index
from terrainmap.sinks import Sink, open_mcap_sink
from terrainmap.types import Extrinsics, FrameResult, Obstacle, StereoCalibration, StereoFrame

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# 4 m × 3 m at 0.5 m: m0 = 8 cells along x, m1 = 6 along y (not square, so transposes show).
GRID = GridConfig(x_min_m=2.0, length_m=4.0, width_m=3.0, y_center_m=0.5, cell_size_m=0.5)
STAMP0 = 1_700_000_000_123_456_789
CAM_ROTATION = Rotation.from_euler("xyz", [-90 - 5, 1.0, -90], degrees=True).as_matrix()  # optical, pitched


def make_layers(grid: GridConfig, *, cost: bool = True) -> dict[str, np.ndarray]:
    m0, m1 = grid.shape
    ix, iy = np.meshgrid(np.arange(m0), np.arange(m1), indexing="ij")
    layers = {
        "elevation": (ix * 10 + iy).astype(np.float32) / 100,  # unique per cell: 0.01·(10·ix + iy)
        "slope": (ix + iy / 10).astype(np.float32),
        "label": ((ix + 2 * iy) % 4).astype(np.uint8),
        "valid": (ix + iy) % 5 != 0,
    }
    if cost:
        layers["cost"] = np.where(iy == 1, np.nan, ix / m0).astype(np.float32)
    return layers


OCCUPIED = [  # what else occupies the cost map: a part of track 7 (a confirmed obstacle of the frame), track 11 unseen
    Obstacle(np.array([4.8, 0.9, 0.3]), np.array([0.4, 0.3, 0.6]), 0.1, 0.6, 15, 4.9, "positive", 7, True),
    Obstacle(np.array([6.0, -1.0, 0.5]), np.array([0.7, 0.7, 1.0]), 0.5, 1.0, 30, 6.1, "positive", 11, True),
]


def make_frame(index: int, *, grid: GridConfig = GRID, points: int = 50, source: str = "calibration", cost=True):
    rng = np.random.default_rng(index)
    stamp_ns = STAMP0 + index * 100_000_000
    pts = np.c_[rng.uniform(2, 6, points), rng.uniform(-1, 2, points), rng.normal(0, 0.2, points)].astype(np.float32)
    m0, m1 = grid.shape
    height_grid = HeightGrid(
        z=np.zeros((m0, m1)),
        z_top=np.zeros((m0, m1)),
        count=np.ones((m0, m1), int),
        observed=np.ones((m0, m1), bool),
        valid=np.ones((m0, m1), bool),
        config=grid,
    )
    extrinsics = Extrinsics(CAM_ROTATION, np.array([0.2, -0.1, 1.6]), source=source, camera_frame_id="left_optical")
    obstacles = [
        Obstacle(np.array([4.0, 0.5, 0.4]), np.array([1.0, 0.6, 0.8]), 0.3, 0.8, 40, 4.0, "positive", 7, True),
        Obstacle(np.array([5.0, -0.5, -0.2]), np.array([0.5, 0.5, 0.3]), -1.0, 0.3, 9, 5.0, "negative", 8, True),
        Obstacle(np.array([3.0, 1.0, 0.3]), np.array([0.4, 0.4, 0.6]), 0.0, 0.6, 12, 3.0, "positive", 9, False),
    ]
    result = FrameResult(
        index=index,
        stamp_ns=stamp_ns,
        extrinsics=extrinsics,
        points_vehicle=pts,
        pixels=np.zeros((points, 2), np.int32),
        point_labels=rng.integers(0, 4, points).astype(np.uint8),
        grid=height_grid,
        terrain=None,
        layers=make_layers(grid, cost=cost),
        obstacles=[obstacles[k] for k in ([], [0, 2], [0, 1, 2])[index % 3]],  # replaced each frame; #9 tentative
        occupied=OCCUPIED if index % 3 == 2 else [],
    )
    calibration = StereoCalibration(width=4, height=3, fx=1.0, fy=1.0, cx=2.0, cy=1.5, baseline_m=0.5)
    image = np.zeros((3, 4), np.uint8)
    return StereoFrame(index, stamp_ns, image, image, calibration, frame_id="left_optical"), result


def write_frames(path: Path, flavor: str, frames: list, config: Config | None = None, **kwargs) -> None:
    config = config or Config()
    with open_mcap_sink(path, flavor, config=config, metadata={"source": "/logs/run.mcap"}, **kwargs) as sink:
        assert isinstance(sink, Sink)
        for frame, result in frames:
            sink.write(frame, result)


def read_messages(path: Path, factory) -> dict[str, list]:
    """topic → [(log_time, publish_time, decoded)] in log order."""
    topics: dict[str, list] = {}
    with open(path, "rb") as f:
        for _schema, channel, message, decoded in make_reader(f, decoder_factories=[factory]).iter_decoded_messages():
            topics.setdefault(channel.topic, []).append((message.log_time, message.publish_time, decoded))
    return topics


def read_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    return records["terrainmap"]


def expected_quaternion() -> np.ndarray:
    q = Rotation.from_matrix(CAM_ROTATION).as_quat()
    return -q if q[3] < 0 else q


def assert_stamps(topics: dict[str, list], stamp_of) -> None:
    for entries in topics.values():
        for log_time, publish_time, msg in entries:
            assert log_time == publish_time
            assert stamp_of(msg) == log_time


def cell_of(grid: GridConfig, x: float, y: float) -> tuple[int, int]:
    flat = int(cell_index(np.array([[x, y, 0.0]]), grid)[0])
    return divmod(flat, grid.shape[1])


# ---------------------------------------------------------------- Foxglove flavour


def fox_stamp(msg) -> int:
    if hasattr(msg, "transforms"):
        ts = msg.transforms[0].timestamp
    elif hasattr(msg, "deletions"):  # the obstacles' (a delete-all first), the surface's (its entity)
        ts = msg.deletions[0].timestamp if msg.deletions else msg.entities[0].timestamp
    else:
        ts = msg.timestamp
    return ts.seconds * 1_000_000_000 + ts.nanos


def unpack(fields, stride: int, data: bytes, count: int) -> np.ndarray:
    types = {7: "<f4", 1: "u1"}
    dtype = np.dtype(
        {"names": [f.name for f in fields], "formats": [types[f.type] for f in fields],
         "offsets": [f.offset for f in fields], "itemsize": stride}
    )
    return np.frombuffer(data, dtype=dtype, count=count)


@pytest.fixture(scope="module")
def fox_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("fox") / "out.mcap"
    frames = [make_frame(i) for i in range(3)]
    write_frames(path, "foxglove", frames)
    return path, frames


def test_foxglove_grid_layout_and_values(fox_file):
    path, frames = fox_file
    grids = read_messages(path, ProtobufDecoderFactory())["/terrainmap/grid"]
    assert len(grids) == 3
    m0, m1 = GRID.shape
    for (_, _, grid), (_frame, result) in zip(grids, frames, strict=True):
        assert grid.frame_id == "base_link"
        assert grid.column_count == m0
        assert (grid.cell_size.x, grid.cell_size.y) == (0.5, 0.5)
        assert (grid.pose.position.x, grid.pose.position.y, grid.pose.position.z) == (2.0, -1.0, 0.0)
        assert grid.pose.orientation.w == 1.0
        assert [f.name for f in grid.fields] == ["elevation", "slope", "cost", "label", "valid"]
        assert [f.type for f in grid.fields] == [7, 7, 7, 1, 1]
        assert grid.row_stride == m0 * grid.cell_stride and len(grid.data) == m1 * grid.row_stride
        cells = unpack(grid.fields, grid.cell_stride, grid.data, m0 * m1).reshape(m1, m0)
        layers = result.layers
        valid = layers["valid"]
        for name in ("elevation", "slope"):  # none where the cell has no data: the surface only extrapolates
            np.testing.assert_array_equal(cells[name].T, np.where(valid, layers[name], np.nan))
        for name in ("cost", "label"):
            np.testing.assert_array_equal(cells[name].T, layers[name])
        np.testing.assert_array_equal(cells["valid"].T, valid.astype(np.uint8))


def test_foxglove_grid_cell_at_known_position(fox_file):
    """The byte offset of the cell holding (x, y) follows foxglove.Grid's documented formula."""
    path, frames = fox_file
    _, _, grid = read_messages(path, ProtobufDecoderFactory())["/terrainmap/grid"][0]
    layers = frames[0][1].layers
    slope = np.where(layers["valid"], layers["slope"], np.nan)  # as written
    for x, y in [(2.1, -0.9), (5.9, 1.9), (3.3, 1.2)]:
        col = math.floor((x - grid.pose.position.x) / grid.cell_size.x)
        row = math.floor((y - grid.pose.position.y) / grid.cell_size.y)
        offset = row * grid.row_stride + col * grid.cell_stride + grid.fields[1].offset
        value = np.frombuffer(grid.data, "<f4", count=1, offset=offset)[0]
        np.testing.assert_equal(value, slope[cell_of(GRID, x, y)])  # NaN too
    # (3.3, 1.2) is ix = 2, iy = 4: slope 2.4
    assert cell_of(GRID, 3.3, 1.2) == (2, 4)


def test_foxglove_points(fox_file):
    path, frames = fox_file
    clouds = read_messages(path, ProtobufDecoderFactory())["/terrainmap/points"]
    for (_, _, cloud), (_frame, result) in zip(clouds, frames, strict=True):
        assert cloud.frame_id == "base_link"
        assert [(f.name, f.offset, f.type) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("label", 12, 1)]
        points = unpack(cloud.fields, cloud.point_stride, cloud.data, len(cloud.data) // cloud.point_stride)
        np.testing.assert_array_equal(np.c_[points["x"], points["y"], points["z"]], result.points_vehicle)
        np.testing.assert_array_equal(points["label"], result.point_labels)


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_max_points_writes_every_kth_point(tmp_path, flavor):
    """``mcap.max_points``: 50 points capped at 20 keep every 3rd (17), each with its own label;
    the grid is unchanged. 0 (the default) writes them all (the tests above)."""
    from terrainmap.sinks.base import point_stride

    assert (point_stride(50, 20), point_stride(50, 0), point_stride(50, 50), point_stride(0, 20)) == (3, 1, 1, 1)
    config = Config()
    config.mcap.max_points = 20
    frame, result = make_frame(0, points=50)
    path = tmp_path / "o.mcap"
    write_frames(path, flavor, [(frame, result)], config=config)
    factory = ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory()
    ((_, _, cloud),) = read_messages(path, factory)["/terrainmap/points"]
    raw = np.frombuffer(bytes(cloud.data), np.uint8).reshape(-1, 13 if flavor == "foxglove" else 16)
    assert len(raw) == 17 and (flavor == "foxglove" or cloud.width == 17)
    np.testing.assert_array_equal(raw[:, :12].copy().view("<f4"), result.points_vehicle[::3])
    np.testing.assert_array_equal(raw[:, 12], result.point_labels[::3])


def test_foxglove_obstacles_replace_previous_entities(fox_file):
    path, frames = fox_file
    updates = read_messages(path, ProtobufDecoderFactory())["/terrainmap/obstacles"]
    for (_, _, update), (_frame, result) in zip(updates, frames, strict=True):
        assert [d.type for d in update.deletions] == [1]  # ALL
        shown = [o for o in result.obstacles if o.confirmed]  # a tentative track is no obstacle yet
        assert len(update.entities) == len(shown) + len(result.occupied)
        for entity, obstacle in zip(update.entities, shown + result.occupied, strict=True):
            cube = entity.cubes[0]
            assert entity.frame_id == "base_link"
            np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y, cube.pose.position.z], obstacle.center_m)
            np.testing.assert_allclose([cube.size.x, cube.size.y, cube.size.z], obstacle.size_m)
            yaw = 2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w)
            assert yaw == pytest.approx(obstacle.yaw_rad)
        for entity, obstacle in zip(update.entities, shown, strict=False):
            assert entity.texts[0].text == f"{obstacle.track_id} {obstacle.kind} {obstacle.height_m:.2f} m"
        occupied = update.entities[len(shown):]  # grey, after the obstacles
        assert [(e.id, e.texts[0].text) for e in occupied] == [("occupied/0", "part of 7"), ("occupied/1", "11 unseen")][
            : len(occupied)]
        assert all(e.cubes[0].color.r == e.cubes[0].color.g == e.cubes[0].color.b for e in occupied)
        if len(shown) == 2:
            assert update.entities[0].id == "obstacle/7"
            assert update.entities[0].cubes[0].color.r > update.entities[0].cubes[0].color.b  # positive: red
            assert update.entities[1].cubes[0].color.b > update.entities[1].cubes[0].color.r  # negative: blue


def test_the_trackers_parts_and_unseen_tracks_are_drawn_as_such():
    """A fragment 1 m beside a confirmed track is a part of it, drawn as "part of <id>" beside the
    track's own box; the track missed in the next frame is drawn as "<id> unseen"."""
    from terrainmap.config import TrackingConfig
    from terrainmap.sinks.base import shown_boxes
    from terrainmap.tracking import ObstacleTracker

    def detection(x):
        return Obstacle(np.array([x, 0.0, 0.5]), np.ones(3), 0.0, 1.0, 50, x, "positive")

    def drawn(obstacles):
        result = FrameResult(0, 0, Extrinsics(np.eye(3), np.zeros(3)), np.zeros((0, 3), np.float32),
                             np.zeros((0, 2), np.int32), np.zeros(0, np.uint8), None, None, obstacles=obstacles,
                             occupied=[*tracker.parts, *tracker.coasting(3)])
        return [(box.group, box.text) for box in shown_boxes(result)]

    tracker = ObstacleTracker(TrackingConfig())
    for k in range(2):
        (track,) = tracker.update([detection(10.0)], k * 10**8)
    i = track.track_id
    assert drawn(tracker.update([detection(10.0), detection(11.0)], 2 * 10**8)) == [
        ("obstacle", f"{i} positive 1.00 m"), ("occupied", f"part of {i}")]
    assert drawn(tracker.update([], 3 * 10**8)) == [("occupied", f"{i} unseen")]


def test_foxglove_static_transform_once_and_stamps(fox_file):
    path, _frames = fox_file
    topics = read_messages(path, ProtobufDecoderFactory())
    assert "/tf" not in topics and len(topics["/tf_static"]) == 1
    (tf,) = topics["/tf_static"][0][2].transforms
    assert (tf.parent_frame_id, tf.child_frame_id) == ("base_link", "left_optical")
    assert (tf.translation.x, tf.translation.y, tf.translation.z) == (0.2, -0.1, 1.6)
    q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
    np.testing.assert_allclose(q, expected_quaternion(), atol=1e-12)
    assert_stamps(topics, fox_stamp)
    assert [t for t, _, _ in topics["/terrainmap/grid"]] == [STAMP0, STAMP0 + 100_000_000, STAMP0 + 200_000_000]


def test_estimated_extrinsics_go_on_tf_every_frame(tmp_path):
    path = tmp_path / "est.mcap"
    write_frames(path, "foxglove", [make_frame(i, source="estimated") for i in range(3)])
    topics = read_messages(path, ProtobufDecoderFactory())
    assert "/tf_static" not in topics and len(topics["/tf"]) == 3


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_vehicle_pose_goes_on_tf_as_odometry_to_base_link(tmp_path, flavor):
    """Frames with a vehicle pose also write ``odom → base_link`` on /tf, read back equal."""
    yaw = Rotation.from_euler("z", 30, degrees=True)
    frames = []
    for i in range(3):
        frame, result = make_frame(i)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = yaw.as_matrix(), [10.0 + i, -2.0, 0.5]
        frames.append((dataclasses.replace(frame, vehicle_pose=pose, odometry_frame_id="map"), result))
    path = tmp_path / f"odom_{flavor}.mcap"
    write_frames(path, flavor, frames)
    factory = ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory()
    tf = read_messages(path, factory)["/tf"]
    assert [t for t, _, _ in tf] == [f.stamp_ns for f, _ in frames]
    for i, (_, _, msg) in enumerate(tf):
        (t,) = msg.transforms
        if flavor == "foxglove":
            parent, child, xyz, q = t.parent_frame_id, t.child_frame_id, t.translation, t.rotation
        else:
            parent, child, xyz, q = t.header.frame_id, t.child_frame_id, t.transform.translation, t.transform.rotation
        assert (parent, child) == ("map", "base_link")
        np.testing.assert_allclose([xyz.x, xyz.y, xyz.z], [10.0 + i, -2.0, 0.5])
        np.testing.assert_allclose(np.abs(np.dot([q.x, q.y, q.z, q.w], yaw.as_quat())), 1.0, atol=1e-12)


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_messages_are_placed_in_the_vehicle_frame_the_extrinsics_name(tmp_path, flavor):
    """A log whose tf names the vehicle ``base_footprint``: grid, points, obstacles and the camera
    transform all hang from that frame, so the output joins the log's tf tree."""
    frames = []
    for i in range(3):
        frame, result = make_frame(i)
        extrinsics = dataclasses.replace(result.extrinsics, source="tf", vehicle_frame_id="base_footprint")
        frames.append((frame, dataclasses.replace(result, extrinsics=extrinsics)))
    path = tmp_path / f"footprint_{flavor}.mcap"
    write_frames(path, flavor, frames)
    topics = read_messages(path, ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory())
    frame_ids = set()
    for topic, messages in topics.items():
        for _, _, msg in messages:
            if topic in ("/tf", "/tf_static"):
                frame_ids |= {t.parent_frame_id if flavor == "foxglove" else t.header.frame_id for t in msg.transforms}
            elif topic in ("/terrainmap/obstacles", "/terrainmap/surface"):
                parts = msg.entities if flavor == "foxglove" else [m.header for m in msg.markers]
                frame_ids |= {part.frame_id for part in parts}
            else:
                frame_ids.add(msg.frame_id if flavor == "foxglove" else msg.header.frame_id)
    assert frame_ids == {"base_footprint"}
    assert {"/tf_static", "/terrainmap/obstacles"} <= topics.keys() and len(topics) >= 4


def test_grid_without_cost_layer(tmp_path):
    path = tmp_path / "nocost.mcap"
    write_frames(path, "foxglove", [make_frame(0, cost=False)])
    (_, _, grid), = read_messages(path, ProtobufDecoderFactory())["/terrainmap/grid"]
    assert [f.name for f in grid.fields] == ["elevation", "slope", "label", "valid"]
    assert grid.cell_stride == 10


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_metadata_record(tmp_path, flavor):
    path = tmp_path / "meta.mcap"
    frames = [make_frame(i) for i in range(2)]
    write_frames(path, flavor, frames)
    meta = read_metadata(path)
    assert meta["version"] == terrainmap.__version__
    assert meta["source"] == "/logs/run.mcap"
    assert meta["frames"] == "2"
    assert tomllib.loads(meta["config"]) == tomllib.loads(Config().to_toml())
    assert json.loads(meta["extrinsics"]) == frames[0][1].extrinsics.to_dict()
    assert meta["extrinsics_changes"] == "0"


def test_metadata_counts_the_frames_that_moved_the_camera(tmp_path):
    frames = [make_frame(i) for i in range(4)]
    for i in (2, 3):  # a second scene from frame 2 on
        frame, result = frames[i]
        moved = dataclasses.replace(result.extrinsics, translation=np.array([0.2, -0.1, 1.4]))
        frames[i] = (frame, dataclasses.replace(result, extrinsics=moved))
    path = tmp_path / "moved.mcap"
    write_frames(path, "foxglove", frames)
    meta = read_metadata(path)
    assert json.loads(meta["extrinsics"])["translation_m"] == [0.2, -0.1, 1.6] and meta["extrinsics_changes"] == "1"


# ---------------------------------------------------------------- failure handling


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_exception_mid_run_leaves_a_finalised_file(tmp_path, flavor):
    path = tmp_path / "crash.mcap"
    with pytest.raises(RuntimeError, match="boom"):
        with open_mcap_sink(path, flavor, config=Config()) as sink:
            for i in range(2):
                sink.write(*make_frame(i))
            raise RuntimeError("boom")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None  # footer, summary and index written
        assert len(summary.chunk_indexes) >= 1
        grid_topic = "/terrainmap/grid" if flavor == "foxglove" else "/terrainmap/grid_map"
        assert len([m for _, ch, m in reader.iter_messages(topics=[grid_topic])]) == 2
    assert read_metadata(path)["frames"] == "2"


class _DiskFillsUp:
    """An output file on a disk with ``room`` bytes left (None: plenty): a write beyond it writes what
    fits, then fails with ENOSPC, as a full disk does."""

    def __init__(self, file):
        self.file, self.room = file, None

    def write(self, data) -> int:
        fits = len(data) if self.room is None else min(len(data), self.room)
        self.file.write(bytes(data[:fits]))
        if self.room is not None:
            self.room -= fits
            if fits < len(data):
                self.file.flush()
                raise OSError(errno.ENOSPC, "No space left on device")
        return fits

    def __getattr__(self, name):  # tell, flush, close
        return getattr(self.file, name)


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
@pytest.mark.parametrize("frames, room", [(2, 0), (2, 100), (0, 100)])
def test_a_full_disk_leaves_the_frames_before_it_readable(tmp_path, monkeypatch, flavor, frames, room):
    """The disk fills up while the frame after ``frames`` (room 100: in the middle of its chunk) or
    the summary (room 0) is written: the file is cut back to its whole frames and ends there,
    readable from start to end, with its metadata."""
    from terrainmap.sinks import base

    outputs = []

    def output_file(path, mode="r", *args, **kwargs):
        file = open(path, mode, *args, **kwargs)
        if mode == "wb":
            outputs.append(_DiskFillsUp(file))
            return outputs[-1]
        return file

    monkeypatch.setattr(base, "open", output_file, raising=False)
    path = tmp_path / "full.mcap"
    sink = open_mcap_sink(path, flavor, config=Config())
    for index in range(frames):
        sink.write(*make_frame(index))
    (disk,) = outputs
    disk.room = room
    if room:
        with pytest.raises(InputError, match=f"cannot write MCAP output {path}: No space left on device"):
            sink.write(*make_frame(frames))
    kept = "cut back to its first 2 frames, which read back without an index" if frames else \
        r"cut back to its header \(no frame in it\)"
    what = "write" if room else "finish"  # the frame, or the summary
    with pytest.raises(InputError, match=f"cannot {what} MCAP output {path}: No space left on device; {kept}"):
        sink.close()
    assert not sink.finished
    factory = ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory()
    topics = read_messages(path, factory)  # the mcap package's reader: start to end, without a summary
    grid_topic = "/terrainmap/grid" if flavor == "foxglove" else "/terrainmap/grid_map"
    assert [t for t, _, _ in topics.get(grid_topic, [])] == [make_frame(i)[0].stamp_ns for i in range(frames)]
    assert read_metadata(path)["frames"] == str(frames)


_FILE_SIZE_LIMIT = """
import resource, signal, sys
sys.path.insert(0, sys.argv[1])
from test_sinks_mcap import Config, make_frame, open_mcap_sink
from terrainmap.errors import InputError
path, limit = sys.argv[2], int(sys.argv[3])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
try:
    sink = open_mcap_sink(path, "foxglove", config=Config())
except InputError as exc:
    sys.exit(print(exc))
try:
    for index in range(3):
        sink.write(*make_frame(index))
except InputError as exc:
    print(exc)
try:
    sink.close()
except InputError as exc:
    print(exc)
"""


def _whole_frames_end(path: Path) -> list[int]:
    """Where the header and each of 3 frames end in the file of a foxglove sink."""
    sink = open_mcap_sink(path, "foxglove", config=Config())
    ends = [path.stat().st_size]
    for index in range(3):
        sink.write(*make_frame(index))
        ends.append(path.stat().st_size)
    sink.close()
    return ends


def test_a_file_size_limit_hit_in_the_header_or_a_frame_leaves_no_file_or_the_frames_before_it(tmp_path):
    """A real write error (EFBIG past RLIMIT_FSIZE, in a child process): in the header, no file
    is left and one line names the output; 100 bytes into the third frame, the file is cut back to
    two frames and ends there, with no room for the metadata."""
    ends = _whole_frames_end(tmp_path / "sizes.mcap")
    tests = str(Path(__file__).parent)
    for limit, expected in ((20, None), (ends[2] + 100, 2)):
        path = tmp_path / f"limit{limit}.mcap"
        out = subprocess.run([sys.executable, "-c", _FILE_SIZE_LIMIT, tests, str(path), str(limit)],
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        lines = out.stdout.splitlines()
        if expected is None:
            assert lines == [f"cannot write MCAP output {path}: File too large"] and not path.exists()
            continue
        assert lines == [f"cannot write MCAP output {path}: File too large",
                         f"cannot write MCAP output {path}: File too large; cut back to its first 2 frames, "
                         "which read back without an index"]
        topics = read_messages(path, ProtobufDecoderFactory())
        assert [t for t, _, _ in topics["/terrainmap/grid"]] == [make_frame(i)[0].stamp_ns for i in range(2)]


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_a_frame_that_fails_part_way_is_cut_off_and_nothing_more_is_written(tmp_path, monkeypatch, flavor, caplog):
    """An error other than the disk's in the middle of a frame (here out of memory packing its
    points, after its grid was written): close() keeps the frames before it, ends the file there
    and warns; the sink takes no more frames."""
    from terrainmap.sinks import mcap_foxglove, mcap_ros2

    path = tmp_path / "partial.mcap"
    sink = open_mcap_sink(path, flavor, config=Config())
    sink.write(*make_frame(0))
    module, name = (mcap_foxglove, "encode_points") if flavor == "foxglove" else (mcap_ros2, "encode_point_cloud2")

    def out_of_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(module, name, out_of_memory)
    with pytest.raises(MemoryError):
        sink.write(*make_frame(1))
    with pytest.raises(TerrainmapError, match="failed in an earlier frame"):
        sink.write(*make_frame(2))
    sink.close()
    assert not sink.finished and "cut back to its first frame, which reads back" in caplog.text
    factory = ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory()
    topics = read_messages(path, factory)
    assert {topic: len(messages) for topic, messages in topics.items() if topic != "/tf_static"} == {
        topic: 1 for topic in topics if topic != "/tf_static"}  # every topic has frame 0 only
    assert read_metadata(path)["frames"] == "1"


def test_a_sink_without_a_valid_config_is_refused_before_its_file_is_made(tmp_path):
    path = tmp_path / "o.mcap"
    with pytest.raises(ConfigError, match="config must be a Config, got NoneType"):
        open_mcap_sink(path, "foxglove", config=None)
    bad = Config()
    bad.mcap.max_points = -3
    with pytest.raises(ConfigError, match="mcap.max_points"):
        open_mcap_sink(path, "ros2", config=bad)
    assert not path.exists()


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_close_twice_and_write_after_close(tmp_path, flavor):
    path = tmp_path / "twice.mcap"
    sink = open_mcap_sink(path, flavor, config=Config())
    sink.write(*make_frame(0))
    sink.close()
    size = path.stat().st_size
    sink.close()
    assert path.stat().st_size == size
    with pytest.raises(TerrainmapError, match="already closed"):
        sink.write(*make_frame(1))


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
@pytest.mark.parametrize("cut", [False, True])
def test_the_finished_or_cut_back_file_is_synced_to_disk_whole(tmp_path, monkeypatch, flavor, cut):
    """close() has the OS write the file to the device once it is whole (its summary, or the
    ending after the frames kept), so that a power cut after the run loses nothing of it."""
    from terrainmap.sinks import base, mcap_foxglove, mcap_ros2

    synced = []
    monkeypatch.setattr(base.os, "fsync", lambda fd: synced.append(os.fstat(fd).st_size))
    path = tmp_path / "synced.mcap"
    sink = open_mcap_sink(path, flavor, config=Config())
    sink.write(*make_frame(0))
    if cut:
        module, name = (mcap_foxglove, "encode_points") if flavor == "foxglove" else (mcap_ros2, "encode_point_cloud2")
        monkeypatch.setattr(module, name, lambda *args, **kwargs: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            sink.write(*make_frame(1))
    sink.close()
    assert synced == [path.stat().st_size] and sink.finished is not cut


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
@pytest.mark.parametrize("stamp", [-1, 1.7e18, 2**64, True])
def test_a_bad_stamp_is_refused_and_the_frames_before_it_are_kept(tmp_path, flavor, stamp):
    path = tmp_path / "stamp.mcap"
    with open_mcap_sink(path, flavor, config=Config()) as sink:
        sink.write(*make_frame(0))
        frame, result = make_frame(1)
        frame.stamp_ns = result.stamp_ns = stamp
        with pytest.raises(InputError, match="stamp must be a whole number of nanoseconds"):
            sink.write(frame, result)
    assert read_metadata(path)["frames"] == "1"
    with open(path, "rb") as f:
        assert len(list(make_reader(f).iter_messages())) > 0


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_a_source_path_that_is_not_utf8_is_kept_escaped_in_the_metadata(tmp_path, flavor):
    path = tmp_path / "escaped.mcap"
    name = os.fsdecode(b"/logs/bad\xffname.mcap")  # how Python sees a file name that is not UTF-8
    with open_mcap_sink(path, flavor, config=Config(), metadata={"source": name}) as sink:
        sink.write(*make_frame(0))
    assert read_metadata(path)["source"] == "/logs/bad\\udcffname.mcap"


def test_point_labels_must_match_the_points(tmp_path):
    frame, result = make_frame(0)
    result.point_labels = result.point_labels[:-1]
    with open_mcap_sink(tmp_path / "bad.mcap", config=Config()) as sink:
        with pytest.raises(TerrainmapError, match="points but point labels of shape"):
            sink.write(frame, result)


def test_empty_run_is_readable(tmp_path):
    path = tmp_path / "empty.mcap"
    open_mcap_sink(path, "ros2", config=Config()).close()
    assert read_metadata(path)["frames"] == "0"


def test_bad_arguments(tmp_path):
    with pytest.raises(ConfigError, match="flavor"):
        open_mcap_sink(tmp_path / "x.mcap", "rosbag", config=Config())
    with pytest.raises(ConfigError, match="compression"):
        open_mcap_sink(tmp_path / "x.mcap", "ros2", config=Config(), compression="gzip")
    with pytest.raises(ConfigError, match="must be zstd, lz4 or none, got None"):  # (str(None) is 'None')
        open_mcap_sink(tmp_path / "x.mcap", "foxglove", config=Config(), compression=None)
    with pytest.raises(ConfigError, match="metadata must be a mapping of names to texts, got list"):
        open_mcap_sink(tmp_path / "x.mcap", "foxglove", config=Config(), metadata=[("source", "x")])
    assert not (tmp_path / "x.mcap").exists()
    with pytest.raises(InputError, match="no_such_dir"):
        open_mcap_sink(tmp_path / "no_such_dir" / "x.mcap", config=Config())


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_layer_shape_mismatch_is_reported_before_any_message_of_the_frame(tmp_path, flavor):
    """The refused frame leaves nothing (not its /tf) in the file, whose frame count it matches."""
    path = tmp_path / "bad.mcap"
    with open_mcap_sink(path, flavor, config=Config()) as sink:
        frame, result = make_frame(0)
        sink.write(dataclasses.replace(frame, vehicle_pose=np.eye(4)), result)  # with odometry: a /tf each frame
        frame, result = make_frame(1)
        frame = dataclasses.replace(frame, vehicle_pose=np.eye(4))
        result.layers["slope"] = np.zeros((3, 3), np.float32)
        with pytest.raises(TerrainmapError, match="layer 'slope' has shape"):
            sink.write(frame, result)
    with open(path, "rb") as f:
        stamps = {message.log_time for _, _, message in make_reader(f).iter_messages()}
    assert frame.stamp_ns not in stamps and read_metadata(path)["frames"] == "1"


def test_foxglove_layout_names_written_topics_and_fields(fox_file):
    """examples/foxglove_layout.json shows the surface (its mesh, coloured by slope), the points
    coloured by label and the grid, hidden (Foxglove draws it flat), coloured by slope, on our topics."""
    layout = json.loads((Path(__file__).resolve().parents[1] / "examples" / "foxglove_layout.json").read_text())
    panel = layout["configById"][layout["layout"]["first"]]
    assert layout["layout"]["first"].startswith("3D!")
    topics = read_messages(fox_file[0], ProtobufDecoderFactory())
    assert set(panel["topics"]) <= set(topics)
    grid_fields = {f.name for f in topics["/terrainmap/grid"][0][2].fields}
    point_fields = {f.name for f in topics["/terrainmap/points"][0][2].fields}
    grid, points = panel["topics"]["/terrainmap/grid"], panel["topics"]["/terrainmap/points"]
    assert grid["colorField"] == "slope" and grid["colorField"] in grid_fields and not grid["visible"]
    assert panel["topics"]["/terrainmap/surface"]["visible"]
    assert points["colorField"] == "label" and points["colorField"] in point_fields
    assert panel["followTf"] == "base_link"


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
@pytest.mark.parametrize("source", ["tf", "calibration", "estimated"])
def test_the_logs_own_transforms_can_be_left_out(tmp_path, flavor, source):
    """``mcap.log_transforms=false``, for playing the output beside its log: neither the odometry
    pose nor a mount from the log's tf is written again; a pose terrainmap made still is."""
    config = Config()
    config.mcap.log_transforms = False
    frames = [make_frame(i, source=source) for i in range(2)]
    frames = [(dataclasses.replace(frame, vehicle_pose=np.eye(4)), result) for frame, result in frames]
    path = tmp_path / f"own_{flavor}.mcap"
    write_frames(path, flavor, frames, config=config)
    topics = read_messages(path, ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory())
    written = {topic: len(topics.get(topic, ())) for topic in ("/tf", "/tf_static")}
    assert written == {"tf": {"/tf": 0, "/tf_static": 0}, "calibration": {"/tf": 0, "/tf_static": 1},
                       "estimated": {"/tf": 2, "/tf_static": 0}}[source]
    for _, _, msg in topics.get("/tf", ()):  # the camera's, not odom → base_link
        assert [t.child_frame_id for t in msg.transforms] == ["left_optical"]


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_a_camera_pose_through_frames_of_the_logs_tf_is_republished_edge_by_edge(tmp_path, flavor):
    """base_link → cam_link → left_optical in the log: the output has those two edges, not a
    base_link → left_optical that would give the camera frame a second parent beside the log."""
    from test_sources_logs import OPTICAL_Q, write_ros2_log

    from terrainmap.sources import open_source

    with open_source(write_ros2_log(tmp_path / "run.mcap", n=1)) as source:
        extrinsics = next(source.frames()).extrinsics
    frame, result = make_frame(0)
    path = tmp_path / f"chain_{flavor}.mcap"
    write_frames(path, flavor, [(frame, dataclasses.replace(result, extrinsics=extrinsics))])
    (_, _, msg), = read_messages(path, ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory())[
        "/tf_static"]
    edges = []
    for t in msg.transforms:
        parent, child = (t.parent_frame_id, t.child_frame_id) if flavor == "foxglove" else (t.header.frame_id,
                                                                                          t.child_frame_id)
        xyz = t.translation if flavor == "foxglove" else t.transform.translation
        q = t.rotation if flavor == "foxglove" else t.transform.rotation
        edges.append((parent, child, (xyz.x, xyz.y, xyz.z), pytest.approx((q.x, q.y, q.z, q.w), abs=1e-12)))
    assert edges == [("base_link", "cam_link", (1.0, 0.0, 1.5), (0, 0, 0, 1)),
                     ("cam_link", "left_optical", (0.0, 0.1, 0.0), OPTICAL_Q)]


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_fixed_extrinsics_that_change_go_on_tf_static_again(tmp_path, flavor):
    """Fixed extrinsics go on /tf_static when first seen and again where they change (a folder of
    scenes with their own calibrations), not on every frame."""
    frames = [make_frame(i) for i in range(4)]
    for i in (2, 3):  # a second scene from frame 2 on
        frame, result = frames[i]
        moved = dataclasses.replace(result.extrinsics, translation=np.array([0.2, -0.1, 1.4]))
        frames[i] = (frame, dataclasses.replace(result, extrinsics=moved))
    path = tmp_path / f"scenes_{flavor}.mcap"
    write_frames(path, flavor, frames)
    topics = read_messages(path, ProtobufDecoderFactory() if flavor == "foxglove" else Ros2DecoderFactory())
    assert "/tf" not in topics
    assert [t for t, _, _ in topics["/tf_static"]] == [frames[0][0].stamp_ns, frames[2][0].stamp_ns]
    heights = []
    for _, _, msg in topics["/tf_static"]:
        (t,) = msg.transforms
        heights.append(t.translation.z if flavor == "foxglove" else t.transform.translation.z)
    assert heights == [1.6, 1.4]


def test_the_surface_is_a_mesh_over_the_cells_with_data(tmp_path):
    """foxglove.Grid is drawn flat: /terrainmap/surface carries the surface as a triangle list over
    the cell centres at their elevation, the triangles (two a square of four centres) whose corners
    all hold data, each vertex coloured by slope from green (0°) to red (≥ 30°)."""
    frame, result = make_frame(0)
    valid = result.layers["valid"]  # a pattern of cells without data
    result = dataclasses.replace(result, grid=dataclasses.replace(result.grid, valid=valid))
    path = tmp_path / "surface.mcap"
    write_frames(path, "foxglove", [(frame, result)])
    ((_, _, msg),) = read_messages(path, ProtobufDecoderFactory())["/terrainmap/surface"]
    (entity,) = msg.entities
    (mesh,) = entity.triangles
    assert (entity.id, entity.frame_id, entity.timestamp.seconds) == ("terrain", "base_link", frame.stamp_ns // 10**9)
    m0, m1 = GRID.shape
    ix, iy = np.meshgrid(np.arange(m0), np.arange(m1), indexing="ij")
    xyz = np.array([[p.x, p.y, p.z] for p in mesh.points]).reshape(m0, m1, 3)
    np.testing.assert_allclose(xyz[..., 0], GRID.x_min_m + (ix + 0.5) * GRID.cell_size_m)
    np.testing.assert_allclose(xyz[..., 1], GRID.y_min_m + (iy + 0.5) * GRID.cell_size_m)
    np.testing.assert_allclose(xyz[..., 2], result.layers["elevation"], rtol=1e-6)
    faces = np.array(mesh.indices).reshape(-1, 3)
    first = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:]  # of a square's two triangles, those whose
    second = valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]  # three corners all hold data
    assert len(faces) == first.sum() + second.sum() and valid.ravel()[faces].all()
    rgb = np.array([[c.r, c.g, c.b, c.a] for c in mesh.colors]).reshape(m0, m1, 4)
    np.testing.assert_allclose(rgb[0, 0], [0, 1, 38 / 255, 1])  # slope 0: green
    np.testing.assert_allclose(rgb[5, 0], [1, 0, 38 / 255, 1])  # slope 5 rad: red


def test_threads_sharing_a_sink_take_turns(tmp_path, monkeypatch):
    """A frame is written whole before another thread's starts: the second write waits while the
    first is held inside its frame, and the file holds the first frame's messages, then the second's."""
    import threading

    from terrainmap.sinks import mcap_foxglove

    inside, release, encode = threading.Event(), threading.Event(), mcap_foxglove.encode_points

    def held(*args, **kwargs):
        if threading.current_thread().name == "first":
            inside.set()
            release.wait(10)
        return encode(*args, **kwargs)

    monkeypatch.setattr(mcap_foxglove, "encode_points", held)
    path = tmp_path / "shared.mcap"
    with open_mcap_sink(path, config=Config()) as sink:
        first = threading.Thread(target=sink.write, args=make_frame(0), name="first")
        first.start()
        assert inside.wait(10)
        second = threading.Thread(target=sink.write, args=make_frame(1))
        second.start()
        second.join(0.3)
        waited = second.is_alive()
        release.set()
        first.join()
        second.join()
    assert waited and sink.finished and sink.frames_written == 2
    with open(path, "rb") as f:
        order = [message.log_time for _, _, message in make_reader(f).iter_messages(log_time_order=False)]
    assert order == sorted(order)  # as written: frame 0's messages, then frame 1's


@pytest.mark.parametrize("flavor", ["foxglove", "ros2"])
def test_a_sink_dropped_without_close_is_finished(tmp_path, flavor):
    import gc

    path = tmp_path / "dropped.mcap"
    sink = open_mcap_sink(path, flavor, config=Config())
    sink.write(*make_frame(0))
    del sink
    gc.collect()
    with open(path, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count > 0
    assert read_metadata(path)["frames"] == "1"


def test_a_sink_given_no_path_or_no_frame_says_so(tmp_path):
    with pytest.raises(InputError, match=r"^MCAP output: expected a file path, got None$"):
        open_mcap_sink(None, config=Config())
    frame, result = make_frame(0)
    with open_mcap_sink(tmp_path / "x.mcap", config=Config()) as sink:
        for args in ((None, None), (frame, None), (result, frame), (frame, frame)):
            with pytest.raises(InputError, match=r"expected a StereoFrame and its FrameResult, got \w+ and \w+$"):
                sink.write(*args)
        sink.write(frame, result)
    assert sink.frames_written == 1


def test_a_close_from_within_a_write_fails_the_write_and_keeps_the_frames_before(tmp_path, monkeypatch):
    """As a library's signal handler might: the close is refused (the RLock lets it in rather than
    wait for ever), the write fails, and the close after it ends the file with the whole frames."""
    from terrainmap.sinks import mcap_foxglove

    path, encode = tmp_path / "o.mcap", mcap_foxglove.encode_points
    sink = open_mcap_sink(path, config=Config())
    sink.write(*make_frame(0))

    def closing(*args, **kwargs):
        sink.close()
        return encode(*args, **kwargs)

    monkeypatch.setattr(mcap_foxglove, "encode_points", closing)
    with pytest.raises(TerrainmapError, match="close\\(\\) while a frame is being written"):
        sink.write(*make_frame(1))
    sink.close()
    assert sink.frames_written == 1 and not sink.finished
    grids = read_messages(path, ProtobufDecoderFactory())["/terrainmap/grid"]
    assert [stamp for stamp, _, _ in grids] == [make_frame(0)[0].stamp_ns]
