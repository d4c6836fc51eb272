"""terrainmap eval accuracy: metrics on known answers, the truth geometry, the report schema, the CLI."""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from terrainmap.cli.eval_accuracy import accuracy
from terrainmap.config import Config
from terrainmap.cost import occupancy
from terrainmap.errors import ConfigError, InputError
from terrainmap.evaluation import accuracy as acc
from terrainmap.evaluation.scores import BANDS, METRICS, Histogram, MethodScores
from terrainmap.evaluation.truth_grid import grid_truth, height_along_z, observed_cells, truth_obstacles
from terrainmap.sim import SimConfig, simulate
from terrainmap.sim.truth import open_truth
from terrainmap.types import FrameResult, Label, Obstacle


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "hills.mcap"
    simulate(path, SimConfig(scene="hills", frames=3, seed=1, width=320, height=240))
    return path


def _grid(shape=(4, 3), range_m=5.0):
    return np.full(shape, range_m)


# --- scores on hand-built cases -------------------------------------------------------------------------

def test_method_equal_to_truth_scores_zero_error_and_f1_one():
    truth_h = np.random.default_rng(0).normal(size=(4, 3))
    truth_slope = np.full((4, 3), 0.1)
    observed = np.ones((4, 3), bool)
    scores = MethodScores()
    scores.add_cells(truth_h.copy(), truth_slope.copy(), truth_h, truth_slope, observed, _grid())
    labels = np.array([True, True, False, True])
    scores.add_points(labels, labels, np.full(4, 5.0))
    band = scores.summary(frames=1)["0-10"]
    assert band["elevation_rmse_m"] == 0 and band["elevation_bias_m"] == 0 and band["elevation_mae_m"] == 0
    assert band["elevation_p95_m"] < 0.001 and band["slope_error_median_deg"] < 0.01
    assert band["coverage"] == 1 and band["terrain_f1"] == 1
    assert band["obstacle_recall"] is None and band["false_obstacles_per_frame"] is None
    assert scores.summary(frames=1)["20-35"]["elevation_rmse_m"] is None  # nothing in that band


def test_known_errors_coverage_and_confusion_per_band():
    truth = np.zeros((2, 2))
    elevation = np.array([[0.1, -0.3], [np.nan, 0.1]])
    range_m = np.array([[5.0, 5.0], [15.0, 15.0]])
    scores = MethodScores()
    scores.add_cells(elevation, None, truth, truth, np.ones((2, 2), bool), range_m)
    predicted = np.array([True, True, False, False, True])
    actual = np.array([True, False, True, False, True])
    scores.add_points(predicted, actual, np.array([5.0, 5.0, 5.0, 15.0, 25.0]))
    out = scores.summary(frames=2)
    near, mid, everything = out["0-10"], out["10-20"], out["all"]
    assert near["elevation_rmse_m"] == pytest.approx(math.sqrt((0.01 + 0.09) / 2))
    assert near["elevation_bias_m"] == pytest.approx(-0.1) and near["elevation_mae_m"] == pytest.approx(0.2)
    assert mid["coverage"] == 0.5 and everything["coverage"] == 0.75
    assert near["slope_error_median_deg"] is None  # the method has no slope
    # all: tp 2, fp 1, fn 1
    assert everything["terrain_precision"] == pytest.approx(2 / 3)
    assert everything["terrain_recall"] == pytest.approx(2 / 3) and everything["terrain_f1"] == pytest.approx(2 / 3)
    assert near["terrain_precision"] == 0.5 and near["terrain_recall"] == 0.5


def test_obstacle_scores_by_band():
    scores = MethodScores()
    scores.add_obstacles([5.0, 15.0, 18.0], np.array([True, False, True]), [25.0])
    scores.add_obstacles([], np.array([], bool), [])
    out = scores.summary(frames=2)
    assert out["0-10"]["obstacle_recall"] == 1 and out["10-20"]["obstacle_recall"] == 0.5
    assert out["all"]["obstacle_recall"] == pytest.approx(2 / 3) and out["20-35"]["obstacle_recall"] is None
    assert out["all"]["false_obstacles_per_frame"] == 0.5 and out["0-10"]["false_obstacles_per_frame"] == 0


def test_histogram_quantile_within_half_a_bin():
    values = np.random.default_rng(1).uniform(0, 1, 10_001)
    hist = Histogram(0.001, 10.0)
    hist.add(values)
    assert abs(hist.quantile(0.95) - np.quantile(values, 0.95)) <= 0.0011
    assert Histogram(0.01, 1.0).quantile(0.5) is None


# --- truth geometry ----------------------------------------------------------------------------------

class _PlaneTruth:
    """A terrain plane z = 0.2·x + 0.1·y + 1 in the world frame."""

    def height(self, x, y):
        return 0.2 * np.asarray(x) + 0.1 * np.asarray(y) + 1.0


def test_height_along_z_lands_on_the_terrain_for_a_tilted_vehicle():
    pitch, roll = np.radians(-11.0), np.radians(5.0)
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = ry @ rx, [3.0, -2.0, 0.4]
    x, y = np.meshgrid(np.linspace(2, 35, 7), np.linspace(-10, 10, 5), indexing="ij")
    h = height_along_z(_PlaneTruth(), pose, x, y)
    world = np.stack([x, y, h, np.ones_like(x)], -1) @ pose.T
    np.testing.assert_allclose(world[..., 2], _PlaneTruth().height(world[..., 0], world[..., 1]), atol=1e-4)


