"""The small parts under the log sources: topic guessing, pairing, the transform tree, raw decoding."""

import cv2
import numpy as np
import pytest

from terrainmap.errors import DamagedImageError, InputError
from terrainmap.sources.images import decode_raw
from terrainmap.sources.pairing import StereoPairer
from terrainmap.sources.tf import TransformTree, VehiclePoses, quaternion_to_matrix
from terrainmap.sources.topics import calibration_topic, rectified_name, side_tokens, stereo_topics

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


@pytest.mark.parametrize(
    "left, right",
    [
        ("/stereo/left/image_rect_color", "/stereo/right/image_rect_color"),
        ("/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color"),
        ("/cam0/image_raw", "/cam1/image_raw"),
        ("/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw"),
        ("/kitti/image_2", "/kitti/image_3"),
        ("/stereo_camera/left_image", "/stereo_camera/right_image"),
        ("/multisense/l/image", "/multisense/r/image"),
    ],
)
def test_stereo_topics_are_found_by_name(left, right):
    types = {left: IMAGE, right: IMAGE, "/rosout": "rcl_interfaces/msg/Log"}
    assert stereo_topics(types, None, None, "log") == (left, right)


def test_rectified_uncompressed_pair_is_preferred():
    types = {
        "/s/left/image_raw": IMAGE, "/s/right/image_raw": IMAGE,
        "/s/left/image_rect/compressed": COMPRESSED, "/s/right/image_rect/compressed": COMPRESSED,
        "/s/left/image_rect": IMAGE, "/s/right/image_rect": IMAGE,
    }
    assert stereo_topics(types, None, None, "log") == ("/s/left/image_rect", "/s/right/image_rect")
    assert stereo_topics(types, "/s/left/image_raw", None, "log") == ("/s/left/image_raw", "/s/right/image_raw")


def test_depth_and_equally_good_pairs(caplog):
    """image_transport's compressedDepth carries depth maps: never a camera pair of its own; two
    pairs that rank alike (two rigs, or a colour and a mono rendering) are named in a warning."""
    depth = {"/s/left/image_rect/compressedDepth": COMPRESSED, "/s/right/image_rect/compressedDepth": COMPRESSED}
    with pytest.raises(InputError, match="no stereo image topics found"):
        stereo_topics(depth, None, None, "log")
    cameras = {**depth, "/s/left/image_raw/compressed": COMPRESSED, "/s/right/image_raw/compressed": COMPRESSED}
    assert stereo_topics(cameras, None, None, "log") == ("/s/left/image_raw/compressed", "/s/right/image_raw/compressed")
    assert "several" not in caplog.text
    renderings = {f"/s/{side}/image_rect{colour}": IMAGE for side in ("left", "right") for colour in ("", "_color")}
    assert stereo_topics(renderings, None, None, "log") == ("/s/left/image_rect", "/s/right/image_rect")
    assert "several" not in caplog.text  # stereo_image_proc's mono and colour images: one rig
    rigs = {f"/{rig}/{side}/image_raw": IMAGE for rig in ("front", "rear") for side in ("left", "right")}
    assert stereo_topics(rigs, None, None, "log") == ("/front/left/image_raw", "/front/right/image_raw")
    assert ("log: several stereo pairs of image topics: /front/left/image_raw + /front/right/image_raw is used; also "
            "/rear/left/image_raw + /rear/right/image_raw (choose with --left-topic and --right-topic)") in caplog.text


def test_unrelated_topics_do_not_pair():
    assert side_tokens("/front/image", "/rear/image") is None
    assert side_tokens("/cam0/image", "/cam0/depth") is None
    with pytest.raises(InputError, match="log: no stereo image topics found.*/front/image.*; give --left-topic and "
                       "--right-topic$"):
        stereo_topics({"/front/image": IMAGE, "/rear/image": IMAGE}, None, None, "log")
    with pytest.raises(InputError, match=r"topics: /front/image \[.*\]\)$"):  # one image topic: nothing to give
        stereo_topics({"/front/image": IMAGE}, None, None, "log")


