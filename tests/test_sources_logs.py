"""Log sources: real rosbag2/ROS 1 logs, ROS 2 and Foxglove logs written here, bad logs."""

import contextlib
import os
import shutil
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from log_copies import YAML_BOMB, rewrite_mcap, rewrite_rosbag2, ros1_bag, ros1_mcap, split_rosbag2
from mcap.reader import make_reader
from mcap_protobuf.writer import Writer as ProtobufWriter
from mcap_ros2.writer import Writer as Ros2Writer

from terrainmap.errors import CalibrationError, InputError
from terrainmap.sources import open_source
from terrainmap.sources.readers import bag_files
from terrainmap.sources.topics import stereo_topics

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KITTI = DATA / "kitti2015_000005"
REAL_LOGS = ["kitti2015_000005_ros2_raw", "kitti2015_000005_ros2_compressed", "kitti2015_000005_ros1_raw.bag"]

HEADER = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
IMAGE_DEF = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"
INFO_DEF = """std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
"""
TF_DEF = """geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
geometry_msgs/Transform transform
================================================================================
MSG: geometry_msgs/Transform
geometry_msgs/Vector3 translation
geometry_msgs/Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"""
OPTICAL_Q = [-0.5, 0.5, -0.5, 0.5]  # camera link (x fwd, y left, z up) -> optical (x right, y down, z fwd)
OPTICAL_R = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
T0 = 1_700_000_000_000_000_000


def header(stamp_ns: int, frame: str) -> dict:
    return {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9}, "frame_id": frame}


def ros_image(stamp_ns: int, frame: str, array: np.ndarray, encoding: str) -> dict:
    h, w = array.shape[:2]
    return {"header": header(stamp_ns, frame), "height": h, "width": w, "encoding": encoding,
            "is_bigendian": 0, "step": array.strides[0], "data": array.tobytes()}


def cut_short(image, data: bytes):
    """A decoded raw Image message object ``image`` with its ``data`` replaced (cut short)."""
    from types import SimpleNamespace

    fields = ("header", "height", "width", "encoding", "is_bigendian", "step")
    return SimpleNamespace(**{name: getattr(image, name) for name in fields}, data=data)


def info_msg(*args, **changes):
    """A CameraInfo message object (attributes, as a decoder gives it) of :func:`ros_info` with ``changes``."""
    from types import SimpleNamespace

    fields = {**ros_info(*args), **changes}
    return SimpleNamespace(**{**fields, "header": SimpleNamespace(**fields["header"])})