def test_grid_truth_matches_the_truth_pixels(tiny_log):
    config = Config().grid
    with open_truth(tiny_log) as truth:
        frame = next(truth.frames())
        gt = grid_truth(truth, frame, config)
        assert gt.observed.sum() > 100 and not gt.observed[:, 0].any()  # the far right edge is out of view
        assert observed_cells(truth, frame, config, min_pixels=10**6).sum() == 0
        assert np.all(np.isfinite(gt.height_m)) and np.all(gt.slope_rad >= 0)
        near = gt.observed & (gt.range_m < 10)
        assert np.degrees(np.median(gt.slope_rad[near])) < 10  # rolling hills
        boxes = truth_obstacles(frame, truth.calibration)
        assert {b.id for b in boxes} == {o.id for o in frame.obstacles}
        assert all(b.pixels <= np.count_nonzero(frame.instance == b.id) for b in boxes)
        truck = next(b for b in boxes if b.kind == "truck")
        assert truck.pixels > 100 and truck.contains_xy(truck.center_m[:2] + [0, truck.size_m[1] / 2 + 0.4], 0.5)[0]
        assert not truck.contains_xy(truck.center_m[:2] + [0, truck.size_m[1] / 2 + 0.6], 0.5)[0]


def test_obstacle_pixels_count_only_what_both_cameras_see():
    """A left-image pixel whose disparity (fx·B/Z) exceeds its column has no match in the right image."""
    from terrainmap.sim.obstacles import ObstacleBox
    from terrainmap.sim.truth import TruthFrame
    from terrainmap.types import StereoCalibration

    cal = StereoCalibration(width=64, height=8, fx=50.0, fy=50.0, cx=32.0, cy=4.0, baseline_m=0.3)  # 15 px at 1 m
    instance = np.zeros((8, 64), np.uint8)
    instance[:, 0:10] = 1  # at the left edge: out of the right camera's view
    instance[:, 30:40] = 2
    depth = np.full((8, 64), 1.0, np.float32)
    boxes = [ObstacleBox(i, "rock", "box", np.array([5.0, 0, 0.3]), np.ones(3), 0.0, 0.6, np.zeros(3)) for i in (1, 2)]
    frame = TruthFrame(0, 0, np.eye(3), np.zeros(3), boxes, depth, np.zeros((8, 64), np.uint8), instance)
    assert [b.pixels for b in truth_obstacles(frame, cal)] == [0, 80]
    depth[:, 0:10] = 10.0  # 1.5 px of disparity: columns 2–9 are matched
    assert [b.pixels for b in truth_obstacles(frame, cal)] == [64, 80]


# --- one hand-built frame through the scoring ----------------------------------------------------------

def _score_frame(monkeypatch, *, truth=None, truth_boxes=(), obstacles=(), point_labels=(), pixel_labels=(), **options):
    """An evaluation of terrainmap on one hand-built frame: its points 5 m ahead, each on its own
    pixel of a one-row truth image of ``pixel_labels``; ``truth_boxes`` the frame's truth obstacles
    (vehicle frame, the vehicle at the world origin); no cell observed."""
    from terrainmap.evaluation.truth_grid import GridTruth
    from terrainmap.sim.truth import TruthFrame
    from terrainmap.types import Extrinsics

    config = Config()
    shape = config.grid.shape
    gt = GridTruth(np.zeros(shape, bool), np.zeros(shape), np.zeros(shape), np.full(shape, 5.0), list(truth_boxes))
    monkeypatch.setattr(acc, "grid_truth", lambda *args, **kwargs: gt)
    n = len(point_labels)
    width = max(n, 1)
    label_image = np.zeros((1, width), np.uint8)
    label_image[0, :n] = pixel_labels
    frame = TruthFrame(0, 0, np.eye(3), np.zeros(3), [], np.ones((1, width), np.float32), label_image,
                       np.zeros((1, width), np.uint8))
    layers = {"elevation": np.zeros(shape, np.float32), "slope": np.zeros(shape), "valid": np.zeros(shape, bool)}
    result = FrameResult(0, 0, Extrinsics(np.eye(3), np.zeros(3)), np.tile(np.float32([5, 0, 0]), (n, 1)),
                         np.column_stack([np.arange(n), np.zeros(n)]).astype(np.int32),
                         np.array(point_labels, np.uint8), None, None, layers=layers, obstacles=list(obstacles))
    options = {"obstacle_margin_m": 0.5, "obstacle_min_height_m": 0.5, "obstacle_range_m": 20.0,
               "min_visible_pixels": 20, "min_terrain_pixels": 1, **options}
    run = acc._Evaluation(truth, config, ["terrainmap"], options)
    run.add_frame(result, frame)
    return run


def test_points_labelled_below_count_as_not_terrain(monkeypatch):
    """TERRAIN and BELOW on terrain pixels, BELOW and OBSTACLE on obstacle pixels: precision 1, recall 1/2."""
    run = _score_frame(monkeypatch, point_labels=[Label.TERRAIN, Label.BELOW, Label.BELOW, Label.OBSTACLE],
                       pixel_labels=[1, 1, 2, 2])
    scores = run.scores["terrainmap"].summary(frames=1)["all"]
    assert scores["terrain_precision"] == 1 and scores["terrain_recall"] == 0.5


class _PitsTruth:
    """Level terrain at height 0 with round pits (centre x, y, depth) of radius 0.4 m, world frame."""

    def __init__(self, *pits):
        self.pits = pits

    def height(self, x, y):
        h = np.zeros(np.broadcast(x, y).shape)
        for px, py, depth in self.pits:
            h = np.where(np.hypot(np.asarray(x) - px, np.asarray(y) - py) < 0.4, -depth, h)
        return h


def test_a_negative_obstacle_is_false_only_where_the_truth_is_shallower_than_half_min_depth(monkeypatch):
    """With ``obstacles.min_depth_m`` 0.3 m, a negative obstacle over a true pit 0.2 m deep is right, over one
    0.1 m deep false."""
    assert Config().obstacles.min_depth_m == 0.3
    truth = _PitsTruth((10.0, 3.0, 0.2), (12.0, -3.0, 0.1))
    ditches = [Obstacle(np.array([x, y, -0.1]), np.array([1.0, 1.0, 0.2]), 0.0, 0.2, 30, float(np.hypot(x, y)),
                        kind="negative", track_id=k, confirmed=True) for k, (x, y) in enumerate([(10, 3), (12, -3)])]
    run = _score_frame(monkeypatch, truth=truth, obstacles=ditches)
    assert run.scores["terrainmap"].summary(frames=1)["all"]["false_obstacles_per_frame"] == 1


