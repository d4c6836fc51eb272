import json
import os
import re
import sys
import tomllib
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from terrainmap.cli.main import cli, main


def test_config_prints_effective_toml():
    result = CliRunner().invoke(cli, ["config", "--set", "terrain.control_points_x=12"])
    assert result.exit_code == 0, result.output
    data = tomllib.loads(result.output)
    assert data["terrain"]["control_points_x"] == 12 and data["grid"]["cell_size_m"] == 0.5


def test_bad_override_is_a_one_line_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["config", "--set", "terrain.degree=0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.strip() == "Error: terrain.degree: must be 1..5, got 0"
    with pytest.raises(SystemExit) as exc:  # --verbose, before the command: a bad option stays one line
        main(["-v", "config", "--set", "terrain.degree=0"])
    assert exc.value.code == 2 and capsys.readouterr().err == err
    with pytest.raises(SystemExit) as exc:  # while reading: the traceback
        main(["-v", "info", str(Path(__file__).parent / "nonexistent.mcap")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" in err and "InputError" in err


def test_a_file_named_like_the_verbose_flag_is_no_flag(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["info", "--", "-v"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["process"], r"Error: Missing argument 'LOG'\. \(see 'terrainmap process --help'\)"),
        (["bogus"], r"Error: No such command 'bogus'\. \(see 'terrainmap --help'\)"),
        # (click 8.2 and 8.3 word it "No such option: --nope")
        (["config", "--nope"], r"Error: No such option(: --nope| '--nope'\.) \(see 'terrainmap config --help'\)"),
        (["config", "-v"], r"Error: No such option(: -v| '-v'\.) \(-v goes before the command: terrainmap -v COMMAND \.\.\.\)"),
    ],
)
def test_usage_errors_are_one_line(capsys, args, line):
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    (got,) = capsys.readouterr().err.splitlines()
    assert re.fullmatch(line, got), got


@pytest.mark.parametrize(("flags", "quiet"), [([], True), (["-v"], False)])
def test_opencv_and_rerun_log_lines_are_silenced_unless_verbose(monkeypatch, flags, quiet):
    """Their own lines (libpng's, Rerun's on a full disk) would add to the one-line error."""
    for name in ("OPENCV_LOG_LEVEL", "RUST_LOG"):
        monkeypatch.delenv(name, raising=False)
    assert CliRunner().invoke(cli, [*flags, "config"]).exit_code == 0
    assert (os.environ.get("OPENCV_LOG_LEVEL"), os.environ.get("RUST_LOG")) == (("SILENT", "off") if quiet else (None, None))


@pytest.mark.parametrize(
    ("error", "code", "line"),
    [
        (KeyboardInterrupt(), 130, "Interrupted."),
        (PermissionError(13, "Permission denied", "/reports/x.json"), 2, "Error: /reports/x.json: Permission denied"),
        (MemoryError("Unable to allocate 26.0 GiB for an array with shape (243, 243, 243, 243)"), 2,
         "Error: out of memory (Unable to allocate 26.0 GiB for an array with shape (243, 243, 243, 243)); "
         "a smaller grid, terrain net or image may fit"),
    ],
)
def test_interruptions_and_os_errors_end_with_one_line(monkeypatch, capsys, error, code, line):
    from terrainmap.cli import main as main_module

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(main_module.cli, "main", fail)
    with pytest.raises(SystemExit) as exc:
        main(["config"])
    assert exc.value.code == code
    assert capsys.readouterr().err.splitlines() == [line]


@pytest.mark.parametrize("terminal", [False, True])
def test_ctrl_c_in_a_command_ends_with_interrupted_after_the_terminal_s_caret_c_only(monkeypatch, capsys, terminal):
    """click prints an empty line before its Abort; terrainmap's "Interrupted." is alone, after a
    line end only on a terminal, where the "^C" that Ctrl-C echoes would precede it."""
    import click

    def interrupted(self, ctx):
        raise KeyboardInterrupt

    monkeypatch.setattr(click.Group, "invoke", interrupted)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    with pytest.raises(SystemExit) as exc:
        main(["config"])
    assert exc.value.code == 130
    assert capsys.readouterr().err == ("\n" if terminal else "") + "Interrupted.\n"


def test_eval_artificial_obstacle_writes_json_csv_and_plot(tmp_path):
    args = ["eval", "artificial-obstacle", "--nets", "5,25", "--widths", "0.8,8", "--heights", "1,3"]
    out = [
        "--json", str(tmp_path / "r.json"), "--csv", str(tmp_path / "r.csv"), "--plot", str(tmp_path / "r.png")
    ]
    result = CliRunner().invoke(cli, args + out)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0] == "max deviation [% of obstacle height], 5×5 control points" and "" in lines  # blank between
    assert "25×25 control points" in result.output
    assert lines[-3:] == [f"wrote {tmp_path / name}" for name in ("r.json", "r.csv", "r.png")]
    rows = json.loads((tmp_path / "r.json").read_text())
    assert len(rows) == 8
    assert list(rows[0]) == ["scene", "control_points", "width_m", "height_m", "max_deviation_m", "max_deviation_pct"]
    assert rows[0]["scene"] == "flat"
    assert all(r["max_deviation_pct"] == pytest.approx(100 * r["max_deviation_m"] / r["height_m"]) for r in rows)
    thin = [r for r in rows if r["control_points"] == 25 and r["width_m"] == 0.8]
    assert all(r["max_deviation_pct"] < 5 for r in thin)
    assert (tmp_path / "r.csv").read_text().startswith(
        "scene,control_points,width_m,height_m,max_deviation_m,max_deviation_pct")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_artificial_obstacle_takes_the_degree_from_the_config_unless_given():
    args = ["eval", "artificial-obstacle", "--nets", "5", "--widths", "4", "--heights", "1"]
    table = {extra: CliRunner().invoke(cli, [*args, *extra]).output.splitlines()[-1]
             for extra in ((), ("--set", "terrain.degree=2"), ("--degree", "2"), ("--set", "terrain.degree=2", "--degree", "3"))}
    assert len(set(table.values())) == 2  # degree 3 (default, or given) and degree 2 (config, or given)
    assert table[()] == table[("--set", "terrain.degree=2", "--degree", "3")] != table[("--set", "terrain.degree=2")]
    assert table[("--set", "terrain.degree=2")] == table[("--degree", "2")]


@pytest.mark.parametrize("widths", ["a,b", "1,,2", "1,"])
def test_eval_rejects_bad_lists(widths):
    result = CliRunner().invoke(cli, ["eval", "artificial-obstacle", "--widths", widths])
    assert result.exit_code != 0 and "comma-separated numbers" in result.output


def test_outputs_are_checked_before_any_work(tmp_path):
    (tmp_path / "same.csv").symlink_to(tmp_path / "same.json")  # one file under both names
    result = CliRunner().invoke(cli, ["eval", "artificial-obstacle", "--json", str(tmp_path / "same.json"),
                                      "--csv", str(tmp_path / "same.csv")])
    assert result.exit_code == 2 and "--json and --csv are the same file" in result.output
    if os.path.isdir("/proc"):  # Linux refuses new files there: found before the benchmark runs
        result = CliRunner().invoke(cli, ["bench", "--json", "/proc/terrainmap-bench.json"])
        assert result.exit_code == 2 and "cannot write /proc/terrainmap-bench.json" in result.output


def test_a_report_is_named_by_its_suffix_so_that_a_slip_replaces_no_log(tmp_path):
    """A slip that names a log for a report: refused, the log left as it was; an earlier report of
    the same name is replaced, run after run."""
    log = tmp_path / "drive.mcap"
    log.write_bytes(b"\x89MCAP0\r\n")
    args = ["eval", "artificial-obstacle", "--nets", "5", "--widths", "4", "--heights", "1"]
    for option in ("--json", "--csv"):
        result = CliRunner().invoke(cli, [*args, option, str(log)])
        assert result.exit_code == 2 and f"{log} must end in .{option[2:]}" in result.output
    assert log.read_bytes() == b"\x89MCAP0\r\n"
    (tmp_path / "old.json").write_text("{}")
    for _ in range(2):
        result = CliRunner().invoke(cli, [*args, "--json", str(tmp_path / "old.json"), "--csv", str(tmp_path / "rows.csv")])
        assert result.exit_code == 0, result.output
    assert (tmp_path / "old.json").read_text().startswith("[") and (tmp_path / "rows.csv").read_text()


def test_bench_reports_every_stage(tmp_path, monkeypatch):
    import tempfile

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    result = CliRunner().invoke(cli, ["bench", "--runs", "2", "--process-frames", "3", "--json", str(tmp_path / "b.json")])
    assert result.exit_code == 0, result.output
    assert not any(scratch.iterdir())  # the MCAPs that mcap_write and process write are gone with their folders
    assert "machine:" in result.output
    assert "frame_total / sgbm_alone:" in result.output and "grid + labels, ms (numpy's floor for their passes: " in result.output
    assert "frame_every_row / sgbm_alone:" in result.output
    stages = json.loads((tmp_path / "b.json").read_text())
    for name in ("grid", "surface", "labels", "grid_labels_floor", "obstacles", "sgbm_alone", "frame_total", "upright",
                 "mcap_write"):
        assert set(stages[name]) == {"median_ms", "min_ms", "max_ms", "runs"}
        assert 0 < stages[name]["min_ms"] <= stages[name]["median_ms"] <= stages[name]["max_ms"]
    process = stages["process"]  # the runner over a still simulated log, three times
    assert process["runs"] == 3 and process["frames"] == 3
    assert 0 < process["min_fps"] <= process["median_fps"] <= process["max_fps"]
    assert "process, frames/s over 3 pairs of a still simulated log (640×480), 3 runs: median " in result.output
    assert process["failed"] == {}
    assert "process: fewer than 10 pairs (" in result.output and "not held to the goal" in result.output


def test_bench_refuses_a_still_log_longer_than_it_writes():
    result = CliRunner().invoke(cli, ["bench", "--process-frames", "1001"])
    assert result.exit_code == 2 and "--process-frames" in result.output and "at most 1000 without --log" in result.output


def test_bench_goal_lines_show_the_digits_that_decide(monkeypatch):
    """A ratio of 1.6004 misses 1.6: printed with the digits that show it, not "1.60 (MISSES ...)"."""
    from terrainmap import bench as lib

    monkeypatch.setattr(lib, "all_stages", lambda config, frame: {})
    monkeypatch.setattr(lib, "run", lambda config, runs, stages: {})
    monkeypatch.setattr(lib, "goals", lambda results: [("a", 1.6004, 1.6), ("b", 1.5996, 1.6), ("c", 1.6, 1.6),
                                                       ("d", 1.2345, 1.6), ("e", 1.60004, 1.6)])
    rate = {"median_fps": 14.9996, "min_fps": 14.0, "max_fps": 16.0, "runs": 3, "frames": 40, "failed": {}}
    monkeypatch.setattr(lib, "process_rate", lambda config, log, frames, **kwargs: rate)
    result = CliRunner().invoke(cli, ["bench", "--runs", "1"])
    assert result.exit_code == 0, result.output
    assert "process, frames/s (median): 14.9996 (MISSES the goal of at least 15)" in result.output
    assert "a: 1.6004 (MISSES the goal of at most 1.6)" in result.output
    assert "b: 1.60 (meets the goal of at most 1.6)" in result.output
    assert "c: 1.60 (meets" in result.output and "d: 1.23 (meets" in result.output
    assert "e: 1.60004 (MISSES" in result.output


def test_bench_times_the_first_pair_of_a_log(tmp_path):
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=320, height=240, focal_px=250.0))
    result = CliRunner().invoke(cli, ["bench", "--log", str(log), "--runs", "1", "--process-frames", "2",
                                      "--json", str(tmp_path / "b.json")])
    assert result.exit_code == 0, result.output
    assert f"input: the first stereo pair of {log}, 320×240" in result.output
    assert f"process, frames/s over the first 2 stereo pairs of {log} (320×240), 3 runs: " in result.output
    assert "the goal of at least 15 frames/s is set at 640×480, so the rate is not held to it" in result.output
    stages = json.loads((tmp_path / "b.json").read_text())
    assert {"grid", "surface", "labels", "obstacles", "sgbm_alone", "frame_total", "upright", "mcap_write"} <= set(stages)
    # the log's topics can be named, as for process (a log whose names do not give them away)
    topic = CliRunner().invoke(cli, ["bench", "--log", str(log), "--runs", "1", "--left-topic", "/stereo/left/raw"])
    assert "left topic '/stereo/left/raw' is not an image topic of this log" in str(topic.exception)