def ros_info(stamp_ns: int, frame: str, w: int, h: int, tx: float, d=(0.0,) * 5, r=np.eye(3)) -> dict:
    return {"header": header(stamp_ns, frame), "height": h, "width": w, "distortion_model": "plumb_bob",
            "d": list(d), "k": [400.0, 0, w / 2, 0, 400.0, h / 2, 0, 0, 1], "r": np.ravel(r).tolist(),
            "p": [400.0, 0, w / 2, tx, 0, 400.0, h / 2, 0, 0, 0, 1, 0], "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


def tf_message(stamp_ns: int, parent: str, child: str, xyz, q) -> dict:
    x, y, z = xyz
    return {"transforms": [{"header": header(stamp_ns, parent), "child_frame_id": child, "transform": {
        "translation": {"x": x, "y": y, "z": z}, "rotation": dict(zip("xyzw", q, strict=True))}}]}


def rewrite_ros2_log(src: Path, dst: Path, edit) -> Path:
    """``src`` (a ROS 2 MCAP) copied message by message by mcap_ros2's writer, each decoded message
    passed through ``edit(type name, message) -> messages`` (written 1 ns apart in log time)."""
    from mcap_ros2.decoder import DecoderFactory

    with open(src, "rb") as f, open(dst, "wb") as out, Ros2Writer(out) as writer:
        schemas = {}
        for schema, channel, message, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            if schema.name not in schemas:
                schemas[schema.name] = writer.register_msgdef(schema.name, schema.data.decode())
            for k, edited in enumerate(edit(schema.name, decoded)):
                writer.write_message(channel.topic, schemas[schema.name], edited, message.log_time + k)
    return dst


def pair_images(i: int, shape=(6, 8, 3)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(i)
    return rng.integers(0, 255, shape, dtype=np.uint8), rng.integers(0, 255, shape, dtype=np.uint8)


def write_ros2_log(path: Path, n: int = 6, *, camera_info=True, tf=True, topics=("/cam/left/image_rect", "/cam/right/image_rect"),
                   encode=lambda a: (a, "rgb8"), d=(0.0,) * 5, right_offset_ns=2_000_000, chunk_size=1024,
                   right_tx=-400.0 * 0.25, extra_tf=(), frame_ids=("left_optical", "right_optical"), r=np.eye(3),
                   info_frame_ids=None, dynamic_tf=()) -> Path:
    """A ROS 2 MCAP: tf_static and camera_info first, then n pairs at 10 Hz (right 2 ms late) and
    one unpaired left image in the middle. ``extra_tf``: more static (parent, child, xyz, q);
    ``dynamic_tf``: such transforms on /tf, after the static ones; ``frame_ids``: the left and
    right camera messages' header frame ids (the infos' too, unless ``info_frame_ids`` gives
    theirs); ``d``, ``r``: both infos'."""
    with open(path, "wb") as f, Ros2Writer(f, chunk_size=chunk_size) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        if tf:
            tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF + HEADER)
            for parent, child, xyz, q in (("base_link", "cam_link", (1.0, 0.0, 1.5), (0, 0, 0, 1)),
                                          ("cam_link", "left_optical", (0.0, 0.1, 0.0), OPTICAL_Q),
                                          ("odom", "base_link", (5.0, 5.0, 0.0), (0, 0, 0, 1)), *extra_tf):
                writer.write_message("/tf_static", tf_schema, tf_message(T0, parent, child, xyz, q), T0)
            for parent, child, xyz, q in dynamic_tf:
                writer.write_message("/tf", tf_schema, tf_message(T0, parent, child, xyz, q), T0)
        if camera_info:
            info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
            info_frames = info_frame_ids or frame_ids
            for side, tx, frame in (("left", 0.0, info_frames[0]), ("right", right_tx, info_frames[1])):
                writer.write_message(f"/cam/{side}/camera_info", info_schema, ros_info(T0, frame, 8, 6, tx, d, r), T0)
        for i in range(n):
            stamp = T0 + i * 100_000_000
            left, right = pair_images(i)
            writer.write_message(topics[0], image_schema, ros_image(stamp, frame_ids[0], *encode(left)), stamp)
            if i == n // 2:
                writer.write_message(topics[0], image_schema, ros_image(stamp + 50_000_000, frame_ids[0], *encode(left)), stamp + 1)
            writer.write_message(topics[1], image_schema, ros_image(stamp + right_offset_ns, frame_ids[1], *encode(right)),
                                 stamp + right_offset_ns)
    return path


@pytest.fixture
def kitti():
    if not KITTI.is_dir():
        pytest.skip("shared KITTI data not available")
    with open_source(KITTI) as source:
        return next(source.frames())


@pytest.mark.parametrize("log", REAL_LOGS)
def test_real_logs_give_the_folder_images_and_calibration(kitti, log):
    with open_source(DATA / log) as source:
        frames = list(source.frames())
        info = source.describe()
    assert len(frames) == 1
    np.testing.assert_array_equal(frames[0].left, kitti.left)
    np.testing.assert_array_equal(frames[0].right, kitti.right)
    for field in ("width", "height", "fx", "fy", "cx", "cy", "baseline_m", "cx_right", "doffs", "rectified"):
        assert getattr(frames[0].calibration, field) == pytest.approx(getattr(kitti.calibration, field)), field
    assert frames[0].stamp_ns == 1317380000 * 10**9 and frames[0].frame_id == "left_camera_optical"
    assert info["left_topic"].startswith("/stereo/left/image_rect_color") and info["right_topic"].startswith("/stereo/right/")
    assert info["calibration_topics"] == ["/stereo/left/camera_info", "/stereo/right/camera_info"]
    assert frames[0].extrinsics is None and "estimated" in info["extrinsics"]


def test_foxglove_protobuf_log_from_kitti_images(kitti, tmp_path):
    path = tmp_path / "foxglove.mcap"
    calib = kitti.calibration
    fx, cx, cy, b = calib.fx, calib.cx, calib.cy, calib.baseline_m
    h, w = kitti.left.shape[:2]
    with open(path, "wb") as f, ProtobufWriter(f) as writer:
        transforms = FrameTransforms(transforms=[
            # the rotation left unset, as a mount that only shifts is often written: no rotation
            FrameTransform(parent_frame_id="base_link", child_frame_id="camera", translation={"x": 0.5, "z": 1.6}),
            FrameTransform(parent_frame_id="camera", child_frame_id="left_optical", rotation=dict(zip("xyzw", OPTICAL_Q, strict=True))),
        ])
        writer.write_message("/tf_static", transforms, log_time=T0, publish_time=T0)
        for side, tx in (("left", 0.0), ("right", -fx * b)):
            info = CameraCalibration(frame_id=f"{side}_optical", width=w, height=h, distortion_model="plumb_bob",
                                     D=[0.0] * 5, K=[fx, 0, cx, 0, fx, cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                                     P=[fx, 0, cx, tx, 0, fx, cy, 0, 0, 0, 1, 0])
            info.timestamp.FromNanoseconds(T0)
            writer.write_message(f"/stereo/{side}/calibration", info, log_time=T0, publish_time=T0)
        left = RawImage(frame_id="left_optical", width=w, height=h, encoding="rgb8", step=w * 3, data=kitti.left.tobytes())
        ok, png = cv2.imencode(".png", cv2.cvtColor(kitti.right, cv2.COLOR_RGB2BGR))
        right = CompressedImage(frame_id="right_optical", format="png", data=png.tobytes())
        for msg, topic in ((left, "/stereo/left/image"), (right, "/stereo/right/image")):
            msg.timestamp.FromNanoseconds(T0 + 1000)
            writer.write_message(topic, msg, log_time=T0 + 1000, publish_time=T0 + 1000)
    # a raw and a compressed topic do not form a pair by guessing: name them
    with open_source(path, left_topic="/stereo/left/image", right_topic="/stereo/right/image") as source:
        frame = next(source.frames())
        info = source.describe()
    np.testing.assert_array_equal(frame.left, kitti.left)
    np.testing.assert_array_equal(frame.right, kitti.right)
    assert frame.calibration.baseline_m == pytest.approx(b) and frame.calibration.fx == fx
    assert info["format"] == "mcap" and {t["type"] for t in info["topics"]} >= {"foxglove.RawImage", "foxglove.CameraCalibration"}
    ext = frame.extrinsics
    assert ext.source == "tf" and ext.vehicle_frame_id == "base_link" and ext.camera_frame_id == "left_optical"
    np.testing.assert_allclose(ext.translation, [0.5, 0.0, 1.6])
    np.testing.assert_allclose(ext.rotation, OPTICAL_R, atol=1e-12)


def test_ros2_log_pairs_by_stamp_selects_and_composes_tf(tmp_path, caplog):
    path = write_ros2_log(tmp_path / "run.mcap")
    with open_source(path) as source:
        frames = list(source.frames())
        assert "1 of 13 image messages had no partner within 10.0 ms (--pair-tolerance-ms)" in caplog.text
        late = list(source.frames(start_s=0.3, every=2))
    assert [f.index for f in frames] == list(range(6))  # the extra left image found no partner
    assert [f.stamp_ns - T0 for f in frames] == [i * 100_000_000 for i in range(6)]
    np.testing.assert_array_equal(frames[4].right, pair_images(4)[1])
    assert [f.index for f in late] == [3, 5]
    calib = late[0].calibration
    assert calib.baseline_m == pytest.approx(0.25) and (calib.width, calib.height) == (8, 6)
    ext = late[0].extrinsics
    assert ext.vehicle_frame_id == "base_link"  # not odom: the chain stops at the vehicle frame
    np.testing.assert_allclose(ext.translation, [1.0, 0.1, 1.5])
    np.testing.assert_allclose(ext.rotation, OPTICAL_R, atol=1e-12)
    with open_source(path, pair_tolerance_ns=1_000_000) as strict:
        assert list(strict.frames()) == []


def test_cameras_just_over_the_pairing_tolerance_are_told_what_would_pair_them(tmp_path, caplog):
    path = write_ros2_log(tmp_path / "late.mcap", right_offset_ns=15_000_000)  # right 15 ms late, at 10 Hz
    with open_source(path) as source:
        assert list(source.frames()) == []
    assert ("13 of 13 image messages had no partner within 10.0 ms (--pair-tolerance-ms); the cameras' stamps lie "
            "about 15.0 ms apart: --pair-tolerance-ms 19 would pair them") in caplog.text
    with open_source(path, pair_tolerance_ns=19_000_000) as source:
        assert len(list(source.frames())) == 6


def test_duplicate_image_messages_make_no_second_frame(tmp_path, caplog):
    """A log with every image recorded twice (two recorders, a republisher): one frame per stamp."""
    twice = rewrite_ros2_log(write_ros2_log(tmp_path / "once.mcap", n=3), tmp_path / "twice.mcap",
                             lambda name, msg: [msg, msg] if name == "sensor_msgs/msg/Image" else [msg])
    with open_source(twice) as source:
        stamps = [f.stamp_ns for f in source.frames()]
    assert stamps == [T0 + i * 100_000_000 for i in range(3)]
    assert "7 image messages repeated the message before them on their topic, stamp and image (duplicates)" in caplog.text


def test_rosbag2_directory_of_several_files(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    write_ros2_log(bag / "bag_1.mcap", n=2, tf=False, camera_info=False)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  relative_file_paths: [bag_0.mcap, bag_1.mcap]\n")
    with open_source(bag) as source:
        info = source.describe()
        assert info["format"] == "rosbag2" and len(info["files"]) == 2 and info["frames"] == 4
        assert len(list(source.frames())) == 4
    with open_source(bag / "metadata.yaml") as source:  # its metadata.yaml stands for it, as in `ros2 bag`
        assert source.describe()["files"] == info["files"]
    from terrainmap.cli.process_cmd import default_output
    from terrainmap.sources import log_path

    assert default_output(log_path(bag / "metadata.yaml")) == tmp_path / "bag.terrain.mcap"  # beside the folder
    # one of its files alone: beside the folder too, where it does not join the recording
    assert default_output(bag / "bag_1.mcap") == tmp_path / "bag_1.terrain.mcap"
    # a link (into a read-only dataset store, say) gets its output beside the link, as named
    (tmp_path / "links").mkdir()
    (tmp_path / "links" / "run").symlink_to(bag, target_is_directory=True)
    assert default_output(tmp_path / "links" / "run") == tmp_path / "links" / "run.terrain.mcap"
    assert default_output(tmp_path / "links" / "run" / ".") == tmp_path / "links" / "run.terrain.mcap"


def test_a_listed_file_missing_from_a_rosbag2_directory_is_damage(tmp_path, caplog):
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    write_ros2_log(bag / "bag_2.mcap", n=2, tf=False, camera_info=False)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  relative_file_paths: "
                                       "[bag_0.mcap, bag_1.mcap, bag_2.mcap, bag_2.mcap]\n")  # bag_1 lost, bag_2 twice
    with open_source(bag) as source:
        info = source.describe()
        assert info["damage"] == f"{bag / 'metadata.yaml'} lists bag_1.mcap, not in the folder"
        assert len(info["files"]) == 2 and len(list(source.frames())) == 4
    assert "bag_1.mcap, not in the folder: their messages are lost" in caplog.text


@pytest.mark.parametrize("text", ["", "rosbag2_bagfile_information: [\n", "\0"])
def test_an_unreadable_rosbag2_metadata_file_is_damage(tmp_path, caplog, text):
    """Its files are read in name order all the same; ``info --check`` then exits 1 (README)."""
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    (bag / "metadata.yaml").write_text(text)
    with open_source(bag) as source:
        assert source.describe()["damage"] == f"{bag / 'metadata.yaml'} is unreadable; the folder's files are read in " \
                                              "name order"
        assert len(list(source.frames())) == 2
    assert "metadata.yaml: unreadable (" in caplog.text


def test_files_that_give_a_topic_two_types_are_not_read_as_one_log(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "a.mcap", n=2)
    with open(bag / "b.mcap", "wb") as f, ProtobufWriter(f) as writer:
        writer.write_message("/tf_static", FrameTransforms(), log_time=T0, publish_time=T0)
    with pytest.raises(InputError, match=r"topic /tf_static is tf2_msgs/msg/TFMessage in a.mcap but "
                                         r"foxglove.FrameTransforms in b.mcap: these files are not one log"):
        open_source(bag)


def test_rosbag2_directory_without_metadata_is_read_in_file_order(tmp_path):
    """A recording killed before rosbag2 wrote metadata.yaml leaves only its .mcap files, numbered
    from 0 without leading zeros: bag_2 comes before bag_10."""
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    for k in range(1, 11):
        write_ros2_log(bag / f"bag_{k}.mcap", n=2, tf=False, camera_info=False)
    with open_source(bag) as source:
        info = source.describe()
        assert info["format"] == "rosbag2" and [Path(f).name for f in info["files"]] == [f"bag_{k}.mcap" for k in range(11)]
        assert len(list(source.frames())) == 22


@pytest.mark.parametrize(
    "encode, expect",
    [
        (lambda a: (cv2.cvtColor(a, cv2.COLOR_RGB2BGR), "bgr8"), lambda a: a),
        (lambda a: (cv2.cvtColor(a, cv2.COLOR_RGB2BGRA), "bgra8"), lambda a: a),
        (lambda a: (cv2.cvtColor(a, cv2.COLOR_RGB2RGBA), "rgba8"), lambda a: a),
        (lambda a: (a[:, :, 1].copy(), "mono8"), lambda a: a[:, :, 1]),
        (lambda a: (a[:, :, 1].astype(np.uint16) * 4, "16UC1"), None),
        (lambda a: (a[:, :, 1].copy(), "bayer_grbg8"), lambda a: cv2.cvtColor(a[:, :, 1], cv2.COLOR_BayerGRBG2RGB)),
    ],
)
def test_ros_image_encodings(tmp_path, encode, expect):
    path = write_ros2_log(tmp_path / "enc.mcap", n=1, encode=encode)
    frame = next(open_source(path).frames())
    left, right = pair_images(0)
    if expect is None:  # 16 bit: one common scale for the pair
        scale = 255.0 / max(left[:, :, 1].max(), right[:, :, 1].max())
        np.testing.assert_allclose(frame.left, np.round(left[:, :, 1] * scale), atol=1)
    else:
        np.testing.assert_array_equal(frame.left, expect(left))
        np.testing.assert_array_equal(frame.right, expect(right))


def test_unsupported_encoding_names_topic_and_encoding(tmp_path):
    depth = lambda a: (a[:, :, 0].astype(np.float32), "32FC1")  # noqa: E731 (a depth image, not a camera's)
    path = write_ros2_log(tmp_path / "depth.mcap", n=1, encode=depth)
    with pytest.raises(InputError, match=f"^{path}: /cam/left/image_rect: unsupported image encoding '32FC1'"):
        list(open_source(path).frames())


def test_left_and_right_images_of_two_sizes_name_the_log_and_both_topics(tmp_path):
    right_side = iter([False, False, True])  # the pair's left image, an unpaired left one, then the right
    path = write_ros2_log(tmp_path / "sizes.mcap", n=1, encode=lambda a: (a[:-1] if next(right_side) else a, "rgb8"))
    with pytest.raises(InputError, match=f"^{path}: left and right images differ in size: /cam/left/image_rect is "
                                         "8×6, /cam/right/image_rect is 8×5$"):
        list(open_source(path).frames())


def test_topic_overrides_and_partner_guessing(tmp_path):
    path = write_ros2_log(tmp_path / "cams.mcap", n=2, topics=("/cam0/image_raw", "/cam1/image_raw"), camera_info=False)
    calib = tmp_path / "calib.yaml"
    calib.write_text("width: 8\nheight: 6\nfx: 400\nfy: 400\ncx: 4\ncy: 3\nbaseline_m: 0.2\n"
                     "extrinsics:\n  rotation: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]\n  translation_m: [0, 0, 1.5]\n")
    with open_source(path, right_topic="/cam1/image_raw", calibration=calib) as source:
        assert (source.left_topic, source.right_topic) == ("/cam0/image_raw", "/cam1/image_raw")
        frame = next(source.frames())
        assert frame.calibration.baseline_m == 0.2
        assert (frame.extrinsics.source, frame.extrinsics.camera_frame_id) == ("calibration", "left_optical")
    with open_source(path, left_topic="/cam1/image_raw", right_topic="/cam0/image_raw", calibration=calib) as swapped:
        np.testing.assert_array_equal(next(swapped.frames()).left, pair_images(0)[1])
    with pytest.raises(InputError, match="'/nope' is not an image topic.*/cam0/image_raw"):
        open_source(path, left_topic="/nope")


def test_missing_camera_info_is_reported_then_raised(tmp_path):
    path = write_ros2_log(tmp_path / "nocal.mcap", n=1, camera_info=False)
    with open_source(path) as source:
        assert source.describe()["calibration"].startswith("missing")
        with pytest.raises(CalibrationError, match="no camera calibration topic.*--calibration"):
            next(source.frames())


def test_raw_distorted_images_give_an_unrectified_calibration(tmp_path):
    path = write_ros2_log(tmp_path / "raw.mcap", n=1, topics=("/cam/left/image_raw", "/cam/right/image_raw"), d=(0.1, -0.05, 0, 0, 0))
    calib = next(open_source(path).frames()).calibration
    assert not calib.rectified and calib.dist_left[0] == 0.1
    np.testing.assert_allclose(calib.R, np.eye(3))
    np.testing.assert_allclose(calib.T, [-0.25, 0, 0])


@pytest.mark.parametrize("d, r, message", [
    ((np.nan, 0, 0, 0, 0), np.eye(3), r"dist_left must hold finite coefficients below 1e6, got \[nan"),
    ((0.1, 0, 0), np.eye(3), "dist_left must hold 4, 5, 8, 12 or 14 coefficients"),
    ((0.1, 0, 0, 0, 0), np.diag([1.0, 1.0, 2.0]), "R must be a rotation matrix"),
])
def test_raw_images_with_a_camera_info_that_cannot_rectify_them_are_refused_where_it_is_read(tmp_path, d, r, message):
    """The distortion and the stereo rotation are checked with the rest of the calibration, so
    that `info --check` says what `process` would refuse, and a bad info part way is passed over
    with a warning like any unusable one."""
    path = write_ros2_log(tmp_path / "raw.mcap", n=1, topics=("/cam/left/image_raw", "/cam/right/image_raw"), d=d, r=r)
    with open_source(path) as source:
        assert source.calibration is None
        with pytest.raises(CalibrationError, match=f"^{path}: /cam/left/camera_info \\+ /cam/right/camera_info: {message}"):
            next(source.frames())


def test_undistorted_raw_images_with_a_rectifying_rotation_are_still_rectified():
    """D = 0 alone does not make images rectified: a CameraInfo's R (here 2° about y on the left)
    still has to be applied; an all-zero R is an unset one (monocular drivers publish that)."""

    from scipy.spatial.transform import Rotation

    from terrainmap.sources.messages import calibration_from_infos, camera_info

    turn = Rotation.from_euler("y", 2, degrees=True).as_matrix()
    infos = [camera_info(info_msg(T0, side, 8, 6, tx, (0.0,) * 5, r), side)
             for side, tx, r in (("left", 0.0, turn), ("right", -100.0, np.eye(3)))]
    calib = calibration_from_infos(*infos, rectified_images=False, source="test")
    assert not calib.rectified
    np.testing.assert_allclose(calib.R, turn, atol=1e-12)
    unset = [camera_info(info_msg(T0, side, 8, 6, tx, (0.0,) * 5, np.zeros((3, 3))), side)
             for side, tx in (("left", 0.0), ("right", -100.0))]
    assert calibration_from_infos(*unset, rectified_images=False, source="test").rectified
    no_tx = [camera_info(info_msg(T0, side, 8, 6, 0.0), side) for side in ("left", "right")]
    with pytest.raises(CalibrationError, match="test: the right camera's projection P has the same Tx.*--calibration"):
        calibration_from_infos(*no_tx, rectified_images=True, source="test")
    left, right = (camera_info(info_msg(T0, side, 8, 6, tx), side)
                   for side, tx in (("left", 0.0), ("right", -100.0)))
    with pytest.raises(CalibrationError, match="test: the left camera info is 8×6 px but the right one 100×100"):
        calibration_from_infos(left, {**right, "width": 100, "height": 100}, rectified_images=True, source="test")
    narrow = {**right, "P": right["P"] * [[0.5], [0.5], [1]]}
    with pytest.raises(CalibrationError, match=r"different focal lengths \(fx 400 and 200, fy 400 and 200 px\)"):
        calibration_from_infos(left, narrow, rectified_images=True, source="test")
    squashed = {**right, "P": right["P"] * [[1], [0.5], [1]]}  # fy alone differs: the message shows it
    with pytest.raises(CalibrationError, match=r"different focal lengths \(fx 400 and 400, fy 400 and 200 px\)"):
        calibration_from_infos(left, squashed, rectified_images=True, source="test")
    lower = {**right, "P": right["P"] + [[0, 0, 0, 0], [0, 0, 30, 0], [0, 0, 0, 0]]}  # cy 30 px further down
    with pytest.raises(CalibrationError, match=r"principal points at different rows \(cy 3 and 33 px\)"):
        calibration_from_infos(left, lower, rectified_images=True, source="test")
    broken = {**right, "P": right["P"] * np.nan}
    with pytest.raises(CalibrationError, match=r"test: the right camera info's projection P is not finite"):
        calibration_from_infos(left, broken, rectified_images=True, source="test")
    broken = {**right, "R": right["R"] * np.nan}
    with pytest.raises(CalibrationError, match=r"test: the right camera info's rectifying rotation R is not finite"):
        calibration_from_infos(left, broken, rectified_images=True, source="test")
    assert calibration_from_infos(left, {**right, "width": 0, "height": 0}, rectified_images=True, source="test")


def test_distortion_models_opencv_cannot_apply_are_refused_and_an_empty_d_is_none():

    from terrainmap.sources.messages import calibration_from_infos, camera_info

    def infos(model, d):
        return [camera_info(info_msg(T0, side, 8, 6, tx, d, distortion_model=model), side)
                for side, tx in (("left", 0.0), ("right", -100.0))]

    with pytest.raises(CalibrationError, match="test: the left camera's distortion model 'equidistant' is not supported"):
        calibration_from_infos(*infos("equidistant", (0.1, 0.01, 0, 0)), rectified_images=False, source="test")
    assert calibration_from_infos(*infos("equidistant", (0.1, 0.01, 0, 0)), rectified_images=True, source="test").rectified
    calib = calibration_from_infos(*infos("rational_polynomial", (0.1, 0.01, 0, 0, 0, 0.02, 0, 0)),
                                   rectified_images=False, source="test")
    assert not calib.rectified and len(calib.dist_left) == 8
    assert calibration_from_infos(*infos("", ()), rectified_images=False, source="test").rectified  # empty D: none


@pytest.mark.parametrize("log", ["negative/rosbag2_cdr_test", "negative/rosbag2_talker", "negative/grid_map_ros1.bag"])
def test_logs_without_stereo_say_so(log):
    if not (DATA / log).exists():
        pytest.skip("shared negative logs not available")
    with pytest.raises(InputError, match="no stereo image topics found") as info:
        open_source(DATA / log)
    assert "\n" not in str(info.value)


def test_video_topics_are_named_as_not_read():
    types = {"/cam/left/video": "foxglove.CompressedVideo", "/cam/right/video": "foxglove.CompressedVideo",
             "/tf": "foxglove.FrameTransforms"}
    with pytest.raises(InputError, match=r"log.mcap: no stereo image topics found .*; video topics "
                       r"\(/cam/left/video, /cam/right/video\) are not read: decode them to image messages first"):
        stereo_topics(types, None, None, "log.mcap")
    with pytest.raises(InputError, match="left topic '/cam/left/video' is not an image topic .* video topics"):
        stereo_topics(types, "/cam/left/video", "/cam/right/video", "log.mcap")


def test_truncated_log_yields_what_it_can_then_raises(tmp_path):
    path = write_ros2_log(tmp_path / "full.mcap", n=20)
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with open_source(cut) as source:
        frames = []
        with pytest.raises(InputError, match="cut.mcap: log is truncated or corrupt"):
            for frame in source.frames():
                frames.append(frame)
    assert 3 <= len(frames) < 20
    np.testing.assert_array_equal(frames[2].left, pair_images(2)[0])


def test_describe_gives_the_span_of_the_log_times_in_every_format(tmp_path):
    """tf and camera infos at T0, 6 pairs 100 ms apart, each right image 2 ms after its left: 0.502 s
    as an indexed MCAP, scanned without its summary, as rosbag2 in sqlite3 and as a ROS 1 bag."""
    log = write_ros2_log(tmp_path / "run.mcap", n=6)
    unindexed = tmp_path / "unindexed.mcap"
    unindexed.write_bytes(log.read_bytes()[:-40])  # footer and magic cut off: read from start to end
    db3 = rewrite_rosbag2(log, tmp_path / "bag", storage="sqlite3")
    for path in (log, unindexed, db3, ros1_bag(log, tmp_path / "run.bag")):
        with open_source(path) as source:
            assert source.describe()["duration_s"] == pytest.approx(0.502, abs=1e-9), path


def test_truncated_log_names_its_damage_in_describe(tmp_path):
    path = write_ros2_log(tmp_path / "full.mcap", n=20)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with open_source(path) as source:
        assert source.describe()["damage"] is None
    with open_source(cut) as source:
        assert source.describe()["damage"].startswith(f"{cut}: truncated or corrupt after ")


def _one_message_a_camera(path: Path, schema: tuple[str, str, bytes], encoding: str, data: bytes) -> Path:
    """An MCAP of one message on each of two image topics: ``schema`` (name, encoding, text),
    message ``encoding`` and ``data``."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        schema_id = writer.register_schema(*schema)
        for topic in ("/cam/left/image_rect", "/cam/right/image_rect"):
            writer.add_message(writer.register_channel(topic, encoding, schema_id), log_time=1, data=data, publish_time=1)
        writer.finish()
    return path


def test_unparsable_schema_names_the_topic_and_prints_nothing(tmp_path, capfd):
    """mcap_ros2's definition parser prints the bad line to stderr before raising: kept quiet,
    and the error says which topic's schema it is (not that the log is truncated)."""
    path = _one_message_a_camera(tmp_path / "schema.mcap", ("sensor_msgs/msg/Image", "ros2msg", b"int32 x y z\n"),
                                 "cdr", b"\0" * 20)
    with pytest.raises(InputError, match="topic /cam/left/image_rect: unreadable schema sensor_msgs/msg/Image"):
        with open_source(path) as source:
            list(source.frames())
    assert capfd.readouterr().err == ""


def test_a_log_of_an_encoding_without_a_decoder_names_both_encodings(tmp_path):
    path = _one_message_a_camera(tmp_path / "json.mcap", ("foxglove.RawImage", "jsonschema", b"{}"), "json", b"{}")
    with pytest.raises(InputError, match="no decoder for topic /cam/left/image_rect \\(message encoding 'json', "
                                         "schema encoding 'jsonschema'; terrainmap reads "):
        with open_source(path) as source:
            list(source.frames())


@pytest.mark.parametrize("damage", ["half", "overwrite", "garbage"])
def test_corrupt_real_log_gives_one_line_error(tmp_path, damage):
    real = DATA / "kitti2015_000005_ros2_raw" / "kitti2015_000005_ros2_raw.mcap"
    if not real.is_file():
        pytest.skip("shared ROS 2 log not available")
    bad = tmp_path / "bad.mcap"
    data = bytearray(real.read_bytes())
    if damage == "half":
        data = data[: len(data) // 2]
    elif damage == "overwrite":
        data[len(data) // 3: len(data) // 3 + 4096] = b"\xff" * 4096
        data[-200:-8] = b"\x00" * 192
    else:
        data = b"\x89MCAP0\r\n" + b"\x07" * 100
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError) as info:
        with open_source(bad) as source:
            list(source.frames())
    assert "bad.mcap" in str(info.value) and "\n" not in str(info.value)
    assert "truncated or corrupt" in str(info.value) or "not a readable MCAP file" in str(info.value)


@pytest.mark.parametrize(("data", "why"), [(b"", "it is empty"), (b"garbage\n", "it does not begin with MCAP's magic bytes"),
                                         (b"\x89MCAP", "it ends within MCAP's 8 magic bytes")])
def test_a_file_named_mcap_that_is_no_mcap_says_so(tmp_path, data, why):
    bad = tmp_path / "notes.mcap"
    bad.write_bytes(data)
    with pytest.raises(InputError, match=rf"^{bad}: not an MCAP file \({why}\)$"):
        open_source(bad)


def test_ros1_bag_truncated(tmp_path):
    real = DATA / "kitti2015_000005_ros1_raw.bag"
    if not real.is_file():
        pytest.skip("shared ROS 1 bag not available")
    bad = tmp_path / "bad.bag"
    shutil.copy(real, bad)
    bad.write_bytes(real.read_bytes()[:4000])
    with pytest.raises(InputError, match="bad.bag"):
        list(open_source(bad).frames())


def _same_frames(a, b):
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        assert (x.index, x.stamp_ns, x.frame_id) == (y.index, y.stamp_ns, y.frame_id)
        np.testing.assert_array_equal(x.left, y.left)
        np.testing.assert_array_equal(x.right, y.right)
        assert x.calibration.baseline_m == y.calibration.baseline_m and x.calibration.fx == y.calibration.fx
        for ext in ("translation", "rotation"):
            np.testing.assert_array_equal(*(getattr(f.extrinsics, ext, None) for f in (x, y)))
        np.testing.assert_array_equal(x.vehicle_pose, y.vehicle_pose)


@pytest.mark.parametrize("storage, compression", [("sqlite3", "none"), ("sqlite3", "file"), ("mcap", "file"),
                                                  ("mcap", "message"), ("sqlite3", "message")])
def test_rosbag2_in_sqlite3_storage_or_compressed_reads_like_the_mcap_log(tmp_path, storage, compression):
    log = write_ros2_log(tmp_path / "run.mcap", encode=lambda a: (cv2.cvtColor(a, cv2.COLOR_RGB2BGR), "bgr8"))
    bag = rewrite_rosbag2(log, tmp_path / "bag", storage=storage, compression=compression)
    with open_source(log) as source:
        expected = list(source.frames())
    with open_source(bag) as source:
        info = source.describe()
        _same_frames(list(source.frames()), expected)
        assert [f.index for f in source.frames(start_s=0.3, every=2)] == [3, 5]
    with open_source(bag, left_topic="/cam/left/image_rect", right_topic="/cam/right/image_rect") as named:
        assert len(list(named.frames())) == 6  # topics may be named, as for any log
    with open_source(bag, pair_tolerance_ns=1_000_000) as strict:
        assert list(strict.frames()) == []  # and the pairing tolerance (the right images are 2 ms late)
    assert info["format"] == "rosbag2" and info["frames"] == 6 and info["odometry_topics"] == []
    assert [Path(f).parent for f in info["files"]] == [bag]


def _open_bag_files() -> list[str]:
    """The files named ``bag_*.db3`` or ``bag_*.mcap`` this process has open (a split bag's, or
    their decompressed copies)."""
    fds = Path("/proc/self/fd")
    if not fds.is_dir():
        pytest.skip("no /proc/self/fd to count open files in")
    names = []
    for fd in fds.iterdir():
        with contextlib.suppress(OSError):  # the listing's own descriptor is gone by now
            name = Path(os.readlink(fd)).name.removesuffix(" (deleted)")  # a temporary copy, removed
            if name.startswith("bag_") and name.endswith((".db3", ".mcap")):
                names.append(name)
    return names


@pytest.mark.parametrize("storage, compression", [("sqlite3", "none"), ("sqlite3", "file"), ("mcap", "message")])
def test_a_split_rosbag2_is_read_with_one_file_open_at_a_time(tmp_path, storage, compression):
    """rosbags opens every file of a split bag at once and keeps them open (a bag of more files
    than the open-file limit could not be read); terrainmap reads them one at a time, and gives
    the frames of the same bag unsplit."""
    log = write_ros2_log(tmp_path / "run.mcap", n=8)
    bag = split_rosbag2(log, tmp_path / "bag", 6, storage=storage, compression=compression)
    with open_source(rewrite_rosbag2(log, tmp_path / "whole", storage=storage, compression=compression)) as whole:
        expected = list(whole.frames())
    frames, most_open = [], 0
    with open_source(bag) as source:
        assert len(source.describe()["files"]) == 6
        for frame in source.frames():
            most_open = max(most_open, len(_open_bag_files()))
            frames.append(frame)
    _same_frames(frames, expected)
    assert most_open == 1 and _open_bag_files() == []


@pytest.mark.parametrize("compression", ["none", "file"])
def test_a_rosbag2_closed_part_way_lets_go_of_its_files_and_reads_from_any_working_folder(tmp_path, monkeypatch,
                                                                                       compression):
    """A library user may stop reading frames, close the source and keep the iterator: no file
    stays open (nor a deleted temporary copy's disk space). A bag opened by a relative path is
    read whatever the working folder is later."""
    split_rosbag2(write_ros2_log(tmp_path / "run.mcap", n=8), tmp_path / "bag", 3, compression=compression)
    monkeypatch.chdir(tmp_path)
    with open_source(Path("bag")) as source:
        frames = source.frames()
        next(frames)
        monkeypatch.chdir("/")
        assert len(list(frames)) == 7
        frames = source.frames()
        next(frames)
    assert _open_bag_files() == []


def test_each_file_of_a_sqlite3_rosbag2_is_indexed_once(tmp_path, monkeypatch):
    """rosbags indexes a whole file each time it opens it (a second per million messages), and
    opening a log reads a few messages of several topics in turn: the files are indexed once, as
    the bag opens, and read without it."""
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    log = write_ros2_log(tmp_path / "run.mcap", n=8)
    opened = Counter()
    index = Sqlite3Reader.open
    monkeypatch.setattr(Sqlite3Reader, "open", lambda self: (opened.update([self.path.name]), index(self))[1])
    for bag in (rewrite_rosbag2(log, tmp_path / "whole"), split_rosbag2(log, tmp_path / "bag", 3)):
        opened.clear()
        with open_source(bag) as source:
            assert len(list(source.frames())) == 8
        assert len(opened) == len(bag_files(bag)) and set(opened.values()) == {1}, opened


def test_a_file_of_a_split_rosbag2_damaged_or_changed_is_named(tmp_path):
    """rosbags checks every file as the bag opens; one read later must still be that file."""
    log = write_ros2_log(tmp_path / "run.mcap", n=8)
    bag = split_rosbag2(log, tmp_path / "bag", 6)
    def replace(f):  # another file's bytes (of the same size) and time
        shutil.copy(bag / "bag_0.db3", f)
        os.utime(f, ns=(10**18, 10**18))

    for k, change in enumerate((lambda f: f.unlink(), replace)):
        copy = shutil.copytree(bag, tmp_path / f"copy{k}")
        with open_source(copy) as source:
            change(copy / "bag_3.db3")  # removed, or another file's bytes written into it
            with pytest.raises(InputError, match=f"{copy / 'bag_3.db3'}: changed or removed since the bag was opened"):
                list(source.frames())
    mcap = split_rosbag2(log, tmp_path / "mcap", 3, storage="mcap", compression="message")
    (mcap / "mcap_1.mcap").write_bytes((mcap / "mcap_1.mcap").read_bytes()[:-20])
    with pytest.raises(InputError, match=r"mcap: not a readable rosbag2 \(ReaderError: mcap_1.mcap: "):
        open_source(mcap)


def test_errors_in_a_file_compressed_rosbag2_name_the_bags_file_not_its_decompressed_copy(tmp_path, monkeypatch):
    """rosbags decompresses each ``.db3.zstd`` into a temporary folder as ``.db3``: a damaged
    file is named as the bag holds it, and a copy removed while the bag is open as the copy of it."""
    import re
    import tempfile

    import zstandard

    bag = split_rosbag2(write_ros2_log(tmp_path / "run.mcap", n=8), tmp_path / "bag", 3, compression="file")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "temp"))  # where rosbags decompresses
    (tmp_path / "temp").mkdir()
    with open_source(bag) as source:
        (copy,) = (tmp_path / "temp").glob("*/bag_1.db3")
        copy.unlink()
        with pytest.raises(InputError, match=re.escape(f"{copy} (the decompressed copy of {bag.resolve() / 'bag_1.db3.zstd'}): "
                                                       "changed or removed since the bag was opened")):
            list(source.frames())
    (bag / "bag_1.db3.zstd").write_bytes(zstandard.ZstdCompressor().compress(b"not a database" * 100))
    with pytest.raises(InputError, match=r"bag: not a readable rosbag2 \(\w+: bag_1\.db3\.zstd: "):
        open_source(bag)


def test_rosbag2_sqlite3_of_the_real_log_gives_its_frames(tmp_path):
    real = DATA / "kitti2015_000005_ros2_raw"
    if not real.is_dir():
        pytest.skip("shared data not available")
    bag = rewrite_rosbag2(real, tmp_path / "bag", storage="sqlite3", compression="file")
    with open_source(real) as a, open_source(bag) as b:
        _same_frames(list(b.frames()), list(a.frames()))


def test_damaged_or_incomplete_sqlite3_bags_are_named(tmp_path):
    bag = rewrite_rosbag2(write_ros2_log(tmp_path / "run.mcap", n=1), tmp_path / "bag")
    db3 = next(bag.glob("*.db3"))
    metadata = (bag / "metadata.yaml").read_bytes()
    (bag / "metadata.yaml").unlink()
    with pytest.raises(InputError, match="needs its metadata.yaml"):
        open_source(bag)
    (bag / "metadata.yaml").write_bytes(metadata)
    db3.write_bytes(db3.read_bytes()[:200])
    with pytest.raises(InputError, match=f"{bag}: not a readable rosbag2"):
        open_source(bag)


def _footprint_log(path: Path, mount_xyz, footprint_q, frames: int = 1) -> Path:
    """odom → base_footprint (at x = 10 + i m, turned by ``footprint_q``) → base_link (``mount_xyz``,
    fixed) → the camera, 0.5 m ahead of base_link and 1 m up: a log of ``frames`` stereo pairs."""
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF + HEADER)
        for parent, child, xyz, q in (("base_footprint", "base_link", mount_xyz, (0, 0, 0, 1)),
                                      ("base_link", "left_optical", (0.5, 0, 1.0), OPTICAL_Q)):
            writer.write_message("/tf_static", tf_schema, tf_message(T0, parent, child, xyz, q), T0)
        for side, tx in (("left", 0.0), ("right", -100.0)):
            writer.write_message(f"/cam/{side}/camera_info", info_schema, ros_info(T0, f"{side}_optical", 8, 6, tx), T0)
        for i in range(frames):
            stamp = T0 + i * 100_000_000
            writer.write_message("/tf", tf_schema, tf_message(stamp, "odom", "base_footprint", (10.0 + i, 0, 0),
                                                              footprint_q), stamp)
            for side, image in zip(("left", "right"), pair_images(i), strict=True):
                writer.write_message(f"/cam/{side}/image_rect", image_schema,
                                     ros_image(stamp, f"{side}_optical", image, "rgb8"), stamp + 1)
    return path


