import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.config import Config, GridConfig, SegmentationConfig
from terrainmap.errors import InputError
from terrainmap.grid import cell_centers, cell_index, quantize
from terrainmap.pipeline import map_points
from terrainmap.segmentation import (
    cell_planes,
    label_cells,
    label_points,
    surface_under_points,
    thresholds,
    widen_at_edges,
)
from terrainmap.synthetic import cloud, rolling_terrain
from terrainmap.types import Extrinsics, Label, StereoCamera

# A camera 1.8 m up, pitched 6° down, f·B = 500 px × 0.3 m (the simulator's rig)
_PITCH = np.deg2rad(6.0)
_OPTICAL = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # optical x, y, z in base_link
_ROT = np.array([[np.cos(_PITCH), 0, np.sin(_PITCH)], [0, 1, 0], [-np.sin(_PITCH), 0, np.cos(_PITCH)]]) @ _OPTICAL
CAMERA_POSE = Extrinsics(rotation=_ROT, translation=np.array([0.0, 0.0, 1.8]))
CAMERA = StereoCamera.from_rig(500.0, 0.3, CAMERA_POSE)  # no image: the tolerances are the same across it


def test_per_point_surface_matches_exact_evaluation():
    config = Config()
    pts = cloud(60_000, seed=2)
    terrain = map_points(pts, config).terrain
    idx = cell_index(pts, config.grid)
    planes = cell_planes(terrain.elevation, terrain.dz_dx, terrain.dz_dy, config.grid)
    approx = surface_under_points(pts, planes, idx)
    exact = terrain.surface.evaluate(pts[:, 0].astype(float), pts[:, 1].astype(float))
    err = np.abs(approx - exact)
    assert np.median(err) < 0.001 and np.percentile(err, 99) < 0.01
    m0, m1 = config.grid.shape
    corners = np.isin(idx, [0, m1 - 1, (m0 - 1) * m1, m0 * m1 - 1])  # where the clamped spline bends most
    assert err[~corners].max() < 0.05


@pytest.mark.filterwarnings("error")  # non-finite points are labelled quietly
def test_points_are_labelled_against_the_surface():
    config = Config()
    rng = np.random.default_rng(0)
    x = rng.uniform(3, 30, 20_000)
    y = rng.uniform(-10, 10, 20_000)
    ground = np.column_stack([x, y, rolling_terrain(x, y) + rng.normal(0, 0.02, x.size)])
    pole = np.column_stack([np.full(200, 15.0), np.full(200, 2.0), rolling_terrain(15, 2) + np.linspace(0.6, 2, 200)])
    hole = np.array([[10.0, -3.0, rolling_terrain(10, -3) - 1.0]])
    outside = np.array([[100.0, 0, 0], [np.nan, 1, 1], [10, 50, 0], [np.inf, 0, 1], [5, 0, -np.inf]])
    pts = np.vstack([ground, pole, hole, outside]).astype(np.float32)
    labels = map_points(pts, config).point_labels
    n = len(ground)
    assert np.mean(labels[:n] == Label.TERRAIN) > 0.99
    assert np.all(labels[n : n + 200] == Label.OBSTACLE)
    assert labels[n + 200] == Label.BELOW
    assert np.all(labels[-5:] == Label.UNKNOWN)