def test_bench_says_when_process_could_not_be_timed_or_pairs_failed_and_keeps_the_stage_timings(tmp_path):
    """Only the first pair serves the stages; a later pair that ends process (images of two sizes)
    leaves process untimed, said in one line, and pairs that give no terrain keep the rate (faster
    without the fit) from being held to the goal."""
    import cv2
    import numpy as np

    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=320, height=240, focal_px=250.0, format="folder"))
    third = sorted((log / "right").iterdir())[2]
    cv2.imwrite(str(third), cv2.resize(cv2.imread(str(third)), (160, 120)))
    result = CliRunner().invoke(cli, ["bench", "--log", str(log), "--runs", "1", "--json", str(tmp_path / "b.json")])
    assert result.exit_code == 0, result.output
    assert "process: not timed (" in result.output and "differ in size" in result.output
    stages = json.loads((tmp_path / "b.json").read_text())
    assert "frame_total" in stages and "process" not in stages
    for side in ("left", "right"):
        for path in sorted((log / side).iterdir())[1:]:  # flat grey: no points, no terrain
            cv2.imwrite(str(path), np.full((240, 320), 128, np.uint8))
    result = CliRunner().invoke(cli, ["bench", "--log", str(log), "--runs", "1"])
    assert result.exit_code == 0, result.output
    assert f"the first 3 stereo pairs of {log} (320×240)" in result.output
    assert "process: 2 of those pairs failed (" in result.output and "not held to the goal" in result.output