def test_odometry_of_base_footprint_gives_the_pose_of_base_link_the_camera_is_mounted_on(tmp_path):
    """The common tree odom → base_footprint (moving), base_footprint → base_link 0.3 m up
    (fixed), camera under base_link: a frame's vehicle pose is base_link's, as its extrinsics are."""
    with open_source(_footprint_log(tmp_path / "footprint.mcap", (0, 0, 0.3), (0, 0, 0, 1), frames=3)) as source:
        frame = next(iter(source.frames()))
    assert frame.extrinsics.vehicle_frame_id == "base_link"
    np.testing.assert_allclose(frame.vehicle_pose[:3, 3], [10.0, 0.0, 0.3])


def _odometry_log(path: Path, pose_stamps, pairs) -> Path:
    """A ROS 2 log with the camera on base_link, odometry odom → base_link moving at 1 m/s along x
    stamped ``pose_stamps`` (ns, logged then) and a stereo pair for each ``(header stamp, log
    time)`` of ``pairs`` (ns), in log-time order."""
    events = [(t, 0, t) for t in pose_stamps] + [(log_time, 1, (stamp, i)) for i, (stamp, log_time) in enumerate(pairs)]
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF + HEADER)
        writer.write_message("/tf_static", tf_schema, tf_message(T0, "base_link", "left_optical", (0.5, 0, 1.0), OPTICAL_Q), T0)
        for side, tx in (("left", 0.0), ("right", -100.0)):
            writer.write_message(f"/cam/{side}/camera_info", info_schema, ros_info(T0, f"{side}_optical", 8, 6, tx), T0)
        for log_time, kind, what in sorted(events):
            if kind == 0:
                pose = tf_message(what, "odom", "base_link", ((what - T0) / 1e9, 0, 0), (0, 0, 0, 1))
                writer.write_message("/tf", tf_schema, pose, log_time)
                continue
            stamp, i = what
            for side, image in zip(("left", "right"), pair_images(i), strict=True):
                writer.write_message(f"/cam/{side}/image_rect", image_schema, ros_image(stamp, f"{side}_optical", image, "rgb8"),
                                     log_time)
    return path


