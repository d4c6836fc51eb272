"""Bad input to the library's entry points raises terrainmap's own errors, naming what is wrong,
instead of an error from numpy, OpenCV or Python deep inside (found by fuzzing the public API)."""

import dataclasses
import re

import numpy as np
import pytest

from terrainmap.config import Config, GridConfig, StereoConfig, load_config
from terrainmap.cost import traversability_cost
from terrainmap.errors import CalibrationError, ConfigError, InputError
from terrainmap.grid import quantize
from terrainmap.obstacle_stage import make_tracker, run_obstacle_stage
from terrainmap.obstacles import terrain_at
from terrainmap.sources import open_source
from terrainmap.sources.calibration import terrainmap_calibration
from terrainmap.stereo import StereoMatcher
from terrainmap.synthetic import cloud
from terrainmap.terrain import estimate_terrain
from terrainmap.tracking import ObstacleTracker
from terrainmap.types import Extrinsics, StereoCalibration, StereoCamera

C = Config()
AXIS, UP = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.8])


@pytest.mark.parametrize(("args", "message"), [
    ((UP, AXIS, 0.0), "StereoCamera: needs focal_baseline > 0"),  # labelled every point terrain
    ((UP, np.zeros(3), 150.0), "StereoCamera: needs focal_baseline > 0 and an axis"),
    ((np.array([0.0, 0.0, np.nan]), AXIS, 150.0), "StereoCamera: center_m must be 3 finite numbers"),
    ((UP, AXIS[:2], 150.0), "StereoCamera: axis must be 3 finite numbers"),
    ((UP, AXIS, 150.0, np.array([0.0, -1.0, 0.0]), 0.0), "StereoCamera: fx_px must be > 0"),
])
def test_a_stereo_camera_is_checked(args, message):
    with pytest.raises(InputError, match=message):
        StereoCamera(*args)


def test_terrain_at_needs_the_grids_elevation_and_matching_points():
    with pytest.raises(InputError, match=r"terrain_at: elevation must have shape \(68, 44\), got \(5, 5\)"):
        terrain_at(np.array([30.0]), np.array([8.0]), np.zeros((5, 5)), C.grid)  # read the wrong grid before
    with pytest.raises(InputError, match=r"terrain_at: y must have shape \(2,\), got \(1,\)"):
        terrain_at(np.array([1.0, 2.0]), np.array([1.0]), np.zeros(C.grid.shape), C.grid)
    with np.errstate(all="raise"):  # no numpy warning for a point at infinity: NaN
        assert np.isnan(terrain_at(np.array([np.inf]), np.array([0.0]), np.ones(C.grid.shape), C.grid)).all()


