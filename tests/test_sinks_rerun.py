"""Rerun recordings: verified by the SDK's own tool and read back with its reader."""

import collections
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from rerun.chunk import RrdReader

from terrainmap import runner
from terrainmap.cli.main import cli
from terrainmap.config import Config
from terrainmap.sinks.rerun_recording import NO_POINT, RerunSink
from terrainmap.sources import open_source

ENTITIES = {
    "/world/vehicle", "/world/vehicle/points", "/world/vehicle/camera/image", "/world/vehicle/camera/image/labels",
    "/depth", "/world/vehicle/grid/samples", "/world/vehicle/grid/equalized", "/world/vehicle/terrain/slope",
    "/world/vehicle/terrain/elevation", "/world/vehicle/terrain/cost", "/world/vehicle/obstacles", "/world/vehicle/occupied",
    "/timings/surface", "/stats/fit/iterations",
}


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    from terrainmap.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("rrd") / "sim.mcap"
    simulate(path, SimConfig(scene="mounds", frames=3, seed=4, width=320, height=240, focal_px=250.0))
    return path


def _rows(path: Path) -> dict[str, int]:
    reader = RrdReader(str(path))
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1  # default layout embedded
    rows = collections.Counter()
    for chunk in reader.store().stream().to_chunks():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def _verify(path: Path) -> None:
    rerun = Path(sys.executable).with_name("rerun")
    done = subprocess.run([str(rerun), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_process_writes_a_verified_recording_with_every_stage(log, tmp_path):
    rrd = tmp_path / "out.rrd"
    result = CliRunner().invoke(cli, ["process", str(log), "-o", str(tmp_path / "o.mcap"), "--rrd", str(rrd)])
    assert result.exit_code == 0, result.output
    assert f"wrote {rrd}" in result.output
    _verify(rrd)
    rows = _rows(rrd)
    assert ENTITIES <= set(rows)
    assert all(rows[e] == 3 for e in ENTITIES)  # one row per frame on the frame timeline


def test_vehicle_pose_places_the_vehicle_frame_in_the_odometry_frame(log, tmp_path):
    """The simulated log's odometry (odom → base_link on /tf) becomes the per-frame transform of
    ``world/vehicle``, under which every computed layer is logged."""
    import numpy as np

    rrd = tmp_path / "pose.rrd"
    with open_source(log) as source:
        frames = list(source.frames())
    with open_source(log) as source:
        runner.run(source.frames(), Config(), [RerunSink(rrd, config=Config())])
    chunks = [c for c in RrdReader(str(rrd)).store().stream().to_chunks() if str(c.entity_path) == "/world/vehicle"]
    batches = [c.to_record_batch() for c in chunks if not c.is_static]
    translations = [row[0] for b in batches for row in b.column("Transform3D:translation").to_pylist()]
    rotations = [row[0] for b in batches for row in b.column("Transform3D:mat3x3").to_pylist()]
    assert len(translations) == len(frames) == 3
    for frame, t, m in zip(frames, translations, rotations):
        np.testing.assert_allclose(t, frame.vehicle_pose[:3, 3], atol=1e-6)
        np.testing.assert_allclose(np.reshape(m, (3, 3)).T, frame.vehicle_pose[:3, :3], atol=1e-6)  # column-major
    assert len({tuple(t) for t in translations}) == 3  # the vehicle moves


def test_recording_is_complete_when_the_run_fails_part_way(log, tmp_path):
    with open_source(log) as source:
        frames = list(source.frames())

    def broken():
        yield from frames[:2]
        raise KeyboardInterrupt

    rrd = tmp_path / "cut.rrd"
    sink = RerunSink(rrd, config=Config())
    with pytest.raises(KeyboardInterrupt):
        runner.run(broken(), Config(), [sink])
    sink.close()  # closing twice is harmless
    _verify(rrd)
    assert _rows(rrd)["/world/vehicle/points"] == 2


def test_points_are_subsampled_for_display(log, tmp_path):
    config = Config()
    config.rerun.max_points = 1000
    rrd = tmp_path / "few.rrd"
    with open_source(log) as source:
        runner.run(source.frames(max_frames=1), config, [RerunSink(rrd, config=config)])
    reader = RrdReader(str(rrd))
    points = [c for c in reader.store().stream().to_chunks() if str(c.entity_path) == "/world/vehicle/points"]
    batch = points[0].to_record_batch()
    column = next(name for name in batch.schema.names if name.endswith("positions"))
    assert len(batch.column(column)[0]) <= 1000


def test_camera_and_depth_use_the_rectified_pinhole(log, tmp_path):
    """Input rectified here has a pinhole other than the raw calibration: the recording's camera
    and depth image must follow the images and disparities it shows, not ``frame.calibration``."""
    import dataclasses

    import numpy as np

    from terrainmap.pipeline import PipelineState, process_frame

    config = Config()
    with open_source(log) as source:
        frame = next(source.frames())
    from scipy.spatial.transform import Rotation

    result = process_frame(frame, config, PipelineState(config))
    r1 = Rotation.from_euler("x", 3, degrees=True).as_matrix()  # as cv2.stereoRectify turns a camera
    result.pinhole = dataclasses.replace(result.pinhole, fx=2 * frame.calibration.fx, fy=2 * frame.calibration.fy,
                                         rectifying_rotation=tuple(r1.ravel()), doffs=4.0)  # Z = f·B / (d + doffs)
    rrd = tmp_path / "pinhole.rrd"
    with RerunSink(rrd, config=config) as sink:
        sink.write(frame, result)
    batches = [(str(c.entity_path), c.to_record_batch()) for c in RrdReader(str(rrd)).store().stream().to_chunks()]
    pinhole = next(b for path, b in batches if path == "/world/vehicle/camera" and "Pinhole:image_from_camera" in b.schema.names)
    assert pinhole.column("Pinhole:image_from_camera")[0].as_py()[0][0] == 2 * frame.calibration.fx
    turn = np.reshape(_columns(rrd, "/world/vehicle/camera", "Transform3D:mat3x3")[0][0], (3, 3)).T  # column-major
    np.testing.assert_allclose(turn, result.extrinsics.rotation @ r1.T, atol=1e-6)  # the rectified camera's pose
    depth_image = next(b for path, b in batches if path == "/depth")
    depth = np.frombuffer(bytes(depth_image.column("DepthImage:buffer")[0].as_py()[0]), np.float32)
    disparity = result.disparity[::2, ::2].ravel()
    seen = np.isfinite(disparity) & (disparity > 0)
    expected = result.pinhole.fx * result.pinhole.baseline_m / (disparity[seen] + 4.0)
    np.testing.assert_allclose(depth[seen], expected, rtol=1e-5)


def _columns(path: Path, entity: str, column: str) -> dict[int, list]:
    """frame → the column's value in that frame's row of ``entity`` (a list of instances)."""
    out = {}
    for chunk in RrdReader(str(path)).store().stream().to_chunks():
        if str(chunk.entity_path) != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if column in batch.schema.names:
            out.update(zip(batch.column("frame").to_pylist(), batch.column(column).to_pylist(), strict=True))
    return out


def test_what_the_recording_shows_is_what_was_computed(log, tmp_path, keep_sink):
    """Read back, per frame: the terrain mesh's heights are the elevation layer, the equalized
    samples are the fit's, the boxes are the confirmed obstacles (half their size), and the label
    image holds each point's label at its pixel."""
    import numpy as np

    rrd = tmp_path / "content.rrd"
    keep = keep_sink
    with open_source(log) as source:
        sink = RerunSink(rrd, config=Config())
        runner.run(source.frames(), Config(), [keep, sink])
    mesh = _columns(rrd, "/world/vehicle/terrain/elevation", "Mesh3D:vertex_positions")
    equalized = _columns(rrd, "/world/vehicle/grid/equalized", "Points3D:positions")
    boxes = _columns(rrd, "/world/vehicle/obstacles", "Boxes3D:half_sizes")
    occupied = _columns(rrd, "/world/vehicle/occupied", "Boxes3D:half_sizes")
    greys = [c for colors in _columns(rrd, "/world/vehicle/occupied", "Boxes3D:colors").values() for c in colors or []]
    assert greys and all(c >> 24 == (c >> 16) & 255 == (c >> 8) & 255 for c in greys)  # RGBA packed, r = g = b
    labels = _columns(rrd, "/world/vehicle/camera/image/labels", "SegmentationImage:buffer")
    assert len(keep.results) == 3 and any(boxes.values()) and any(occupied.values())  # (a track unseen in frame 2)
    for k, result in enumerate(keep.results):
        np.testing.assert_allclose(np.array(mesh[k])[:, 2], result.layers["elevation"].ravel(), atol=1e-6)
        valid = result.grid.valid
        np.testing.assert_allclose(np.array(equalized[k])[:, 2], result.terrain.samples[valid], atol=1e-6)
        confirmed = [o for o in result.obstacles if o.confirmed]
        shown = np.array(boxes.get(k) or []).reshape(-1, 3)
        np.testing.assert_allclose(shown, [o.size_m / 2 for o in confirmed] or np.zeros((0, 3)), atol=1e-6)
        grey = np.array(occupied.get(k) or []).reshape(-1, 3)
        np.testing.assert_allclose(grey, [o.size_m / 2 for o in result.occupied] or np.zeros((0, 3)), atol=1e-6)
        image = np.array(labels[k][0], np.uint8).reshape(result.image.shape[:2])  # one image, its bytes
        np.testing.assert_array_equal(image[result.pixels[:, 1], result.pixels[:, 0]], result.point_labels)
        pointless = np.ones(image.shape, bool)
        pointless[result.pixels[:, 1], result.pixels[:, 0]] = False
        assert pointless.any() and (image[pointless] == NO_POINT).all()  # transparent, not "unknown" grey
        depth = np.array(_columns(rrd, "/depth", "DepthImage:buffer")[k][0], np.uint8).view(np.float32)
        stereo = Config().stereo  # no data outside the range that points are kept in
        assert ((depth == 0) | ((depth >= stereo.min_range_m) & (depth <= stereo.max_range_m))).all()
        assert (depth == 0).any() and (depth > 0).any()
    elevation = np.concatenate([r.layers["elevation"][r.grid.valid] for r in keep.results])
    assert sink._elevation_span == (elevation.min(), elevation.max())  # one colour scale for the whole run


def test_a_failed_frame_clears_the_results_and_says_why(log, tmp_path):
    """A frame the pipeline cannot process (blank images: no disparity) keeps its place on the
    timeline: the results of the frame before are cleared, a warning names it."""
    import dataclasses

    import numpy as np

    rrd = tmp_path / "failed.rrd"
    with open_source(log) as source:
        frames = list(source.frames())
    blank = np.zeros_like(frames[1].left)
    frames[1] = dataclasses.replace(frames[1], left=blank, right=blank)
    summary = runner.run(frames, Config(), [RerunSink(rrd, config=Config())])
    assert summary.frames_done == 2 and summary.frames_failed == 1
    _verify(rrd)
    (reason,) = summary.failures
    ((frame, (text,)),) = _columns(rrd, "/log", "TextLog:text").items()
    assert frame == 1 and text.startswith(f"frame 1 failed ({reason}): ")
    assert set(_columns(rrd, "/world/vehicle/points", "Points3D:positions")) == {0, 2}
    for entity in ("/world/vehicle/points", "/world/vehicle/terrain", "/world/vehicle/obstacles"):
        assert 1 in _columns(rrd, entity, "Clear:is_recursive"), entity  # not frame 0's results


def test_the_blueprint_hides_the_other_meshes_and_plots_the_counts(log, tmp_path):
    rrd = tmp_path / "layout.rrd"
    with open_source(log) as source:
        runner.run(source.frames(max_frames=1), Config(), [RerunSink(rrd, config=Config())])
    reader = RrdReader(str(rrd))
    hidden, origins = set(), set()
    for chunk in reader.store(store=reader.blueprints()[0]).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "EntityBehavior:visible" in batch.schema.names and batch.column("EntityBehavior:visible").to_pylist() == [[False]]:
            hidden.add(str(chunk.entity_path).split("/overrides", 1)[1].removesuffix("/visualizers"))
        for name in batch.schema.names:
            if name.endswith(":space_origin"):
                origins.update(origin for row in batch.column(name).to_pylist() for origin in row)
    assert hidden == {"/world/vehicle/terrain/elevation", "/world/vehicle/terrain/cost"}
    assert {"/stats/counts", "/log"} <= origins


def test_camera_model_and_pose_are_logged_per_frame_where_they_change(log, tmp_path):
    """A folder of several scenes changes the camera between frames: each frame must show its own
    pinhole and pose (a static log would overwrite them all with the last one)."""
    import dataclasses

    import numpy as np

    from terrainmap.pipeline import PipelineState, process_frame

    config = Config()
    with open_source(log) as source:
        frames = list(source.frames())
    state = PipelineState(config)
    results = [process_frame(frame, config, state) for frame in frames]
    results[2].pinhole = dataclasses.replace(results[2].pinhole, cy=results[2].pinhole.cy - 40)
    results[2].extrinsics = dataclasses.replace(results[2].extrinsics, translation=np.array([0.5, 0.0, 2.0]))
    rrd = tmp_path / "cameras.rrd"
    with RerunSink(rrd, config=config) as sink:
        for frame, result in zip(frames, results):
            sink.write(frame, result)
    entity = "/world/vehicle/camera"
    assert not any(c.is_static for c in RrdReader(str(rrd)).store().stream().to_chunks() if str(c.entity_path) == entity)
    pinholes = _columns(rrd, entity, "Pinhole:image_from_camera")
    translations = _columns(rrd, entity, "Transform3D:translation")
    assert sorted(pinholes) == sorted(translations) == [0, 2]  # logged where it holds first and where it changes
    assert pinholes[2][0][7] == pinholes[0][0][7] - 40  # cy, in the column-major 3×3
    np.testing.assert_allclose(translations[0][0], results[0].extrinsics.translation, atol=1e-6)
    np.testing.assert_allclose(translations[2][0], [0.5, 0.0, 2.0])


def test_a_recording_that_cannot_be_finished_fails_with_one_line(log, tmp_path, monkeypatch, capsys):
    """Rerun's file writer dies on a full disk, and its flush then waits for ever: the sink gives
    up once the file stops growing, the run says which output is lost and which is readable, and
    the CLI ends the process (os._exit) instead of hanging in Rerun's exit handler."""
    from terrainmap.cli.main import main
    from terrainmap.sinks import rerun_recording

    def dead_writer(self, *, timeout_sec):
        raise RuntimeError("File-writer thread shut down prematurely")

    monkeypatch.setattr(rerun_recording, "_STUCK", [])
    monkeypatch.setattr(rerun_recording, "_FLUSH_WAIT_S", 0.01)
    monkeypatch.setattr(rerun_recording, "_STALL_S", 0.05)  # the disk has room: a dead writer is waited for
    monkeypatch.setattr(rerun_recording.rr.RecordingStream, "flush", dead_writer)
    exits = []

    def os_exit(code):
        exits.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(os, "_exit", os_exit)
    out, rrd = tmp_path / "o.mcap", tmp_path / "o.rrd"
    with pytest.raises(SystemExit):
        main(["process", str(log), "-o", str(out), "--rrd", str(rrd), "--max-frames", "2"])
    captured = capsys.readouterr()
    assert exits == [2]
    assert captured.err.strip().splitlines()[-1] == f"Error: cannot finish Rerun output {rrd}: its file writer " \
                                                    "stopped (File-writer thread shut down prematurely); the part " \
                                                    "written is removed"
    assert not rrd.exists()  # cut short, it would read back in no Rerun tool
    assert f"wrote 2 frames to {out} before stopping" in captured.out  # the MCAP only: it reads back
    assert rerun_recording.exit_would_hang()


def test_a_recording_on_a_slow_disk_is_waited_for_while_the_disk_has_room(tmp_path, monkeypatch):
    """A file that stands still for a few flushes on a disk with room (a slow network disk) is
    waited for, not taken for a dead writer; on a full disk one standing flush is enough."""
    import shutil
    from collections import namedtuple

    from terrainmap.errors import InputError
    from terrainmap.sinks import rerun_recording

    calls = []

    def slow(self, *, timeout_sec):
        calls.append(timeout_sec)
        if len(calls) < 4:  # three timeouts without the file growing, then done
            raise RuntimeError("flush timed out")

    monkeypatch.setattr(rerun_recording, "_FLUSH_WAIT_S", 0.01)
    monkeypatch.setattr(rerun_recording.rr.RecordingStream, "flush", slow)
    from terrainmap.config import Config

    sink = rerun_recording.RerunSink(tmp_path / "slow.rrd", config=Config())
    sink.close()
    assert len(calls) == 4 and sink.finished
    calls.clear()
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 30, 1 << 30, 4096))
    monkeypatch.setattr(rerun_recording, "_STUCK", [])
    (tmp_path / "full.rrd").symlink_to(tmp_path / "target.rrd")  # written through a link
    full = rerun_recording.RerunSink(tmp_path / "full.rrd", config=Config())
    with pytest.raises(InputError, match="No space left on device; the part written is removed"):
        full.close()
    assert len(calls) == 2  # the size seen, then one flush with no growth
    assert not (tmp_path / "target.rrd").exists() and (tmp_path / "full.rrd").is_symlink()