def test_bench_names_the_log_whose_first_stamp_no_mcap_can_hold(tmp_path, capsys):
    """As process does, not the benchmark's temporary MCAP that would refuse the stamp."""
    from terrainmap.cli.main import main
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=2, seed=1, width=64, height=48, format="folder"))
    (log / "timestamps.txt").write_text("-1\n-2\n")
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--log", str(log), "--runs", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2  # the log's stamp file, where process names it too
    assert err[-1] == f"Error: {log / 'timestamps.txt'}: stamp -1 ns lies outside 1970–2262 (0 to 2^63 − 1 ns)"


def test_bench_refuses_a_log_without_stereo(tmp_path, capsys):
    from terrainmap.cli.main import main

    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--log", str(tmp_path / "empty")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"Error: {tmp_path / 'empty'}: not a known stereo source")


def test_bench_stages_take_turns_and_goals_follow_the_medians():
    from terrainmap import bench

    calls = []
    stages = {name: (lambda name=name: calls.append(name)) for name in ("sgbm_alone", "frame_total")}
    results = bench.run(runs=3, stages=stages, warmup=1)
    assert calls == ["sgbm_alone", "frame_total"] * 4  # interleaved: one call of each per round
    assert results["frame_total"]["runs"] == 3
    fake = {"grid": 3.0, "surface": 6.0, "labels": 1.5, "sgbm_alone": 20.0, "frame_total": 34.0, "frame_every_row": 36.0}
    checks = bench.goals({name: {"median_ms": ms} for name, ms in fake.items()})
    assert checks == [
        ("surface (estimation, slope, cell labels), ms", 6.0, 5.0),
        ("grid + labels, ms", 4.5, 5.0),
        ("frame_total / sgbm_alone", 1.7, 1.6),
        ("frame_every_row / sgbm_alone", 1.8, 1.6),
    ]
    floor = bench.goals({name: {"median_ms": ms} for name, ms in {**fake, "grid_labels_floor": 3.25}.items()})
    assert floor[1] == ("grid + labels, ms (numpy's floor for their passes: 3.25)", 4.5, 5.0)


