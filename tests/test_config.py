import math
import re
import tomllib

import numpy as np
import pytest

from terrainmap.config import Config, load_config
from terrainmap.errors import ConfigError
from terrainmap.grid import quantize
from terrainmap.synthetic import cloud
from terrainmap.terrain import estimate_terrain


def test_defaults_are_the_papers():
    c = Config()
    assert (c.terrain.degree, c.terrain.control_points_x, c.terrain.control_points_y) == (3, 25, 25)
    assert c.grid.cell_size_m == 0.5 and (c.grid.length_m, c.grid.width_m) == (34.0, 22.0)
    assert c.grid.shape == (68, 44)
    c.validate()


def test_toml_round_trip_and_overrides(tmp_path):
    path = tmp_path / "c.toml"
    c = Config()
    c.terrain.control_points_x = 15
    c.stereo.mode = "hh"
    path.write_text(c.to_toml())
    loaded = load_config(path, overrides=["grid.cell_size_m=0.25", "grid.fill_empty=false"])
    assert loaded.terrain.control_points_x == 15 and loaded.stereo.mode == "hh"
    assert loaded.grid.cell_size_m == 0.25 and loaded.grid.fill_empty is False
    assert load_config(path).to_dict() == c.to_dict()


@pytest.mark.parametrize(
    "override, message",
    [
        ("terrain.degree=x", "terrain.degree: cannot use 'x'"),
        ("terrain.nope=1", r"unknown field terrain.nope \(fields: .*control_points_x.*degree"),
        ("grid.cellsize=1", r"unknown field grid.cellsize \(did you mean grid.cell_size_m\?\)"),
        ("nope.x=1", "unknown section"),
        ("degree=3", "expected section.field=value"),
        ("grid.length_m=33.3", "whole number of cells"),
        ("terrain.start_control_points=0", "terrain.start_control_points: must be >= 1"),
        ("terrain.control_points_x=3", r"at least degree \+ 1"),
        ("terrain.control_points_x=200", r"control_points_x × control_points_y: must be at most 4096 \(64×64\), got 200×25"),
        ("grid.x_min_m=1e30", r"grid.x_min_m: must be within ±10000 m"),
        ("stereo.max_range_m=1e300", "stereo.max_range_m: must be at most 10000 m"),
        ("terrain.weight_max=1e308", r"terrain.weight_max: must be in \(1, 1e6\]"),
        ("terrain.smoothness=1e300", r"terrain.smoothness: must be in \(0, 1000\]"),
        ("grid.cell_size_m=nan", "cannot use 'nan'"),
        ("grid.cell_size_m=0_5", "grid.cell_size_m: cannot use '0_5', expected a number"),  # Python's float() reads 5
        ("terrain.degree=\uff13", "terrain.degree: cannot use '\uff13', expected an integer"),  # a full-width 3
        ("grid.stereo_noise_px=-0.5", "grid.stereo_noise_px: must be >= 0"),
        ("mcap.max_points=-1", r"mcap.max_points: must be >= 0 \(0: every point\)"),
        ("segmentation.below_tolerance_px=-1", "segmentation.below_tolerance_px: must be >= 0"),
        ("tracking.report_misses=11", "tracking.report_misses: must be in 0..tracking.max_misses"),
        ("tracking.reconfirm_misses=-1", "tracking.reconfirm_misses: must be >= 0"),
        ("tracking.max_extrapolation_s=0", "tracking.max_extrapolation_s: must be > 0"),
        ("stereo.texture_measure=sobel", "stereo.texture_measure: must be variance or x_gradient"),
        ("stereo.texture_margin_px=-1", "stereo.texture_margin_px: must be in 0..100"),
        ("stereo.left_margin_px=-1", "stereo.left_margin_px: must be in 0..1024"),
        ("stereo.right_margin_px=2000", "stereo.right_margin_px: must be in 0..1024"),
        ("stereo.fattening_trim_px=-1", r"stereo.fattening_trim_px: must be in 0..100"),
        ("stereo.fattening_jump_px=0", "stereo.fattening_jump_px: must be > 0"),
        ("segmentation.edge_margin_m=-0.1", "segmentation.edge_margin_m: must be in "),
        ("segmentation.side_band=0", r"segmentation.side_band: must be in \(0, 0.5\]"),
        ("segmentation.side_gain=-1", r"segmentation.side_gain: must be in \[0, 100\]"),
        ("stereo.vertical_passes=3", "stereo.vertical_passes: must be 1 or 2, got 3"),
        ("stereo.pass_tolerance_px=0", "stereo.pass_tolerance_px: must be > 0"),
        ("grid.cell_size_m=0.001", "at most 2000 per axis"),  # 34 000 × 22 000 cells: a typo, not a map
        ("grid.length_m=1e300", "at most 2000 per axis"),
        ("grid.width_m=1e-9", r"grid.width_m: must hold at least one cell of 0.5 m, got 1e-09"),
        ("stereo.p2_per_pixel=99999999999", "stereo.p2_per_pixel: must be at most 10000"),
        ("stereo.num_disparities=4096", "stereo.num_disparities: must be at most 1024"),
        ("stereo.texture_window=99999", "stereo.texture_window: must be odd and in 3..101"),
        # Fields with no range of their own: squares and quotients of such values overflow mid-run
        ("stereo.min_texture=1e160", r"stereo.min_texture: must be at most 1e\+06 in magnitude, got 1e\+160"),
        ("tracking.measurement_std_m=1e200", "tracking.measurement_std_m: must be at most 1e"),
        ("stereo.disp12_max_diff=-2147483649", r"stereo.disp12_max_diff: must be within -2147483648..2147483647"),
        # ... and where a tiny value divides (a divide by zero, an overflow in a cast before)
        ("stereo.min_range_m=1e-300", r"stereo.min_range_m: must be in \[0.01 m, max_range_m\)"),
        ("segmentation.upright_min_range_m=1e-300", "segmentation.upright_min_range_m: must be 0 or >= 0.01 m"),
        ("terrain.control_weight_min=1e-300", r"terrain.control_weight_min: must be in \[1e-6, 1\]"),
    ],
)
def test_bad_values_name_the_field(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=[override])