def test_a_negative_obstacles_depression_is_measured_on_a_ring_just_beyond_its_half_width(monkeypatch):
    """The truth's depth under a 1 m wide negative obstacle is taken against a ring of radius 0.5 + 0.5 m
    (half its width plus the margin): a pit 0.2 m deep in level ground is a right detection, though the ground
    2–3 m away lies 0.3 m lower still."""

    class PitInAHollow:
        def height(self, x, y):
            r = np.hypot(np.asarray(x) - 10.0, np.asarray(y) - 3.0)
            return np.where(r < 0.4, -0.2, np.where((r > 2.0) & (r < 3.0), -0.3, 0.0))

    ditch = Obstacle(np.array([10.0, 3.0, -0.1]), np.array([1.0, 1.0, 0.2]), 0.0, 0.2, 30, float(np.hypot(10, 3)),
                     kind="negative", track_id=1, confirmed=True)
    run = _score_frame(monkeypatch, truth=PitInAHollow(), obstacles=[ditch])
    assert run.scores["terrainmap"].summary(frames=1)["all"]["false_obstacles_per_frame"] == 0

def test_only_truth_obstacles_within_the_obstacle_range_count(monkeypatch):
    """A truth rock at 10 m (tracked) and one at 25 m (not) with ``obstacle_range_m`` 20: recall 1, and only the
    near one has a frames-to-confirmation entry."""
    from terrainmap.evaluation.truth_grid import TruthObstacle

    rocks = [TruthObstacle(k, "rock", np.array([x, y, 0.5]), np.ones(3), 0.0, 1.0, 100)
             for k, (x, y) in ((1, (10.0, 2.0)), (2, (25.0, -2.0)))]
    track = Obstacle(np.array([10.0, 2.0, 0.5]), np.ones(3), 0.0, 1.0, 80, 10.2, track_id=7, confirmed=True)
    run = _score_frame(monkeypatch, truth_boxes=rocks, obstacles=[track], obstacle_range_m=20.0)
    assert run.scores["terrainmap"].summary(frames=1)["all"]["obstacle_recall"] == 1
    assert run.report(Path("log.mcap"), Counter(), 0.0)["obstacles"]["frames_to_confirmation"] == {"1 rock": 0}



def test_points_on_sky_pixels_are_not_scored(monkeypatch):
    """A point labelled TERRAIN on a sky pixel is neither a true nor a false terrain point."""
    run = _score_frame(monkeypatch, point_labels=[Label.TERRAIN, Label.TERRAIN, Label.OBSTACLE], pixel_labels=[1, 0, 2])
    scores = run.scores["terrainmap"].summary(frames=1)["all"]
    assert scores["terrain_precision"] == 1 and scores["terrain_recall"] == 1


def test_an_obstacle_exactly_as_tall_and_as_far_as_the_limits_is_eligible(monkeypatch):
    """``obstacle_min_height_m`` and ``obstacle_range_m`` are "at least" and "within": a rock 0.5 m tall
    at 20.0 m counts, and its track matches it."""
    from terrainmap.evaluation.truth_grid import TruthObstacle

    rock = TruthObstacle(1, "rock", np.array([20.0, 0.0, 0.25]), np.ones(3), 0.0, 0.5, 100)
    track = Obstacle(np.array([20.0, 0.0, 0.25]), np.ones(3), 0.0, 0.5, 80, 20.0, track_id=3, confirmed=True)
    run = _score_frame(monkeypatch, truth_boxes=[rock], obstacles=[track], obstacle_range_m=20.0,
                       obstacle_min_height_m=0.5)
    assert run.scores["terrainmap"].summary(frames=1)["all"]["obstacle_recall"] == 1


def test_a_detection_within_the_margin_of_a_true_footprint_is_not_false(monkeypatch):
    """A confirmed obstacle 0.3 m beside a true rock's footprint (margin 0.5 m) is the rock, not a false
    obstacle; 0.7 m beside it, it is."""
    from terrainmap.evaluation.truth_grid import TruthObstacle

    rock = TruthObstacle(1, "rock", np.array([10.0, 0.0, 0.5]), np.ones(3), 0.0, 1.0, 100)
    for offset, false in ((0.8, 0), (1.2, 1)):  # the footprint ends 0.5 m from the centre
        track = Obstacle(np.array([10.0, offset, 0.5]), np.ones(3), 0.0, 1.0, 80, 10.0, track_id=3, confirmed=True)
        run = _score_frame(monkeypatch, truth_boxes=[rock], obstacles=[track])
        assert run.scores["terrainmap"].summary(frames=1)["all"]["false_obstacles_per_frame"] == false, offset


# --- evaluate(): a perfect pipeline scores perfectly; schema; errors ---------------------------------------

def _oracle(truth_path, config: Config, spoil_far_cells: bool = False, blocking: bool = True):
    """A process_frame that returns the truth itself (truth pixels as points, truth layers, truth
    obstacles, a cost of 1 on their footprints, or nowhere without ``blocking``); with
    ``spoil_far_cells``, its elevation is 5 m off beyond 10 m, where its cells are marked not
    valid (no data: what ``process`` writes as NaN)."""
    truth = open_truth(truth_path)
    frames = {f.stamp_ns: f for f in truth.frames()}
    cal, ext = truth.calibration, truth.extrinsics

    def process_frame(frame, cfg, state):
        tf = frames[frame.stamp_ns]
        gt = grid_truth(truth, tf, cfg.grid)
        v, u = np.nonzero(tf.label > 0)
        z = tf.depth[v, u]
        cam = np.column_stack([(u - cal.cx) / cal.fx * z, (v - cal.cy) / cal.fy * z, z])
        points = (cam @ ext.rotation.T + ext.translation).astype(np.float32)
        labels = np.where(tf.label[v, u] == 1, Label.TERRAIN, Label.OBSTACLE).astype(np.uint8)
        obstacles = [Obstacle(b.center_m, b.size_m, b.yaw_rad, b.height_m, b.pixels, b.range_m, confirmed=True)
                     for b in gt.obstacles if b.pixels > 0]
        layers = {"elevation": gt.height_m.astype(np.float32), "slope": gt.slope_rad, "valid": np.ones(gt.range_m.shape, bool),
                  "cost": occupancy(obstacles, cfg.grid, 0.0).astype(np.float32) * blocking}
        if spoil_far_cells:
            far = gt.range_m > 10
            layers["elevation"][far] += 5
            layers["valid"][far] = False
        return FrameResult(frame.index, frame.stamp_ns, ext, points, np.column_stack([u, v]), labels, None, None,
                           layers=layers, obstacles=obstacles)

    return process_frame


