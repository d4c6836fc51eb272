import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.config import GridConfig
from terrainmap.errors import FrameError, InputError
from terrainmap.grid import cell_centers, cell_index, quantize
from terrainmap.types import Extrinsics, StereoCamera

SMALL = GridConfig(x_min_m=0.0, length_m=3.0, width_m=2.0, y_center_m=0.0, cell_size_m=1.0)  # 3×2 cells
MEAN = dataclasses.replace(SMALL, sigma_factor=0.0)  # Z = the cell mean


def test_cell_geometry_and_indexing():
    xs, ys = cell_centers(SMALL)
    np.testing.assert_allclose(xs, [0.5, 1.5, 2.5])
    np.testing.assert_allclose(ys, [-0.5, 0.5])
    pts = np.array([[0.1, -0.9, 0], [2.9, 0.9, 0], [3.1, 0, 0], [1, 5, 0], [np.nan, 0, 0], [1, np.inf, 0]])
    np.testing.assert_array_equal(cell_index(pts, SMALL), [0, 5, 6, 6, 6, 6])


def test_eq1_on_hand_built_cells():
    pts = np.array(
        [
            # cell (0,0): mean 1, σ = 0.8165, min 0 → max(0, 0.1835)
            [0.5, -0.5, 0.0], [0.5, -0.5, 1.0], [0.5, -0.5, 2.0],
            # cell (1,1): min 0 dominates mean − σ (= 2.5 − 4.33)
            [1.5, 0.5, 0.0], [1.5, 0.5, 0.0], [1.5, 0.5, 0.0], [1.5, 0.5, 10.0],
            # cell (2,0): a single point
            [2.5, -0.5, 0.7],
        ]
    )
    g = quantize(pts, SMALL)
    assert g.z[0, 0] == pytest.approx(1 - np.sqrt(2 / 3))
    assert g.z_top[0, 0] == pytest.approx(1 + np.sqrt(2 / 3))
    assert g.z[1, 1] == pytest.approx(0.0)
    assert g.z[2, 0] == pytest.approx(0.7)
    np.testing.assert_array_equal(g.count, [[3, 0], [0, 4], [1, 0]])
    mean = quantize(pts, MEAN)  # k = 0 skips the minimum
    np.testing.assert_allclose(mean.z[[0, 1, 2], [0, 1, 0]], [1.0, 2.5, 0.7])
    np.testing.assert_array_equal(mean.z_top[g.observed], g.z_top[g.observed])
    half = quantize(pts, dataclasses.replace(SMALL, sigma_factor=0.5))  # Z = max(min, mean − k·σ)
    assert half.z[0, 0] == pytest.approx(1 - 0.5 * np.sqrt(2 / 3))


# A level camera 1.8 m up at the origin, f·B = 150 px·m (the simulator's rig without its pitch)
_RIG = StereoCamera.from_rig(
    500.0, 0.3, Extrinsics(rotation=np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), translation=np.array([0, 0, 1.8]))
)
_FAR = GridConfig(x_min_m=14.0, length_m=2.0, width_m=2.0, y_center_m=0.0, cell_size_m=1.0)  # 2×2 cells, 14–16 m