def test_the_last_pair_before_the_camera_stops_gets_its_pose_from_the_odometry_after_it(tmp_path):
    """Odometry at 100 Hz for 5 s, images at 10 Hz for the first second: the last pair waited for a
    pose after its stamp and was released only by an image that never came, its pose gone by then
    (and the tracks reset); now each odometry message releases the pairs waiting for it."""
    images = [T0 + 5_000_000 + i * 100_000_000 for i in range(10)]  # 5 ms after a pose each
    path = _odometry_log(tmp_path / "stops.mcap", [T0 + k * 10_000_000 for k in range(500)], [(t, t + 1) for t in images])
    with open_source(path) as source:
        frames = list(source.frames())
    assert len(frames) == 10
    assert all(f.vehicle_pose is not None for f in frames)
    np.testing.assert_allclose([f.vehicle_pose[0, 3] for f in frames], [0.005 + 0.1 * i for i in range(10)])


def test_images_and_odometry_stamped_by_different_clocks_are_warned_about_once(tmp_path, caplog):
    """Images stamped in seconds since boot, the tf in Unix time: no pair can have a pose, which
    used to go without a word."""
    logged = [T0 + i * 100_000_000 for i in range(3)]
    pairs = [(100 * 10**9 + i * 100_000_000, t + 1) for i, t in enumerate(logged)]  # stamped 100 s after boot
    path = _odometry_log(tmp_path / "clocks.mcap", logged, pairs)
    with open_source(path) as source:
        frames = list(source.frames())
    assert len(frames) == 3 and all(f.vehicle_pose is None for f in frames)
    (warning,) = [m for m in caplog.messages if "different clocks" in m]
    assert warning.startswith(f"{path}: the stereo pair stamped 100.000 s has no vehicle pose: the odometry (/tf) is "
                              f"stamped around {logged[1] / 1e9:.3f} s")  # the newest pose: the pair waited for two