def test_a_pipeline_equal_to_the_truth_scores_perfectly(tiny_log, monkeypatch):
    monkeypatch.setattr(acc, "process_frame", _oracle(tiny_log, Config()))
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap"])
    assert report["frames"] == 3
    for band in ("0-10", "10-20", "all"):
        scores = report["methods"]["terrainmap"][band]
        assert scores["elevation_rmse_m"] < 1e-5 and scores["elevation_p95_m"] <= 0.001
        assert scores["slope_error_median_deg"] <= 0.01 and scores["coverage"] == 1
        assert scores["terrain_f1"] == 1 and scores["false_obstacles_per_frame"] == 0
    assert report["methods"]["terrainmap"]["all"]["obstacle_recall"] == 1
    assert all(v == 0 for v in report["obstacles"]["frames_to_confirmation"].values())
    assert all(v == 0 for v in report["obstacles"]["id_switches"].values())
    assert all(v == 0 for v in report["obstacles"]["duplicate_frames"].values())
    assert report["obstacles"]["blocked_by_cost"] == 1
    monkeypatch.setattr(acc, "process_frame", _oracle(tiny_log, Config(), blocking=False))
    assert acc.evaluate(tiny_log, Config(), methods=["terrainmap"])["obstacles"]["blocked_by_cost"] == 0


def test_cells_without_data_are_not_scored_but_lower_the_coverage(tiny_log, monkeypatch):
    """terrainmap is scored on its elevation as written: the surface's extrapolation into cells
    without data (NaN in the output) does not count against its RMSE, only against its coverage."""
    monkeypatch.setattr(acc, "process_frame", _oracle(tiny_log, Config(), spoil_far_cells=True))
    scores = acc.evaluate(tiny_log, Config(), methods=["terrainmap"])["methods"]["terrainmap"]
    assert scores["0-10"]["elevation_rmse_m"] < 1e-5 and scores["0-10"]["coverage"] == 1
    assert scores["10-20"]["elevation_rmse_m"] is None and scores["10-20"]["coverage"] == 0
    assert 0 < scores["all"]["coverage"] < 1 and scores["all"]["elevation_rmse_m"] < 1e-5


def test_late_confirmations_id_switches_and_false_obstacles_are_counted(tiny_log, monkeypatch):
    """The oracle again, but nothing confirmed in the first frame, every track id changed in the
    third, and one confirmed obstacle 11 m away where the truth has none, in every frame."""
    import dataclasses

    oracle = _oracle(tiny_log, Config())

    def flawed(frame, cfg, state):
        result = oracle(frame, cfg, state)
        obstacles = [dataclasses.replace(o, track_id=k + 50 * (frame.index == 2), confirmed=frame.index > 0)
                     for k, o in enumerate(result.obstacles)]
        ghost = Obstacle(np.array([8.0, -8.0, 0.5]), np.array([1.0, 1.0, 1.0]), 0.0, 1.0, 40, 11.3, confirmed=True)
        return dataclasses.replace(result, obstacles=[*obstacles, ghost])

    monkeypatch.setattr(acc, "process_frame", flawed)
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap"])
    confirmation, switches = report["obstacles"]["frames_to_confirmation"], report["obstacles"]["id_switches"]
    assert confirmation["2 pedestrian"] == 1  # eligible in frame 0, confirmed in frame 1
    assert max(confirmation.values()) == 1  # (the rock becomes eligible later: 0)
    assert switches["2 pedestrian"] == 1  # matched in frames 1 and 2 under two ids
    assert report["methods"]["terrainmap"]["10-20"]["false_obstacles_per_frame"] == 1
    assert report["methods"]["terrainmap"]["0-10"]["false_obstacles_per_frame"] == 0


def test_the_track_that_carries_an_obstacle_into_range_keeps_the_credit(tiny_log, monkeypatch):
    """The pedestrian (18.3, 17.9, 17.5 m away) comes within an 18 m range in frame 1. Its track
    (id 0 here, 0.3 m off its centre) carries it from frame 0; in frame 1 a second track sits on its
    centre. The credit stays with the first track: no id switch when the second one is gone; the
    frame with both is counted as a frame with two tracks."""
    import dataclasses

    oracle = _oracle(tiny_log, Config())

    def duplicated(frame, cfg, state):
        result = oracle(frame, cfg, state)
        pedestrian = next(o for o in result.obstacles if o.height_m == pytest.approx(1.8, abs=0.05))
        carried = dataclasses.replace(pedestrian, center_m=pedestrian.center_m + [0.3, 0, 0], track_id=0)
        fragment = [dataclasses.replace(pedestrian, track_id=99)] if frame.index == 1 else []
        return dataclasses.replace(result, obstacles=[carried, *fragment])

    monkeypatch.setattr(acc, "process_frame", duplicated)
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap"], obstacle_range_m=18.0)
    assert report["obstacles"]["frames_to_confirmation"]["2 pedestrian"] == 0  # eligible and matched in frame 1
    assert report["obstacles"]["id_switches"]["2 pedestrian"] == 0
    assert report["obstacles"]["duplicate_frames"]["2 pedestrian"] == 1