def test_calibration_topic_by_namespace():
    infos = ["/stereo/left/camera_info", "/stereo/right/camera_info", "/other/camera_info"]
    assert calibration_topic("/stereo/left/image_rect_color/compressed", infos) == "/stereo/left/camera_info"
    assert calibration_topic("/stereo/right/image_rect_color", infos) == "/stereo/right/camera_info"
    assert calibration_topic("/elsewhere/image", infos) is None
    assert calibration_topic("/left_image", infos, side=("left", "right")) is None  # only a top-level one could do


@pytest.mark.parametrize(
    ("left_image", "left_info"),
    [("/cam/left_image", "/cam/left_info"), ("/stereo/left/image_rect", "/stereo/camera_info_left"),
     ("/left_image", "/left_calibration")],  # top-level topics share no namespace: the side decides
)
def test_calibration_topics_in_one_namespace_go_by_their_side_token(left_image, left_info):
    right_image, right_info = (t.replace("left", "right") for t in (left_image, left_info))
    infos = [left_info, right_info]  # the right one sorts last: a tie on namespace alone picks it
    sides = side_tokens(left_image, right_image)
    left = calibration_topic(left_image, infos, side=sides)
    assert (left, calibration_topic(right_image, infos, exclude=left, side=sides[::-1])) == (left_info, right_info)


def test_pairer_matches_within_tolerance_and_stays_bounded():
    pairer = StereoPairer(tolerance_ns=5, max_buffer=4)
    assert pairer.push(0, 100, "L1") is None
    assert pairer.push(1, 103, "R1") == (100, "L1", "R1")
    assert pairer.push(1, 203, "R2") is None  # right first this time
    assert pairer.push(0, 200, "L2") == (200, "L2", "R2")
    for i in range(100):  # a left camera with no right partner
        pairer.push(0, 1000 + 100 * i, i)
    assert all(len(buffer) <= 4 for buffer in pairer._waiting) and pairer.dropped >= 96
    assert pairer.push(1, 1000 + 100 * 99 + 2, "R") == (1000 + 100 * 99, 99, "R")


@pytest.mark.parametrize(
    "period_ms, right_late_ms, tolerance_ms",
    [(10, 0, 10), (33, 15, 20)],  # 100 Hz synchronised at the default tolerance; 30 Hz, right 15 ms late, widened
)
def test_after_a_dropped_image_the_pairs_are_not_made_one_frame_apart(period_ms, right_late_ms, tolerance_ms):
    """A tolerance of about a period or more: after left image 5 is lost, left 6 is closer to
    right 6 than to the right 5 that waits unpaired, and so on; every later pair stays whole."""
    ms = 1_000_000
    pairer = StereoPairer(tolerance_ns=tolerance_ms * ms)
    messages = sorted([(i * period_ms * ms, 0, i) for i in range(20) if i != 5]
                      + [((i * period_ms + right_late_ms) * ms, 1, i) for i in range(20)])
    pairs = [p for t, side, i in messages if (p := pairer.push(side, t, i)) is not None]
    assert [(left, right) for _, left, right in pairs] == [(i, i) for i in range(20) if i != 5]


def test_pairer_skips_duplicates_and_measures_what_the_tolerance_missed():
    pairer = StereoPairer(tolerance_ns=10, same=lambda a, b: a[0] == b[0])  # (a message's content: its first letter)
    assert pairer.push(0, 100, "L") is None and pairer.push(0, 100, "L again") is None  # recorded twice
    assert pairer.push(1, 101, "R") == (100, "L", "R") and pairer.push(1, 101, "R again") is None
    assert pairer.repeated == 2 and pairer.dropped == 0
    # a clock coarser than the frame rate: two images, one stamp; both kept, the second pairs on
    assert pairer.push(0, 300, "A") is None and pairer.push(1, 301, "B") == (300, "A", "B")
    assert pairer.push(0, 300, "C") is None and pairer.push(1, 301, "D") == (300, "C", "D") and pairer.repeated == 2
    for i in range(5, 9):  # right 15 past left: over the tolerance
        pairer.push(0, 100 + 100 * i, i)
        pairer.push(1, 115 + 100 * i, i)
    assert pairer.offset_ns == 15  # not 85, from each left to the right before it


def test_a_topic_is_taken_for_rectified_by_a_word_of_its_name():
    assert rectified_name("/stereo/left/image_rect_color") and rectified_name("/cam/left/rectified/compressed")
    assert not rectified_name("/directional/left/image_raw") and not rectified_name("/correction/left/image")


