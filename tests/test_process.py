"""End-to-end: `terrainmap process` and the runner on the real KITTI frame and bad input."""

import dataclasses
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from log_copies import rewrite_mcap, rewrite_rosbag2
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from terrainmap import pipeline, runner
from terrainmap.cli.main import cli
from terrainmap.config import Config
from terrainmap.sinks import open_mcap_sink
from terrainmap.sources import open_source


def _grids(path):
    """The foxglove.Grid messages of an output MCAP, decoded independently of the writer."""
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [msg for _, ch, _, msg in reader.iter_decoded_messages() if ch.topic == "/terrainmap/grid"]


def _elevation(grid):
    offset = next(f.offset for f in grid.fields if f.name == "elevation")
    return np.frombuffer(grid.data, np.uint8).reshape(-1, grid.cell_stride)[:, offset : offset + 4].copy().view("<f4")


def test_process_kitti_folder_and_the_rosbag2_logs_give_the_same_layers(shared_data, tmp_path):
    """The folder, both rosbag2 logs and a copy of the raw one in sqlite3 storage, zstd-compressed."""
    rewrite_rosbag2(shared_data / "kitti2015_000005_ros2_raw", tmp_path / "db3", compression="file")
    outputs = []
    for log in (*(shared_data / name for name in ("kitti2015_000005", "kitti2015_000005_ros2_raw",
                                                  "kitti2015_000005_ros2_compressed")), tmp_path / "db3"):
        out = tmp_path / f"{log.name}.mcap"
        result = CliRunner().invoke(cli, ["process", str(log), "-o", str(out)])
        assert result.exit_code == 0, result.output
        assert "processed 1 frame in" in result.output and f"wrote {out}" in result.output
        outputs.append(_grids(out))
    assert all(len(grids) == 1 for grids in outputs)
    reference = _elevation(outputs[0][0])
    for grids in outputs[1:]:
        np.testing.assert_allclose(_elevation(grids[0]), reference, atol=1e-5, equal_nan=True)


def test_refuses_to_overwrite_and_reports_missing_paths(shared_data, tmp_path):
    out = tmp_path / "o.mcap"
    out.write_bytes(b"keep")
    result = CliRunner().invoke(cli, ["process", str(shared_data / "kitti2015_000005"), "-o", str(out)])
    assert result.exit_code != 0 and "--overwrite" in result.output
    assert out.read_bytes() == b"keep"
    result = CliRunner().invoke(cli, ["process", str(tmp_path / "nope"), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2 and "does not exist" in result.output
    result = CliRunner().invoke(cli, ["process", str(shared_data / "kitti2015_000005"), "-o", str(out / "x.mcap")])
    assert result.exit_code == 2 and f"{out} is not a folder" in result.output and "folder " not in result.output


@pytest.mark.parametrize("name", ["negative/rosbag2_talker", "negative/rosbag2_cdr_test", "negative/grid_map_ros1.bag"])
def test_logs_without_stereo_end_with_one_clear_line(shared_data, tmp_path, capsys, name):
    from terrainmap.cli.main import main

    out = tmp_path / "o.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["process", str(shared_data / name), "-o", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("Error: ") and "no stereo" in err[-1]
    assert "Traceback" not in "\n".join(err)


def test_frames_without_terrain_are_counted_and_the_run_goes_on(shared_data, tmp_path):
    with open_source(shared_data / "kitti2015_000005") as source:
        good = next(source.frames())
    blank = type(good)(**{**good.__dict__, "index": 1, "left": np.zeros_like(good.left), "right": np.zeros_like(good.right)})
    again = type(good)(**{**good.__dict__, "index": 2})
    config = Config()
    out = tmp_path / "o.mcap"
    summary = runner.run([good, blank, again], config, [open_mcap_sink(out, config=config)])
    assert summary.frames_done == 2 and summary.frames_failed == 1
    assert set(summary.failures) <= {"no_points_in_area", "too_few_cells", "no_ground"}
    assert len(_grids(out)) == 2


def test_output_is_finalised_when_the_run_fails_part_way(shared_data, tmp_path):
    with open_source(shared_data / "kitti2015_000005") as source:
        good = next(source.frames())

    def frames():
        yield good
        raise KeyboardInterrupt  # e.g. Ctrl-C, or a source that breaks mid-log

    config = Config()
    out = tmp_path / "o.mcap"
    with pytest.raises(KeyboardInterrupt):
        runner.run(frames(), config, [open_mcap_sink(out, config=config)])
    assert len(_grids(out)) == 1  # summary and index written: the file reads back whole


def test_a_config_that_fails_validation_still_finalises_the_open_outputs(tmp_path):
    from terrainmap.errors import ConfigError

    config = Config()
    out = tmp_path / "o.mcap"
    sink = open_mcap_sink(out, config=config)
    config.terrain.degree = 0  # set in code after the sink opened: the run's own check refuses it
    with pytest.raises(ConfigError, match="terrain.degree"):
        runner.run(iter([]), config, [sink])
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None  # closed: summary and index written


def test_a_log_cut_before_its_first_pair_names_the_damage_and_writes_nothing(shared_data, tmp_path, capsys):
    """Half of the KITTI rosbag2 file holds the left image but not the right one: one error line
    that names the damage and the missing pair, and no output file (a log cut after some frames
    keeps them: the next test)."""
    from terrainmap.cli.main import main

    log = tmp_path / "cut.mcap"
    src = next((shared_data / "kitti2015_000005_ros2_raw").glob("*.mcap"))
    log.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(SystemExit) as exc:
        main(["process", str(log), "-o", str(tmp_path / "o.mcap")])
    assert exc.value.code == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"Error: {log}: truncated or corrupt after") and "; before it, no stereo image topics found" in line
    assert not (tmp_path / "o.mcap").exists()


def test_log_cut_after_a_frame_gives_one_error_line_and_that_frame(tmp_path, capsys):
    """The frames before the damage are processed and written; stderr holds the one error line,
    stdout says what was written; ``info`` names the damage."""
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=4, seed=1, width=320, height=240, focal_px=250.0))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: log.stat().st_size * 7 // 10])
    out = tmp_path / "o.mcap"
    from terrainmap.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(["process", str(cut), "-o", str(out)])
    captured = capsys.readouterr()
    assert exc.value.code == 2
    assert captured.err.splitlines() == [f"Error: {cut}: log is truncated or corrupt after 5 messages of "
                                         "/stereo/left/image_rect, /stereo/right/image_rect, /tf, "
                                         "/stereo/left/camera_info, /stereo/right/camera_info (EndOfFile)"]
    assert f"wrote 1 frame to {out} before stopping" in captured.out
    assert len(_grids(out)) == 1
    main(["info", str(cut)])
    captured = capsys.readouterr()
    assert f"damage:             {cut}: truncated or corrupt after" in captured.out and captured.err == ""


