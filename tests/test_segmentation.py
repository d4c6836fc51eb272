import numpy as np

from terrainmap.config import Config, GridConfig, SegmentationConfig
from terrainmap.grid import cell_index, quantize
from terrainmap.pipeline import map_points
from terrainmap.segmentation import cell_planes, label_cells, label_points, surface_under_points
from terrainmap.synthetic import cloud, rolling_terrain
from terrainmap.types import Label


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


def test_points_are_labelled_against_the_surface():
    config = Config()
    rng = np.random.default_rng(0)
    x = rng.uniform(3, 30, 20_000)
    y = rng.uniform(-10, 10, 20_000)
    ground = np.column_stack([x, y, rolling_terrain(x, y) + rng.normal(0, 0.02, x.size)])
    pole = np.column_stack([np.full(200, 15.0), np.full(200, 2.0), rolling_terrain(15, 2) + np.linspace(0.6, 2, 200)])
    hole = np.array([[10.0, -3.0, rolling_terrain(10, -3) - 1.0]])
    outside = np.array([[100.0, 0, 0], [np.nan, 1, 1], [10, 50, 0]])
    pts = np.vstack([ground, pole, hole, outside]).astype(np.float32)
    labels = map_points(pts, config).point_labels
    n = len(ground)
    assert np.mean(labels[:n] == Label.TERRAIN) > 0.99
    assert np.all(labels[n : n + 200] == Label.OBSTACLE)
    assert labels[n + 200] == Label.BELOW
    assert np.all(labels[-3:] == Label.UNKNOWN)


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
         [2.5, -0.5, -0.8]]  # hole
    )
    grid = quantize(pts, grid_cfg)
    labels = label_cells(grid, np.zeros(grid.shape), SegmentationConfig())
    assert labels[0, 0] == Label.TERRAIN
    assert labels[1, 0] == Label.OBSTACLE
    assert labels[2, 0] == Label.BELOW
    assert labels[3, 1] == Label.UNKNOWN  # no point