def _stereo_ground(n: int, noise_px: float, seed: int = 0, rise: float = 0.0) -> np.ndarray:
    """Points of the plane z = rise·(x − 15) at 10–20 m, each moved along its camera ray by a
    disparity error."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(10, 20, n)
    ground = np.column_stack([x, rng.uniform(-1, 1, n), rise * (x - 15)])
    ray = ground - _RIG.center_m
    depth = ray @ _RIG.axis
    return _RIG.center_m + ray * (1 + depth * rng.normal(0, noise_px, n) / _RIG.focal_baseline)[:, None]


def test_stereo_noise_no_longer_pulls_eq1_below_the_ground():
    pts = _stereo_ground(200_000, 0.5)
    paper = quantize(pts, dataclasses.replace(_FAR, stereo_noise_px=0.0), camera=_RIG)
    aware = quantize(pts, _FAR, camera=_RIG)
    assert np.all(paper.z < -0.06)  # eq. 1: about σ_s of the noise (8–9 cm at 14–16 m) below
    assert np.all(np.abs(aware.z) < 0.02)
    np.testing.assert_array_equal(quantize(pts, _FAR).z, paper.z)  # no rig: the paper's eq. 1
    # The height a pixel of disparity moves level ground: depth · camera height / (f·B), 15 m → 0.18 m
    np.testing.assert_allclose(paper.height_per_px, 1.8 * np.array([[14.5] * 2, [15.5] * 2]) / 150, rtol=0.02)
    assert quantize(pts, _FAR).height_per_px is None


def test_on_slope_takes_the_noise_of_ground_facing_the_camera():
    """On ground rising 0.3 m per m (17°) the same disparity noise moves points 3.5× more in height
    than the level-ground discount assumes at 15 m: Z stays ~σ_s low until the slope is known."""
    pts = _stereo_ground(200_000, 0.5, rise=0.3)
    level = quantize(pts, _FAR, camera=_RIG)
    truth = 0.3 * (cell_centers(_FAR)[0] - 15)[:, None]
    gx, gy = np.full(level.shape, 0.3), np.zeros(level.shape)
    sloped = level.on_slope(gx, gy)
    assert np.all(level.z - truth < -0.15)
    # What is left is the spread of a 1 m cell on a 17° slope itself, 0.3/√12 = 9 cm: eq. 1's own.
    assert np.all(np.abs(sloped.z - truth + 0.087) < 0.03)
    np.testing.assert_allclose(sloped.height_per_px, 15 * (1.8 + 0.3 * 15) / 150, rtol=0.1)
    np.testing.assert_array_equal(level.on_slope(0 * gx, gy).z, level.z)
    no_rig = quantize(pts, _FAR)
    assert no_rig.on_slope(gx, gy) is no_rig


def test_stereo_noise_discount_keeps_obstacles_out_of_the_sample():
    """A 1.5 m object sharing a cell with noisy ground spreads far beyond the noise: Z stays low."""
    ground = _stereo_ground(20_000, 0.5)
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.full(1_500, 14.5), rng.uniform(-0.9, -0.1, 1_500), rng.uniform(0, 1.5, 1_500)])
    g = quantize(np.vstack([ground, wall]), _FAR, camera=_RIG)
    assert g.z[0, 0] < 0.05 and g.z_top[0, 0] > 0.5


def test_empty_cells_take_the_mean_of_observed_neighbours_else_invalid():
    cfg = GridConfig(x_min_m=0.0, length_m=5.0, width_m=5.0, y_center_m=2.5, cell_size_m=1.0)
    pts = np.array([[0.5, 0.5, 1.0], [1.5, 0.5, 3.0]])
    g = quantize(pts, cfg)
    assert g.valid[0, 1] and not g.observed[0, 1]
    assert g.z[0, 1] == pytest.approx(2.0)  # neighbours (0,0) and (1,0)
    assert g.z_top[0, 1] == g.z[0, 1]  # a filled cell's top is its sample
    assert g.z[2, 1] == pytest.approx(3.0)  # only (1,0) is a neighbour
    assert not g.valid[4, 4] and g.z[4, 4] == 0.0  # INVALID, Z := 0
    assert g.valid.sum() == 2 + 4  # the two observed cells and their four empty neighbours
    off = quantize(pts, dataclasses.replace(cfg, fill_empty=False))
    assert off.valid.sum() == 2


def test_bad_input():
    with pytest.raises(InputError, match="N×3"):
        quantize(np.zeros((5, 2)), SMALL)
    with pytest.raises(FrameError) as err:
        quantize(np.zeros((0, 3)), SMALL)
    assert err.value.reason == "no_points_in_area"
    with pytest.raises(FrameError):
        quantize(np.array([[100.0, 0, 0], [np.nan, np.nan, np.nan]]), SMALL)


@given(
    st.lists(st.tuples(st.floats(0, 2.999), st.floats(-0.999, 0.999), st.floats(-5, 5)), min_size=1, max_size=60)
)
@settings(max_examples=80, deadline=None)
def test_sample_stays_within_the_cell_range(points):
    """Eq. 1 keeps every sample within [min z, max z] of its cell (paper Sec. IV)."""
    pts = np.array(points)
    g = quantize(pts, SMALL)
    idx = cell_index(pts, SMALL)
    for cell in np.unique(idx):
        z = pts[idx == cell, 2]
        ix, iy = divmod(int(cell), 2)
        assert z.min() - 1e-9 <= g.z[ix, iy] <= z.max() + 1e-9
        assert g.z[ix, iy] <= g.z_top[ix, iy] + 1e-9
        assert g.z_top[ix, iy] >= z.mean() - 1e-9


def test_grid_does_not_depend_on_the_order_of_the_points():
    """The per-cell sums are spread over copies of each bin (grid._LANES); whether a cell's points
    come in one run, as from a camera, or scattered, the grid is the same."""
    from terrainmap.synthetic import cloud

    grid = GridConfig()
    points = cloud(20_001, grid=grid, seed=4)  # camera order; an odd count exercises the offsets' tail
    shuffled = points[np.random.default_rng(0).permutation(len(points))]
    a, b = quantize(points, grid), quantize(shuffled, grid)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_allclose(a.z, b.z, atol=1e-9)
    np.testing.assert_allclose(a.z_top, b.z_top, atol=1e-9)
    reference = np.zeros(grid.shape)
    idx = cell_index(points, grid)
    inside = idx < reference.size
    np.add.at(reference.reshape(-1), idx[inside], 1)
    np.testing.assert_array_equal(a.count, reference)


def test_an_index_of_the_wrong_length_is_named():
    with pytest.raises(InputError, match=r"quantize: index must have shape \(3,\), got \(5,\)"):
        quantize(np.ones((3, 3)), GridConfig(), index=np.zeros(5, np.intp))


def test_per_bin_sums_and_extremes_match_a_plain_reduction():
    """PerBin spreads each bin over lanes (grid._LANES); folded back, its sums, minima and maxima
    are those of one bin per index, with empty bins at 0 and ±inf."""
    from terrainmap.grid import PerBin

    rng = np.random.default_rng(3)
    idx = np.repeat(rng.integers(0, 7, 40), rng.integers(1, 9, 40))  # runs, as a camera gives them
    values = rng.normal(size=idx.size)
    per = PerBin(idx, 9)  # bins 7 and 8 stay empty; 9 is not a power of two
    np.testing.assert_array_equal(per.sum(), np.bincount(idx, minlength=9))
    np.testing.assert_allclose(per.sum(values), np.bincount(idx, values, 9), atol=1e-12)
    for ufunc, identity in ((np.minimum, np.inf), (np.maximum, -np.inf)):
        expected = np.full(9, identity)
        ufunc.at(expected, idx, values)
        np.testing.assert_array_equal(per.reduce(ufunc, values), expected)