@pytest.mark.parametrize("overrides, message", [
    (["stereo.vertical_passes=2", "stereo.vertical_passes_min_range_m=30", "stereo.vertical_passes_max_range_m=8"],
     r"stereo.vertical_passes_min_range_m: \(30 m\) must be below stereo.vertical_passes_max_range_m \(8 m\)"),
    (["obstacles.min_cells=3000"], r"obstacles.min_cells: \(3000\) exceeds the grid's 2992 cells"),
    (["terrain.min_valid_cells=3000"], r"terrain.min_valid_cells: \(3000\) exceeds the grid's 68×44 = 2992 cells"),
])
def test_settings_that_cannot_work_together_or_with_the_grid_are_refused(overrides, message):
    """Accepted before, they silently did nothing (the second pass), found no obstacle or failed
    every frame."""
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=overrides)


def test_set_reads_numbers_as_toml_writes_them():
    assert load_config(overrides=["rerun.max_points=100_000"]).rerun.max_points == 100_000  # as in a TOML file
    assert load_config(overrides=["grid.sigma_factor=.5"]).grid.sigma_factor == 0.5
    with pytest.raises(ConfigError, match="rerun.max_points: cannot use '1__0', expected an integer"):
        load_config(overrides=["rerun.max_points=1__0"])


def test_a_string_set_may_be_quoted_as_in_toml():
    assert load_config(overrides=['stereo.mode="sgbm"']).stereo.mode == "sgbm"
    assert load_config(overrides=["stereo.mode='sgbm'"]).stereo.mode == "sgbm"


def test_a_whole_number_written_with_a_point_is_an_integer_in_set_as_in_toml(tmp_path):
    """``--set terrain.degree=3.0`` is 3, as TOML's ``degree = 3.0`` is; 3.5 is refused by both."""
    path = tmp_path / "c.toml"
    path.write_text("[terrain]\ndegree = 3.0\n")
    assert load_config(path).terrain.degree == 3 == load_config(overrides=["terrain.degree=3.0"]).terrain.degree
    # An integer written as one is read exactly, not through a float (which gives ...992)
    with pytest.raises(ConfigError, match="must be within -2147483648..2147483647, got 9007199254740993$"):
        load_config(overrides=["rerun.max_points=9007199254740993"])
    with pytest.raises(ConfigError, match="terrain.degree: cannot use '3.5', expected an integer"):
        load_config(overrides=["terrain.degree=3.5"])


@pytest.mark.parametrize("overrides", ["grid.length_m=22", [22], [None]])
def test_overrides_must_be_a_list_of_strings(overrides):
    """A single string (an easy slip for a list of one) is refused, not parsed letter by letter."""
    with pytest.raises(ConfigError, match="overrides must be a list of 'section.field=value' strings"):
        load_config(overrides=overrides)
    assert load_config(overrides=None) == Config()
    assert load_config(overrides=(t for t in ["obstacles.min_points=5"])).obstacles.min_points == 5  # read once