def test_the_whole_frame_stages_are_each_a_new_frame_to_the_tracker(monkeypatch):
    """Each timed call of frame_total and frame_every_row is the next frame (a later stamp): the
    tracker runs its whole update and confirms obstacles, as in process, instead of taking a
    repeated stamp for a frame logged twice."""
    from terrainmap import bench
    from terrainmap.config import Config
    from terrainmap.tracking import ObstacleTracker

    stamps, update = {}, ObstacleTracker.update
    monkeypatch.setattr(ObstacleTracker, "update", lambda self, obstacles, stamp_ns, *args: (
        stamps.setdefault(id(self), []).append(stamp_ns), update(self, obstacles, stamp_ns, *args))[1])
    stages = bench.frame_stages(Config())
    results = [stages[name]() for name in ("frame_total", "frame_every_row", "frame_total")]
    assert all(len(s) == len(set(s)) and s == sorted(s) for s in stamps.values()) and len(stamps) == 2
    assert any(o.confirmed for o in results[-1].obstacles)


def test_the_numpy_floor_labels_every_point():
    from terrainmap import bench
    from terrainmap.config import Config
    from terrainmap.synthetic import cloud

    points = cloud(5000, grid=Config().grid)
    labels = bench.numpy_floor(points, Config())()
    assert labels.shape == (5000,) and labels.dtype.name == "uint8"
    # its table of tangent planes and thresholds is all zeros: a point is "above" or "below" unless z is 0
    assert (labels == (points[:, 2] != 0)).all()