@pytest.mark.parametrize("good_after", [True, False])
def test_a_first_camera_info_without_projection_gives_way_to_the_next_usable_one(tmp_path, good_after):
    """A driver that publishes an all-zero camera info before the real one: the log's calibration
    is the first usable one of each side; where none of the first few is, the error says so."""
    path = tmp_path / "infos.mcap"
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        for k in range(3):
            for side, tx in (("left", 0.0), ("right", -100.0)):
                info = ros_info(T0 + k, f"{side}_optical", 8, 6, tx)
                if k == 0 or not good_after:
                    info["p"] = [0.0] * 12
                writer.write_message(f"/cam/{side}/camera_info", info_schema, info, T0 + k)
        for side, image in zip(("left", "right"), pair_images(0), strict=True):
            writer.write_message(f"/cam/{side}/image_rect", image_schema, ros_image(T0 + 10, f"{side}_optical", image, "rgb8"),
                                 T0 + 10)
    if good_after:
        with open_source(path) as source:
            assert source.calibration.baseline_m == pytest.approx(0.25)
    else:
        with pytest.raises(CalibrationError, match=rf"^{path}: /cam/left/camera_info: camera calibration without a "
                                                   r"projection matrix P \(nor is any of the 2 messages after it\)$"):
            open_source(path).frames().__next__()


def test_an_indexed_mcap_without_statistics_has_unknown_counts_and_reads_whole(tmp_path):
    """The statistics record is optional in MCAP: the message counts are then unknown, not 0, in
    the log alone and in a rosbag2 folder with a second file that has them; the span comes from
    the chunk indexes."""
    log = write_ros2_log(tmp_path / "counted.mcap")
    (tmp_path / "bag").mkdir()
    plain = rewrite_mcap(log, tmp_path / "bag" / "a_0.mcap", use_statistics=False)
    shutil.copy(log, tmp_path / "bag" / "a_1.mcap")
    with open_source(log) as counted, open_source(plain) as source:
        expected, info = counted.describe(), source.describe()
        _same_frames(list(source.frames()), list(counted.frames()))
    assert expected["frames"] == 6 and info["frames"] is None and "no message counts" in info["frames_note"]
    assert {t["count"] for t in info["topics"]} == {None} and info["duration_s"] == expected["duration_s"]
    with open_source(tmp_path / "bag") as bag:
        assert bag.describe()["frames"] is None


def test_camera_messages_without_a_frame_id_are_in_camera_optical(tmp_path):
    """A driver that leaves header.frame_id empty: the camera frame is ``camera_optical``, not ''
    (the outputs' /tf would place an unnamed frame, which tf2 ignores)."""
    log = write_ros2_log(tmp_path / "unnamed.mcap", tf=False, frame_ids=("", "/"))
    with open_source(log) as source:
        frames = list(source.frames())
        assert source.frame_id == source.describe()["frame_id"] == "camera_optical"
    assert {f.frame_id for f in frames} == {"camera_optical"}  # what an estimated camera pose is placed in


def test_copies_of_a_simulated_drive_keep_its_vehicle_poses(tmp_path):
    """A drive (dynamic /tf odom → base_link) as rosbag2 in sqlite3 storage, ROS 1 bag and ROS 1 MCAP."""
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "drive.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=64, height=48, focal_px=50.0))
    db3 = rewrite_rosbag2(log, tmp_path / "bag", storage="sqlite3")
    bag = ros1_bag(db3, tmp_path / "drive.bag")
    with open_source(log) as source:
        expected = list(source.frames())
    assert all(f.vehicle_pose is not None for f in expected) and expected[2].vehicle_pose[0, 3] > expected[0].vehicle_pose[0, 3]
    for copy in (db3, bag, ros1_mcap(bag, tmp_path / "ros1.mcap")):
        with open_source(copy) as source:
            _same_frames(list(source.frames()), expected)
            assert source.describe()["odometry_topics"] == ["/tf"]


def test_ros1_mcap_reads_like_the_ros1_bag_it_was_converted_from(tmp_path):
    log = write_ros2_log(tmp_path / "run.mcap", encode=lambda a: (cv2.cvtColor(a, cv2.COLOR_RGB2BGR), "bgr8"))
    bag = ros1_bag(log, tmp_path / "run.bag")
    mcap = ros1_mcap(bag, tmp_path / "ros1.mcap")
    with open_source(log) as a, open_source(bag) as b, open_source(mcap) as c:
        expected = list(a.frames())
        _same_frames(list(b.frames()), expected)
        _same_frames(list(c.frames()), expected)
        assert {t["type"] for t in c.describe()["topics"]} == {"sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo",
                                                              "tf2_msgs/msg/TFMessage"}


def test_a_ros1_bag_cut_short_gives_its_frames_before_the_cut(tmp_path):
    """A recording cut off (no index): its frames up to the cut, then the damage named."""
    log = write_ros2_log(tmp_path / "run.mcap", n=6)
    bag = _rewritten(ros1_bag(log, tmp_path / "run.bag"), tmp_path / "chunks.bag", chunk_bytes=256)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size * 2 // 3])
    with open_source(log) as source:
        expected = list(source.frames())
    with open_source(cut) as source:
        assert source.describe()["damage"].startswith(f"{cut}: truncated or corrupt after ")
        frames = []
        with pytest.raises(InputError, match=rf"^{cut}: bag is truncated or corrupt after \d+ messages of "):
            for frame in source.frames():
                frames.append(frame)
    _same_frames(frames, expected[: len(frames)])
    assert 2 <= len(frames) < len(expected)


def _rewritten(bag: Path, dst: Path, *, garbage: tuple[str, int] | None = None, chunk_bytes: int = 1 << 20) -> Path:
    """``bag`` (ROS 1) rewritten in chunks of about ``chunk_bytes``, with the ``which``-th message
    of ``topic`` replaced by garbage bytes where ``garbage`` is ``(topic, which)``."""
    from rosbags.rosbag1 import Reader, Writer

    with Reader(bag) as reader:
        messages = list(reader.messages())
    writer, connections, seen = Writer(dst), {}, 0
    writer.chunk_threshold = chunk_bytes
    writer.open()
    for connection, stamp, raw in messages:
        if connection.topic not in connections:
            connections[connection.topic] = writer.add_connection(
                connection.topic, connection.msgtype, msgdef=connection.msgdef.data, md5sum=connection.digest)
        if garbage is not None and connection.topic == garbage[0]:
            seen += 1
            raw = bytes(range(64)) if seen == garbage[1] + 1 else raw
        writer.write(connections[connection.topic], stamp, raw)
    writer.close()
    return dst


def test_a_message_of_a_ros1_bag_that_cannot_be_decoded_is_skipped(tmp_path, caplog):
    log = write_ros2_log(tmp_path / "run.mcap", n=3)
    bag = _rewritten(ros1_bag(log, tmp_path / "run.bag"), tmp_path / "bad.bag", garbage=("/cam/left/image_rect", 0))
    with open_source(bag) as source:
        assert len(list(source.frames())) == 2  # of 3: the pair of the bad image is lost
        (skipped,) = source.skipped()
    assert skipped.startswith(f"{bag}: /cam/left/image_rect message at log time ")
    assert "not a readable sensor_msgs/msg/Image" in skipped and "damaged, skipped" in caplog.text


def test_ros1_mcap_of_the_real_bag(tmp_path):
    real = DATA / "kitti2015_000005_ros1_raw.bag"
    if not real.is_file():
        pytest.skip("shared data not available")
    with open_source(real) as a, open_source(ros1_mcap(real, tmp_path / "ros1.mcap")) as b:
        _same_frames(list(b.frames()), list(a.frames()))