def test_numpy_scalars_in_a_config_built_in_code_become_python_numbers():
    """Values computed with numpy (np.float32, np.int64, np.bool_) are accepted and stored as the
    Python numbers they hold, so that the config still writes as TOML that reads back."""
    config = Config()
    config.grid.length_m, config.terrain.degree, config.grid.fill_empty = np.float32(22.0), np.int64(2), np.bool_(False)
    config.validate()
    assert (type(config.grid.length_m), type(config.terrain.degree), type(config.grid.fill_empty)) == (float, int, bool)
    written = tomllib.loads(config.to_toml())
    assert written["grid"]["length_m"] == 22.0 and written["terrain"]["degree"] == 2
    config.grid.cell_size_m = np.float64(0.5)  # equal to the value checked last: not validated again
    assert tomllib.loads(config.to_toml())["grid"]["cell_size_m"] == 0.5  # written as TOML all the same


def test_a_limit_on_two_fields_that_a_file_broke_names_the_file(tmp_path):
    """The check on the control net's size names two fields: where the file gave one of them (and
    no ``--set`` replaced it), the message starts with the file, as for one field."""
    path = tmp_path / "c.toml"
    path.write_text("[terrain]\ncontrol_points_x = 100000\n")
    with pytest.raises(ConfigError, match=f"^{re.escape(str(path))}: terrain.control_points_x × control_points_y: "):
        load_config(path)
    with pytest.raises(ConfigError, match="^terrain.control_points_x × control_points_y: "):
        load_config(path, overrides=["terrain.control_points_x=9999"])
    path.write_text("[terrain]\ncontrol_points_x = 10\n")  # fine alone: the --set value breaks the limit
    with pytest.raises(ConfigError, match="^terrain.control_points_x × control_points_y: "):
        load_config(path, overrides=["terrain.control_points_y=1000"])


@pytest.mark.parametrize(
    "toml, message",
    [
        ("[terrain]\ndegree = true", "terrain.degree: cannot use True, expected an integer"),
        ('[grid]\ncell_size_m = "0.5"', "grid.cell_size_m: cannot use '0.5', expected a number"),
        ("[stereo]\nmode = 3", "stereo.mode: cannot use 3, expected a string"),
    ],
)
def test_a_toml_value_must_have_the_fields_kind(tmp_path, toml, message):
    """A TOML value is typed: a quoted number or a bare number for a name is a mistake to report
    (``--set`` values are text and are converted)."""
    path = tmp_path / "c.toml"
    path.write_text(toml + "\n")
    with pytest.raises(ConfigError, match=f"^{re.escape(str(path))}: {message}"):
        load_config(path)


@pytest.mark.parametrize(
    "section, values, message",
    [
        ("grid", {"z_min_m": -math.inf}, "grid.z_min_m: must be finite"),
        ("grid", {"x_min_m": math.nan}, "grid.x_min_m: must be finite"),
        ("terrain", {"degree": "3"}, "terrain.degree: must be an integer, got '3'"),
        ("terrain", {"degree": 3.0}, "terrain.degree: must be an integer"),
        ("grid", {"fill_empty": 1}, "grid.fill_empty: must be true or false"),
        ("terrain", {"weight_max": math.inf}, "terrain.weight_max: must be finite"),
    ],
)
def test_a_config_built_in_code_is_checked_for_kinds_and_finite_numbers(section, values, message):
    config = Config()
    for name, value in values.items():
        setattr(getattr(config, section), name, value)
    with pytest.raises(ConfigError, match=message):
        config.validate()


def test_the_pipeline_checks_a_config_built_in_code():
    from terrainmap.pipeline import PipelineState, map_points

    config = Config()
    config.grid.cell_size_m = 0.0
    with pytest.raises(ConfigError, match="grid.cell_size_m: must be > 0"):
        map_points(cloud(1000, grid=Config().grid), config)
    config = Config()
    config.terrain.degree = 0
    with pytest.raises(ConfigError, match="terrain.degree: must be 1..5"):
        PipelineState(config)