def test_eval_artificial_obstacle_on_a_simulated_base_frame(tmp_path, capsys):
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "base.mcap"
    simulate(log, SimConfig(scene="flat", frames=1, seed=3, width=320, height=240, focal_px=250.0))
    result = CliRunner().invoke(
        cli,
        ["eval", "artificial-obstacle", "--base", str(log), "--nets", "25", "--widths", "0.8,12",
         "--heights", "2", "--position", "12,0", "--json", str(tmp_path / "r.json")],
    )
    assert result.exit_code == 0, result.output
    thin, wide = json.loads((tmp_path / "r.json").read_text())
    assert thin["max_deviation_pct"] < wide["max_deviation_pct"]
    assert thin["scene"] == f"{log}, stereo pair 0"  # a report says which base it is of
    topics = ["--left-topic", "/stereo/left/image_rect", "--right-topic", "/stereo/right/image_rect"]
    named = CliRunner().invoke(cli, ["eval", "artificial-obstacle", "--base", str(log), "--nets", "25", "--widths",
                                     "0.8,12", "--heights", "2", "--position", "12,0", *topics,
                                     "--json", str(tmp_path / "n.json")])
    assert named.exit_code == 0, named.output
    assert json.loads((tmp_path / "n.json").read_text()) == [thin, wide]
    with pytest.raises(SystemExit) as exc:  # a base frame with no point in the area
        main(["eval", "artificial-obstacle", "--base", str(log), "--nets", "25", "--set", "grid.x_min_m=-100"])
    assert exc.value.code == 2
    assert capsys.readouterr().err.startswith(f"Error: {log}: stereo pair 0: no finite point lies in the grid area")


def test_eval_robustness_reports_both_fits():
    result = CliRunner().invoke(cli, ["eval", "robustness", "--seeds", "2"])
    assert result.exit_code == 0, result.output
    assert "iterative (Algorithm V-B.1) RMSE" in result.output and "single unweighted fit" in result.output


def test_eval_robustness_writes_what_the_library_gives_as_json(tmp_path):
    from terrainmap.config import Config
    from terrainmap.evaluation import robustness

    out = tmp_path / "r.json"
    result = CliRunner().invoke(cli, ["eval", "robustness", "--seeds", "2", "--noise", "0.05", "--json", str(out)])
    assert result.exit_code == 0, result.output
    expected = robustness.run(Config(), seeds=range(2), noise_m=0.05)
    assert json.loads(out.read_text()) == {**expected, "noise_m": 0.05, "outlier_fraction": 0.1, "outlier_max_m": 2.0,
                                           "empty_fraction": 0.3, "seeds": 2}
    assert f"{100 * expected['iterative_rmse_m']:.2f} cm" in result.output


def test_eval_robustness_ratio_is_the_single_fits_rmse_over_the_iterative_ones():
    from terrainmap.config import Config
    from terrainmap.evaluation import robustness

    r = robustness.run(Config(), seeds=range(1))
    assert r["ratio"] == pytest.approx(r["single_fit_rmse_m"] / r["iterative_rmse_m"]) and r["ratio"] > 2