def test_a_baseline_missing_from_the_camera_infos_comes_from_tf(tmp_path):
    """Cameras calibrated one by one (right Tx = 0) with both optical frames in tf: the baseline is
    the right frame's offset along the left's x axis."""
    right = ("cam_link", "right_optical", (0.0, -0.15, 0.0), OPTICAL_Q)  # the left one is at y = 0.1: 0.25 m apart
    path = write_ros2_log(tmp_path / "tf.mcap", n=2, right_tx=0.0, extra_tf=[right])
    with open_source(path) as source:
        frame = next(source.frames())
    assert frame.calibration.baseline_m == pytest.approx(0.25) and frame.calibration.rectified
    assert frame.calibration.source.endswith("stereo pose from tf (left_optical → right_optical)")
    # infos that name no frame (a driver that leaves them empty): the images' frames are looked up
    path = write_ros2_log(tmp_path / "unnamed.mcap", n=2, right_tx=0.0, extra_tf=[right], info_frame_ids=("", ""))
    with open_source(path) as source:
        assert next(source.frames()).calibration.baseline_m == pytest.approx(0.25)
    path = write_ros2_log(tmp_path / "none.mcap", n=2, right_tx=0.0)
    with open_source(path) as source, pytest.raises(
            CalibrationError, match=r"tf does not relate the cameras' frames \(left_optical → right_optical\)"):
        next(source.frames())
    # the stereo pose on the dynamic /tf (ROS 1's static_transform_publisher sends it there), also
    # where /tf_static already places the left camera; and in ROS 1 tf's own message type
    path = write_ros2_log(tmp_path / "dynamic.mcap", n=2, right_tx=0.0, dynamic_tf=[right])
    with open_source(path) as source:
        frame = next(source.frames())
    assert frame.calibration.baseline_m == pytest.approx(0.25) and frame.extrinsics.source == "tf"
    above = ("cam_link", "right_optical", (0.0, -0.15, 0.1), OPTICAL_Q)
    path = write_ros2_log(tmp_path / "above.mcap", n=2, right_tx=0.0, extra_tf=[above])
    with open_source(path) as source, pytest.raises(
            CalibrationError, match=r"tf places the right camera at \(0.250, -0.100, 0.000\) m turned by 0.00°.*"
                                    "not a rectified pair .*use the raw image topics"):
        next(source.frames())
    # The same cameras on raw topics: no rectified pair, so rectified here with tf's pose.
    raw = write_ros2_log(tmp_path / "raw.mcap", n=2, right_tx=0.0, extra_tf=[above],
                         topics=("/cam/left/image_raw", "/cam/right/image_raw"))
    with open_source(raw) as source:
        calib = next(source.frames()).calibration
    assert not calib.rectified
    np.testing.assert_allclose(calib.T, [-0.25, 0.1, 0.0], atol=1e-12)  # p_right = R·p_left + T
    np.testing.assert_allclose(calib.R, np.eye(3), atol=1e-12)


def test_rectified_images_whose_rows_do_not_agree_take_no_baseline_from_tf():
    from terrainmap.sources.messages import calibration_from_infos, camera_info

    left, right = (camera_info(info_msg(T0, side, 8, 6, 0.0), side) for side in ("left", "right"))
    beside = np.eye(4)
    beside[0, 3] = 0.3
    assert calibration_from_infos(left, right, rectified_images=True, source="t", right_in_left=beside).baseline_m == 0.3
    low = {**right, "P": right["P"] + [[0, 0, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 0]]}  # cy 2 px lower
    with pytest.raises(CalibrationError, match=r"principal points at different rows \(cy 3 and 5 px\)"):
        calibration_from_infos(left, low, rectified_images=True, source="t", right_in_left=beside)
    from scipy.spatial.transform import Rotation

    turned = beside.copy()
    turned[:3, :3] = Rotation.from_euler("y", 0.2, degrees=True).as_matrix()  # 1.4 px at fx = 400
    with pytest.raises(CalibrationError, match="turned by 0.20°"):
        calibration_from_infos(left, right, rectified_images=True, source="t", right_in_left=turned)
    assert not calibration_from_infos(left, right, rectified_images=False, source="t", right_in_left=turned).rectified


def test_raw_cameras_calibrated_one_by_one_take_their_pose_from_tf():
    from scipy.spatial.transform import Rotation

    from terrainmap.sources.messages import calibration_from_infos, camera_info

    d = (-0.1, 0.01, 0.0, 0.0, 0.0)
    left, right = (camera_info(info_msg(T0, side, 8, 6, 0.0, d), side) for side in ("left", "right"))
    right["K"] = right["K"] * [[1.02], [1.02], [1]]  # another lens: focal lengths 2 % apart
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("y", 1.5, degrees=True).as_matrix()
    pose[:3, 3] = [0.3, 0.002, -0.004]
    calib = calibration_from_infos(left, right, rectified_images=False, source="test", right_in_left=pose)
    assert not calib.rectified and calib.baseline_m == pytest.approx(np.linalg.norm(pose[:3, 3]))
    p_left = np.array([1.0, -0.5, 7.0])  # a point seen by both: p_right = R·p_left + T
    np.testing.assert_allclose(calib.R @ p_left + calib.T, np.linalg.solve(pose, [*p_left, 1])[:3], atol=1e-12)
    np.testing.assert_array_equal(calib.K_right, right["K"])
    behind = pose.copy()
    behind[0, 3] = -0.3
    with pytest.raises(CalibrationError, match="not to its right"):
        calibration_from_infos(left, right, rectified_images=False, source="test", right_in_left=behind)


def test_camera_info_binning_and_region_of_interest_give_the_published_images_camera():
    """As ROS's image_geometry: the window's offset off the principal point, then the binning."""
    from types import SimpleNamespace

    from terrainmap.sources.messages import calibration_from_infos, camera_info

    full = {"width": 64, "height": 48, "k": [400.0, 0, 30, 0, 410.0, 20, 0, 0, 1],
            "p": [400.0, 0, 30, -100.0, 0, 410.0, 20, 0, 0, 0, 1, 0]}
    roi = SimpleNamespace(x_offset=8, y_offset=4, width=32, height=24, do_rectify=True)
    info = camera_info(info_msg(T0, "left", 8, 6, 0.0, **full, roi=roi, binning_x=2, binning_y=4), "/cam/left/camera_info")
    np.testing.assert_allclose(info["K"], [[200, 0, 11], [0, 102.5, 4], [0, 0, 1]])
    np.testing.assert_allclose(info["P"][:2], [[200, 0, 11, -50], [0, 102.5, 4, 0]])
    assert (info["width"], info["height"], info["roi"]) == (16, 6, True)
    binned = camera_info(info_msg(T0, "left", 8, 6, 0.0, **full, binning_x=2, binning_y=2), "/t")
    assert (binned["width"], binned["height"], binned["K"][0, 2], binned["P"][0, 3]) == (32, 24, 15.0, -50.0)
    whole = SimpleNamespace(x_offset=0, y_offset=0, width=64, height=48, do_rectify=False)
    assert camera_info(info_msg(T0, "left", 8, 6, 0.0, **full, roi=whole), "/t")["K"][0, 2] == 30
    outside = SimpleNamespace(x_offset=40, y_offset=4, width=32, height=24, do_rectify=False)
    with pytest.raises(CalibrationError, match=r"/t: region of interest 32×24 at \(40, 4\) reaches outside"):
        camera_info(info_msg(T0, "left", 8, 6, 0.0, **full, roi=outside), "/t")
    with pytest.raises(CalibrationError, match=r"/t: binning 4294967295×1 leaves no pixel of the 64×48 image"):
        camera_info(info_msg(T0, "left", 8, 6, 0.0, **full, binning_x=2**32 - 1), "/t")
    distorted = [camera_info(info_msg(T0, side, 8, 6, 0.0, (0.1, 0, 0, 0, 0), **{**full, "p": p}, roi=roi), side)
                 for side, p in (("left", [400.0, 0, 30, 0, 0, 410.0, 20, 0, 0, 0, 1, 0]), ("right", full["p"]))]
    with pytest.raises(CalibrationError, match="region of interest and distortion.*raw image topics"):
        calibration_from_infos(*distorted, rectified_images=True, source="test")
    assert not calibration_from_infos(*distorted, rectified_images=False, source="test").rectified


def test_a_log_of_binned_images_uses_the_binned_camera(tmp_path):
    """Images of 8×6 published with camera infos calibrated at 16×12 and binning 2."""
    def binned_infos(name, msg):
        if name == "sensor_msgs/msg/CameraInfo":
            msg.width, msg.height, msg.binning_x, msg.binning_y = 16, 12, 2, 2
            msg.k = [2 * v if i in (0, 2, 4, 5) else v for i, v in enumerate(msg.k)]
            msg.p = [2 * v if i in (0, 2, 3, 5, 6) else v for i, v in enumerate(msg.p)]
        return [msg]

    path = write_ros2_log(tmp_path / "plain.mcap", n=1)
    binned = rewrite_ros2_log(path, tmp_path / "binned.mcap", binned_infos)
    with open_source(path) as a, open_source(binned) as b:
        expected, frame = next(a.frames()), next(b.frames())
    for field in ("width", "height", "fx", "fy", "cx", "cy", "baseline_m"):
        assert getattr(frame.calibration, field) == pytest.approx(getattr(expected.calibration, field)), field


@pytest.mark.parametrize("paths", ["5", "[[bag_0.mcap]]", "*i"])
def test_a_rosbag2_whose_metadata_lists_no_files_is_read_from_its_mcap_files(tmp_path, caplog, paths):
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    (bag / "metadata.yaml").write_text(f"{YAML_BOMB}rosbag2_bagfile_information:\n  relative_file_paths: {paths}\n")
    with open_source(bag) as source:
        assert len(list(source.frames())) == 2
    assert "relative_file_paths is no list of file names" in caplog.text


def test_a_sqlite3_rosbag2_whose_metadata_lists_no_files_is_refused_naming_the_key(tmp_path):
    """rosbags would read a string of file names letter by letter and miss each letter's file."""
    log = write_ros2_log(tmp_path / "run.mcap", n=2)
    bag = rewrite_rosbag2(log, tmp_path / "bag", storage="sqlite3")
    metadata = bag / "metadata.yaml"
    metadata.write_text(metadata.read_text().replace("relative_file_paths:\n  - ", "relative_file_paths: "))
    with pytest.raises(InputError, match="metadata.yaml: relative_file_paths must be a list of file names$"):
        open_source(bag)


@pytest.mark.parametrize(("text", "reason"), [("", "no rosbag2_bagfile_information mapping"),
                                              ("rosbag2_bagfile_information: [unclosed\n", "ParserError")])
def test_an_unreadable_rosbag2_metadata_is_warned_about_once(tmp_path, caplog, text, reason):
    bag = tmp_path / "bag"
    bag.mkdir()
    write_ros2_log(bag / "bag_0.mcap", n=2)
    (bag / "metadata.yaml").write_text(text)
    with open_source(bag) as source:
        assert len(list(source.frames())) == 2
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "metadata.yaml" in r.getMessage()]
    assert warning.startswith(f"{bag / 'metadata.yaml'}: unreadable (") and reason in warning