def test_report_schema_on_a_simulated_log(tiny_log):
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap", "ransac_plane"], max_frames=2)
    json.dumps(report)  # JSON-able
    assert report["frames"] == 2 and report["log"] == str(tiny_log)
    assert set(report["methods"]) == {"terrainmap", "ransac_plane"}
    for scores in report["methods"].values():
        assert list(scores) == list(BANDS) == ["0-10", "10-20", "0-20", "20-35", "all"]
        assert all(list(band) == list(METRICS) for band in scores.values())
    tm, plane = report["methods"]["terrainmap"]["all"], report["methods"]["ransac_plane"]["all"]
    assert plane["obstacle_recall"] is None and plane["false_obstacles_per_frame"] is None
    assert tm["false_obstacles_per_frame"] is not None and 0 <= tm["coverage"] <= 1
    assert 0 < tm["terrain_f1"] <= 1 and tm["elevation_rmse_m"] < 2.0
    assert report["config"]["grid"]["cell_size_m"] == 0.5 and report["seconds"]["wall"] > 0
    # the plane covers every observed cell, terrainmap those with data: the common cells are terrainmap's
    common = report["common_cells"]["terrainmap"]["all"]
    assert common["cells"] > 0 and common["cells"] == report["common_cells"]["ransac_plane"]["all"]["cells"]
    assert common["elevation_rmse_m"] == pytest.approx(tm["elevation_rmse_m"])
    assert plane["coverage"] == 1 and tm["coverage"] < 1
    assert report["obstacles"]["false_on_steep_ground_per_frame"] is not None
    alone = acc.evaluate(tiny_log, Config(), methods=["ransac_plane"], max_frames=1)["obstacles"]
    assert alone["false_on_steep_ground_per_frame"] is None and alone["frames_to_confirmation"] == {}


def _strip_truth(src, dst):
    """Copy an MCAP without its /truth/... channels."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as fin, open(dst, "wb") as fout:
        reader, writer = make_reader(fin), Writer(fout)
        writer.start()
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages():
            if channel.topic.startswith("/truth"):
                continue
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id], channel.metadata)
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()


def test_a_log_without_truth_is_an_input_error_naming_the_topics(tiny_log, tmp_path):
    plain = tmp_path / "plain.mcap"
    _strip_truth(tiny_log, plain)
    with pytest.raises(InputError, match=r"plain\.mcap.*missing topics.*/truth/"):
        acc.evaluate(plain, Config(), methods=["terrainmap"])
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(tiny_log.read_bytes()[: tiny_log.stat().st_size // 2])
    with pytest.raises(InputError, match=r"cut\.mcap: the log has no summary \(cut short"):
        acc.evaluate(cut, Config(), methods=["terrainmap"])
    bag = tmp_path / "drive.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(InputError, match=r"drive\.bag: not an MCAP file; the ground truth is read from logs"):
        acc.evaluate(bag, Config(), methods=["terrainmap"])


def test_unknown_method_lists_the_available_ones(tiny_log):
    with pytest.raises(ConfigError, match=r"unknown method 'nope'; available: terrainmap, .*ransac_plane"):
        acc.evaluate(tiny_log, Config(), methods=["terrainmap", "nope"])
    result = CliRunner().invoke(accuracy, [str(tiny_log), "--methods", "terrainmap,nope"])
    assert result.exit_code == 2 and "unknown method 'nope'; available: terrainmap" in result.output


def test_table_lists_each_true_obstacle():
    from terrainmap.evaluation.accuracy_report import format_table

    report = {"log": "x.mcap", "frames": 3, "failed_frames": {"no_ground": 2}, "methods": {}, "obstacles": {
        "min_height_m": 0.5, "range_m": 20.0,
        "frames_to_confirmation": {"1 pedestrian": 2, "3 pole": None}, "id_switches": {"1 pedestrian": 1},
        "duplicate_frames": {"1 pedestrian": 3}, "blocked_by_cost": 0.9251}}
    lines = format_table(report).splitlines()
    assert lines[0] == "x.mcap: 3 frames, failed: no_ground ×2"
    assert lines[-3].split() == ["1", "pedestrian", "2", "1", "3"]
    assert lines[-2].split() == ["3", "pole", "never", "—", "—"]
    assert lines[-1] == "true obstacles within 20.0 m whose footprint holds a cell of cost 1, per frame: 92.5 %"


def test_cli_prints_the_table_and_writes_json_and_plot(tiny_log, tmp_path):
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    result = CliRunner().invoke(accuracy, [
        str(tiny_log), "--methods", "terrainmap,lowest_point", "--max-frames", "2", "--json", str(out_json),
        "--plot", str(out_png), "--set", "terrain.control_points_x=15", "--obstacle-margin", "1",
    ])
    assert result.exit_code == 0, result.output
    for text in ("range 0-10 m", "range 10-20 m", "all ranges", "rmse_m", "terrainmap", "lowest_point", "wall time"):
        assert text in result.output
    report = json.loads(out_json.read_text())
    if report["obstacles"]["frames_to_confirmation"]:
        assert "frames to confirm" in result.output
        for key in report["obstacles"]["frames_to_confirmation"]:
            assert key in result.output
    assert report["frames"] == 2 and report["config"]["terrain"]["control_points_x"] == 15
    assert report["obstacles"]["margin_m"] == 1.0
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_log_no_frame_of_which_can_be_scored_is_an_error_and_writes_no_report(tiny_log, tmp_path):
    out_json = tmp_path / "r.json"
    result = CliRunner().invoke(accuracy, [str(tiny_log), "--methods", "terrainmap", "--max-frames", "2", "--json",
                                           str(out_json), "--set", "grid.z_min_m=40", "--set", "grid.z_max_m=50"])
    assert result.exit_code == 2 and f"no frame of {tiny_log} could be scored (no_points_in_area ×2)" in result.output
    assert not out_json.exists()  # a report of nulls only would read as a result


def test_match_tracks_keeps_a_matching_track_and_switches_only_when_it_is_lost():
    """CLEAR MOT: two tracks on one obstacle do not make switches while the credited one matches."""
    both = np.array([[True, True]])
    assert acc.match_tracks(both, np.array([[1.0, 0.2]]), [None], [7, 9]).tolist() == [1]  # first: the nearest
    assert acc.match_tracks(both, np.array([[0.1, 0.8]]), [9], [7, 9]).tolist() == [1]  # still matching: kept
    assert acc.match_tracks(both, np.array([[0.5, 0.3]]), [9], [7, 4]).tolist() == [1]  # lost: the nearest
    assert acc.match_tracks(np.zeros((1, 2), bool), np.ones((1, 2)), [7], [7, 4]).tolist() == [-1]
    assert acc.match_tracks(np.zeros((0, 0), bool), np.zeros((0, 0)), [], []).tolist() == []


def test_a_frame_with_no_true_obstacle_in_view_is_scored(tiny_log):
    """No truth obstacle counts (none is 100 m tall), as in the last frames of a long drive that
    has passed them all: the frames are scored all the same (a reshape of no rows failed)."""
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap"], max_frames=2, obstacle_min_height_m=100.0)
    assert report["frames"] == 2 and report["obstacles"]["frames_to_confirmation"] == {}
    assert report["methods"]["terrainmap"]["all"]["obstacle_recall"] is None


def test_match_tracks_is_one_to_one():
    """One cluster over a car and the rock beside it finds the nearer of the two, not both; two
    tracks find two truths wherever a one-to-one pairing allows it (the Hungarian method, not
    the nearest pair first); a track kept by continuity is not given to another truth."""
    hits = np.array([[True], [True]])
    assert acc.match_tracks(hits, np.array([[1.2], [0.9]]), [None, None], [4]).tolist() == [-1, 0]
    hits, distances = np.array([[True, True], [True, False]]), np.array([[0.2, 0.5], [0.3, np.inf]])
    assert acc.match_tracks(hits, distances, [None, None], [4, 5]).tolist() == [1, 0]
    assert acc.match_tracks(hits, distances, [5, None], [4, 5]).tolist() == [1, 0]
    assert acc.match_tracks(hits, distances, [4, 4], [4, 5]).tolist() == [0, -1]  # truth 0 keeps track 4
    hits, distances = np.array([[True, True], [True, True]]), np.array([[0.2, 0.9], [0.3, 0.4]])
    assert acc.match_tracks(hits, distances, [None, None], [4, 5]).tolist() == [0, 1]  # 0.6 m in all, not 1.2


def test_one_track_between_two_obstacles_finds_one_of_them(tiny_log, monkeypatch):
    """The oracle's obstacles merged into one confirmed track at the pedestrian's centre with a
    footprint over every truth: it is the pedestrian's, and every other eligible obstacle is missed."""
    import dataclasses

    oracle = _oracle(tiny_log, Config())

    def merged(frame, cfg, state):
        result = oracle(frame, cfg, state)
        pedestrian = next(o for o in result.obstacles if o.height_m == pytest.approx(1.8, abs=0.05))
        return dataclasses.replace(result, obstacles=[dataclasses.replace(pedestrian, track_id=3)])

    monkeypatch.setattr(acc, "process_frame", merged)
    report = acc.evaluate(tiny_log, Config(), methods=["terrainmap"], obstacle_margin_m=40.0)
    others = dict(report["obstacles"]["frames_to_confirmation"])
    assert others.pop("2 pedestrian") == 0 and others and set(others.values()) == {None}
    assert report["methods"]["terrainmap"]["all"]["obstacle_recall"] < 1