def test_eval_robustness_takes_outliers_lower_than_the_usual_20_cm():
    """Outliers up to 10 cm (below the 20 cm the generator's default starts at) are drawn and
    reach the fits: the single unweighted fit, which they pull up, is far nearer the truth."""
    import re

    def single_fit_rmse(*extra):
        result = CliRunner().invoke(cli, ["eval", "robustness", "--seeds", "1", *extra])
        assert result.exit_code == 0, result.output
        return float(re.search(r"single unweighted fit RMSE ([\d.]+) cm", result.output).group(1))

    assert single_fit_rmse("--outlier-max", "0.1") < single_fit_rmse() / 4


@pytest.mark.parametrize("argv", [[], ["eval"]])
def test_a_bare_command_group_shows_its_help_not_an_error(argv, capsys):
    from terrainmap.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"Usage: terrainmap {' '.join(argv)}".rstrip() + " [OPTIONS] COMMAND [ARGS]...")
    assert "Error" not in err


def test_an_output_that_cannot_be_written_is_named_and_leaves_no_partial_file(tmp_path, monkeypatch, capsys):
    """A full disk while writing a report, a plot or a simulated log: one line naming the file,
    and no half-written report or plot left behind."""
    import errno
    from pathlib import Path

    import cv2

    from terrainmap.cli.main import main
    from terrainmap.sim import folder_log, mcap_log

    full = OSError(errno.ENOSPC, "No space left on device")

    def no_space(*args, **kwargs):
        raise full

    for argv, path in (
        (["eval", "artificial-obstacle", "--nets", "5", "--widths", "1", "--heights", "1", "--json"], "r.json"),
        (["eval", "artificial-obstacle", "--nets", "5", "--widths", "1", "--heights", "1", "--plot"], "r.png"),
    ):
        with monkeypatch.context() as patch:
            patch.setattr(Path, "replace", no_space)  # the report's last step
            patch.setattr("matplotlib.figure.Figure.savefig", lambda self, p, **k: (Path(p).write_bytes(b"PNG"), no_space()))
            with pytest.raises(SystemExit) as exc:
                main([*argv, str(tmp_path / path)])
        assert exc.value.code == 2
        assert capsys.readouterr().err.splitlines()[-1] == f"Error: cannot write {tmp_path / path}: No space left on device"
        assert list(tmp_path.iterdir()) == []
    # A simulated log, full in its second frame: removed (without its summary, or with frames and
    # stamps that disagree, it would be damaged; the same command renders it again).
    sim = ["--frames", "2", "--width", "32", "--height", "24", "--focal-px", "25"]
    write = mcap_log.McapLog.write
    monkeypatch.setattr(mcap_log.McapLog, "write", lambda log, frame: no_space() if frame.index else write(log, frame))
    with pytest.raises(SystemExit):
        main(["simulate", str(tmp_path / "s.mcap"), *sim])
    assert capsys.readouterr().err.splitlines()[-1] == (f"Error: {tmp_path / 's.mcap'}: cannot write the simulated "
                                                        "log (No space left on device); the part written is removed")
    imwrite = cv2.imwrite
    monkeypatch.setattr(folder_log.cv2, "imwrite", lambda path, image: "000001" not in path and imwrite(path, image))
    with pytest.raises(SystemExit):
        main(["simulate", str(tmp_path / "drive"), *sim])
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"Error: {tmp_path / 'drive'}: cannot write the simulated log (OpenCV cannot write "
        f"{tmp_path / 'drive' / 'left' / '000001'}.png); the part written is removed")
    assert list(tmp_path.iterdir()) == []