def test_a_rosbag2_whose_files_are_gone_says_so(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  relative_file_paths: [bag_0.mcap]\n")
    with pytest.raises(InputError, match=r"bag: a rosbag2 folder whose metadata.yaml lists bag_0.mcap, none of them"):
        open_source(bag)


def test_a_rosbag2_source_that_fails_to_open_lets_go_of_its_bag(tmp_path, monkeypatch):
    from terrainmap.errors import NoStereoError
    from terrainmap.sources.readers import Rosbag2Bag

    log = write_ros2_log(tmp_path / "run.mcap", n=1)
    bag = rewrite_rosbag2(log, tmp_path / "bag", compression="file")
    closed = []
    monkeypatch.setattr(Rosbag2Bag, "close", lambda self: closed.append(self.path))
    with pytest.raises(NoStereoError):
        open_source(bag, left_topic="/cam/left/camera_info")  # no image topic: refused after the bag opened
    assert closed == [bag]


def test_a_pair_whose_image_cannot_be_decoded_is_skipped_and_reading_goes_on(tmp_path, monkeypatch, caplog):
    from terrainmap.errors import DamagedImageError
    from terrainmap.sources import images, messages

    log = write_ros2_log(tmp_path / "run.mcap", n=4)
    decode, calls = messages.image_array, []

    def third_image_damaged(msg, msg_type, topic):
        calls.append(topic)
        if len(calls) == 3:  # the second pair's left image
            raise DamagedImageError(f"{topic}: cannot decode the compressed image (9 bytes)")
        return decode(msg, msg_type, topic)

    monkeypatch.setattr(messages, "image_array", third_image_damaged)
    with open_source(log) as source:
        frames = list(source.frames(max_frames=3))
        (skipped,) = source.skipped()
    assert [f.index for f in frames] == [0, 2, 3]  # max_frames counts the frames yielded
    assert skipped.startswith(f"{log}: stereo pair at ") and "cannot decode the compressed image" in skipped
    assert "damaged, skipped" in caplog.text
    png = cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes()
    with pytest.raises(DamagedImageError, match=r"/t: cannot decode the compressed image"):
        images.decode_compressed(png[:-12], "/t")  # cut before its IEND chunk


def test_a_pair_whose_raw_image_is_cut_short_is_skipped_and_reading_goes_on(tmp_path, monkeypatch, caplog):
    """A raw Image whose data is shorter than its height × step is damage of that pair, as a
    compressed image that cannot be decoded is: the pair is skipped, named by the log and its time."""
    from terrainmap.sources import messages

    log = write_ros2_log(tmp_path / "run.mcap", n=4)
    decode, calls = messages.image_array, []

    def third_image_cut_short(msg, msg_type, topic):
        calls.append(topic)
        if len(calls) == 3:  # the second pair's left image: 8×6 rgb8 needs 144 bytes
            msg = cut_short(msg, bytes(msg.data)[:50])
        return decode(msg, msg_type, topic)

    monkeypatch.setattr(messages, "image_array", third_image_cut_short)
    with open_source(log) as source:
        frames = list(source.frames())
        (skipped,) = source.skipped()
    assert [f.index for f in frames] == [0, 2, 3]
    assert skipped.startswith(f"{log}: stereo pair at 1700000000.100 s") and "needs more than the 50 bytes given" in skipped
    assert "damaged, skipped" in caplog.text


def test_pairs_that_never_decode_end_the_reading_after_20_in_a_row(tmp_path, monkeypatch):
    """Every image of a log cut short is no damage here and there: the 20th such pair in a row ends
    the reading with one error; fewer in a row are skipped and the pairs between them kept."""
    from terrainmap.sources import messages
    from terrainmap.sources.base import MAX_DAMAGED_IN_A_ROW

    log = write_ros2_log(tmp_path / "run.mcap", n=MAX_DAMAGED_IN_A_ROW + 2)
    decode, good = messages.image_array, set()

    def left_cut_short(msg, msg_type, topic):
        if int(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) in good or topic.endswith("right/image_rect"):
            return decode(msg, msg_type, topic)
        return decode(cut_short(msg, b""), msg_type, topic)

    monkeypatch.setattr(messages, "image_array", left_cut_short)
    with open_source(log) as source, pytest.raises(InputError) as exc:
        list(source.frames())
    assert str(exc.value).startswith(f"{log}: 20 stereo pairs in a row cannot be read, which is no damage here and "
                                     f"there (the last: {log}: stereo pair at 1700000001.900 s (")
    good.add(T0 + 10 * 100_000_000)  # the 11th pair decodes: never 20 in a row
    with open_source(log) as source:
        assert [f.index for f in source.frames()] == [10] and len(source.skipped()) == MAX_DAMAGED_IN_A_ROW + 1


@pytest.mark.parametrize("tolerance", [-1, 1.5, "10", True, None])
def test_a_pair_tolerance_that_is_no_whole_number_of_nanoseconds_is_refused(tolerance):
    """The library's pairing tolerance is checked as the CLI's is: a negative one would pair
    nothing and say nothing."""
    from terrainmap.errors import ConfigError

    with pytest.raises(ConfigError, match="pair tolerance must be a whole number of nanoseconds"):
        open_source("examples/offroad_demo.mcap", pair_tolerance_ns=tolerance)


def _write_pairs(path: Path, stamps: list[tuple[int | None, int | None]], right_late_ns: int = 2_000_000) -> Path:
    """A ROS 2 MCAP with camera infos and, per entry (left header stamp, right header stamp; None:
    no message), pair i's images logged at T0 + i·100 ms (the right one ``right_late_ns`` later)."""
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        for side, tx in (("left", 0.0), ("right", -400.0 * 0.25)):
            writer.write_message(f"/cam/{side}/camera_info", info_schema, ros_info(T0, f"{side}_optical", 8, 6, tx, (0.0,) * 5), T0)
        for i, stamps_i in enumerate(stamps):
            log_time = T0 + i * 100_000_000
            for side, stamp, image, late in zip(("left", "right"), stamps_i, pair_images(i), (0, right_late_ns), strict=True):
                if stamp is not None:
                    message = ros_image(stamp, f"{side}_optical", image, "rgb8")
                    writer.write_message(f"/cam/{side}/image_rect", image_schema, message, log_time + late)
    return path


def test_images_without_header_stamps_are_paired_by_log_time_with_a_warning(tmp_path, caplog):
    """A driver that never sets header stamps (all 0): pairing by stamp would pair every left
    image with any right one, and a lost image would shift every later pair. The log time stands
    in, with one warning per topic."""
    stamps = [(0, 0)] * 6
    stamps[2] = (0, None)  # pair 2 lost its right image
    with open_source(_write_pairs(tmp_path / "unstamped.mcap", stamps)) as source:
        frames = list(source.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    for frame, i in zip(frames, [0, 1, 3, 4, 5], strict=True):
        np.testing.assert_array_equal(frame.left, pair_images(i)[0])
        np.testing.assert_array_equal(frame.right, pair_images(i)[1])
        assert frame.stamp_ns == T0 + i * 100_000_000
    assert caplog.text.count("/cam/left/image_rect and /cam/right/image_rect has images with no header stamp (0); "
                             "both cameras' images are paired and placed by log time") == 1
    assert "1 of 11 image messages had no partner" in caplog.text


def test_when_one_camera_has_no_header_stamps_both_are_paired_by_log_time(tmp_path, caplog):
    """Left images stamped 40 ms before they are logged, right ones unstamped: one clock, the log
    time, pairs them all."""
    stamps = [(T0 + i * 100_000_000 - 40_000_000, 0) for i in range(4)]
    with open_source(_write_pairs(tmp_path / "half.mcap", stamps)) as source:
        frames = list(source.frames())
    assert [f.stamp_ns for f in frames] == [T0 + i * 100_000_000 for i in range(4)]
    assert "/cam/right/image_rect has images with no header stamp (0)" in caplog.text


def test_images_left_without_a_partner_at_the_end_of_the_log_are_counted(tmp_path, caplog):
    """The right camera stops two pairs before the left: those two left images are reported."""
    stamps = [(T0 + i * 100_000_000, T0 + i * 100_000_000 + 1_000_000) for i in range(6)]
    stamps[4:] = [(T0 + i * 100_000_000, None) for i in (4, 5)]
    with open_source(_write_pairs(tmp_path / "right_stops.mcap", stamps)) as source:
        assert len(list(source.frames())) == 4
    assert "2 of 10 image messages had no partner within 10.0 ms" in caplog.text


def test_images_left_unpaired_by_half_the_frame_period_are_reported_with_that_limit(tmp_path, caplog):
    """Right images 60 ms after the left at 10 Hz, a tolerance of 70 ms: once the period is known
    each right image pairs with the next left one, 40 ms away, and the warning names the limit
    that left images unpaired, half the period, not the tolerance they were within."""
    stamps = [(T0 + i * 100_000_000, T0 + i * 100_000_000 + 60_000_000) for i in range(6)]
    with open_source(_write_pairs(tmp_path / "offset.mcap", stamps), pair_tolerance_ns=70_000_000) as source:
        assert len(list(source.frames())) == 5
    assert ("2 of 12 image messages had no partner within 50.0 ms, half the cameras' frame period "
            "(--pair-tolerance-ms 70.0)") in caplog.text


def test_images_logged_far_behind_their_partners_are_reported_as_such(tmp_path, caplog):
    """Right images logged 5 s (50 pairs) after their left partners: the pairing buffer holds 32
    messages a side, and the warning says that the buffer, not the tolerance, lost the rest."""
    stamps = [(T0 + i * 100_000_000, T0 + i * 100_000_000) for i in range(40)]
    with open_source(_write_pairs(tmp_path / "late.mcap", stamps, right_late_ns=5_000_000_000)) as source:
        assert len(list(source.frames())) == 32
    assert ("16 of 80 image messages had no partner within 10.0 ms (--pair-tolerance-ms); 8 of them left a "
            "full pairing buffer: one camera's images are logged over 32 messages behind the other's") in caplog.text


def _write_with_infos(path: Path, focal_px: list[float], right_late: int = 0) -> Path:
    """A ROS 2 MCAP of len(focal_px) pairs, each with its camera infos (focal length focal_px[i],
    0: a left info without its projection matrix; baseline 0.25 m) logged just before the images;
    the right camera's messages logged ``right_late`` pairs late."""
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        for i, fx in enumerate(focal_px):
            stamp = T0 + i * 100_000_000
            for side, tx, image in zip(("left", "right"), (0.0, -(fx or 400.0) * 0.25), pair_images(i), strict=True):
                info = ros_info(stamp, f"{side}_optical", 8, 6, tx)
                info["k"][0] = info["k"][4] = info["p"][0] = info["p"][5] = fx or (0.0 if side == "left" else 400.0)
                log_time = stamp + (right_late * 100_000_000 + 1000 if side == "right" else 0)
                writer.write_message(f"/cam/{side}/camera_info", info_schema, info, log_time)
                writer.write_message(f"/cam/{side}/image_rect", image_schema,
                                     ros_image(stamp, f"{side}_optical", image, "rgb8"), log_time)
    return path


def test_a_calibration_that_changes_part_way_applies_to_the_pairs_after_it(tmp_path, caplog):
    """Camera infos published with the images, whose focal length changes at pair 3 (the driver
    reloaded another calibration): the pairs after it get the new calibration, with one warning;
    repeated identical infos change nothing."""
    path = _write_with_infos(tmp_path / "recalibrated.mcap", [400.0] * 3 + [500.0] * 3)
    with open_source(path) as source:
        frames = list(source.frames())
        assert source.describe()["calibration"]["fx"] == 400.0  # what info shows: the first
    assert [f.calibration.fx for f in frames] == [400.0] * 3 + [500.0] * 3
    assert all(f.calibration.baseline_m == pytest.approx(0.25) for f in frames)  # never a left-new, right-old mix
    assert caplog.text.count("the camera calibration changes at") == 1
    assert f"{path}: the camera calibration changes at {(T0 + 300_000_000) / 1e9:.3f} s (fx 500 px, baseline 0.25 m, " \
           "8×6, was fx 400 px, baseline 0.25 m, 8×6); the frames after use it" in caplog.text


def _write_resized(path: Path, sizes: list[tuple[int, int]], infos: int) -> Path:
    """A ROS 2 MCAP whose camera infos are logged right after their images (image_transport's
    order), the images of pair i of ``sizes[i]`` (rows, columns), the infos of the first
    ``infos`` pairs' sizes only (then the last of those again)."""
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        for i, (rows, cols) in enumerate(sizes):
            stamp = T0 + i * 100_000_000
            info_rows, info_cols = sizes[min(i, infos - 1)]
            for side, tx, image in zip(("left", "right"), (0.0, -100.0), pair_images(i, (rows, cols, 3)), strict=True):
                writer.write_message(f"/cam/{side}/image_rect", image_schema,
                                     ros_image(stamp, f"{side}_optical", image, "rgb8"), stamp)
                writer.write_message(f"/cam/{side}/camera_info", info_schema,
                                     ros_info(stamp, f"{side}_optical", info_cols, info_rows, tx), stamp + 1)
    return path


def test_images_that_change_size_part_way_skip_the_one_pair_logged_before_its_infos(tmp_path, caplog):
    """The driver switches from 8×6 to 16×12 at pair 3: that pair still holds the old calibration
    (its infos come after it) and is skipped with a warning; the run goes on with the new one."""
    path = _write_resized(tmp_path / "resized.mcap", [(6, 8)] * 3 + [(12, 16)] * 3, infos=6)
    with open_source(path) as source:
        frames = list(source.frames())
        assert len(source.skipped()) == 1
    assert [(f.index, f.calibration.width) for f in frames] == [(0, 8), (1, 8), (2, 8), (4, 16), (5, 16)]
    assert caplog.text.count("images of a new size before their camera infos, skipped") == 1


def test_images_whose_new_size_never_gets_its_calibration_end_the_run_naming_both_sizes(tmp_path):
    path = _write_resized(tmp_path / "resized.mcap", [(6, 8)] * 3 + [(12, 16)] * 3, infos=3)
    with open_source(path) as source, pytest.raises(CalibrationError, match=f"^{path}: .*calibration is for 8×6 images "
                                                                                 "but /cam/left/image_rect is 16×12"):
        list(source.frames())


def test_unusable_camera_infos_part_way_keep_the_calibration_before_with_one_warning(tmp_path, caplog):
    path = _write_with_infos(tmp_path / "broken.mcap", [400.0] * 2 + [0.0] * 4)
    with open_source(path) as source:
        frames = list(source.frames())
    assert [f.calibration.fx for f in frames] == [400.0] * 6
    assert caplog.text.count("is unusable, the calibration before is kept") == 1


def test_after_a_clock_reset_pairs_are_given_as_they_come_with_their_poses(tmp_path, caplog):
    """Image and odometry stamps go back 100 s part way (a restarted clock), the odometry lagging
    150 ms: the pairs before the reset no longer wait for a pose after them, so that pairs keep
    coming as the log is read (memory stays bounded) and those after the reset get poses."""
    path = tmp_path / "reset.mcap"
    starts = [T0 + 100_000_000_000] * 10 + [T0] * 10
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF + HEADER)
        for side, tx in (("left", 0.0), ("right", -100.0)):
            writer.write_message(f"/cam/{side}/camera_info", info_schema, ros_info(T0, f"{side}_optical", 8, 6, tx), 0)
        for i, start in enumerate(starts):
            stamp, log_time = start + i % 10 * 100_000_000, T0 + 200_000_000_000 + i * 100_000_000
            for side, image in zip(("left", "right"), pair_images(i), strict=True):
                writer.write_message(f"/cam/{side}/image_rect", image_schema,
                                     ros_image(stamp, f"{side}_optical", image, "rgb8"), log_time + 1000)
            writer.write_message("/tf", tf_schema, tf_message(stamp - 150_000_000, "odom", "base_link", (i, 0, 0),
                                                              (0, 0, 0, 1)), log_time)
    with open_source(path) as source:
        read, messages = [0], source.reader.messages

        def counting(topics):
            for message in messages(topics):
                read[0] += 1
                yield message

        source.reader.messages = counting
        given = [(ref.index, read[0], ref.load().vehicle_pose is not None) for ref in source._pairs()]
    total = 2 + 3 * 20
    assert [index for index, _, _ in given] == list(range(20))
    assert all(at < total for index, at, _ in given if index < 15)  # not all held back to the end
    assert sum(posed for index, _, posed in given if index >= 10) >= 8
    assert caplog.text.count("odometry: the clock went back") == 1


@pytest.mark.parametrize("right_late", [1, 2])
def test_a_calibration_change_is_found_when_one_camera_is_logged_late(tmp_path, caplog, right_late):
    """The right camera's images and infos logged one or two pairs behind the left's: its infos
    are paired with the left's by stamp, so the change is seen, without a mixed calibration."""
    path = _write_with_infos(tmp_path / "late.mcap", [400.0] * 3 + [500.0] * 3, right_late=right_late)
    with open_source(path) as source:
        frames = list(source.frames())
    assert [f.calibration.fx for f in frames] == [400.0] * 3 + [500.0] * 3
    assert caplog.text.count("the camera calibration changes at") == 1 and "unusable" not in caplog.text


def test_a_change_on_one_side_goes_with_the_other_sides_single_info(tmp_path, caplog):
    """The left info is a single (latched) message; the right one, republished, changes its
    baseline at pair 3: the change is taken with the left's one message."""
    path = tmp_path / "latched.mcap"
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        writer.write_message("/cam/left/camera_info", info_schema, ros_info(T0, "left_optical", 8, 6, 0.0), T0)
        for i in range(6):
            stamp = T0 + i * 100_000_000
            baseline = 0.25 if i < 3 else 0.5
            writer.write_message("/cam/right/camera_info", info_schema,
                                 ros_info(stamp, "right_optical", 8, 6, -400.0 * baseline), stamp)
            for side, image in zip(("left", "right"), pair_images(i), strict=True):
                writer.write_message(f"/cam/{side}/image_rect", image_schema,
                                     ros_image(stamp, f"{side}_optical", image, "rgb8"), stamp)
    with open_source(path) as source:
        assert [f.calibration.baseline_m for f in source.frames()] == [0.25] * 3 + [0.5] * 3
    assert caplog.text.count("the camera calibration changes at") == 1


def test_a_first_image_without_a_stamp_does_not_put_the_log_on_log_time(tmp_path, caplog):
    """Only the first left image is unstamped (a driver whose clock was not set yet): the log is
    still paired by header stamp, that one image by its log time."""
    stamps = [(T0 + i * 100_000_000, T0 + i * 100_000_000 + 1_000_000) for i in range(6)]
    stamps[0] = (0, stamps[0][1])
    with open_source(_write_pairs(tmp_path / "first.mcap", stamps)) as source:
        frames = list(source.frames())
    assert [f.stamp_ns for f in frames] == [T0 + i * 100_000_000 for i in range(6)]
    assert "no header stamp" not in caplog.text


def test_each_image_topic_takes_the_camera_info_naming_its_side_among_three(tmp_path):
    """A third camera's info in the pair's namespace (a colour camera beside it) ties with both on
    namespace: the right images take the info naming their side, not the other one left."""
    path = tmp_path / "three_infos.mcap"
    with open(path, "wb") as f, Ros2Writer(f) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_DEF + HEADER)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", INFO_DEF + HEADER)
        for name, tx in (("left", 0.0), ("right", -100.0), ("color", 0.0)):
            writer.write_message(f"/cam/{name}_info", info_schema, ros_info(T0, f"{name}_optical", 8, 6, tx), T0)
        for side, image in zip(("left", "right"), pair_images(0), strict=True):
            writer.write_message(f"/cam/{side}_image", image_schema, ros_image(T0, f"{side}_optical", image, "rgb8"), T0 + 1)
    with open_source(path) as source:
        assert source.calibration_topics == ("/cam/left_info", "/cam/right_info")
        assert source.calibration.baseline_m == pytest.approx(0.25)