def test_a_config_changed_in_place_between_frames_is_checked_and_used():
    """A library user who edits the run's config between frames: the change is validated (a
    ConfigError, not a numpy error) and takes effect (the matcher is rebuilt for new SGBM
    settings), as with a new Config."""
    from terrainmap.bench import sim_frame
    from terrainmap.pipeline import PipelineState, process_frame

    frame = sim_frame(width=160, height=120)
    config = Config()
    state = PipelineState(config)
    first = process_frame(frame, config, state)
    matcher = state.matcher
    config.stereo.block_size = 9
    second = process_frame(frame, config, state)
    assert state.matcher is not matcher and state.matcher.config.block_size == 9
    fresh = process_frame(frame, config, PipelineState(config))
    np.testing.assert_array_equal(second.disparity, fresh.disparity)
    assert not np.array_equal(first.disparity, second.disparity, equal_nan=True)
    config.grid.cell_size_m = 0.0
    with pytest.raises(ConfigError, match="grid.cell_size_m: must be > 0"):
        process_frame(frame, config, state)
    config.grid.cell_size_m = 0.5
    # values equal to the ones checked, but of another kind: checked too
    for section, name, value, message in (("stereo", "drop_sky", 1 + 0j, "stereo.drop_sky: must be true or false"),
                                          ("grid", "z_max_m", np.array([10.0, 10.0]), "grid.z_max_m: must be a number"),
                                          ("segmentation", "obstacle_height_m", True, "must be a number, got True")):
        before = getattr(getattr(config, section), name)
        setattr(getattr(config, section), name, value)
        with pytest.raises(ConfigError, match=message):
            process_frame(frame, config, state)
        setattr(getattr(config, section), name, before)


def test_another_degree_needs_no_other_setting():
    """The first net is raised to degree + 1 control points: degree 5 runs with the defaults."""
    config = load_config(overrides=["terrain.degree=5"])
    terrain = estimate_terrain(quantize(cloud(20_000, grid=config.grid), config.grid), config.terrain)
    assert terrain.surface.control_points.shape == (25, 25) and np.isfinite(terrain.elevation).all()


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    zero = tmp_path / "zero.toml"
    zero.write_text("[terrain]\ndegree = 0\n")
    with pytest.raises(ConfigError, match=r"^.*zero.toml: terrain.degree: must be 1..5, got 0$"):
        load_config(zero)
    with pytest.raises(ConfigError, match=r"^terrain.degree: must be 1..5, got 9$"):  # the --set is to blame
        load_config(zero, overrides=["terrain.degree=9"])
    calibration = tmp_path / "calibration.toml"  # given as the config by a slip
    calibration.write_text("width = 640\nheight = 480\n")
    with pytest.raises(ConfigError, match=r"calibration.toml: unknown top-level key 'width' \(known sections: grid, "):
        load_config(calibration)


def test_the_accuracy_example_loads_and_sets_what_it_says():
    """examples/accuracy.toml, which the README offers for accuracy over frame rate."""
    from pathlib import Path

    config = load_config(Path(__file__).parent.parent / "examples" / "accuracy.toml")
    expected = load_config(
        overrides=[
            "stereo.vertical_passes=2",
            "stereo.vertical_passes_min_range_m=8",
            "stereo.vertical_passes_max_range_m=30",
        ]
    )
    assert config.to_dict() == expected.to_dict() != Config().to_dict()


@pytest.mark.parametrize(
    "override, message",
    [  # the end of each range that the message leaves out
        ("grid.z_min_m=10", "grid.z_min_m: must be below grid.z_max_m"),  # equal to z_max_m's default
        ("cost.max_slope_deg=90", r"cost.max_slope_deg: must be in \[0.1, 90\), got 90"),
        ("rerun.max_points=0", "rerun.max_points: must be >= 1"),
    ],
)
def test_the_open_end_of_a_range_is_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=[override])


@pytest.mark.parametrize(
    "overrides, check",
    [  # the end of each range that the message includes
        (["grid.sigma_factor=5"], lambda c: c.grid.sigma_factor == 5.0),
        (["tracking.max_misses=4", "tracking.report_misses=4"], lambda c: c.tracking.report_misses == 4),
        (["grid.length_m=1000"], lambda c: c.grid.shape[0] == 2000),  # at most 2000 cells per axis
    ],
)
def test_the_closed_end_of_a_range_is_accepted(overrides, check):
    assert check(load_config(overrides=overrides))


@pytest.mark.parametrize("text, value", [("1", True), ("0", False), ("yes", True), ("no", False), ("TRUE", True),
                                         ("on", True), ("Off", False)])