def test_a_disk_whose_free_space_cannot_be_read_is_not_taken_for_full(tmp_path, monkeypatch):
    """``shutil.disk_usage`` failing (no permission on the folder): the writer is waited for as on
    a disk with room, and a dead one is reported as stopped, in one line (InputError)."""
    import shutil

    from terrainmap.config import Config
    from terrainmap.errors import InputError
    from terrainmap.sinks import rerun_recording

    def dead(self, *, timeout_sec):
        raise RuntimeError("File-writer thread shut down prematurely")

    def no_permission(path):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(rerun_recording, "_STUCK", [])
    monkeypatch.setattr(rerun_recording, "_FLUSH_WAIT_S", 0.01)
    monkeypatch.setattr(rerun_recording, "_STALL_S", 0.03)
    monkeypatch.setattr(rerun_recording.rr.RecordingStream, "flush", dead)
    monkeypatch.setattr(shutil, "disk_usage", no_permission)
    sink = rerun_recording.RerunSink(tmp_path / "o.rrd", config=Config())
    with pytest.raises(InputError, match="its file writer stopped"):
        sink.close()


def test_the_timelines_are_the_frame_index_and_the_image_stamp(log, tmp_path):
    """``frame`` is the source's pair index (not a count of frames written) and ``stamp`` the
    image's time, to the nanosecond."""
    rrd = tmp_path / "timelines.rrd"
    with open_source(log) as source:
        frames = list(source.frames(every=2))
    with open_source(log) as source:
        runner.run(source.frames(every=2), Config(), [RerunSink(rrd, config=Config())])
    rows = {}
    for chunk in RrdReader(str(rrd)).store().stream().to_chunks():
        if str(chunk.entity_path) == "/world/vehicle/points" and not chunk.is_static:
            batch = chunk.to_record_batch()
            rows.update(zip(batch.column("frame").to_pylist(), batch.column("stamp").cast("int64").to_pylist(), strict=True))
    assert [f.index for f in frames] == [0, 2]
    assert rows == {f.index: f.stamp_ns for f in frames}