def test_pairer_keeps_every_pair_of_a_camera_logged_a_third_of_a_second_late():
    pairer, period = StereoPairer(tolerance_ns=1_000_000), 33_333_333  # 30 Hz
    stamps = [i * period for i in range(300)]
    arrivals = sorted([(t, 0, t) for t in stamps] + [(t + 300_000_000, 1, t) for t in stamps])  # right logged late
    pairs = [p for _, side, t in arrivals if (p := pairer.push(side, t, t)) is not None]
    assert [p[0] for p in pairs] == stamps and pairer.dropped == 0 and pairer.pushed == 600


def test_transform_tree_composes_up_to_the_vehicle_frame():
    tree = TransformTree()
    tree.add("odom", "base_link", [10, 0, 0], [0, 0, 0, 1])
    tree.add("base_link", "mast", [0.5, 0, 1.0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # yaw 90°
    tree.add("/mast", "/cam_optical", [0.2, 0, 0], [0, 0, 0, 1])
    ext = tree.extrinsics("cam_optical")
    assert ext.vehicle_frame_id == "base_link" and ext.source == "tf"
    np.testing.assert_allclose(ext.translation, [0.5, 0.2, 1.0], atol=1e-12)
    np.testing.assert_allclose(ext.rotation, quaternion_to_matrix([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]))
    assert tree.extrinsics("unknown_frame") is None
    other = TransformTree()  # no base_link: the highest frame below the world frames is the vehicle
    other.add("map", "odom", [5, 0, 0], [0, 0, 0, 1])
    other.add("odom", "chassis", [10, 0, 0], [0, 0, 0, 1])
    other.add("chassis", "cam", [1, 2, 3], [0, 0, 0, 1])
    other.add("world", "fixed_cam", [1, 2, 3], [0, 0, 0, 1])
    assert other.extrinsics("cam").vehicle_frame_id == "chassis"
    np.testing.assert_allclose(other.extrinsics("cam").translation, [1, 2, 3])
    assert other.extrinsics("fixed_cam") is None  # only a world frame above it: estimated instead


def test_a_camera_drivers_own_tree_is_no_vehicle(caplog):
    """A RealSense's tree alone (camera_link → infra1 frame → its optical frame, all at one point):
    camera_link is the camera's body, in which the pose would be 0 m up and turned as the camera
    is; the pose is left to the ground estimate, with a warning."""
    tree = TransformTree()
    tree.add("camera_link", "camera_infra1_frame", [0, 0, 0], [0, 0, 0, 1])
    tree.add("camera_infra1_frame", "camera_infra1_optical_frame", [0, 0, 0], [-0.5, 0.5, -0.5, 0.5])
    assert tree.extrinsics("camera_infra1_optical_frame") is None  # vehicle frame camera_link, 0 m up, before
    assert caplog.messages == ["tf: the camera frame camera_infra1_optical_frame lies 0.00 m from the origin of "
                               "camera_link, the highest frame above it (no base_link or base_footprint): taken for "
                               "the camera's own body, not the vehicle; the camera pose is estimated from the ground"]
    tree.add("rover", "camera_link", [0.4, 0, 1.2], [0, 0, 0, 1])  # mounted on something: that is the vehicle
    assert tree.extrinsics("camera_infra1_optical_frame").vehicle_frame_id == "rover"


def test_broken_static_transforms_are_skipped_with_a_warning(caplog):
    tree = TransformTree()
    tree.add("base_link", "camera", [0, 0, 1.5], [0, 0, 0, 0])  # zero quaternion: no rotation at all
    tree.add("base_link", "lidar", [np.nan, 0, 1.5], [0, 0, 0, 1])
    tree.add("base_link", "lidar", [np.nan, 0, 1.5], [0, 0, 0, 1])  # a dynamic tf repeats it: said once
    assert len(tree) == 0
    assert [r.getMessage().split(" is ")[0] for r in caplog.records] == ["tf: the transform base_link → camera",
                                                                          "tf: the transform base_link → lidar"]


def test_quaternions_of_any_scale_are_normalised_without_overflow():
    half_turn = np.array([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    with np.errstate(all="raise"):
        for scale in (1e-5, 1.0, 1e200):
            np.testing.assert_allclose(quaternion_to_matrix(scale * half_turn), quaternion_to_matrix(half_turn))


def test_vehicle_poses_interpolate_and_keep_to_one_odometry_frame(caplog):
    yaw90 = [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]
    poses = VehiclePoses(tolerance_ns=50)
    assert poses.at(100) is None and poses.newest_ns is None
    poses.add(100, "/odom", "/base_link", [0, 0, 0], [0, 0, 0, 1])
    poses.add(200, "odom", "base_link", [1, 2, 0], yaw90)
    poses.add(150, "odom", "base_link", [9, 9, 9], [0, 0, 0, 1])  # older than the newest: ignored
    poses.add(300, "map", "base_link", [5, 5, 5], [0, 0, 0, 1])  # another odometry frame: ignored
    poses.add(300, "base_link", "camera", [5, 5, 5], [0, 0, 0, 1])  # not a vehicle pose
    poses.add(310, "odom", "base_link", [np.nan, 0, 0], [0, 0, 0, 1])  # broken: skipped, with one warning
    poses.add(320, "odom", "base_link", [0, 0, 0], [0, 0, 0, 0])
    assert caplog.text.count("such poses are ignored") == 1
    assert poses.parent == "odom" and poses.newest_ns == 200
    early, late = poses.at(125), poses.at(175)
    np.testing.assert_allclose(early[:3, 3], [0.25, 0.5, 0])
    # the rotation along the shortest arc: 22.5° and 67.5° of the 90° turn
    yaw = [np.degrees(np.arctan2(pose[1, 0], pose[0, 0])) for pose in (early, late, poses.at(200))]
    np.testing.assert_allclose(yaw, [22.5, 67.5, 90.0])
    np.testing.assert_allclose(poses.at(200)[:3, :3], quaternion_to_matrix(yaw90), atol=1e-12)
    for pose in (early, late):
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)  # a rotation
    # within the tolerance beyond the first and the last: the motion between the two nearest carried on
    np.testing.assert_allclose(poses.at(250)[:3, 3], [1.5, 3, 0])
    np.testing.assert_allclose(poses.at(50)[:3, 3], [-0.5, -1, 0])
    yaw = [np.degrees(np.arctan2(pose[1, 0], pose[0, 0])) for pose in (poses.at(250), poses.at(50))]
    np.testing.assert_allclose(yaw, [135.0, -45.0])
    assert poses.at(251) is None and poses.at(49) is None
    alone = VehiclePoses(tolerance_ns=50)
    alone.add(100, "odom", "base_link", [1, 2, 0], yaw90)
    np.testing.assert_allclose(alone.at(140), alone.at(100))  # one pose: no motion to carry on
    assert alone.at(151) is None
    close = VehiclePoses(tolerance_ns=50)
    close.add(100, "odom", "base_link", [0, 0, 0], [0, 0, 0, 1])
    close.add(101, "odom", "base_link", [0.01, 0, 0], [0, 0, 0, 1])  # (noise) 1 ns apart: carried on 1 ns at most
    np.testing.assert_allclose(close.at(150)[:3, 3], [0.02, 0, 0])
    bounded = VehiclePoses(horizon_ns=1000)
    for k in range(100):
        bounded.add(100 * k, "odom", "base_link", [k, 0, 0], [0, 0, 0, 1])
    assert len(bounded._stamps) == 11 and bounded.at(9850)[0, 3] == pytest.approx(98.5)


def test_vehicle_poses_start_again_after_the_clock_goes_back(caplog):
    """A clock reset (stamps back by more than the horizon): the poses after it are kept and
    looked up, with one warning, instead of being ignored for the rest of the log."""
    poses = VehiclePoses(tolerance_ns=50, horizon_ns=1000)
    for k in range(5):
        poses.add(10_000 + 100 * k, "odom", "base_link", [k, 0, 0], [0, 0, 0, 1])
    poses.add(10_300, "odom", "base_link", [9, 9, 9], [0, 0, 0, 1])  # within the horizon: out of order, ignored
    poses.add(3_000, "odom", "base_link", [9, 9, 9], [0, 0, 0, 1])  # one stale pose: ignored
    poses.add(3_000, "odom", "base_link", [9, 9, 9], [0, 0, 0, 1])  # repeated: still stale, not a clock
    poses.add(0, "odom", "base_link", [9, 9, 9], [0, 0, 0, 1])  # never stamped: ignored
    poses.add(10_500, "odom", "base_link", [5, 0, 0], [0, 0, 0, 1])
    assert poses.newest_ns == 10_500 and "clock went back" not in caplog.text
    for k in range(3):  # the clock reset: poses in a row far back
        poses.add(500 + 100 * k, "odom", "base_link", [10 + k, 0, 0], [0, 0, 0, 1])
    assert poses.newest_ns == 700 and poses.at(650)[0, 3] == pytest.approx(11.5)
    assert poses.at(10_200) is None  # the poses before the reset are gone
    assert caplog.text.count("odometry: the clock went back") == 1


def test_decode_raw_handles_row_padding_and_big_endian():
    image = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    rows = np.zeros((3, 10), np.uint8)
    rows[:, :8] = image.astype(">u2").view(np.uint8).reshape(3, 8)
    out = decode_raw(rows.tobytes(), width=4, height=3, step=10, encoding="mono16", name="/t", big_endian=True)
    np.testing.assert_array_equal(out, image)
    with pytest.raises(InputError, match="/t: image of 4×3 rgb8"):
        decode_raw(b"\x00" * 10, width=4, height=3, step=12, encoding="rgb8", name="/t")
    with pytest.raises(InputError, match=r"/t: mono8 image of size 0×0 \(no pixel\)"):
        decode_raw(b"\x00" * 10, width=0, height=0, step=0, encoding="mono8", name="/t")


def _smooth_rgb(height=12, width=16, scale=1):
    """A colour image whose channels change slowly (so demosaicing can restore it), ×scale."""
    v, u = np.mgrid[0:height, 0:width]
    rgb = np.stack([100 + 4 * u, 60 + 5 * v, 180 - 3 * u - 2 * v], axis=-1)
    return (rgb * scale).astype(np.uint16 if scale > 1 else np.uint8)


# The colour channel (0 R, 1 G, 2 B) of the pixels (0, 0), (0, 1), (1, 0), (1, 1) of each 2×2 tile.
BAYER_TILES = {"rggb": (0, 1, 1, 2), "bggr": (2, 1, 1, 0), "gbrg": (1, 2, 0, 1), "grbg": (1, 0, 2, 1)}


@pytest.mark.parametrize("pattern", sorted(BAYER_TILES))
@pytest.mark.parametrize("bits", [8, 16])
def test_decode_raw_demosaics_bayer_patterns(pattern, bits):
    rgb = _smooth_rgb(scale=1 if bits == 8 else 256)
    mosaic = np.zeros(rgb.shape[:2], rgb.dtype)
    for (dv, du), channel in zip(((0, 0), (0, 1), (1, 0), (1, 1)), BAYER_TILES[pattern]):
        mosaic[dv::2, du::2] = rgb[dv::2, du::2, channel]
    out = decode_raw(mosaic.tobytes(), width=16, height=12, step=0, encoding=f"bayer_{pattern}{bits}", name="/t")
    assert out.shape == rgb.shape and out.dtype == rgb.dtype
    # bilinear demosaicing restores a linear ramp exactly away from the borders
    tolerance = 1 if bits == 8 else 256
    np.testing.assert_allclose(out[2:-2, 2:-2].astype(float), rgb[2:-2, 2:-2], atol=tolerance)


def test_decode_raw_reads_yuv422_in_both_byte_orders():
    luma = np.tile(np.arange(16, 236, 20, dtype=np.uint8)[:10], (3, 1))  # 3×10, grey ramp
    chroma = np.full(luma.shape, 128, np.uint8)  # neutral: no colour
    chroma[2] = np.tile([200, 128], 5)  # last row: U (blue difference) high, V neutral
    uyvy = np.stack([chroma, luma], axis=-1)  # [U, Y1, V, Y2, ...]: chroma first in each byte pair
    yuyv = np.stack([luma, chroma], axis=-1)
    a = decode_raw(uyvy.tobytes(), width=10, height=3, step=20, encoding="uyvy", name="/t")
    b = decode_raw(yuyv.tobytes(), width=10, height=3, step=20, encoding="yuv422_yuy2", name="/t")
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, decode_raw(uyvy.tobytes(), width=10, height=3, step=20, encoding="YUV422", name="/t"))
    grey = a[:2].astype(int)
    assert a.shape == (3, 10, 3) and (grey.max(-1) - grey.min(-1) <= 1).all()  # neutral chroma: grey
    assert (np.diff(grey[0, :, 1]) > 0).all()  # brighter with Y
    assert (a[2, :, 2].astype(int) - a[2, :, 0] > 40).all()  # high U: bluer than red
    with pytest.raises(InputError, match="/t: uyvy image of odd width 9"):
        decode_raw(bytes(54), width=9, height=3, step=18, encoding="uyvy", name="/t")


@pytest.mark.parametrize("encoding", ["nv12", "nv21", "NV12"])
def test_decode_raw_reads_yuv420_semi_planar(encoding):
    """An image turned to planar YUV 4:2:0 (I420) by OpenCV, its chroma planes interleaved as the
    encoding orders them and the rows padded to a step of 20, reads back as the image."""
    rgb = _smooth_rgb()  # 12×16
    i420 = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420)  # Y (12 rows), U (3 rows of 16), V (3 rows of 16)
    y, u, v = i420[:12], i420[12:15].reshape(6, 8), i420[15:18].reshape(6, 8)
    first, second = (u, v) if encoding.lower() == "nv12" else (v, u)
    chroma = np.stack([first, second], axis=-1).reshape(6, 16)
    padded = np.zeros((18, 20), np.uint8)
    padded[:, :16] = np.vstack([y, chroma])
    out = decode_raw(padded.tobytes(), width=16, height=12, step=20, encoding=encoding, name="/t")
    assert out.shape == rgb.shape and out.dtype == np.uint8
    np.testing.assert_array_equal(out, cv2.cvtColor(i420, cv2.COLOR_YUV2RGB_I420))  # OpenCV's planar reading
    assert np.abs(out.astype(float) - rgb).mean() < 4  # chroma shared by 2×2 pixels of a colour ramp
    swapped = "nv21" if encoding.lower() == "nv12" else "nv12"  # the other chroma order: wrong colours
    wrong = decode_raw(padded.tobytes(), width=16, height=12, step=20, encoding=swapped, name="/t")
    assert np.abs(wrong.astype(float) - rgb).max() > 20
    with pytest.raises(InputError, match="/t: nv12 image of size 16×11: YUV 4:2:0 needs an even width and height"):
        decode_raw(bytes(400), width=16, height=11, step=16, encoding="nv12", name="/t")
    with pytest.raises(DamagedImageError, match="needs more than the 200 bytes given"):  # one message cut short
        decode_raw(bytes(200), width=16, height=12, step=16, encoding="nv12", name="/t")
    with pytest.raises(InputError, match="/t: image of 16×12 rgb8: a step of 16 bytes is shorter than a row of 48") as exc:
        decode_raw(bytes(1000), width=16, height=12, step=16, encoding="rgb8", name="/t")  # a header wrong on every message
    assert not isinstance(exc.value, DamagedImageError)


@pytest.mark.parametrize("encoding, order", [("rgb16", (0, 1, 2)), ("bgr16", (2, 1, 0)), ("16UC3", (2, 1, 0))])
def test_decode_raw_reads_16_bit_colour(encoding, order):
    rgb = _smooth_rgb(scale=256)
    out = decode_raw(rgb[:, :, order].tobytes(), width=16, height=12, step=0, encoding=encoding, name="/t")
    np.testing.assert_array_equal(out, rgb)


def test_transform_tree_relates_two_frames_through_their_common_ancestor():
    tree = TransformTree()
    optical = [-0.5, 0.5, -0.5, 0.5]  # link (x fwd, y left, z up) -> optical (x right, y down, z fwd)
    tree.add("base_link", "cam_link", [1.0, 0.0, 1.5], [0, 0, 0, 1])
    tree.add("cam_link", "left_optical", [0.0, 0.06, 0.0], optical)
    tree.add("cam_link", "right_optical", [0.0, -0.06, 0.0], optical)
    tree.add("odom", "base_link", [5.0, 0.0, 0.0], [0, 0, 0, 1])
    right_in_left = tree.relative("left_optical", "right_optical")
    np.testing.assert_allclose(right_in_left[:3, 3], [0.12, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(right_in_left[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(tree.relative("base_link", "left_optical")[:3, 3], [1.0, 0.06, 1.5])
    assert tree.relative("left_optical", "elsewhere") is None and tree.relative("left_optical", "left_optical") is None


def test_pairer_takes_a_difference_of_exactly_the_tolerance():
    """The tolerance is inclusive: stamps at most ``tolerance_ns`` apart pair."""
    pairer = StereoPairer(tolerance_ns=5)
    assert pairer.push(0, 100, "L1") is None
    assert pairer.push(1, 105, "R1") == (100, "L1", "R1")
    assert pairer.push(1, 206, "R2") is None
    assert pairer.push(0, 200, "L2") is None  # 6 ns apart


def test_pairer_refuses_a_difference_of_half_a_frame_period():
    """Once the periods are known (100 ns here), a pair must differ by less than half the shorter
    one, whatever the tolerance: half a period apart, each image is as near a neighbour's partner."""
    pairer = StereoPairer(tolerance_ns=100)
    for stamp in (0, 100):
        pairer.push(0, stamp, "L")
        assert pairer.push(1, stamp, "R") == (stamp, "L", "R")
    assert pairer.push(0, 200, "L") is None
    assert pairer.push(1, 249, "R") == (200, "L", "R")  # 49 ns: less than half of 100
    assert pairer.push(0, 300, "L") is None
    assert pairer.push(1, 350, "R") is None  # 50 ns: half the period


def test_the_first_transform_seen_for_a_frame_wins():
    tree = TransformTree()
    tree.add("base_link", "cam", [1.0, 0.0, 0.0], [0, 0, 0, 1])
    tree.add("base_link", "cam", [5.0, 0.0, 0.0], [0, 0, 0, 1])
    tree.add("odom", "cam", [9.0, 0.0, 0.0], [0, 0, 0, 1])
    extrinsics = tree.extrinsics("cam")
    assert extrinsics is not None and extrinsics.vehicle_frame_id == "base_link"  # not under odom
    np.testing.assert_allclose(extrinsics.translation, [1.0, 0.0, 0.0])


@pytest.mark.parametrize("path", ["", None, 5])
def test_an_empty_path_or_no_path_is_refused_not_taken_for_the_current_folder(path):
    from terrainmap.sources import open_source

    with pytest.raises(InputError, match="expected the path of a log or folder, got"):
        open_source(path)


def test_a_closed_source_reads_no_more(tmp_path):
    from terrainmap.sim import SimConfig, simulate
    from terrainmap.sources import open_source

    log = tmp_path / "drive.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, width=64, height=48, focal_px=50.0))
    source = open_source(log)
    frames = source.frames()
    next(frames)  # being read when it is closed: the log's reader would read on
    source.close()
    for reading in (frames, source.frames()):
        with pytest.raises(InputError, match=f"{log}: the source is closed; open it again"):
            next(reading)


def test_an_image_or_calibration_of_a_foxglove_schema_without_frame_id_is_in_the_default_frame():
    """Foxglove's RawImage, CompressedImage and CameraCalibration had no frame_id before August
    2022: such messages are in ``camera_optical``, as those whose frame id was left empty."""
    from types import SimpleNamespace

    from terrainmap.sources.messages import frame_id

    assert frame_id(SimpleNamespace(width=8, height=6)) == "camera_optical"  # an AttributeError before
    assert frame_id(SimpleNamespace(frame_id="/cam0")) == "cam0"


def test_a_compressed_depth_image_is_named_as_such_not_taken_for_damage():
    from types import SimpleNamespace

    from terrainmap.sources.messages import image_array

    depth = SimpleNamespace(format="16UC1; compressedDepth png", data=bytes(12) + b"\x89PNG")
    with pytest.raises(InputError, match=r"^/cam/depth: a compressedDepth image \(format '16UC1; compressedDepth png'\) "
                                         "is a depth map, not a camera image"):
        image_array(depth, "sensor_msgs/msg/CompressedImage", "/cam/depth")