def test_sections_built_in_code_are_checked_where_they_are_used():
    points = cloud(20_000, grid=C.grid)
    with pytest.raises(ConfigError, match="grid.cell_size_m: must be > 0"):
        quantize(points, dataclasses.replace(C.grid, cell_size_m=0.0))  # ZeroDivisionError before
    grid = quantize(points, C.grid)
    with pytest.raises(ConfigError, match="terrain.control_points_x"):
        estimate_terrain(grid, dataclasses.replace(C.terrain, control_points_x=2))
    with pytest.raises(ConfigError, match="tracking.gate_m: must be finite, got nan"):
        ObstacleTracker(dataclasses.replace(C.tracking, gate_m=float("nan")))  # never associated before
    with pytest.raises(ConfigError, match="tracking.measurement_std_m: must be at most 1e"):
        ObstacleTracker(dataclasses.replace(C.tracking, measurement_std_m=1e200))  # as Config.validate checks
    with pytest.raises(ConfigError, match="grid.length_m: must be a number, got '34'"):
        quantize(points, GridConfig(length_m="34"))
    with pytest.raises(ConfigError, match="grid.length_m"):
        ObstacleTracker(C.tracking, area=GridConfig(length_m=-34.0))
    zeros = np.zeros(C.grid.shape)
    with pytest.raises(ConfigError, match="cost.max_step_m: must be >= 0.001"):  # NaN cost everywhere before
        traversability_cost(zeros, zeros, zeros > -1, C.grid, [], dataclasses.replace(C.cost, max_step_m=0.0), step=zeros)
    with pytest.raises(ConfigError, match="cost.occupied_misses: must be in 0..1000, got -1"):
        traversability_cost(zeros, zeros, zeros > -1, C.grid, [], dataclasses.replace(C.cost, occupied_misses=-1))
    bad = Config()
    bad.cost.occupied_misses = None
    point = np.float32([[10.0, 0.0, 0.0]])
    with pytest.raises(ConfigError, match="cost.occupied_misses"):  # TypeError in the tracker before
        run_obstacle_stage(point, np.zeros(1, np.uint8), quantize(point, C.grid),
                           {"elevation": zeros, "slope": zeros, "label": np.zeros(C.grid.shape, np.uint8)}, 0,
                           make_tracker(bad), bad)
    calibration = StereoCalibration(64, 48, 100.0, 100.0, 32.0, 24.0, 0.5)
    with pytest.raises(ConfigError, match="stereo.mode"):
        StereoMatcher(calibration, dataclasses.replace(StereoConfig(), mode="x"))  # KeyError before
    # another section than the stage's: AttributeErrors before
    for call, want in [(lambda: estimate_terrain(grid, C.grid), "terrain (a TerrainConfig), got GridConfig"),
                       (lambda: quantize(points, C.terrain), "grid (a GridConfig), got TerrainConfig"),
                       (lambda: traversability_cost(zeros, zeros, zeros > -1, C.cost, [], C.cost), "grid (a GridConfig)"),
                       (lambda: StereoMatcher(calibration, C.grid), "stereo (a StereoConfig), got GridConfig"),
                       (lambda: ObstacleTracker(C.grid), "tracking (a TrackingConfig), got GridConfig")]:
        with pytest.raises(ConfigError, match=rf"^expected config\.{re.escape(want)}"):
            call()


