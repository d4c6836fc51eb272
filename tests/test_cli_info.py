"""``terrainmap info`` through click's CliRunner."""

import json
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from terrainmap.cli.info_cmd import info
from terrainmap.cli.main import cli
from terrainmap.cli.source_options import SourceOptions, source_options

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"{path} not available")
    return path


def test_info_on_a_rosbag2_prints_topics_calibration_and_extrinsics():
    result = CliRunner().invoke(cli, ["info", str(need(DATA / "kitti2015_000005_ros2_raw"))])
    assert result.exit_code == 0, result.output
    assert "format:" in result.output and "rosbag2" in result.output
    assert "/stereo/left/image_rect_color   sensor_msgs/msg/Image" in result.output
    assert "left topic:" in result.output and "baseline_m: 0.532725" in result.output
    assert "will be estimated" in result.output


def test_info_json_on_the_kitti_folder():
    result = CliRunner().invoke(info, ["--json", str(need(DATA / "kitti2015_000005"))])
    assert result.exit_code == 0, result.output
    description = json.loads(result.output)
    assert description["format"] == "kitti-stereo" and description["frames"] == 1
    assert description["calibration"]["fx"] == pytest.approx(721.5377)


def test_info_topic_and_calibration_options(tmp_path):
    calib = tmp_path / "c.yaml"
    calib.write_text("width: 1242\nheight: 375\nfx: 700\nfy: 700\ncx: 600\ncy: 170\nbaseline_m: 0.5\n")
    log = need(DATA / "kitti2015_000005_ros2_compressed")
    args = ["--json", "--left-topic", "/stereo/right/image_rect_color/compressed",
            "--right-topic", "/stereo/left/image_rect_color/compressed", "--calibration", str(calib), str(log)]
    description = json.loads(CliRunner().invoke(info, args).output)
    assert description["left_topic"] == "/stereo/right/image_rect_color/compressed"
    assert description["calibration"]["baseline_m"] == 0.5