def test_set_reads_a_flag_from_each_of_its_spellings(text, value):
    assert load_config(overrides=[f"grid.fill_empty={text}"]).grid.fill_empty is value


def test_a_flag_set_in_code_where_a_number_belongs_is_refused():
    """``True`` is an int to Python; a config built in code must still hold a number there."""
    config = Config()
    config.terrain.degree = True
    with pytest.raises(ConfigError, match="terrain.degree: must be an integer, got True"):
        config.validate()


def test_set_takes_spaces_around_the_equals_sign_as_toml_does():
    config = load_config(overrides=["stereo.mode = hh", "grid.fill_empty = false", " terrain.degree =2"])
    assert (config.stereo.mode, config.grid.fill_empty, config.terrain.degree) == ("hh", False, 2)


def test_a_whole_config_or_a_dict_where_a_section_belongs_is_a_config_error():
    """A stage given the whole config (or a section given as a dict or None) is told what it wants."""
    from terrainmap.tracking import ObstacleTracker

    with pytest.raises(ConfigError, match=r"expected config.tracking \(a TrackingConfig\), got Config"):
        ObstacleTracker(Config())
    for value, got in (({"cell_size_m": 1.0}, "dict"), (None, "NoneType")):
        with pytest.raises(ConfigError, match=f"grid: must be a GridConfig, got {got}"):
            Config(grid=value).validate()


def test_entry_points_given_the_wrong_object_say_what_they_want():
    """A section where the whole config belongs, a config where the area belongs, no sinks, a number
    for a path: each a one-line error naming what was expected, not an AttributeError or TypeError."""
    from terrainmap import runner
    from terrainmap.errors import TerrainmapError
    from terrainmap.pipeline import map_points
    from terrainmap.tracking import ObstacleTracker

    config = Config()
    with pytest.raises(ConfigError, match="map_points: config must be the whole Config, got GridConfig"):
        map_points(np.zeros((10, 3)), config.grid)
    with pytest.raises(ConfigError, match="ObstacleTracker: area must be the GridConfig, got TrackingConfig"):
        ObstacleTracker(config.tracking, area=config.tracking)
    with pytest.raises(TerrainmapError, match=r"run: sinks must be a list of sinks \(write and close\), got None"):
        runner.run(iter([]), config, None)
    with pytest.raises(TerrainmapError, match="run: frames must be an iterable of StereoFrame, got int"):
        runner.run(5, config, [])
    with pytest.raises(ConfigError, match="config file: expected a path, got 5"):
        load_config(5)


def test_a_misspelt_field_set_in_code_is_an_error_not_a_new_attribute():
    config = Config()
    with pytest.raises(AttributeError, match="'GridConfig' object has no attribute 'cellsize_m'"):
        config.grid.cellsize_m = 1.0  # silently ignored, with the default used, before
    with pytest.raises(AttributeError):
        config.segmentaton = None


def test_a_config_file_with_a_byte_order_mark_and_a_set_with_spaces_are_read(tmp_path):
    """Windows Notepad saves UTF-8 with a byte order mark; a --set may have spaces around its parts."""
    path = tmp_path / "bom.toml"
    path.write_bytes("\ufeff[terrain]\ndegree = 2\n".encode())
    config = load_config(path, overrides=["grid. cell_size_m = 0.25"])
    assert config.terrain.degree == 2 and config.grid.cell_size_m == 0.25


@pytest.mark.parametrize(("setting", "line"), [
    ("stereo.left_margin_px=2000", "stereo.left_margin_px: must be in 0..1024, got 2000"),
    ("terrain.threshold_factor=-1", "terrain.threshold_factor: must be > 0, got -1.0"),
    ("extrinsics.iterations=0", "extrinsics.iterations: must be in 1..100000, got 0"),  # a 0 in the range is no value
    # messages that say the value already, or relate the field to another, are left as they are
    ("grid.z_min_m=50", "grid.z_min_m: must be below grid.z_max_m"),
    ("stereo.max_range_m=0.005", "stereo.min_range_m: must be in [0.01 m, max_range_m)"),  # not min_range_m's value
    ("stereo.num_disparities=17", "stereo.num_disparities: must be 0 (auto) or a positive multiple of 16, got 17"),
    ("obstacles.min_cells=100000",
     "obstacles.min_cells: (100000) exceeds the grid's 2992 cells: no obstacle could be found"),
])
def test_a_range_error_says_the_value_it_got(setting, line):
    with pytest.raises(ConfigError) as exc:
        load_config(None, [setting])
    assert str(exc.value) == line