def test_a_damaged_chunk_is_skipped_and_the_run_goes_on(tmp_path, capsys, caplog):
    """Bytes changed inside a chunk (a bad disk, a broken copy) fail its CRC: the chunk is skipped
    with a warning naming it, never processed as a frame of wrong pixels, and the frames of the
    other chunks are processed; the summary says what was lost."""
    from terrainmap.cli.main import main
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=4, seed=1, width=320, height=240, focal_px=250.0))
    with open(log, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        left = next(i for i, c in summary.channels.items() if c.topic == "/stereo/left/image_rect")
        chunks = sorted((c for c in summary.chunk_indexes if left in c.message_index_offsets),
                        key=lambda c: c.chunk_start_offset)
        victim = chunks[1]  # frames lie before and after it
        stamps = [m.log_time for _, _, m in reader.iter_messages(topics=["/stereo/left/image_rect"])]
    data = bytearray(log.read_bytes())
    middle = victim.chunk_start_offset + victim.chunk_length // 2
    data[middle : middle + 16] = bytes(b ^ 0x5A for b in data[middle : middle + 16])
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    out = tmp_path / "o.mcap"
    main(["process", str(bad), "-o", str(out)])
    captured = capsys.readouterr()
    where = f"{bad}: chunk at byte {victim.chunk_start_offset}, log time "
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]  # stderr outside pytest
    assert where in warning and "CRC" in warning.upper() and warning.endswith("damaged, skipped")
    assert f"skipped 1 damaged part: {where}" in captured.out
    written = [g.timestamp.seconds * 10**9 + g.timestamp.nanos for g in _grids(out)]
    lost = sorted(set(stamps) - set(written))  # the frames whose left image the chunk held
    assert 1 <= len(lost) < len(stamps) and all(victim.message_start_time <= t <= victim.message_end_time for t in lost)
    assert max(written) > victim.message_end_time  # the run went on past the damage


def test_a_damaged_summary_is_not_trusted_and_the_log_is_read_from_start_to_end(tmp_path, caplog):
    """The summary (index) of an MCAP names its channels; one whose CRC fails (here a topic name
    changed in it) is ignored with a warning and the log is read linearly, chunk CRCs checked;
    ``info --check`` reads it whole and fails all the same, naming the damage."""
    import json
    import struct

    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=2, seed=1, width=64, height=48, focal_px=50.0))
    data = bytearray(log.read_bytes())
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    at = data.index(b"/stereo/left/image_rect", summary_start)
    renamed = data.copy()
    renamed[at + len("/stereo/le")] = ord("F")  # /stereo/leFt/image_rect, in the summary only
    channel = summary_start  # the summary's first Channel record (opcode 0x04; a record: opcode, length, content)
    while data[channel] != 0x04:
        channel += 1 + 8 + struct.unpack_from("<Q", data, channel + 1)[0]
    unschemed = data.copy()
    unschemed[channel + 1 + 8 + 2 + 1] ^= 0xFF  # its schema id names no schema: reading must stop before it
    unparsable = data.copy()
    unparsable[at] ^= 0xFF  # the topic is no longer UTF-8: mcap cannot parse the summary at all
    for damage in (renamed, unschemed, unparsable):
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(bytes(damage))
        with open_source(bad) as source:
            assert source.describe()["left_topic"] == "/stereo/left/image_rect"
            assert len(list(source.frames())) == 2
            assert source.describe()["damage"] == (
                f"{bad}: its summary (the index) is damaged (CRC mismatch); reading the file from start to end")
        assert f"{bad}: its summary (the index) is damaged (CRC mismatch)" in caplog.text
        checked = CliRunner().invoke(cli, ["info", "--json", "--check", str(bad)])  # reads whole, yet is damaged
        assert checked.exit_code == 1
        assert json.loads(checked.output)["check"] == (
            "2 stereo pairs read and decoded, to the end, but the log is damaged (see damage)")