def test_sigterm_ends_a_command_like_ctrl_c_and_leaves_no_partial_report(tmp_path, monkeypatch, capsys):
    """A supervisor's SIGTERM during `eval` (which has no graceful stop of its own) ends it with
    "Interrupted." and exit code 143, not silently; the report being written is not left half
    done, and SIGTERM's handler is given back afterwards."""
    import signal
    from pathlib import Path

    def terminated(*args, **kwargs):
        signal.raise_signal(signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(Path, "replace", terminated)  # the report's last step
    with pytest.raises(SystemExit) as exc:
        main(["eval", "artificial-obstacle", "--nets", "5", "--widths", "1", "--heights", "1",
              "--json", str(tmp_path / "r.json")])
    assert exc.value.code == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "Interrupted.\n"  # one line: no empty one before it
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_signal_a_destructor_swallows_still_ends_the_command_as_interrupted(monkeypatch, capsys):
    """A SIGTERM that lands in a destructor (Rerun's recording, freed as a run ends) raises its
    interrupt where Python only prints it: the command then still ends as interrupted, exit
    code 143, not 0."""
    import signal

    class Swallows:
        def __del__(self):
            signal.raise_signal(signal.SIGTERM)

    @click.command()
    def swallow():
        Swallows()

    monkeypatch.setitem(cli.commands, "swallow", swallow)
    with pytest.raises(SystemExit) as exc:
        main(["swallow"])
    assert exc.value.code == 128 + signal.SIGTERM
    assert capsys.readouterr().err.splitlines()[-1] == "Interrupted."


def test_the_console_command_flushes_its_output_and_keeps_the_exit_code():
    """``terrainmap`` (``run``) ends the process at once after the command, not through the
    interpreter's slow exit: what a command wrote into a pipe and left in the buffer still
    arrives, and the exit code (and a ``sys.exit`` message) is the command's."""
    import subprocess
    import sys

    def console(*args):
        code = ("import sys, click; from terrainmap.cli.main import cli, run; "
                "cli.add_command(click.command('buffered')(lambda: sys.stdout.write('left in the buffer'))); "
                "cli.add_command(click.command('says')(lambda: sys.exit('fatal: a message'))); run()")
        buffered = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
        return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60,
                              env=buffered)

    done = console("buffered")
    assert done.returncode == 0 and done.stdout == "left in the buffer"
    says = console("says")
    assert says.returncode == 1 and says.stderr == "fatal: a message\n"
    bad = console("config", "--set", "grid.nope=1")
    assert bad.returncode == 2 and bad.stdout == "" and bad.stderr.startswith("Error: ")


def test_a_report_written_through_a_symbolic_link_keeps_the_link(tmp_path):
    """A report path that is a symbolic link: the file it links to gets the report, and the link
    stays a link (the report is written beside the target, then renamed onto it)."""
    import json

    target = tmp_path / "reports" / "latest.json"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "r.json"
    link.symlink_to(target)
    result = CliRunner().invoke(
        cli, ["eval", "artificial-obstacle", "--nets", "5", "--widths", "1", "--heights", "1", "--json", str(link)]
    )
    assert result.exit_code == 0, result.output
    assert link.is_symlink() and json.loads(target.read_text())[0]["control_points"] == 5
    assert sorted(p.name for p in target.parent.iterdir()) == ["latest.json"]
    target.unlink()  # a link to a file not there yet: the file is made, the link stays
    result = CliRunner().invoke(
        cli, ["eval", "artificial-obstacle", "--nets", "5", "--widths", "1", "--heights", "1", "--json", str(link)]
    )
    assert result.exit_code == 0, result.output
    assert link.is_symlink() and json.loads(target.read_text())[0]["control_points"] == 5


@pytest.mark.parametrize(("argv", "line"), [
    (["eval", "artificial-obstacle", "--nets", "3"],
     "Error: --nets (terrain.control_points_x: must be at least degree + 1 = 4, got 3)"),
    (["eval", "artificial-obstacle", "--base", str(Path(__file__).parents[1] / "examples" / "offroad_demo.mcap"),
      "--length", "10", "--cell", "0.25"],  # would be ignored: the area is the config's grid then
     "Error: --length, --cell set the flat scene's area; with --base the area is the config's grid "
     "(--set grid.length_m=... and the like) (see 'terrainmap eval artificial-obstacle --help')"),
    (["eval", "artificial-obstacle", "--nets", "100"],
     "Error: --nets (terrain.control_points_x × control_points_y: must be at most 4096 (64×64), got 100×100)"),
    (["eval", "artificial-obstacle", "--cell", "100"],
     "Error: --length/--cell (grid.length_m: must hold at least one cell of 100.0 m, got 22.0)"),
    (["eval", "artificial-obstacle", "--frame", "2"],
     "Error: --frame picks a stereo pair of the --base log; give --base too "
     "(see 'terrainmap eval artificial-obstacle --help')"),
    (["eval", "artificial-obstacle", "--length", "1e-9"],  # no cell at all: named as the option, not the net
     "Error: --length/--cell (grid.length_m: must hold at least one cell of 0.5 m, got 1e-09)"),
    (["eval", "artificial-obstacle", "--left-topic", "/x"],  # would be ignored without the log
     "Error: --left-topic is for the log of --base; give --base too (see 'terrainmap eval artificial-obstacle --help')"),
    (["bench", "--runs", "1", "--right-topic", "/x", "--pair-tolerance-ms", "5"],
     "Error: --right-topic, --pair-tolerance-ms are for the log of --log; give --log too (see 'terrainmap bench --help')"),
    (["config", "--config", "a.toml", "--config", "b.toml"],  # click would keep b.toml alone
     "Error: Invalid value for '--config': given 2 times; give one file, and --set for single fields "
     "(see 'terrainmap config --help')"),
    (["process", "x.mcap", "-o", ""],
     "Error: Invalid value for '-o' / '--output': must name a file, got an empty path (see 'terrainmap process --help')"),
])
def test_errors_name_the_option_the_user_gave(argv, line, capsys):
    from terrainmap.cli.main import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines() == [line]