def test_odometry_of_a_turned_base_footprint_carries_the_mount_of_base_link_turned(tmp_path):
    """base_link 0.5 m ahead of base_footprint, the vehicle turned 90° left in odom: base_link
    lies 0.5 m along odom's y from base_footprint (pose · mount, not mount · pose)."""
    path = _footprint_log(tmp_path / "turned.mcap", (0.5, 0, 0.3), (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)))  # 90° about z
    with open_source(path) as source:
        frame = next(iter(source.frames()))
    assert frame.extrinsics.vehicle_frame_id == "base_link"
    np.testing.assert_allclose(frame.vehicle_pose[:3, 3], [10.0, 0.5, 0.3], atol=1e-12)
    np.testing.assert_allclose(frame.vehicle_pose[:3, :2], [[0, -1], [1, 0], [0, 0]], atol=1e-12)


def test_a_pair_tolerance_of_zero_pairs_only_equal_stamps(tmp_path):
    path = _write_pairs(tmp_path / "exact.mcap", [(T0, T0), (T0 + 100_000_000, T0 + 100_000_001)])
    with open_source(path, pair_tolerance_ns=0) as source:
        assert [frame.stamp_ns for frame in source.frames()] == [T0]


def test_a_log_cut_short_while_it_is_read_ends_the_reading_naming_the_change(tmp_path, caplog):
    """Chunks the index points past the new end are no damage to skip (and a run would end with
    exit code 0 and half the frames): the file is not the one opened, and reading stops saying so."""
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "run.mcap"
    simulate(log, SimConfig(scene="flat", frames=6, seed=1, width=320, height=240, focal_px=250.0))
    with open(log, "rb") as f:
        assert len(make_reader(f).get_summary().chunk_indexes) > 3
    with open_source(log) as source:
        frames = source.frames()
        next(frames)
        os.truncate(log, log.stat().st_size // 3)
        with pytest.raises(InputError, match=rf"^{log}: changed while it was being read \(\d+ bytes, was \d+; chunk at "
                                             r"byte \d+, log time [\d.]+–[\d.]+ s: "):
            list(frames)
    assert "damaged, skipped" not in caplog.text