def test_a_message_that_cannot_be_decoded_is_skipped_and_the_run_goes_on(tmp_path, capsys, caplog, monkeypatch):
    """Bytes of one image message that its reader cannot decode (written so, the chunk's CRC
    holds): that frame is lost with a warning naming the topic and time, the others are processed."""
    from terrainmap.cli.main import main
    from terrainmap.errors import InputError
    from terrainmap.sim import SimConfig, simulate
    from terrainmap.sources import readers

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=160, height=120, focal_px=125.0))
    seen = []

    def garble_second_left(topic: str, data: bytes) -> bytes:
        if topic == "/stereo/left/image_rect":
            seen.append(topic)
            if len(seen) == 2:
                return data[:4] + b"\xff" * 40  # a CDR header, then no readable Image
        return data

    bad = rewrite_mcap(log, tmp_path / "bad.mcap", garble_second_left)
    everyone = rewrite_mcap(log, tmp_path / "wrong_type.mcap",
                            lambda topic, data: data[:4] + b"\xff" * 40 if topic == "/stereo/left/image_rect" else data)
    monkeypatch.setattr(readers, "_MAX_UNDECODABLE", 3)  # a channel whose every message fails is no damage
    with pytest.raises(InputError, match=r"topic /stereo/left/image_rect: 3 messages in a row are not a readable "
                                         "sensor_msgs"), open_source(everyone) as source:
        list(source.frames())
    caplog.clear()
    out = tmp_path / "o.mcap"
    main(["process", str(bad), "-o", str(out)])
    captured = capsys.readouterr()
    warning, unpaired = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "1 of 5 image messages had no partner" in unpaired  # the lost image's right one
    assert warning.startswith(f"{bad}: /stereo/left/image_rect message at log time ") and \
        "not a readable sensor_msgs/msg/Image" in warning
    assert "processed 2 frames" in captured.out and "skipped 1 damaged part: " in captured.out
    assert len(_grids(out)) == 2


def test_unusable_calibration_is_reported(shared_data, tmp_path, capsys):
    from terrainmap.cli.main import main

    folder = tmp_path / "kitti"
    shutil.copytree(shared_data / "kitti2015_000005", folder)
    calib = next((folder / "calib_cam_to_cam").glob("*.txt"))
    lines = calib.read_text().splitlines()
    # Give the right camera the left camera's projection: zero baseline.
    p2 = next(line for line in lines if line.startswith("P_rect_02")).split(":", 1)[1]
    calib.write_text("\n".join(f"P_rect_03:{p2}" if line.startswith("P_rect_03") else line for line in lines))
    with pytest.raises(SystemExit) as exc:
        main(["process", str(folder), "-o", str(tmp_path / "o.mcap")])
    assert exc.value.code == 2
    assert "baseline" in capsys.readouterr().err


@pytest.mark.parametrize("poses", ["tf", "estimated, then another camera"])
def test_overlapped_runner_gives_the_sequential_results(tmp_path, keep_sink, poses):
    """The runner matches frames in two worker threads ahead of the main thread; its results are
    those of process_frame frame by frame, also where the camera pose is estimated from the first
    frame (the frames after it wait for that pose) and where a new calibration part way starts
    the pose afresh, and OpenCV's thread count is given back afterwards."""
    import cv2

    from terrainmap.pipeline import PipelineState, process_frame
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="mounds", frames=6, seed=2, width=320, height=240, focal_px=250.0))

    def frames():
        with open_source(log) as source:
            for frame in source.frames():
                if poses != "tf":
                    scene_b = frame.index >= 3  # another camera from the fourth frame on
                    calibration = dataclasses.replace(frame.calibration, source="scene_b/calib.txt") if scene_b else frame.calibration
                    frame = dataclasses.replace(frame, extrinsics=None, calibration=calibration)
                yield frame

    config = Config()
    threads = cv2.getNumThreads()
    keep = keep_sink
    summary = runner.run(frames(), config, [keep])
    assert cv2.getNumThreads() == threads
    state = PipelineState(config)
    expected = [process_frame(frame, config, state) for frame in frames()]
    assert summary.frames_done == 6
    assert summary.extrinsics is keep.results[-1].extrinsics  # the camera pose `process` reports
    sources = {r.extrinsics.source for r in keep.results}
    assert sources == ({"tf"} if poses == "tf" else {"estimated"})
    for got, want in zip(keep.results, expected, strict=True):
        # the stereo rig reaches the terrain stage (eq. 1's noise discount, the labelling floors)
        assert got.grid.camera is not None and got.grid.height_per_px is not None
        np.testing.assert_array_equal(got.extrinsics.translation, want.extrinsics.translation)
        np.testing.assert_array_equal(got.point_labels, want.point_labels)
        np.testing.assert_array_equal(got.layers["elevation"], want.layers["elevation"])
        assert [o.track_id for o in got.obstacles] == [o.track_id for o in want.obstacles]
    if poses != "tf":  # each camera's pose estimated on its own first frame
        first, second = keep.results[0].extrinsics, keep.results[3].extrinsics
        assert all(r.extrinsics is first for r in keep.results[:3])
        assert all(r.extrinsics is second for r in keep.results[3:]) and second is not first