@pytest.mark.parametrize(
    "damaged, content",
    [("scene.json", b"\xff\xfe garbage"), ("scene.json", b"{}"), ("terrain.npz", b"garbage"), ("000000.npz", b"x"),
     ("terrain.npz", "cut"), ("000000.npz", "cut")],  # cut: the file's first 300 bytes (no zip directory)
)
def test_damaged_truth_files_are_named(tmp_path, damaged, content):
    from terrainmap.errors import InputError
    from terrainmap.sim import SimConfig, open_truth, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=1, seed=1, width=64, height=48, format="folder"))
    file = log / "truth" / damaged
    file.write_bytes(file.read_bytes()[:300] if content == "cut" else content)
    with pytest.raises(InputError, match=f"truth/{damaged}: damaged ground truth"):
        with open_truth(log) as truth:
            list(truth.frames())


@pytest.mark.parametrize(
    "change, message",
    [(lambda a: {"depth": np.zeros((10, 10), np.float32)}, "differ in size"),
     (lambda a: {"obstacle_size_m": a["obstacle_size_m"] * np.nan}, "obstacle 1 is not a finite box of positive size"),
     (lambda a: {"obstacle_size_m": -a["obstacle_size_m"]}, "obstacle 1 is not a finite box of positive size")],
)
def test_truth_arrays_that_do_not_fit_are_named(tmp_path, change, message):
    from terrainmap.errors import InputError
    from terrainmap.sim import SimConfig, open_truth, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=1, seed=1, width=64, height=48, format="folder"))
    frame = log / "truth" / "000000.npz"
    with np.load(frame) as data:
        arrays = dict(data)
    np.savez(frame, **{**arrays, **change(arrays)})
    with pytest.raises(InputError, match=f"000000.npz: damaged ground truth .*{message}"):
        with open_truth(log) as truth:
            list(truth.frames())


@pytest.mark.parametrize("command", ["accuracy", "stereo"])
def test_truth_images_of_another_size_than_the_stereo_images_are_named(tmp_path, capsys, command):
    """Truth whose depth, label and instance images agree with each other but not with the
    stereo pair: one line naming the frame and both sizes, not an IndexError from the scoring."""
    from terrainmap.cli.main import main
    from terrainmap.sim import SimConfig, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=1, seed=1, width=64, height=48, format="folder"))
    frame = log / "truth" / "000000.npz"
    with np.load(frame) as data:
        arrays = dict(data)
    np.savez(frame, **{**arrays, **{k: arrays[k][:10] for k in ("depth", "label", "instance")}})
    with pytest.raises(SystemExit) as exc:
        main(["eval", command, str(log)])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1
    assert err[0].startswith(f"Error: {log}: the ground truth of the stereo frame at stamp ")
    assert err[0].endswith(" is 64×10 pixels, its images 64×48")