@pytest.mark.filterwarnings("error")
def test_points_over_cells_without_a_surface_are_unknown():
    grid = GridConfig()
    pts = cloud(5_000, seed=4)
    flat = np.zeros(grid.shape)
    elevation = flat.copy()
    elevation[:, : grid.shape[1] // 2] = np.nan  # the surface is missing on one side
    labels = label_points(pts, elevation, flat, flat, grid, SegmentationConfig())
    idx = cell_index(pts, grid)
    missing = (idx < flat.size) & np.isnan(np.append(elevation.ravel(), 0.0)[idx])
    assert missing.any() and (~missing & (idx < flat.size)).any()
    assert np.all(labels[missing] == Label.UNKNOWN)
    assert np.all(labels[~missing & (idx < flat.size)] != Label.UNKNOWN)
    assert np.all(label_points(pts, np.full(grid.shape, np.nan), flat, flat, grid, SegmentationConfig()) == Label.UNKNOWN)


def test_thresholds_grow_with_range():
    config = SegmentationConfig(obstacle_height_m=0.2, threshold_per_m=0.01)
    grid = GridConfig()
    elevation = np.zeros(grid.shape)
    near_far = np.array([[3.0, 0.0, 0.3], [30.0, 0.0, 0.3]], np.float32)  # 0.3 m above flat ground
    labels = label_points(near_far, elevation, elevation, elevation, grid, config)
    assert list(labels) == [Label.OBSTACLE, Label.TERRAIN]  # 0.2 + 0.3 = 0.5 m threshold at 30 m


def test_cell_labels():
    grid_cfg = GridConfig(x_min_m=0, length_m=4, width_m=2, cell_size_m=1)
    pts = np.array(
        [[0.5, -0.5, 0.0], [0.5, -0.5, 0.02],  # terrain
         [1.5, -0.5, 0.0], [1.5, -0.5, 1.5], [1.5, -0.5, 1.6],  # something standing up
         [2.5, -0.5, -0.8],  # hole
         [3.5, -0.5, 0.0], [3.5, -0.5, 0.0], [3.5, -0.5, 0.0], [3.5, -0.5, 0.0], [3.5, -0.5, -2.0]]  # a pit
    )
    grid = quantize(pts, grid_cfg)
    labels = label_cells(grid, np.zeros(grid.shape), SegmentationConfig())
    assert labels[0, 0] == Label.TERRAIN
    assert labels[1, 0] == Label.OBSTACLE
    assert labels[2, 0] == Label.BELOW
    # below goes by eq. 1's Z (mean − σ = −1.2 m here), although the cell's top (mean + σ) is 0.4 m up
    assert grid.z_top[3, 0] > 0.25 and labels[3, 0] == Label.BELOW
    assert labels[3, 1] == Label.UNKNOWN  # no point


@settings(max_examples=50, deadline=None)
@given(x=st.floats(3, 30), y=st.floats(-10, 10), gx=st.floats(-0.5, 0.5), gy=st.floats(-0.5, 0.5),
       z=st.floats(-2, 2))
def test_height_per_px_is_the_height_change_of_a_disparity_error(x, y, gx, gy, z):
    # Move the surface point along its camera ray as a disparity error of δ px does (Z = f·B / d)
    # and measure its height above the tangent plane: first order in δ, it is δ · height_per_px.
    point = np.array([x, y, z])
    ray = point - CAMERA.center_m
    depth = ray @ CAMERA.axis
    delta = 1e-4
    depth_moved = CAMERA.focal_baseline / (CAMERA.focal_baseline / depth - delta)
    moved = CAMERA.center_m + ray * depth_moved / depth
    rise = (moved[2] - z) - gx * (moved[0] - x) - gy * (moved[1] - y)
    expected = CAMERA.height_per_px(x, y, z, gx, gy)
    assert abs(abs(rise) / delta - expected) <= 1e-3 * max(expected, 1e-3)


def test_stereo_thresholds_grow_where_disparity_noise_lifts_points():
    config, grid = SegmentationConfig(), GridConfig()  # the default: 1 px
    assert config.disparity_tolerance_px == 1.0
    flat = np.zeros(grid.shape)
    fixed = thresholds(grid, config)
    above, below = thresholds(grid, config, CAMERA, flat, flat, flat)
    assert np.all(above >= fixed[0]) and np.all(below >= fixed[1])
    ix = int((20.0 - grid.x_min_m) / grid.cell_size_m)
    iy = grid.shape[1] // 2
    # 1 px at 20 m on flat ground moves a point ≈ 20 × 1.8 / 150 = 0.24 m: under the fixed 0.45 m
    assert above[ix, iy] == fixed[0][ix, iy]
    # ground rising at 0.3 towards the camera: 20 × |−1.8 − 0.3 × 20| / 150 ≈ 1.0 m
    rising = thresholds(grid, config, CAMERA, flat, np.full(grid.shape, 0.3), flat)[0]
    assert 0.9 < rising[ix, iy] < 1.2
    off = SegmentationConfig(disparity_tolerance_px=0.0, below_tolerance_px=0.0)  # range only
    assert np.array_equal(thresholds(grid, off, CAMERA, flat, flat, flat)[0], fixed[0])
    assert np.array_equal(thresholds(grid, off, CAMERA, flat, flat, flat)[1], fixed[1])


def test_the_below_threshold_has_its_own_wider_floor():
    """SGBM reads ground disparity low, so the floor under the below threshold is 2 px (above: 1 px)."""
    config, grid = SegmentationConfig(), GridConfig()
    assert config.below_tolerance_px == 2.0
    flat, rising = np.zeros(grid.shape), np.full(grid.shape, 0.3)
    xs, ys = cell_centers(grid)
    per_px = CAMERA.height_per_px(xs[:, None], ys[None, :], flat, rising, flat)
    above, below = thresholds(grid, config, CAMERA, flat, rising, flat)
    fixed_above, fixed_below = thresholds(grid, config)
    assert np.allclose(above, np.maximum(fixed_above, per_px))
    assert np.allclose(below, np.maximum(fixed_below, 2.0 * per_px))
    assert np.any(below > above)  # where the 2 px floor is binding
    only_above = SegmentationConfig(below_tolerance_px=0.0)
    assert np.array_equal(thresholds(grid, only_above, CAMERA, flat, rising, flat)[1], fixed_below)
    assert np.array_equal(thresholds(grid, only_above, CAMERA, flat, rising, flat)[0], above)


def test_layers_and_index_of_the_wrong_shape_are_named():
    from terrainmap.errors import InputError

    grid, config = GridConfig(), SegmentationConfig()
    pts = cloud(1000, grid=grid)
    flat = np.zeros(grid.shape)
    with pytest.raises(InputError, match=r"label_points: elevation must have shape \(68, 44\), got \(3, 3\)"):
        label_points(pts, np.zeros((3, 3)), flat, flat, grid, config)
    with pytest.raises(InputError, match=r"label_points: index must have shape \(1000,\)"):
        label_points(pts, flat, flat, flat, grid, config, index=np.zeros(5, np.intp))
    with pytest.raises(InputError, match="N×3"):
        label_points(pts[:, :2], flat, flat, flat, grid, config)
    with pytest.raises(InputError, match=r"label_cells: elevation must have shape \(68, 44\), got \(3, 3\)"):
        label_cells(quantize(pts, grid), np.zeros((3, 3)), config)


def test_the_sections_given_are_checked_where_no_thresholds_are():
    """A NaN threshold labelled every point TERRAIN, a negative one every point BELOW, without a word."""
    from terrainmap.errors import ConfigError

    grid = GridConfig()
    pts, flat = cloud(1000, grid=grid), np.zeros(grid.shape)
    for value, message in ((float("nan"), "must be finite"), (-1.0, "must be > 0")):
        config = SegmentationConfig(obstacle_height_m=value)
        with pytest.raises(ConfigError, match=f"segmentation.obstacle_height_m: {message}"):
            label_points(pts, flat, flat, flat, grid, config)
        with pytest.raises(ConfigError, match=f"segmentation.obstacle_height_m: {message}"):
            label_cells(quantize(pts, grid), flat, config)
    with pytest.raises(ConfigError, match=r"expected config.grid \(a GridConfig\), got SegmentationConfig"):
        label_points(pts, flat, flat, flat, SegmentationConfig(), SegmentationConfig())


def test_cells_holding_counts_points_per_cell_and_ignores_the_outside():
    from terrainmap.segmentation import cells_holding

    index = np.array([0, 0, 0, 5, 5, 6, 12, 12, 12])  # 12 = outside a 3×4 grid
    held = cells_holding(index, (3, 4), 2)
    assert held.shape == (3, 4) and held.ravel().tolist() == [True] + [False] * 4 + [True] + [False] * 6


def test_thresholds_are_widened_at_the_edge_of_the_observed_area_only():
    observed = np.zeros((8, 9), bool)
    observed[2:7, 1:9] = True  # touches the grid's last column: cells there have outside neighbours
    above, below = np.full((8, 9), 0.3), np.full((8, 9), 0.5)
    wide_above, wide_below = widen_at_edges((above, below), observed, 0.1)
    interior = np.zeros_like(observed)
    interior[3:6, 2:8] = True
    edge = observed & ~interior
    np.testing.assert_allclose(wide_above[edge], 0.4)
    np.testing.assert_allclose(wide_below[edge], 0.6)
    np.testing.assert_allclose(wide_above[~edge], 0.3)
    np.testing.assert_allclose(wide_below[~edge], 0.5)
    assert widen_at_edges((above, below), observed, 0.0) == (above, below)


def test_a_cell_missing_one_of_its_8_neighbours_is_on_the_edge():
    """A single unobserved cell puts each of its 8 neighbours (7 observed neighbours each) on the edge."""
    observed = np.ones((7, 7), bool)
    observed[3, 3] = False
    wide_above, _ = widen_at_edges((np.zeros((7, 7)), np.zeros((7, 7))), observed, 0.1)
    ring = np.zeros_like(observed)
    ring[2:5, 2:5] = True
    ring[3, 3] = False
    np.testing.assert_allclose(wide_above[ring], 0.1)
    np.testing.assert_allclose(wide_above[1:-1, 1:-1][~ring[1:-1, 1:-1]], 0.0)


def test_column_is_where_a_point_appears_in_the_image():
    camera = StereoCamera.from_rig(500.0, 0.3, CAMERA_POSE, cx_px=319.5, width_px=640)
    ahead = np.array([10.0, 0.0, 1.8 - 10.0 * np.tan(_PITCH)])  # on the optical axis
    assert camera.column(*ahead) == pytest.approx(319.5)
    # 20 m ahead, 5 m to the right (−y): u = cx + f · 5 / depth, depth along the pitched axis
    point = np.array([20.0, -5.0, 0.0])
    depth = (point - camera.center_m) @ camera.axis
    assert camera.column(*point) == pytest.approx(319.5 + 500.0 * 5.0 / depth)
    assert camera.column(-5.0, 0.0, 0.0) == pytest.approx(319.5)  # behind the camera: the centre
    with pytest.raises(InputError, match="StereoCamera.column needs the image"):
        CAMERA.column(*point)  # no image given
    assert StereoCamera.from_rig(500.0, 0.3, CAMERA_POSE, width_px=640).cx_px == 319.5  # the centre by default


def test_tolerances_grow_towards_the_image_sides():
    config, grid = SegmentationConfig(), GridConfig()
    assert (config.side_band, config.side_gain) == (0.2, 3.0)
    camera = StereoCamera.from_rig(500.0, 0.3, CAMERA_POSE, cx_px=319.5, width_px=640)
    flat, rising = np.zeros(grid.shape), np.full(grid.shape, 0.3)  # the disparity floor binds on the slope
    plain = thresholds(grid, config, CAMERA, flat, rising, flat)
    sided = thresholds(grid, config, camera, flat, rising, flat)
    xs, ys = cell_centers(grid)
    u = camera.column(xs[:, None], ys[None, :], flat)
    middle = np.abs(u - 319.5) < 0.25 * 640  # more than a fifth of the width from both sides
    for with_sides, without in zip(sided, plain):
        assert np.array_equal(with_sides[middle], without[middle])
        assert np.all(with_sides >= without)
    ix = int((15.0 - grid.x_min_m) / grid.cell_size_m)  # 15 m ahead
    iy = int(np.argmin(np.abs(u[ix] - 630.0)))  # the cell about 10 px from the image's right side
    gain = 1 + 3.0 * (1 - (639.5 - u[ix, iy]) / 128)  # 128 px: the band, a fifth of 640; 639.5: the side
    per_px = camera.height_per_px(xs[ix], ys[iy], 0.0, 0.3, 0.0)
    assert sided[0][ix, iy] == pytest.approx(max(plain[0][ix, iy], per_px * gain))
    assert sided[0][ix, iy] > 2.5 * plain[0][ix, iy]
    off = SegmentationConfig(side_gain=0.0)
    assert all(np.array_equal(a, b) for a, b in zip(thresholds(grid, off, camera, flat, rising, flat), plain))


def test_huge_coordinates_are_outside_the_area_without_numpy_warnings():
    """z = 1e300 (its square overflows in the grid's trash bin) and float64 coordinates past
    float32 are points outside the area: UNKNOWN, and no overflow warning on the way."""
    import warnings

    points = np.vstack([cloud(20_000, seed=3).astype(np.float64),
                        [[5, 0, 1e300], [1e300, 0, 0], [5, 1e39, 0], [-1e300, -1e300, -1e300]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = map_points(points, Config())
    assert (result.point_labels[-4:] == Label.UNKNOWN).all()


def test_fixed_thresholds_grow_with_the_horizontal_distance_and_each_has_its_own_base():
    """Above: ``obstacle_height_m`` + ``threshold_per_m`` · √(x² + y²) at the cell centre; below:
    ``below_depth_m`` + the same growth (distinct bases, so that one cannot stand for the other)."""
    grid = GridConfig()
    config = SegmentationConfig(obstacle_height_m=0.25, below_depth_m=0.5, threshold_per_m=0.01)
    above, below = thresholds(grid, config)
    xs, ys = cell_centers(grid)
    distance = np.hypot(xs[:, None], ys[None, :])
    np.testing.assert_allclose(above, 0.25 + 0.01 * distance)
    np.testing.assert_allclose(below, 0.5 + 0.01 * distance)