@pytest.mark.parametrize(("words", "expected"), [("terrainmap pro", "plain,process"),
                                                 ("terrainmap process --fl", "plain,--flavor")])
def test_tab_completion_as_the_readme_sets_it_up(words, expected, monkeypatch, capsys):
    """Through main, as the console command runs, with an OpenCV setting it would refuse for work."""
    env = {"_TERRAINMAP_COMPLETE": "bash_complete", "COMP_WORDS": words, "COMP_CWORD": str(len(words.split()) - 1),
           "OPENCV_FOR_THREADS_NUM": "abc"}
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(SystemExit) as exc:
        main([])
    assert exc.value.code == 0 and expected in capsys.readouterr().out.splitlines()


def test_frame_failures_are_counted_and_the_commonest_reasons_first_message_said():
    from terrainmap.cli.options import failures

    assert failures({"a": 1, "b": 3}, {"b": "frame 2: why", "a": "frame 0: x"}) == "b ×3, a ×1; frame 2: why"
    assert failures({"no_ground": 1}, {"no_ground": "frame 0: no_ground"}) == "no_ground ×1"  # nothing more to say
    assert failures({"a": 2}) == "a ×2" and failures({}) == ""


def test_a_slow_runs_rate_is_not_shown_as_zero():
    from terrainmap.cli.process_cmd import _fps

    assert (_fps(0.0412), _fps(0.5), _fps(0.999), _fps(16.63)) == ("0.041", "0.5", "1.0", "16.6")


@pytest.mark.parametrize("name", ["OPENCV_FOR_THREADS_NUM", "OPENCV_IO_MAX_IMAGE_PIXELS"])
@pytest.mark.parametrize("value", ["abc", "-1", " 2", "", "1.5", "2GB", "1k", "18446744073709551616"])
def test_an_opencv_setting_in_the_environment_that_opencv_cannot_read_is_one_line(monkeypatch, capsys, name, value):
    """OpenCV would raise mid-run (the thread count) or abort the process (the image size)."""
    monkeypatch.setenv(name, value)
    with pytest.raises(SystemExit) as exc:
        main(["config"])
    assert exc.value.code == 2
    assert capsys.readouterr().err == (f"Error: environment variable {name} must be a whole number, or one with KB "
                                       f"or MB after it (OpenCV reads it), got {value!r}\n")


@pytest.mark.parametrize("value", ["2", "1MB", "20Kb", "1kb", "18446744073709551615"])
def test_an_opencv_setting_that_opencv_reads_is_taken(monkeypatch, capsys, value):
    monkeypatch.setenv("OPENCV_IO_MAX_IMAGE_PIXELS", value)
    main(["config"])
    assert "[grid]" in capsys.readouterr().out


def test_an_output_that_is_a_symbolic_link_to_itself_is_one_line(tmp_path, capsys):
    loop = tmp_path / "loop.json"
    loop.symlink_to(loop)
    with pytest.raises(SystemExit) as exc:
        main(["eval", "robustness", "--seeds", "1", "--json", str(loop)])
    assert exc.value.code == 2
    assert capsys.readouterr().err.startswith(f"Error: --json {loop}: a symbolic link that leads back to itself")