def test_info_errors_are_one_line_messages(tmp_path, capsys):
    from terrainmap.cli.main import main

    with pytest.raises(SystemExit) as exit_info:
        main(["info", str(tmp_path / "does" / "not" / "exist")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("Error: ") and "does not exist" in err and "\n" not in err


def test_info_given_a_topic_the_log_lacks_is_an_error_as_process_makes_it(tmp_path, capsys):
    from test_sources_logs import write_ros2_log

    from terrainmap.cli.main import main

    log = write_ros2_log(tmp_path / "run.mcap", n=2)
    with pytest.raises(SystemExit) as exit_info:
        main(["info", str(log), "--right-topic", "/nope"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == (f"Error: {log}: right topic '/nope' is not an image topic of this log "
                                               "(image topics: /cam/left/image_rect, /cam/right/image_rect)")
    cut = tmp_path / "cut.mcap"  # a recording killed before the topic's first message: described, with its damage
    cut.write_bytes(log.read_bytes()[:200])
    result = CliRunner().invoke(info, ["--right-topic", "/cam/right/image_rect", str(cut)])
    assert result.exit_code == 0 and "damage:" in result.output, result.output
    assert "stereo pair: none, so process cannot use it (truncated or corrupt after 0 messages" in result.output


@pytest.mark.parametrize("log", ["negative/rosbag2_talker", "negative/grid_map_ros1.bag"])
def test_info_describes_a_log_without_stereo_and_says_why_process_cannot_use_it(log):
    result = CliRunner().invoke(info, ["--json", str(need(DATA / log))])
    assert result.exit_code == 0
    description = json.loads(result.output)
    assert description["topics"] and any(t["count"] for t in description["topics"])
    assert description["stereo_pair"].startswith("none, so process cannot use it (no stereo image topics found")
    checked = CliRunner().invoke(info, ["--check", str(DATA / log)])
    assert checked.exit_code == 1 and "check:" in checked.output and "no stereo pair to read" in checked.output


def test_source_options_collect_into_open_and_frames_kwargs():
    seen = {}

    @click.command()
    @source_options
    def cmd(source_opts: SourceOptions):
        seen["open"], seen["frames"] = source_opts.open_kwargs(), source_opts.frames_kwargs()

    result = CliRunner().invoke(cmd, ["--start", "2.5", "--every", "3", "--max-frames", "7", "--pair-tolerance-ms", "4",
                                      "--left-topic", "/a/left"])
    assert result.exit_code == 0, result.output
    assert seen["open"] == {"left_topic": "/a/left", "right_topic": None, "calibration": None, "pair_tolerance_ns": 4_000_000}
    assert seen["frames"] == {"start_s": 2.5, "end_s": None, "every": 3, "max_frames": 7}
    assert CliRunner().invoke(cmd, ["--every", "0"]).exit_code == 2


def test_json_output_has_no_nan():
    from terrainmap.cli.info_cmd import _json_safe

    assert _json_safe({"fx": float("nan"), "P": [1.0, float("inf")], "name": "x"}) == {"fx": None, "P": [1.0, None], "name": "x"}


def test_check_reads_every_stereo_pair_and_finds_a_damaged_chunk_the_index_does_not_show(tmp_path):
    """An indexed MCAP with a corrupt chunk looks intact to ``info`` (its summary is whole);
    ``--check`` reads the pairs as process would, finds the damage and exits 1. Reading skips
    the damaged chunk and goes on (here it is the last: two pairs of three are read)."""
    from mcap.reader import make_reader

    from terrainmap.sim import SimConfig
    from terrainmap.sim.simulate import simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=320, height=240, focal_px=250.0))  # 3 chunks
    intact = CliRunner().invoke(info, ["--check", str(log)])
    assert intact.exit_code == 0, intact.output
    assert "check:" in intact.output and "3 stereo pairs read and decoded, to the end" in intact.output
    assert json.loads(CliRunner().invoke(info, ["--json", "--check", str(log)]).output)["skipped"] == []  # for scripts

    with open(log, "rb") as f:
        last = max(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(log.read_bytes())
    middle = last.chunk_start_offset + last.chunk_length // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    log.write_bytes(bytes(data))
    unchecked = CliRunner().invoke(info, [str(log)])
    assert unchecked.exit_code == 0 and "check:" not in unchecked.output
    damaged = CliRunner().invoke(info, ["--json", "--check", str(log)])
    assert damaged.exit_code == 1
    check = json.loads(damaged.output)["check"]
    assert check.startswith("2 stereo pairs read and decoded, to the end, skipping 1 damaged part: "), check
    assert f"{log}: chunk at byte {last.chunk_start_offset}, log time " in check and "CRC" in check.upper()
    assert [part[: len(str(log))] for part in json.loads(damaged.output)["skipped"]] == [str(log)]  # all, for scripts
    assert "\n" not in check


def test_a_damaged_chunk_met_while_describing_is_shown_as_damage(tmp_path):
    """Plain ``info`` reads the first camera infos and transforms: a chunk that fails there is named
    on the ``damage:`` line, not only in a warning above a line saying "-"."""
    from mcap.reader import make_reader

    from terrainmap.sim import SimConfig
    from terrainmap.sim.simulate import simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=320, height=240, focal_px=250.0))
    with open(log, "rb") as f:  # the second chunk holds the first frame's camera infos
        second = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    data = bytearray(log.read_bytes())
    middle = second.chunk_start_offset + second.chunk_length // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    log.write_bytes(bytes(data))
    result = CliRunner().invoke(info, [str(log)])
    assert result.exit_code == 0
    assert f"damage:             {log}: chunk at byte {second.chunk_start_offset}, log time" in result.output


def test_check_fails_when_no_left_and_right_images_pair_up(tmp_path):
    """Stereo topics whose stamps never agree within the pairing tolerance hold no stereo pair for
    process: ``--check`` says so and exits 1."""
    import struct

    from log_copies import rewrite_mcap

    from terrainmap.sim import SimConfig
    from terrainmap.sim.simulate import simulate

    def later(topic: str, data: bytes) -> bytes:  # the right images' header stamps 50 ms later
        if topic != "/stereo/right/image_rect":
            return data
        data = bytearray(data)
        sec, nsec = struct.unpack_from("<iI", data, 4)  # CDR: 4-byte header, then stamp sec, nanosec
        stamp = sec * 10**9 + nsec + 50_000_000
        struct.pack_into("<iI", data, 4, stamp // 10**9, stamp % 10**9)
        return bytes(data)

    log, shifted = tmp_path / "sim.mcap", tmp_path / "shifted.mcap"
    simulate(log, SimConfig(scene="flat", frames=2, seed=1, width=64, height=48, focal_px=50.0))
    rewrite_mcap(log, shifted, later)
    result = CliRunner().invoke(info, ["--check", str(shifted)])
    assert result.exit_code == 1, result.output
    assert "0 stereo pairs read and decoded, to the end (no left and right images whose stamps agree within " \
           "--pair-tolerance-ms)" in result.output


def test_check_fails_where_process_could_not_match_the_images(tmp_path):
    """8 px wide images read and decode, but no disparity range fits them: process refuses the
    calibration at its first frame, and so does ``--check``."""
    from test_sources_folders import generic_folder

    result = CliRunner().invoke(info, ["--check", str(generic_folder(tmp_path, n=2))])
    assert result.exit_code == 1, result.output
    assert "check:       fails after 0 stereo pairs: " in result.output
    assert "calibration.yaml: images 8 px wide cannot be matched over disparities 0..16 px" in result.output