def test_files_nested_too_deep_and_names_too_long_are_input_errors(tmp_path):
    deep = tmp_path / "calibration.yaml"
    deep.write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(InputError, match="calibration.yaml: cannot parse the calibration file"):
        terrainmap_calibration(deep)  # RecursionError before
    toml = tmp_path / "deep.toml"
    toml.write_text("[grid]\nx = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match=r"deep.toml: not valid TOML \(values nested too deep\)"):
        load_config(toml)
    with pytest.raises(InputError, match="cannot be read"):
        open_source(tmp_path / ("a" * 300))  # OSError (file name too long) before


def test_the_pipelines_arguments_of_another_type_are_named():
    """A library caller's slip in process_frame's, PipelineState's, map_points' or cloud's
    arguments: terrainmap's error naming the argument, not an AttributeError deep inside."""
    from terrainmap.pipeline import PipelineState, map_points, process_frame
    from terrainmap.types import StereoFrame

    image = np.zeros((48, 64), np.uint8)
    calibration = StereoCalibration(fx=50.0, fy=50.0, cx=32.0, cy=24.0, baseline_m=0.3, width=64, height=48)
    frame = StereoFrame(index=0, stamp_ns=0, left=image, right=image, calibration=calibration)
    state = PipelineState(Config())
    for args, error, message in [
        ((None, C, state), InputError, "process_frame: frame must be a StereoFrame, got NoneType"),
        ((frame, {}, state), ConfigError, "process_frame: config must be the whole Config, got dict"),
        ((frame, C, None), InputError, "process_frame: state must be a PipelineState, got NoneType"),
        ((dataclasses.replace(frame, extrinsics=(np.eye(3), np.zeros(3))), C, state), InputError,
         "process_frame: frame.extrinsics must be an Extrinsics or None, got tuple"),
        ((dataclasses.replace(frame, stamp_ns=1.5e18), C, state), InputError,
         "frame 0 has stamp 1.5e.18; a stamp is a whole number of nanoseconds"),
        ((dataclasses.replace(frame, index="a"), C, state), InputError,  # refused by the sinks only, before
         "process_frame: frame.index must be a whole number, got 'a'"),
        ((dataclasses.replace(frame, frame_id=5), C, state), InputError,  # a TypeError in the sinks before
         r"process_frame: frame.frame_id must be a frame name \(a non-empty str\), got 5"),
        ((dataclasses.replace(frame, extrinsics=Extrinsics(np.eye(3), np.zeros(3), vehicle_frame_id=None)), C, state),
         InputError, "process_frame: frame.extrinsics.vehicle_frame_id must be a frame name"),
    ]:
        with pytest.raises(error, match=message):
            process_frame(*args)
    with pytest.raises(ConfigError, match="PipelineState: config must be the whole Config, got GridConfig"):
        PipelineState(GridConfig())
    with pytest.raises(InputError, match="map_points: camera must be a StereoCamera or None, got str"):
        map_points(cloud(1000), C, camera="cam")
    with pytest.raises(InputError, match="quantize: camera must be a StereoCamera or None, got str"):
        quantize(cloud(1000), C.grid, camera="cam")
    with pytest.raises(InputError, match=r"estimate_terrain: grid must be a HeightGrid \(terrainmap.grid.quantize\), "
                                         "got ndarray"):
        estimate_terrain(cloud(1000), C.terrain)
    zeros = np.zeros(C.grid.shape)
    with pytest.raises(InputError, match=r"traversability_cost: obstacles must be Obstacles \(a list\), got NoneType"):
        traversability_cost(zeros, zeros, zeros > -1, C.grid, None, C.cost)
    with pytest.raises(InputError, match="cloud: n_points must be a whole number >= 0, got -1"):
        cloud(-1)


def test_the_evaluations_name_a_config_that_is_none():
    from terrainmap.evaluation import accuracy, disparity, robustness

    for call, what in ((lambda: accuracy.evaluate("log.mcap", None), "eval accuracy"),
                       (lambda: disparity.evaluate_disparity("folder", None), "eval stereo"),
                       (lambda: robustness.run(None), "robustness")):
        with pytest.raises(ConfigError, match=f"^{what}: config must be a Config, got NoneType$"):
            call()


def test_the_surface_and_the_truth_name_points_that_are_no_arrays_of_numbers(tmp_path):
    """RationalSurface (and slope_at) and Truth.height: x, y that do not broadcast or are no
    numbers are InputError; Truth.height gives NaN at a NaN point (not an IndexError from the
    heightfield's integer cast)."""
    from terrainmap.sim import SimConfig, open_truth, simulate
    from terrainmap.slope import slope_at

    surface = estimate_terrain(quantize(cloud(20_000), C.grid), C.terrain).surface
    for x, y in (([1.0, 2.0, 3.0], [1.0, 2.0]), ("a", "b")):
        with pytest.raises(InputError, match="surface: x and y must be broadcastable arrays of numbers"):
            slope_at(surface, x, y)
    log = simulate(tmp_path / "t.mcap", SimConfig(scene="flat", frames=1, width=32, height=24, focal_px=25.0))["path"]
    truth = open_truth(log)
    heights = truth.height([5.0, np.nan, 5.0], [0.0, 0.0, np.inf])
    assert np.isfinite(heights[0]) and np.isnan(heights[1:]).all()
    with pytest.raises(InputError, match="Truth.height: x and y must be broadcastable arrays of numbers"):
        truth.height([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(InputError, match="open_truth: path must be a str or Path, got int"):
        open_truth(5)
    with pytest.raises(CalibrationError, match="calibration must be the path of a file, got int"):
        open_source(log, calibration=5)
