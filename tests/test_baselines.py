import numpy as np
import pytest

from terrainmap.config import Config
from terrainmap.evaluation.baselines import METHODS, available_methods, gradient
from terrainmap.extrinsics import extrinsics_from_pose
from terrainmap.grid import cell_centers
from terrainmap.synthetic import cloud, rolling_terrain
from terrainmap.types import Label


@pytest.fixture(scope="module")
def scene():
    config = Config()
    points = cloud(60_000, seed=5)
    xs, ys = cell_centers(config.grid)
    return config, points, rolling_terrain(xs[:, None], ys[None, :])


@pytest.mark.parametrize("name", available_methods())
def test_every_available_method_gives_layers_and_labels(scene, name):
    config, points, truth = scene
    out = METHODS[name](points, config, extrinsics_from_pose(1.6))
    assert out.elevation.shape == config.grid.shape
    assert out.point_labels.shape == (len(points),) and out.point_labels.dtype == np.uint8
    assert set(np.unique(out.point_labels)) <= {int(v) for v in Label}
    if out.slope is not None:
        assert out.slope.shape == config.grid.shape


def test_terrainmap_beats_the_flat_and_single_fit_baselines_on_rolling_terrain(scene):
    config, points, truth = scene

    covered = np.isfinite(METHODS["terrainmap"](points, config, None).elevation)  # the cells with data

    def rmse(name):
        e = METHODS[name](points, config, None).elevation[covered]
        return float(np.sqrt(np.mean((e - truth[covered]) ** 2)))

    assert covered.mean() > 0.9
    assert rmse("terrainmap") < 0.06
    assert rmse("terrainmap") < rmse("ransac_plane") / 5


def test_gradient_of_a_grid_with_empty_cells_has_a_slope_wherever_a_neighbour_has_a_value():
    """A plane with holes: exact wherever a neighbour along the axis has a value (np.gradient gives
    NaN beside every hole), equal to np.gradient on a full grid, NaN with no neighbour."""
    x, y = np.meshgrid(np.arange(6.0), np.arange(5.0), indexing="ij")
    plane = 0.5 * (0.2 * x - 0.3 * y)  # cells of 0.5 m: 0.1 and -0.15 m per m
    np.testing.assert_allclose(gradient(plane, 0.5), np.gradient(plane, 0.5))
    holes = plane.copy()
    holes[2, 2] = holes[0, 4] = np.nan
    gx, gy = gradient(holes, 0.5)
    has = np.isfinite(holes)
    np.testing.assert_allclose(gx[has], 0.2)  # one-sided beside the holes
    np.testing.assert_allclose(gy[has], -0.3)
    holes[4, :] = np.nan  # row 5's only x neighbour: no x slope there
    gx, gy = gradient(holes, 0.5)
    assert np.isnan(gx[5]).all() and np.isfinite(gy[5]).all() and np.isfinite(gx[3, :2]).all()
    lone = np.full((3, 3), np.nan)
    lone[1, 1] = 1.0
    assert np.isnan(gradient(lone, 0.5)).all()


@pytest.mark.parametrize("how", ["missing", "broken"])
def test_optional_methods_are_listed_only_when_installed_and_importable(monkeypatch, how):
    """Not installed (the import raises ModuleNotFoundError) or a broken build (found, then an
    OSError for a missing shared library): the method is not listed, and nothing raises."""
    import importlib

    from terrainmap.evaluation import baselines

    optional = ("CSF", "pypatchworkpp")
    error = {"missing": lambda name: ModuleNotFoundError(f"No module named {name!r}", name=name),
             "broken": lambda name: OSError(f"{name}: cannot open shared object file")}[how]

    def fails(name, real=importlib.import_module):
        if name in optional:
            raise error(name)
        return real(name)

    monkeypatch.setattr(importlib, "import_module", fails)
    baselines._importable.cache_clear()  # what an earlier call found
    try:
        assert available_methods() == ["terrainmap", "bspline_single", "ransac_plane", "lowest_point"]
    finally:
        baselines._importable.cache_clear()


def test_baselines_label_with_terrainmaps_thresholds_for_the_rig(scene):
    """Given the stereo rig, a baseline labels against its surface with terrainmap's thresholds
    and their disparity-error floors, so that only the surfaces differ between the methods."""
    from terrainmap.segmentation import label_points, thresholds
    from terrainmap.types import StereoCamera

    config, points, _ = scene
    camera = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 60.0)  # a short baseline
    out = METHODS["ransac_plane"](points, config, None, camera)
    gx, gy = np.gradient(out.elevation, config.grid.cell_size_m)  # exact on a plane
    limits = thresholds(config.grid, config.segmentation, camera, out.elevation, gx, gy)
    expected = label_points(points, out.elevation, gx, gy, config.grid, config.segmentation, limits=limits)
    np.testing.assert_array_equal(out.point_labels, expected)
    assert (out.point_labels != METHODS["ransac_plane"](points, config, None).point_labels).any()


def test_lowest_point_takes_each_cells_lowest_point_and_says_nothing_in_empty_cells():
    config = Config()
    points = np.array([[10.25, 0.25, 0.4], [10.3, 0.3, 0.1], [10.2, 0.2, 0.25], [12.25, -3.25, -0.2],
                       [80.0, 0.0, 0.0]])  # the last one beyond the grid
    out = METHODS["lowest_point"](points, config)
    ix, iy = np.floor((points[:, :2] - [config.grid.x_min_m, config.grid.y_min_m]) / config.grid.cell_size_m).astype(int).T
    assert out.elevation[ix[0], iy[0]] == pytest.approx(0.1) and out.elevation[ix[3], iy[3]] == pytest.approx(-0.2)
    assert np.isfinite(out.elevation).sum() == 2
    assert out.point_labels[-1] == Label.UNKNOWN  # outside the grid: not scored, not an obstacle


def test_ransac_plane_fits_the_ground_not_the_outliers_above_it():
    """A plane z = 0.02·x − 0.01·y sampled over the grid with 30 % of the points 0.6 m above it: the
    plane RANSAC returns is the ground's, within a centimetre (the final fit takes the inliers only)."""
    config = Config()
    rng = np.random.default_rng(4)
    xs, ys = cell_centers(config.grid)
    x, y = rng.uniform(xs[0], xs[-1], 5000), rng.uniform(ys[0], ys[-1], 5000)
    z = 0.02 * x - 0.01 * y + np.where(rng.random(5000) < 0.3, 0.6, 0.0)
    out = METHODS["ransac_plane"](np.column_stack([x, y, z]), config)
    np.testing.assert_allclose(out.elevation, 0.02 * xs[:, None] - 0.01 * ys[None, :], atol=0.01)