def test_a_recording_of_bad_arguments_is_refused_naming_them(log, tmp_path):
    """As the MCAP sink: a config that is no Config, a path that is none or whose folder does not
    exist, no frame or result, a stamp that no Rerun time holds or an index that is no whole number
    are terrainmap's errors, said before anything is logged."""
    import dataclasses

    from terrainmap.errors import ConfigError, InputError
    from terrainmap.pipeline import PipelineState, process_frame

    with pytest.raises(ConfigError, match="Rerun output .*: config must be a Config, got NoneType"):
        RerunSink(tmp_path / "o.rrd", config=None)
    with pytest.raises(InputError, match="cannot create Rerun output .*: folder .*nowhere does not exist"):
        RerunSink(tmp_path / "nowhere" / "o.rrd", config=Config())
    with pytest.raises(InputError, match="^Rerun output: expected a file path, got None$"):
        RerunSink(None, config=Config())
    with open_source(log) as source:
        frame = next(source.frames())
    result = process_frame(frame, Config(), PipelineState(Config()))
    sink = RerunSink(tmp_path / "o.rrd", config=Config())
    for bad, message in ((dataclasses.replace(frame, stamp_ns=2**63), r"stamp must be a whole number of nanoseconds "
                                                                         r"in \[0, 2\^63\), got 9223372036854775808"),
                         (dataclasses.replace(frame, index="x"), "the frame index must be a whole number, got 'x'")):
        with pytest.raises(InputError, match=message):
            sink.write(bad, result)
    with pytest.raises(InputError, match="the result of frame 0 .* given with frame 1 .*: a result goes with its own frame"):
        sink.write(dataclasses.replace(frame, index=1), result)
    for bad in ((None, None), (frame, None), (frame, frame)):
        with pytest.raises(InputError, match="expected a StereoFrame and its FrameResult, got"):
            sink.write(*bad)
    with pytest.raises(InputError, match="expected a StereoFrame and its FrameResult, got NoneType and NoneType"):
        sink.failed(None, ValueError("x"))
    import numpy as np

    numpy_stamped = dataclasses.replace(frame, stamp_ns=np.int64(frame.stamp_ns))  # stamps read from an array
    sink.write(numpy_stamped, dataclasses.replace(result, stamp_ns=numpy_stamped.stamp_ns))
    sink.close()
    _verify(tmp_path / "o.rrd")
