"""Tests of the simulator's logs: MCAP topics and messages, folder layout, the truth reader, the CLI."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

from terrainmap.cli.main import cli
from terrainmap.config import Config
from terrainmap.errors import ConfigError, InputError
from terrainmap.pipeline import PipelineState, process_frame
from terrainmap.ros2defs import SCHEMAS
from terrainmap.sim import SimConfig, open_truth, simulate
from terrainmap.sim.messages import image_array
from terrainmap.sources import open_source
from terrainmap.sources.images import decode_compressed

FRAMES = 3
SMALL = dict(width=96, height=72, focal_px=80.0, frames=FRAMES, seed=5, scene="mounds")


@pytest.fixture(scope="module")
def mcap_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "drive.mcap"
    simulate(path, SimConfig(**SMALL))
    return path


@pytest.fixture(scope="module")
def folder_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "drive"
    simulate(path, SimConfig(format="folder", **SMALL))
    return path


def _decoded(path):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(ch.topic, schema.name, msg.log_time, dec) for schema, ch, msg, dec in reader.iter_decoded_messages()]


def test_mcap_has_the_topics_types_and_counts_of_a_robot_log(mcap_log):
    messages = _decoded(mcap_log)
    counts: dict[tuple[str, str], int] = {}
    for topic, type_name, _, _ in messages:
        counts[(topic, type_name)] = counts.get((topic, type_name), 0) + 1
    expected = {
        ("/stereo/left/image_rect", "sensor_msgs/msg/Image"): FRAMES,
        ("/stereo/right/image_rect", "sensor_msgs/msg/Image"): FRAMES,
        ("/stereo/left/camera_info", "sensor_msgs/msg/CameraInfo"): FRAMES,
        ("/stereo/right/camera_info", "sensor_msgs/msg/CameraInfo"): FRAMES,
        ("/tf", "tf2_msgs/msg/TFMessage"): FRAMES,
        ("/tf_static", "tf2_msgs/msg/TFMessage"): 1,
        ("/truth/terrain", "grid_map_msgs/msg/GridMap"): 1,
        ("/truth/pose", "geometry_msgs/msg/PoseStamped"): FRAMES,
        ("/truth/obstacles", "visualization_msgs/msg/MarkerArray"): FRAMES,
        ("/truth/left/depth", "sensor_msgs/msg/Image"): FRAMES,
        ("/truth/left/label", "sensor_msgs/msg/Image"): FRAMES,
        ("/truth/left/instance", "sensor_msgs/msg/Image"): FRAMES,
    }
    assert counts == expected
    by_topic = {topic: dec for topic, _, _, dec in messages}
    right = by_topic["/stereo/right/camera_info"]
    assert right.p[3] == pytest.approx(-right.p[0] * 0.3)
    assert by_topic["/stereo/left/image_rect"].encoding == "mono8"
    assert by_topic["/truth/left/depth"].encoding == "32FC1"
    static = by_topic["/tf_static"].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in static] == [
        ("base_link", "left_camera_optical"), ("left_camera_optical", "right_camera_optical")]
    assert by_topic["/tf"].transforms[0].header.frame_id == "odom"
    # every message of a frame carries the frame's stamp
    for topic, _, log_time, dec in messages:
        header = getattr(dec, "header", None)
        if header is not None:
            assert header.stamp.sec * 10**9 + header.stamp.nanosec == log_time, topic


def test_static_transforms_and_the_terrain_truth_are_offered_latched(mcap_log):
    from test_sinks_mcap_ros2 import channel_qos

    qos = channel_qos(mcap_log)
    assert len(qos) == 12
    assert {topic for topic, (_, durability, _) in qos.items() if durability == 1} == {"/tf_static", "/truth/terrain"}


def test_terrain_sources_read_the_simulated_logs_with_true_extrinsics(mcap_log, folder_log):
    for path in (mcap_log, folder_log):
        with open_source(path) as source:
            frames = list(source.frames())
        assert len(frames) == FRAMES
        frame = frames[0]
        assert frame.left.shape == (72, 96) and frame.calibration.baseline_m == pytest.approx(0.3)
        truth = open_truth(path)
        np.testing.assert_allclose(frame.extrinsics.rotation, truth.extrinsics.rotation, atol=1e-9)
        np.testing.assert_allclose(frame.extrinsics.translation, [0, 0, 1.8], atol=1e-9)


def test_mcap_log_frames_carry_the_vehicle_pose_and_obstacles_are_tracked_over_ground(mcap_log, folder_log):
    """The log's dynamic tf (odom → base_link) gives each pair its vehicle pose, and the pipeline
    then tracks obstacles in the odometry frame; the folder layout has no odometry."""
    with open_source(mcap_log) as source:
        frames = list(source.frames())
    truth = list(open_truth(mcap_log).frames())
    for frame, true in zip(frames, truth, strict=True):
        np.testing.assert_allclose(frame.vehicle_pose, true.pose_world_base(), atol=1e-6)
    assert np.linalg.norm(frames[-1].vehicle_pose[:3, 3] - frames[0].vehicle_pose[:3, 3]) > 0.5
    config = Config()
    state = PipelineState(config)
    process_frame(frames[0], config, state)
    assert state.tracker.in_world_frame
    with open_source(folder_log) as source:
        assert next(iter(source.frames())).vehicle_pose is None


def test_mcap_and_folder_truth_agree_and_stream_in_stamp_order(mcap_log, folder_log):
    a, b = open_truth(mcap_log), open_truth(folder_log)
    np.testing.assert_array_equal(a.terrain.z, b.terrain.z)
    assert (a.terrain.x_min_m, a.terrain.y_min_m) == pytest.approx((b.terrain.x_min_m, b.terrain.y_min_m))
    frames_a, frames_b = list(a.frames()), list(b.frames())
    assert [f.stamp_ns for f in frames_a] == [f.stamp_ns for f in frames_b]
    assert np.all(np.diff([f.stamp_ns for f in frames_a]) == 100_000_000)
    for fa, fb in zip(frames_a, frames_b, strict=True):
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_array_equal(fa.label, fb.label)
        np.testing.assert_array_equal(fa.instance, fb.instance)
        np.testing.assert_allclose(fa.pose_world_base(), fb.pose_world_base(), atol=1e-9)
        for oa, ob in zip(fa.obstacles, fb.obstacles, strict=True):
            assert (oa.id, oa.kind, oa.shape) == (ob.id, ob.kind, ob.shape)
            np.testing.assert_allclose(oa.center_m, ob.center_m, atol=1e-9)
            np.testing.assert_allclose(oa.size_m, ob.size_m, atol=1e-9)
            assert oa.yaw_rad == pytest.approx(ob.yaw_rad, abs=1e-9)
            assert oa.height_m == pytest.approx(ob.height_m, abs=1e-6)
            np.testing.assert_allclose(oa.velocity_mps, ob.velocity_mps)
    # the vehicle stands on the terrain the truth describes
    for frame in frames_a:
        x, y, z = frame.position_world_base
        assert z == pytest.approx(float(a.height(x, y)), abs=0.05)


def test_same_config_writes_the_same_log(tmp_path):
    config = SimConfig(**{**SMALL, "frames": 2})
    simulate(tmp_path / "a.mcap", config)
    simulate(tmp_path / "b.mcap", config)
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


def test_compressed_images_are_png_of_the_raw_ones(tmp_path, mcap_log):
    path = tmp_path / "c.mcap"
    simulate(path, SimConfig(compressed=True, **SMALL))
    with open_source(path) as compressed, open_source(mcap_log) as raw:
        for c, r in zip(compressed.frames(), raw.frames(), strict=True):
            np.testing.assert_array_equal(c.left, r.left)
            np.testing.assert_array_equal(c.right, r.right)
    topics = {t for t, *_ in _decoded(path)}
    assert "/stereo/left/image_rect/compressed" in topics and "/stereo/left/image_rect" not in topics


def test_truth_is_read_from_a_rosbag2_folder_of_one_mcap(mcap_log, tmp_path):
    """A simulated MCAP moved into a folder, as a rosbag2 lays it out: the same truth; a bag split
    into several MCAP files is refused with a message that says so."""
    from terrainmap.sim.truth import NoTruthError

    bag = tmp_path / "bag"
    bag.mkdir()
    shutil.copy(mcap_log, bag / "bag_0.mcap")
    with open_truth(mcap_log) as direct, open_truth(bag) as in_bag:
        assert [f.stamp_ns for f in in_bag.frames()] == [f.stamp_ns for f in direct.frames()]
        xy = np.array([[0.0, 5.0, 12.5], [0.0, -1.0, 2.0]])
        np.testing.assert_array_equal(in_bag.height(*xy), direct.height(*xy))
        assert in_bag.description == direct.description
    shutil.copy(mcap_log, bag / "bag_1.mcap")
    with pytest.raises(NoTruthError, match="a log in 2 MCAP files"):
        open_truth(bag)


def test_log_without_truth_is_an_input_error_naming_the_topics(tmp_path):
    path = tmp_path / "plain.mcap"
    with open(path, "wb") as f, Writer(f) as writer:
        schema = writer.register_msgdef("sensor_msgs/msg/Image", SCHEMAS["sensor_msgs/msg/Image"])
        image = {"header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": "cam"}, "height": 1, "width": 1,
                 "encoding": "mono8", "is_bigendian": 0, "step": 1, "data": b"\x00"}
        writer.write_message("/camera/image", schema, image, log_time=1)
    with pytest.raises(InputError, match="/truth/terrain.*/truth/left/depth"):
        open_truth(path)
    with pytest.raises(InputError, match="/truth/terrain.*/truth/left/depth"):
        open_truth(tmp_path)  # a folder of one MCAP (a rosbag2): its truth topics are named
    (tmp_path / "folder").mkdir()
    with pytest.raises(InputError, match="missing truth/scene.json"):
        open_truth(tmp_path / "folder")
    with pytest.raises(InputError, match="does not exist"):
        open_truth(tmp_path / "nothing.mcap")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(InputError, match="junk.mcap"):
        open_truth(tmp_path / "junk.mcap")


def test_bad_options_raise_config_errors_naming_them():
    with pytest.raises(ConfigError, match="^SimConfig.frames: must be in 1..100000, got 0$"):
        SimConfig(frames=0).validate()
    with pytest.raises(ConfigError, match="^SimConfig.scene: unknown scene 'moon'"):
        SimConfig(scene="moon").validate()
    with pytest.raises(ConfigError, match="^SimConfig.baseline_m: must be > 0"):
        SimConfig(baseline_m=-1).validate()
    with pytest.raises(ConfigError, match="^SimConfig.texture_detail: must be within"):
        SimConfig(texture_detail=0).validate()
    # A config built in code with a value of the wrong kind, or no config at all
    with pytest.raises(ConfigError, match="SimConfig.color: must be true or false, got 'no'"):
        SimConfig(color="no").validate()
    with pytest.raises(ConfigError, match="SimConfig.frames: must be an integer, got '5'"):
        SimConfig(frames="5").validate()
    with pytest.raises(ConfigError, match="simulate: expected a SimConfig, got NoneType"):
        simulate(Path("unused.mcap"), None)
    # What process would refuse in the log's camera infos is refused before rendering it
    with pytest.raises(ConfigError, match=r"SimConfig.baseline_m: must be within 0.001..100 m, got 0.0005"):
        SimConfig(baseline_m=0.0005).validate()
    with pytest.raises(ConfigError, match=r"SimConfig.focal_px: must be within 1..1e\+06 pixels, got 0.5"):
        SimConfig(focal_px=0.5).validate()
    # ... and so are images too narrow for its stereo matcher (16 px of disparity at least)
    with pytest.raises(ConfigError, match=r"SimConfig.width: must be 32..4096 pixels, got 16"):
        SimConfig(width=16, height=16).validate()
    SimConfig(width=32, height=16).validate()


def test_cli_simulate_writes_a_log_and_guards_existing_output(tmp_path):
    out = tmp_path / "cli.mcap"
    args = ["simulate", str(out), "--scene", "climb", "--frames", "2", "--width", "64", "--height", "48",
            "--focal-px", "50", "--seed", "2"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "wrote 2 frames" in result.output
    truth = open_truth(out)
    assert truth.config.scene == "climb" and truth.config.seed == 2
    assert len(list(truth.frames())) == 2
    again = CliRunner().invoke(cli, args)
    assert again.exit_code != 0 and "--overwrite" in again.output
    assert CliRunner().invoke(cli, [*args, "--overwrite"]).exit_code == 0
    folder = CliRunner().invoke(cli, ["simulate", str(tmp_path / "run"), "--frames", "1", "--width", "32",
                                      "--height", "24", "--focal-px", "25"])
    assert folder.exit_code == 0, folder.output
    assert folder.output.startswith("wrote 1 frame (32×24")  # no progress bar off a terminal
    assert (tmp_path / "run" / "calibration.yaml").is_file() and (tmp_path / "run" / "truth" / "000000.npz").is_file()
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x.mcap"), "--scene", "moon"])
    assert bad.exit_code != 0 and "moon" in bad.output
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x.mcap"), "--frames", "0"])  # the library names the field
    assert bad.exit_code != 0 and "--frames: must be in 1..100000, got 0" in str(bad.exception)
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x.mcap"), "--baseline-m", "0.0005"])
    assert bad.exit_code != 0 and "--baseline-m: must be within 0.001..100 m" in str(bad.exception)
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x.mcap"), "--camera-height-m", "1e6"])  # as process checks
    assert bad.exit_code != 0 and "--camera-height-m: must be at most 100 m, got 1e+06" in str(bad.exception)
    bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "folder"), "--compressed"])
    assert bad.exit_code != 0 and "--compressed: applies to an MCAP log only" in str(bad.exception)
    for option in ("--focal-px", "--baseline-m", "--speed-mps", "--texture-detail"):  # named as the option
        bad = CliRunner().invoke(cli, ["simulate", str(tmp_path / "x.mcap"), option, "nan"])
        assert bad.exit_code != 0 and f"Invalid value for '{option}': 'nan' is not a finite number" in bad.output


def test_bundled_example_is_what_its_readme_command_writes(tmp_path):
    root = Path(__file__).resolve().parents[1]
    readme = (root / "examples" / "README.md").read_text()
    command = next(line for line in readme.splitlines() if line.startswith("terrainmap simulate examples/"))
    args = command.split()[1:]
    example, args[1] = root / args[1], str(tmp_path / "demo.mcap")
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    # Equal up to the last bits of floating point, which move between numpy / OpenCV releases (a
    # new numpy changed ~1 pixel in 100 000 and depths by < 0.03 %): the same log, not the same bytes.
    written, bundled = _decoded(tmp_path / "demo.mcap"), _decoded(example)
    assert [m[:3] for m in written] == [m[:3] for m in bundled]  # topics, types and stamps
    for (topic, _, _, a), (*_, b) in zip(written, bundled):
        if topic.endswith("/compressed"):
            pa, pb = (decode_compressed(m.data, topic) for m in (a, b))
            assert pa.shape == pb.shape and np.mean(pa != pb) < 1e-4, topic
        elif getattr(a, "encoding", None) == "32FC1":
            np.testing.assert_allclose(image_array(a, topic), image_array(b, topic), rtol=1e-3, err_msg=topic)
        else:
            _assert_close(a, b, topic)
    assert example.stat().st_size < 8_000_000  # "a few MB"
    from test_sinks_mcap_ros2 import channel_qos

    assert channel_qos(tmp_path / "demo.mcap") == channel_qos(example)


def _assert_close(a, b, where: str) -> None:
    """Decoded ROS messages equal, floats to 1e-6 relative."""
    if isinstance(a, float):
        assert a == pytest.approx(b, rel=1e-6, abs=1e-9), where
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for x, y in zip(a, b):
            _assert_close(x, y, where)
    elif isinstance(a, (str, int, bytes, bytearray, memoryview)) or a is None:
        assert a == b, where
    else:
        fields = [f for f in dir(a) if not f.startswith("_") and not callable(getattr(a, f))]
        assert fields, f"{where}: nothing to compare in {type(a).__name__}"
        for field in fields:
            _assert_close(getattr(a, field), getattr(b, field), f"{where}.{field}")


def test_the_bundled_example_is_regenerated_byte_for_byte(tmp_path):
    """examples/README.md's command gives examples/offroad_demo.mcap exactly."""
    example = Path(__file__).parent.parent / "examples" / "offroad_demo.mcap"
    out = tmp_path / "demo.mcap"
    args = ["simulate", str(out), "--scene", "mounds", "--frames", "6", "--seed", "7", "--compressed"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == example.read_bytes()


@pytest.mark.parametrize("options", [{"fps": 1e-6, "frames": 2}, {"fps": 1e-300, "frames": 2},
                                     {"frames": 100_000, "speed_mps": 40.0}])
def test_a_drive_too_long_to_hold_is_refused_before_anything_is_built(options):
    """The scene's terrain spans the whole drive: one that would not fit in memory is refused."""
    with pytest.raises(ConfigError, match=r"SimConfig.frames: a drive of .* m .* more than the 5e\+06 the simulator holds"):
        SimConfig(**options).validate()
    SimConfig(frames=5000, speed_mps=4.0).validate()  # 2 km at 0.2 m: built
    with pytest.raises(ConfigError, match=r"SimConfig.terrain_resolution_m: 0.01 m gives a terrain of 9.2e\+07 cells"):
        SimConfig(frames=1, terrain_resolution_m=0.01).validate()  # a short drive, too fine a terrain


def test_a_folder_output_replaces_only_a_simulated_drive(tmp_path):
    """``--overwrite`` replaces an earlier simulation's folder, but never writes into a folder of
    other files (a user's data); the size reported counts only the files written."""
    from terrainmap.errors import InputError
    from terrainmap.sim import simulate

    small = SimConfig(scene="flat", frames=2, width=32, height=24, focal_px=25.0, format="folder")
    run = tmp_path / "run"
    first = simulate(run, small)
    (run / "notes.txt").write_text("x" * 10_000)  # a file of the user's: not counted, not removed
    again = simulate(run, SimConfig(**{**small.__dict__, "frames": 1}))
    assert again["bytes"] < first["bytes"] and (run / "notes.txt").is_file()
    assert again["bytes"] == sum(p.stat().st_size for p in run.rglob("*") if p.is_file() and p.name != "notes.txt")
    assert not (run / "left" / "000001.png").exists()  # the longer run's last frame is gone
    data = tmp_path / "data"
    (data / "left").mkdir(parents=True)
    (data / "left" / "000001.png").write_bytes(b"mine")
    with pytest.raises(InputError, match=r"data: holds files that are not a simulated drive"):
        simulate(data, small)
    assert (data / "left" / "000001.png").read_bytes() == b"mine" and sorted(data.rglob("*")) == [
        data / "left", data / "left" / "000001.png"]


def test_a_walker_that_stops_at_the_roadside_stands_still_in_the_truth(tmp_path):
    """The mounds pedestrian walks at (0, -1.2) m/s until 2.5 s, then stands (ObstacleSpec.turns);
    at 1 frame/s frame 3 is after the stop: both truth readers give its velocity then (the MCAP
    one from the scene description) and the images show it where the truth has it."""
    options = dict(SMALL, frames=4, fps=1.0)
    for path in (tmp_path / "drive.mcap", tmp_path / "drive"):
        simulate(path, SimConfig(**options, format="folder" if path.suffix == "" else "mcap"))
        walker = [next(o for o in f.obstacles if o.kind == "pedestrian") for f in open_truth(path).frames()]
        assert [list(w.velocity_mps) for w in walker] == [[0, -1.2, 0]] * 3 + [[0, 0, 0]]
        assert walker[3].center_m[:2] == pytest.approx([13.0, 5.0 - 1.2 * 2.5])
        assert {round(w.yaw_rad, 6) for w in walker} == {round(-np.pi / 2, 6)}  # it keeps facing its way


def test_the_static_transforms_mount_the_left_camera_and_put_the_right_one_a_baseline_to_its_right(mcap_log):
    """/tf_static: the left camera 1.8 m above base_link, pitched as the rig says; the right camera
    baseline_m along the left camera's +x (right), unrotated (a rectified pair)."""
    from terrainmap.ros2defs import quaternion_from_matrix
    from terrainmap.sim.rig import CameraRig

    static = next(dec for topic, _, _, dec in _decoded(mcap_log) if topic == "/tf_static").transforms
    left, right = (t.transform for t in static)
    assert (left.translation.x, left.translation.y, left.translation.z) == pytest.approx((0.0, 0.0, 1.8))
    q = (left.rotation.x, left.rotation.y, left.rotation.z, left.rotation.w)
    assert q == pytest.approx(tuple(quaternion_from_matrix(CameraRig().rotation_base_cam())))
    assert (right.translation.x, right.translation.y, right.translation.z) == pytest.approx((0.3, 0.0, 0.0))
    assert (right.rotation.x, right.rotation.y, right.rotation.z, right.rotation.w) == (0.0, 0.0, 0.0, 1.0)


def test_a_stereo_frame_without_its_own_truth_is_an_error_not_the_next_frames_truth():
    from terrainmap.sim.truth import TruthFrame, truth_at

    def frame(stamp):
        image = np.zeros((2, 3), np.float32)
        return TruthFrame(0, stamp, np.eye(3), np.zeros(3), [], image, image.astype(np.uint8), image.astype(np.uint8))

    assert truth_at(iter([frame(100), frame(200)]), 200, Path("x.mcap"), (2, 3)).stamp_ns == 200
    with pytest.raises(InputError, match="x.mcap: no ground truth for the stereo frame at stamp 150"):
        truth_at(iter([frame(100), frame(200)]), 150, Path("x.mcap"), (2, 3))


def test_a_folder_log_has_the_stamps_of_every_frame_written_while_it_is_written(tmp_path):
    """timestamps.txt is written line by line: a simulation killed part way (SIGKILL, a power
    cut) leaves a folder whose stamps agree with its images."""
    lines = []

    def after_frame(index):
        lines.append(len((tmp_path / "drive" / "timestamps.txt").read_text().splitlines()))

    simulate(tmp_path / "drive", SimConfig(format="folder", **{**SMALL, "frames": 3}), progress=after_frame)
    assert lines == [1, 2, 3]