def test_a_truth_grid_that_is_no_grid_is_named():
    from types import SimpleNamespace

    from terrainmap.errors import InputError
    from terrainmap.sim.messages import heightfield_from_grid_map

    info = SimpleNamespace(resolution=0.0, length_x=10.0, length_y=8.0, pose=SimpleNamespace(position=SimpleNamespace(x=0, y=0)))
    grid = SimpleNamespace(layers=["elevation"], info=info, data=[SimpleNamespace(data=[0.0] * 4)],
                           outer_start_index=0, inner_start_index=0)
    with pytest.raises(InputError, match=r"/truth/terrain: GridMap of 10×8 m at 0 m resolution is no grid"):
        heightfield_from_grid_map(grid, "/truth/terrain")
    grid.data = []  # a layer without its data array
    with pytest.raises(InputError, match=r"/truth/terrain: GridMap has 1 layers but 0 data arrays"):
        heightfield_from_grid_map(grid, "/truth/terrain")


@pytest.mark.parametrize(
    "field, value, message",
    [("baseline_m", "x", "ConfigError: SimConfig.baseline_m: must be a number, got 'x'"),
     ("focal_px", 0, "ConfigError: SimConfig.focal_px: must be > 0, got 0"),
     ("frames", None, "ConfigError: SimConfig.frames: must be an integer, got None"), ("nonsense", 1, "TypeError")],
)
def test_a_damaged_scene_description_is_named_not_scored(tmp_path, field, value, message):
    """The simulator's settings stored with the truth (the rig the scoring rebuilds): a value of
    the wrong type or out of range is damaged truth, not warnings and empty scores."""
    import json

    from terrainmap.sim import SimConfig, open_truth, simulate

    log = tmp_path / "log"
    simulate(log, SimConfig(scene="flat", frames=1, seed=1, width=64, height=48, format="folder"))
    scene = log / "truth" / "scene.json"
    description = json.loads(scene.read_text())
    description["config"][field] = value
    scene.write_text(json.dumps(description))
    with pytest.raises(InputError, match=f"scene.json: damaged ground truth \\({message}"):
        open_truth(log)


@pytest.mark.parametrize("where", ["chunk", "summary"])
def test_damaged_truth_in_a_log_is_an_input_error_not_wrong_scores(tmp_path, where):
    """A byte changed in a chunk that holds truth (its CRC fails) or in the summary: the truth is
    refused with one message naming the log, never read as other values."""
    import struct

    from mcap.reader import make_reader

    from terrainmap.errors import InputError
    from terrainmap.sim import SimConfig, open_truth, simulate

    log = tmp_path / "sim.mcap"
    simulate(log, SimConfig(scene="flat", frames=3, seed=1, width=320, height=240, focal_px=250.0))
    data = bytearray(log.read_bytes())
    with open(log, "rb") as file:
        summary = make_reader(file).get_summary()
    if where == "chunk":  # the last chunk: a later frame's truth, not the terrain read at open
        depth = next(i for i, c in summary.channels.items() if c.topic == "/truth/left/depth")
        chunk = [c for c in summary.chunk_indexes if depth in c.message_index_offsets][-1]
        assert chunk is not summary.chunk_indexes[0]
        data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0xFF
    else:
        summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
        data[data.index(b"/truth/left/depth", summary_start) + 8] ^= 0x01  # /truth/left/depth -> .../lefu/...
    log.write_bytes(bytes(data))
    with pytest.raises(InputError, match=f"{log}: damaged") as info:
        with open_truth(log) as truth:
            list(truth.frames())
    if where == "chunk":  # where in the log: the log time of the last truth read before the chunk
        seconds = float(re.search(r"damaged ground truth after log time (\d+\.\d{3}) s", str(info.value))[1])
        assert summary.chunk_indexes[0].message_start_time <= seconds * 1e9 <= chunk.message_start_time + 5e5


def test_bands_take_their_lower_edge_and_precision_is_not_recall():
    """A point at exactly 10 m is in the 10-20 band (``lo <= r < hi``); predicted terrain 4 points
    of which 2 are terrain, no terrain point missed: precision 0.5, recall 1."""
    scores = MethodScores()
    predicted = np.array([True, True, True, True])
    actual = np.array([True, True, False, False])
    scores.add_points(predicted, actual, np.array([10.0, 10.0, 10.0, 10.0]))
    out = scores.summary(frames=1)
    assert out["0-10"]["terrain_precision"] is None
    assert out["10-20"]["terrain_precision"] == 0.5 and out["10-20"]["terrain_recall"] == 1.0


# --- the truth on the grid: hand-built truth with a known answer ----------------------------------------

def _flat_truth(height=lambda x, y: np.zeros(np.shape(x)), translation=(0.25, 0.25, 0.0)):
    """A truth with terrain ``height`` (world frame) seen by a camera on the ground looking along +x
    (optical z = base x, optical x = base −y), 64×8 pixels, fx 50, principal point (32, 4)."""
    from types import SimpleNamespace

    from terrainmap.sim.rig import _OPTICAL_IN_BASE
    from terrainmap.types import Extrinsics, StereoCalibration

    cal = StereoCalibration(width=64, height=8, fx=50.0, fy=50.0, cx=32.0, cy=4.0, baseline_m=0.3)
    return SimpleNamespace(height=lambda x, y: np.asarray(height(np.asarray(x), np.asarray(y)), float),
                           calibration=cal, extrinsics=Extrinsics(_OPTICAL_IN_BASE, np.array(translation)))


def _one_row_frame(label_columns: dict[int, int], depth_m: float = 10.0, pose=(np.eye(3), np.zeros(3)), obstacles=()):
    """A TruthFrame whose row 4 holds pixels of ``label_columns`` (column → label) at ``depth_m``."""
    from terrainmap.sim.truth import TruthFrame

    label = np.zeros((8, 64), np.uint8)
    for u, value in label_columns.items():
        label[4, u] = value
    instance = np.where(label == 2, 1, 0).astype(np.uint8)
    return TruthFrame(0, 0, *pose, list(obstacles), np.full((8, 64), depth_m, np.float32), label, instance)