def test_frames_that_reuse_one_pair_of_buffers_give_the_sequential_results(small_log, keep_sink):
    """A caller's iterator that fills the same two arrays for every frame, as camera drivers do:
    the runner reads frames ahead of those it matches and writes, so it keeps its own copies; the
    results (the images written included) are those of process_frame frame by frame."""
    from terrainmap.pipeline import PipelineState, process_frame

    with open_source(small_log) as source:
        originals = list(source.frames())

    def reusing():
        left, right = np.empty_like(originals[0].left), np.empty_like(originals[0].right)
        for k, frame in enumerate(originals * 2):  # four frames, the second two a second later
            left[...], right[...] = frame.left, frame.right
            yield dataclasses.replace(frame, left=left, right=right, stamp_ns=frame.stamp_ns + k // 2 * 10**9)

    config = Config()
    runner.run(reusing(), config, [keep_sink])
    state = PipelineState(config)
    expected = [process_frame(dataclasses.replace(f, left=f.left.copy(), right=f.right.copy()), config, state)
                for f in reusing()]
    assert len(keep_sink.results) == 4
    for got, want, frame in zip(keep_sink.results, expected, originals * 2, strict=True):
        np.testing.assert_array_equal(got.image, frame.left)
        np.testing.assert_array_equal(got.point_labels, want.point_labels)
        np.testing.assert_array_equal(got.layers["elevation"], want.layers["elevation"])


def test_a_none_among_the_frames_is_an_error_not_their_end(small_log, keep_sink):
    from terrainmap.errors import InputError

    with open_source(small_log) as source:
        first, second = list(source.frames())
    with pytest.raises(InputError, match="frame must be a StereoFrame, got NoneType"):
        runner.run([first, None, second], Config(), [keep_sink])
    assert len(keep_sink.results) == 1


def test_the_runner_waits_for_a_pose_estimated_after_a_failed_frame_and_stops_its_workers_when_a_sink_fails(
    tmp_path, keep_sink
):
    """A blank first frame fails to give a pose (counted); the second estimates it and the frames
    after it use that pose. A sink failing part way ends the run with no matching thread left,
    OpenCV's thread count given back and at most MATCH_WORKERS frames read past the failure; runs
    that overlap (in threads) give it back when the last of them ends."""
    import threading

    import cv2

    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="mounds", frames=6, seed=2, width=320, height=240, focal_px=250.0))
    with open_source(log) as source:
        frames = [dataclasses.replace(f, extrinsics=None) for f in source.frames()]
    blank = np.zeros_like(frames[0].left)
    frames[0] = dataclasses.replace(frames[0], left=blank, right=blank)
    threads = cv2.getNumThreads()
    summary = runner.run(frames, Config(), [keep_sink])
    assert dict(summary.failures) == {"no_ground": 1} and summary.frames_done == 5
    poses = {id(r.extrinsics) for r in keep_sink.results}
    assert len(poses) == 1 and keep_sink.results[0].extrinsics.source == "estimated"

    read = []

    def counted():
        for frame in frames[1:]:
            read.append(frame.index)
            yield frame

    class Failing(type(keep_sink)):
        def write(self, frame, result):
            if frame.index == 2:
                raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        runner.run(counted(), Config(), [Failing()])
    assert max(read) <= 2 + runner.MATCH_WORKERS
    assert not [t for t in threading.enumerate() if t.name.startswith("terrainmap-match")]
    assert cv2.getNumThreads() == threads

    first, second = runner._OPENCV_THREADS.divided(2), runner._OPENCV_THREADS.divided(2)  # two runs' turns
    first.__enter__()
    second.__enter__()
    assert cv2.getNumThreads() == max(1, threads // 2)
    first.__exit__(None, None, None)  # the first run ends before the second
    assert cv2.getNumThreads() == max(1, threads // 2)
    second.__exit__(None, None, None)
    assert cv2.getNumThreads() == threads


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    from terrainmap.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("small") / "sim.mcap"
    simulate(path, SimConfig(scene="flat", frames=2, seed=1, width=320, height=240, focal_px=250.0))
    return path


def test_a_state_given_another_config_tracks_with_that_configs_settings(small_log):
    """A PipelineState built for one config and given another: the tracking (confirmation after
    one hit here) and the area are the config's of the call, not the state's."""
    import dataclasses

    from terrainmap.pipeline import PipelineState, process_frame

    with open_source(small_log) as source:
        frame = next(source.frames())
    eager = dataclasses.replace(Config(), tracking=dataclasses.replace(Config().tracking, confirm_hits=1))
    alone = process_frame(frame, eager, PipelineState(eager))
    borrowed = process_frame(frame, eager, PipelineState(Config()))
    assert sum(o.confirmed for o in alone.obstacles) > 0
    assert [(o.track_id, o.confirmed) for o in borrowed.obstacles] == [(o.track_id, o.confirmed) for o in alone.obstacles]
    first = process_frame(frame, Config(), PipelineState(Config()))  # confirmed after 3 hits: none yet
    assert first.stats["detections"] == len(first.obstacles) > 0 and first.stats["obstacles"] == 0
    assert alone.stats["obstacles"] == sum(o.confirmed for o in alone.obstacles)


def test_a_new_calibration_starts_the_camera_pose_and_the_tracks_afresh(small_log):
    """A folder of unrelated scenes (KITTI, Middlebury) gives each scene its calibration file: the
    pose estimated on one scene and its tracks must not carry over to the next."""
    import dataclasses

    from terrainmap.pipeline import PipelineState, process_frame

    with open_source(small_log) as source:
        frames = [dataclasses.replace(f, extrinsics=None) for f in source.frames()]  # estimated
    config, state = Config(), PipelineState(Config())
    first = [process_frame(frame, config, state) for frame in frames]
    assert first[0].extrinsics.source == "estimated"
    assert first[0].extrinsics.camera_frame_id == frames[0].frame_id == "left_camera_optical"
    assert any(o.confirmed for o in first[1].obstacles)
    wrong = state.extrinsics = dataclasses.replace(state.extrinsics, translation=np.array([0.0, 0.0, 9.0]))
    scene_b = dataclasses.replace(
        frames[1], index=2, stamp_ns=frames[1].stamp_ns + 10**8,
        calibration=dataclasses.replace(frames[1].calibration, source="scene_b/calib.txt"),
    )
    again = process_frame(scene_b, config, state)
    assert again.extrinsics is not wrong and again.extrinsics.translation[2] < 3
    assert again.obstacles and not any(o.confirmed for o in again.obstacles)  # seen once so far


@pytest.mark.parametrize("rotation, translation", [(np.eye(3) * 5, [0, 0, 1.5]), (np.full((3, 3), np.nan), [0, 0, 1.5]),
                                                   (np.eye(3), [0, 1.5]), (np.eye(3).ravel(), [0, 0, 1.5]),
                                                   (np.eye(3), [[0], [0], [1.5]]), (np.eye(3)[None], [0, 0, 1.5])])
def test_a_frame_whose_extrinsics_are_no_rigid_motion_is_refused(small_log, rotation, translation):
    import dataclasses

    from terrainmap.errors import CalibrationError
    from terrainmap.pipeline import PipelineState, process_frame
    from terrainmap.types import Extrinsics

    with open_source(small_log) as source:
        frame = next(iter(source.frames()))
    frame = dataclasses.replace(frame, extrinsics=Extrinsics(np.asarray(rotation), np.asarray(translation, float)))
    with pytest.raises(CalibrationError, match=rf"^{small_log} .*\(pair 0\): extrinsics \("):
        process_frame(frame, Config(), PipelineState(Config()))


def test_outputs_never_replace_the_input_or_each_other(small_log, tmp_path):
    log = tmp_path / "in.mcap"
    shutil.copy(small_log, log)
    before = log.read_bytes()
    for extra in (["-o", str(log)], ["-o", str(tmp_path / "." / "in.mcap")]):
        result = CliRunner().invoke(cli, ["process", str(log), "--overwrite", *extra])
        assert result.exit_code == 2 and "would overwrite the input" in result.output, extra
    for option, suffix in (("-o", ".mcap"), ("--rrd", ".rrd")):  # each output's own suffix: no other file by a slip
        result = CliRunner().invoke(cli, ["process", str(log), "--overwrite", option, str(tmp_path / "notes.txt")])
        assert result.exit_code == 2 and f"notes.txt must end in {suffix}" in result.output, option
    (tmp_path / "in.rrd").symlink_to(log)
    result = CliRunner().invoke(cli, ["process", str(log), "--overwrite", "--rrd", str(tmp_path / "in.rrd")])
    assert result.exit_code == 2 and "would overwrite the input" in result.output
    folder = tmp_path / "bag"
    folder.mkdir()
    shutil.copy(small_log, folder / "bag_0.mcap")
    result = CliRunner().invoke(cli, ["process", str(folder), "-o", str(folder / "bag_0.mcap"), "--overwrite"])
    assert result.exit_code == 2 and "inside the input folder" in result.output
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  relative_file_paths: [bag_0.mcap]\n")
    result = CliRunner().invoke(cli, ["bench", "--log", str(folder / "metadata.yaml"), "--json", str(folder / "b.json")])
    assert result.exit_code == 2 and "inside the input folder" in result.output  # the metadata stands for the bag
    (tmp_path / "hard.mcap").hardlink_to(log)
    result = CliRunner().invoke(cli, ["process", str(log), "-o", str(tmp_path / "hard.mcap"), "--overwrite"])
    assert result.exit_code == 2 and "would overwrite the input" in result.output  # a hard link too
    config = tmp_path / "my.toml"
    config.write_text("[terrain]\ndegree = 3\n")
    (tmp_path / "my.mcap").symlink_to(config)
    result = CliRunner().invoke(cli, ["process", str(log), "--config", str(config), "-o", str(tmp_path / "my.mcap"),
                                      "--overwrite"])
    assert result.exit_code == 2 and "would overwrite the input" in result.output
    result = CliRunner().invoke(cli, ["eval", "accuracy", str(log), "--json", str(log)])
    assert result.exit_code == 2 and "--json" in result.output and "must end in .json" in result.output
    (tmp_path / "o.rrd").symlink_to(tmp_path / "o.mcap")
    result = CliRunner().invoke(cli, ["process", str(log), "-o", str(tmp_path / "o.mcap"), "--rrd", str(tmp_path / "o.rrd")])
    assert result.exit_code == 2 and "same file" in result.output
    assert log.read_bytes() == before


def test_options_or_a_selection_that_fail_before_the_first_frame_leave_an_earlier_output_alone(small_log, tmp_path):
    out = tmp_path / "o.mcap"
    out.write_bytes(b"an earlier run's output")
    for extra, message in ((["--start", "5", "--end", "1"], "end_s (--end) 1.0 s is before start_s (--start) 5.0 s"),
                           (["--start", "500"], "--start/--end select none of the 2 stereo pairs read, up to "
                                                "0.100 s from the first (--start and --end count from it)"),
                           (["--start", "0.01", "--end", "0.02"], "--start/--end select none of the 2 stereo pairs "
                                                                  "read, up to 0.100 s from the first"),
                           (["--start", "-1"], "-1.0 is not in the range x>=0"),
                           (["--pair-tolerance-ms", "1e308"], "1e+308 is not in the range 0<=x<=3600000")):
        result = CliRunner().invoke(cli, ["process", str(small_log), "-o", str(out), "--overwrite", *extra])
        assert result.exit_code != 0 and message in result.output + str(result.exception), extra
    assert out.read_bytes() == b"an earlier run's output"
    if Path("/proc").is_dir():  # an --rrd that cannot be created (Linux refuses new files in /proc)
        rrd = "/proc/terrainmap-test.rrd"
        result = CliRunner().invoke(cli, ["process", str(small_log), "-o", str(out), "--overwrite", "--rrd", rrd])
        assert result.exit_code == 2 and f"cannot write {rrd}" in result.output
        assert out.read_bytes() == b"an earlier run's output"


def test_a_second_signal_waits_while_outputs_are_open():
    """A quick double Ctrl-C: the first asks the run to stop, a second one stops it at once only
    while no output is open, so none is left unfinished."""
    import signal

    from terrainmap.cli.options import GracefulStop

    previous = _in_foreground()
    try:
        # raise_signal delivers to this thread and runs the handler before it returns; os.kill may hand
        # the signal to another thread of the process (OpenCV's, an executor's), its handler a moment later.
        with GracefulStop() as stop:
            signal.raise_signal(signal.SIGINT)
            assert stop.requested
            with stop.outputs_open():
                signal.raise_signal(signal.SIGTERM)  # ignored: outputs are being written
                with pytest.raises(KeyboardInterrupt):
                    stop.check()  # between frames: the run stops there
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def test_a_signal_the_process_was_started_ignoring_stays_ignored():
    """A run started as `cmd &` from a script ignores SIGINT, as the shell asked; GracefulStop
    does not take it over (nor give it back changed)."""
    import signal

    from terrainmap.cli.options import GracefulStop

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with GracefulStop() as stop:
            signal.raise_signal(signal.SIGINT)
            assert not stop.requested
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_an_output_that_is_no_regular_file_is_refused(small_log, tmp_path):
    """Writing to a FIFO would block until a reader came: refused before any work."""
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    result = CliRunner().invoke(cli, ["process", str(small_log), "-o", str(fifo), "--overwrite"])
    assert result.exit_code == 2 and "neither a regular file nor a folder" in result.output
    result = CliRunner().invoke(cli, ["simulate", str(fifo), "--frames", "1"])  # not "Not a directory"
    assert result.exit_code == 2 and "neither a regular file nor a folder" in result.output
    log = shutil.copy(small_log, tmp_path / "run.mcap")
    os.mkfifo(tmp_path / "run.terrain.mcap")  # the default output: its probe would block too
    result = CliRunner().invoke(cli, ["process", str(log), "--overwrite"])
    assert result.exit_code == 2 and "run.terrain.mcap exists and is neither a regular file nor a folder" in result.output
    os.unlink(tmp_path / "run.terrain.mcap")
    (tmp_path / "run.terrain.mcap").mkdir()
    result = CliRunner().invoke(cli, ["process", str(log), "--overwrite"])
    assert result.exit_code == 2 and "run.terrain.mcap (the default output) is a folder; name a file with -o" in result.output


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_output_folder_is_probed_for_writing_too():
    """simulate writes a folder log into an existing folder: one where no file can be made is
    refused at once, before the scene is built (Linux makes no files in /proc/self); and a FIFO
    is named as what it is."""
    from terrainmap.cli.options import Failed, writable

    with pytest.raises(Failed, match="cannot write /proc/self: "):
        writable(Path("/proc/self"))
    result = CliRunner().invoke(cli, ["simulate", "/proc/self", "--overwrite", "--frames", "5000"])
    assert result.exit_code == 2 and "cannot write /proc/self: " in result.output


@pytest.mark.parametrize("stop", ["SIGTERM", "SIGXCPU"])
def test_a_terminated_run_still_finalises_its_output(small_log, tmp_path, stop):
    """SIGTERM (a supervisor stopping the job) and SIGXCPU (a CPU time limit reached) end the run
    like Ctrl-C: the MCAP is readable."""
    import signal

    stop = getattr(signal, stop, None)
    if stop is None:
        pytest.skip("no such signal here")
    import subprocess
    import sys
    import time

    log = tmp_path / "long.mcap"
    from terrainmap.sim import SimConfig, simulate

    simulate(log, SimConfig(scene="flat", frames=40, seed=1, width=320, height=240, focal_px=250.0))
    out = tmp_path / "o.mcap"
    code = "from terrainmap.cli.main import main; main()"
    proc = subprocess.Popen([sys.executable, "-c", code, "process", str(log), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not (out.exists() and out.stat().st_size > 0) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(stop)
    proc.communicate(timeout=60)
    assert proc.returncode == 128 + stop  # what a shell or supervisor expects of a terminated job
    with open(out, "rb") as stream:
        assert make_reader(stream).get_summary() is not None  # finished: summary and index written


_ON_A_TERMINAL = """
import os, pty, select, signal, sys, time
try:
    pid, fd = pty.fork()  # the child's terminal is the pty; closing its other end hangs it up
except OSError:  # no pseudo-terminal to be had here
    sys.exit(77)
if pid == 0:
    signal.signal(signal.SIGHUP, signal.SIG_DFL)  # as in a terminal's session, also where the tests run under nohup
    os.execv(sys.executable, [sys.executable, "-c", "from terrainmap.cli.main import run; run()", *sys.argv[1:]])
seen, deadline = b"", time.monotonic() + 120
while b"frames/s" not in seen and time.monotonic() < deadline:
    if select.select([fd], [], [], 0.1)[0]:
        try:
            seen += os.read(fd, 4096)
        except OSError:
            break
os.close(fd)
sys.exit(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))
"""


@pytest.mark.skipif(not hasattr(signal, "SIGHUP") or not Path("/dev/ptmx").exists(), reason="needs SIGHUP and ptys")
def test_a_hang_up_ends_the_run_like_ctrl_c_with_its_output_finalised(tmp_path):
    """The terminal closes or the SSH session drops part way (SIGHUP): the run stops between
    frames with exit code 129 and a finished MCAP, its last messages not failing (EIO) on the
    terminal that is gone."""
    import subprocess
    import sys

    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "long.mcap"
    simulate(log, SimConfig(scene="flat", frames=40, seed=1, width=320, height=240, focal_px=250.0))
    out = tmp_path / "o.mcap"
    done = subprocess.run([sys.executable, "-c", _ON_A_TERMINAL, "process", str(log), "-o", str(out)], timeout=180)
    if done.returncode == 77:
        pytest.skip("no pseudo-terminal can be opened here")
    assert done.returncode == 128 + signal.SIGHUP
    with open(out, "rb") as stream:
        assert make_reader(stream).get_summary() is not None  # finished: summary and index written
    assert 0 < len(_grids(out)) < 40


def test_a_stamp_outside_the_mcap_range_ends_the_run_with_the_output_readable(small_log, tmp_path):
    import dataclasses

    from terrainmap.errors import InputError

    with open_source(small_log) as source:
        first, second = list(source.frames())
    out = tmp_path / "o.mcap"
    sink = open_mcap_sink(out, "foxglove", config=Config())
    with pytest.raises(InputError, match="frame 1 has stamp -5 ns"):
        runner.run([first, dataclasses.replace(second, stamp_ns=-5)], Config(), [sink])
    assert len(_grids(out)) == 1  # the good frame, finalised


def test_a_log_whose_every_pair_is_damaged_says_so(tmp_path, monkeypatch, capsys):
    from test_sources_logs import write_ros2_log

    from terrainmap.cli.main import main
    from terrainmap.errors import DamagedImageError
    from terrainmap.sources import messages

    def damaged(msg, msg_type, topic):
        raise DamagedImageError(f"{topic}: cannot decode the compressed image (9 bytes)")

    log = write_ros2_log(tmp_path / "run.mcap", n=2)
    monkeypatch.setattr(messages, "image_array", damaged)
    with pytest.raises(SystemExit):
        main(["process", str(log), "-o", str(tmp_path / "o.mcap")])
    (line,) = capsys.readouterr().err.strip().splitlines()[-1:]
    assert line.startswith(f"Error: no frame of {log} could be processed (every one of the 2 stereo pairs selected "
                           f"is damaged; 2 damaged parts skipped, the first: {log}: stereo pair at ")
    assert not (tmp_path / "o.mcap").exists()


def test_a_summary_names_the_first_damaged_parts_and_counts_the_rest(tmp_path, monkeypatch, capsys):
    """Every other pair of an 8-pair log cannot be decoded: the run goes on, and its summary stays
    one line that names three of the four damaged parts and counts the other."""
    from terrainmap.cli.main import main
    from terrainmap.errors import DamagedImageError
    from terrainmap.sim import SimConfig, simulate
    from terrainmap.sources import messages

    decode, calls = messages.image_array, []

    def every_other_pair_damaged(msg, msg_type, topic):
        calls.append(topic)
        if "left" in topic and sum("left" in t for t in calls) % 2 == 0:
            raise DamagedImageError(f"{topic}: cannot decode the compressed image (9 bytes)")
        return decode(msg, msg_type, topic)

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=8, seed=1, width=320, height=240, focal_px=250.0))
    monkeypatch.setattr(messages, "image_array", every_other_pair_damaged)
    main(["process", str(log), "-o", str(tmp_path / "o.mcap")])
    (line,) = [s for s in capsys.readouterr().out.splitlines() if s.startswith("skipped ")]
    assert line.startswith(f"skipped 4 damaged parts: {log}: stereo pair at "), line
    assert line.count(f"{log}: stereo pair at ") == 3 and line.endswith("; and 1 more (warned as they were met)")
    assert len(_grids(tmp_path / "o.mcap")) == 4


def test_a_log_whose_images_never_pair_says_so(tmp_path, capsys):
    """Right images stamped 15 ms after the left (beyond the 10 ms tolerance): the error names the
    tolerance, not the selection."""
    from test_sources_logs import write_ros2_log

    from terrainmap.cli.main import main

    log = write_ros2_log(tmp_path / "run.mcap", n=3, right_offset_ns=15_000_000)
    with pytest.raises(SystemExit):
        main(["process", str(log), "-o", str(tmp_path / "o.mcap")])
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"Error: no frame of {log} could be processed (no left and right images whose stamps agree within "
        "--pair-tolerance-ms)")


def test_a_run_where_every_frame_fails_says_its_output_holds_no_frame(small_log, tmp_path):
    """The output is finalised and readable all the same, and the error names the reasons and says
    what the first frame that failed for the commonest one said (a setting to change, often)."""
    out = tmp_path / "o.mcap"
    result = CliRunner().invoke(cli, ["process", str(small_log), "-o", str(out), "--set", "grid.x_min_m=-100"])
    assert result.exit_code == 2
    assert f"wrote {out} (no frame in it)" in result.output
    why = "no_points_in_area ×2; frame 0: no finite point lies in the grid area between its height limits"
    assert f"no frame of {small_log} could be processed ({why}" in result.output
    assert "processed 0 frames, 2 failed (no_points_in_area ×2) in " in result.output  # the error line says why
    assert "frames/s" not in result.output  # no rate for no frame
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None


class _ClosingSink:
    """A sink that records its close and may fail it."""

    def __init__(self, failure: Exception | None = None) -> None:
        self.failure, self.closed = failure, False

    def write(self, frame, result) -> None:
        pass

    def close(self) -> None:
        self.closed = True
        if self.failure is not None:
            raise self.failure


def test_every_sink_is_closed_when_one_fails_to_close_and_the_first_failure_is_raised():
    sinks = [_ClosingSink(OSError("first disk full")), _ClosingSink(OSError("second")), _ClosingSink()]
    with pytest.raises(OSError, match="first disk full"):
        runner.run(iter([]), Config(), sinks)
    assert [sink.closed for sink in sinks] == [True, True, True]


def test_the_throughput_counts_the_failed_frames_too():
    summary = runner.RunSummary(frames_done=3, wall_s=2.0)
    summary.failures["no_ground"] += 1
    assert (summary.frames_failed, summary.fps) == (1, 2.0)


def test_the_latest_stamp_an_output_holds_is_accepted_and_one_more_refused():
    from terrainmap.errors import InputError
    from terrainmap.types import StereoCalibration, StereoFrame

    image = np.zeros((3, 4), np.uint8)
    calibration = StereoCalibration(width=4, height=3, fx=1.0, fy=1.0, cx=2.0, cy=1.5, baseline_m=0.5)
    pipeline.check_stamp(StereoFrame(0, 2**63 - 1, image, image, calibration))  # 2262-04-11
    with pytest.raises(InputError, match="frame 1 has stamp 9223372036854775808 ns, outside 1970–2262"):
        pipeline.check_stamp(StereoFrame(1, 2**63, image, image, calibration, source="log.mcap"))


def test_an_output_in_a_subfolder_of_the_input_folder_is_refused(small_log, tmp_path, monkeypatch):
    from terrainmap.cli import options

    folder = tmp_path / "bag"
    (folder / "sub").mkdir(parents=True)
    shutil.copy(small_log, folder / "bag_0.mcap")
    probed = []
    monkeypatch.setattr(options, "writable", probed.append)  # the probe makes and removes a file there
    result = CliRunner().invoke(cli, ["process", str(folder), "-o", str(folder / "sub" / "o.mcap")])
    assert result.exit_code == 2 and "lies inside the input folder" in result.output
    assert not (folder / "sub" / "o.mcap").exists() and probed == []  # not even probed for writing


def test_process_frame_refuses_a_negative_stamp_naming_the_frame():
    """A library caller's frame gets the runner's check: the tracker would take a negative stamp."""
    from terrainmap.bench import sim_frame
    from terrainmap.errors import InputError
    from terrainmap.pipeline import PipelineState, process_frame

    frame = dataclasses.replace(sim_frame(), stamp_ns=-1, source="mine.mcap")
    with pytest.raises(InputError, match="^mine.mcap: frame 0 has stamp -1 ns, outside 1970–2262"):
        process_frame(frame, Config(), PipelineState(Config()))


def _in_foreground():
    """SIGINT and SIGTERM handled as in a terminal (a test run in the background inherits SIGINT
    ignored, which GracefulStop leaves so); returns the handlers to put back."""
    import signal

    foreground = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    return {s: signal.signal(s, handler) for s, handler in foreground.items()}


def test_signals_before_the_outputs_open_or_while_they_close_stop_the_run_as_interrupted(
        small_log, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the first frame is read: no output is opened, so an earlier one is kept; Ctrl-C
    while the outputs are closed: they are whole, and the exit code still says interrupted."""
    import signal

    from terrainmap.cli.main import main
    from terrainmap.sinks.base import McapSink
    from terrainmap.sources.base import Source

    out = tmp_path / "o.mcap"
    out.write_bytes(b"an earlier run's output")
    frames, close = Source.frames, McapSink.close

    def interrupted_reading(self, *args, **kwargs):
        signal.raise_signal(signal.SIGINT)
        yield from frames(self, *args, **kwargs)

    def interrupted_closing(self):
        signal.raise_signal(signal.SIGTERM)
        close(self)

    previous = _in_foreground()
    try:
        with monkeypatch.context() as patch:
            patch.setattr(Source, "frames", interrupted_reading)
            with pytest.raises(SystemExit) as exc:
                main(["process", str(small_log), "-o", str(out), "--overwrite"])
        assert exc.value.code == 130 and out.read_bytes() == b"an earlier run's output"
        assert capsys.readouterr().err.splitlines()[-1] == "Interrupted."
        monkeypatch.setattr(McapSink, "close", interrupted_closing)
        with pytest.raises(SystemExit) as exc:
            main(["process", str(small_log), "-o", str(out), "--overwrite"])
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    captured = capsys.readouterr()
    assert exc.value.code == 143 and captured.err.splitlines()[-1] == "Interrupted."
    assert f"wrote {out}" in captured.out and len(_grids(out)) == 2


def test_outputs_that_stop_at_different_frames_are_each_said(small_log, tmp_path, monkeypatch, capsys):
    """The recording fails in the second frame, after the MCAP has written it: the line says what
    each output holds."""
    from terrainmap.cli.main import main
    from terrainmap.sinks import rerun_recording

    write = rerun_recording.RerunSink.write

    def fails_second(self, frame, result):
        if frame.index:
            raise RuntimeError("no more")
        write(self, frame, result)

    monkeypatch.setattr(rerun_recording.RerunSink, "write", fails_second)
    out, rrd = tmp_path / "o.mcap", tmp_path / "o.rrd"
    with pytest.raises(RuntimeError, match="no more"):
        main(["process", str(small_log), "-o", str(out), "--rrd", str(rrd)])
    assert f"wrote 2 frames to {out} and 1 to {rrd} before stopping" in capsys.readouterr().out
    assert len(_grids(out)) == 2


def test_images_that_cannot_be_matched_are_refused_before_any_output_is_written(tmp_path, capsys):
    """8 px wide images and a 16 px disparity range: the first pair's calibration is refused as it is
    read, naming the file, and no output is left behind (an earlier one would stay as it was)."""
    from test_sources_folders import generic_folder

    from terrainmap.cli.main import main

    folder, out = generic_folder(tmp_path / "pairs", n=2), tmp_path / "o.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["process", str(folder), "-o", str(out)])
    assert exc.value.code == 2 and not out.exists()
    assert capsys.readouterr().err.startswith(f"Error: {folder / 'calibration.yaml'}: images 8 px wide cannot be "
                                              "matched over disparities 0..16 px")


def test_a_run_started_with_its_standard_streams_closed_writes_its_output(small_log, tmp_path):
    """`terrainmap process LOG 0<&- 2>&-` (Python gives None for a stream closed at the start): the
    run's messages go nowhere and its output is written whole."""
    import subprocess
    import sys

    out = tmp_path / "o.mcap"
    code = "from terrainmap.cli.main import run; run()"

    def close_streams():
        os.close(0)
        os.close(2)

    done = subprocess.run([sys.executable, "-c", code, "process", str(small_log), "-o", str(out)],
                          stdout=subprocess.PIPE, preexec_fn=close_streams, timeout=120)
    assert done.returncode == 0 and b"wrote " in done.stdout
    with open(out, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count > 0