def test_a_cell_is_observed_by_at_least_min_pixels_terrain_pixels_not_by_obstacle_pixels():
    """Two terrain pixels fall in the cell of (10.25, 0.25) m, three obstacle pixels in that of
    (10.25, −1.75) m: only the first is observed, with up to 2 pixels asked for ("at least")."""
    from terrainmap.grid import cell_index

    grid = Config().grid
    truth = _flat_truth()
    frame = _one_row_frame({32: 1, 33: 1, 42: 2, 43: 2, 44: 2})  # 0.2 m per column at 10 m
    terrain_cell = cell_index(np.array([[10.25, 0.25, 0.0]]), grid)[0]
    for min_pixels in (1, 2):
        observed = observed_cells(truth, frame, grid, min_pixels=min_pixels)
        assert np.flatnonzero(observed).tolist() == [terrain_cell], min_pixels
    assert not observed_cells(truth, frame, grid, min_pixels=3).any()


def test_grid_truth_of_a_plane_gives_its_height_slope_and_range_at_each_cell_centre():
    """Terrain z = 0.1·x − 0.05·y under a vehicle at the origin: the truth height at every cell centre
    is the plane's, its slope atan(|∇z|) and its range the horizontal distance of the centre."""
    from terrainmap.grid import cell_centers

    grid = Config().grid
    truth = _flat_truth(lambda x, y: 0.1 * x - 0.05 * y)
    gt = grid_truth(truth, _one_row_frame({32: 1}), grid)
    xs, ys = cell_centers(grid)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    np.testing.assert_allclose(gt.height_m, 0.1 * x - 0.05 * y, atol=1e-6)
    np.testing.assert_allclose(gt.slope_rad, np.arctan(np.hypot(0.1, 0.05)), atol=1e-6)
    np.testing.assert_allclose(gt.range_m, np.hypot(x, y))


def test_truth_obstacles_are_moved_into_the_vehicle_frame_with_their_heading():
    """The vehicle at (3, 4) heading along world +y (yaw 90°): a box at world (3, 9) heading +y as
    well stands 5 m straight ahead, heading along the vehicle's x; one at world (1, 4) heading +x
    stands 2 m to the left, heading to the vehicle's right (−90°)."""
    from terrainmap.sim.obstacles import ObstacleBox

    yaw90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    boxes = [ObstacleBox(1, "car", "box", np.array([3.0, 9.0, 0.75]), np.array([4.3, 1.8, 1.5]), np.pi / 2, 1.5,
                         np.zeros(3)),
             ObstacleBox(2, "rock", "box", np.array([1.0, 4.0, 0.3]), np.ones(3), 0.0, 0.6, np.zeros(3))]
    frame = _one_row_frame({}, pose=(yaw90, np.array([3.0, 4.0, 0.0])), obstacles=boxes)
    ahead, left = truth_obstacles(frame, _flat_truth().calibration)
    np.testing.assert_allclose(ahead.center_m, [5.0, 0.0, 0.75], atol=1e-12)
    assert ahead.yaw_rad == pytest.approx(0.0, abs=1e-12) and ahead.range_m == pytest.approx(5.0)
    np.testing.assert_allclose(left.center_m, [0.0, 2.0, 0.3], atol=1e-12)
    assert left.yaw_rad == pytest.approx(-np.pi / 2)
    assert ahead.contains_xy(np.array([[7.0, 0.0], [5.0, 1.3]]), 0.0).tolist() == [True, False]  # 4.3 m long, 1.8 m wide


def test_p95_is_the_95th_percentile_of_the_absolute_error():
    from terrainmap.evaluation.scores import ErrorStats

    stats = ErrorStats()
    errors = (np.arange(200) // 2 + 0.5) / 1000 * np.tile([1, -1], 100)  # ±0.5 … ±99.5 mm, each twice
    stats.add(errors)
    summary = stats.summary()
    assert summary["elevation_p95_m"] == pytest.approx(0.095, abs=0.001)
    assert summary["elevation_mae_m"] == pytest.approx(0.05) and summary["elevation_bias_m"] == pytest.approx(0.0)
    assert summary["elevation_rmse_m"] == pytest.approx(np.sqrt(np.mean(errors**2)))


def test_table_puts_each_metric_under_its_own_title():
    from terrainmap.evaluation.accuracy_report import format_table

    values = dict.fromkeys(METRICS, None) | {"elevation_rmse_m": 0.1, "elevation_mae_m": 0.05, "elevation_bias_m": -0.02,
                                             "elevation_p95_m": 0.2, "coverage": 0.9, "terrain_recall": 0.7}
    report = {"log": "x.mcap", "frames": 1, "methods": {"terrainmap": {"0-10": values}}}
    header, row = format_table(report).splitlines()[-2:]
    columns = dict(zip(header.split()[1:], row.split()[1:], strict=True))
    assert columns == {"rmse_m": "0.100", "mae_m": "0.050", "bias_m": "-0.020", "p95_m": "0.200", "slope°": "—",
                       "cover": "0.900", "prec": "—", "recall": "0.700", "f1": "—", "obs_rec": "—", "false/fr": "—"}


@pytest.mark.parametrize("options, message", [
    ({"obstacle_margin_m": float("nan")}, "obstacle_margin_m: must be a finite number >= 0, got nan"),
    ({"obstacle_range_m": -1.0}, "obstacle_range_m: must be a finite number >= 0, got -1.0"),
    ({"min_visible_pixels": "20"}, "min_visible_pixels: must be a whole number >= 0, got '20'"),
    ({"min_terrain_pixels": 0}, "min_terrain_pixels: must be a whole number >= 1, got 0"),
    ({"methods": "terrainmap"}, "methods (--methods): give a list of method names, got the string 'terrainmap'"),
])
def test_evaluate_refuses_scoring_options_that_would_give_wrong_scores(tmp_path, options, message):
    """Checked before the log is opened: a NaN margin scored every detection false, silently."""
    with pytest.raises(ConfigError, match=re.escape(message)):
        acc.evaluate(tmp_path / "absent.mcap", Config(), **options)
