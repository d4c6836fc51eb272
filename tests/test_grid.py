import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.config import GridConfig
from terrainmap.errors import FrameError, InputError
from terrainmap.grid import cell_centers, cell_index, quantize

SMALL = GridConfig(x_min_m=0.0, length_m=3.0, width_m=2.0, y_center_m=0.0, cell_size_m=1.0)  # 3×2 cells
MEAN = GridConfig(**{**SMALL.__dict__, "sigma_factor": 0.0})  # Z = the cell mean


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


def test_empty_cells_take_the_mean_of_observed_neighbours_else_invalid():
    cfg = GridConfig(x_min_m=0.0, length_m=5.0, width_m=5.0, y_center_m=2.5, cell_size_m=1.0)
    pts = np.array([[0.5, 0.5, 1.0], [1.5, 0.5, 3.0]])
    g = quantize(pts, cfg)
    assert g.valid[0, 1] and not g.observed[0, 1]
    assert g.z[0, 1] == pytest.approx(2.0)  # neighbours (0,0) and (1,0)
    assert g.z[2, 1] == pytest.approx(3.0)  # only (1,0) is a neighbour
    assert not g.valid[4, 4] and g.z[4, 4] == 0.0  # INVALID, Z := 0
    assert g.valid.sum() == 2 + 4  # the two observed cells and their four empty neighbours
    off = quantize(pts, GridConfig(**{**cfg.__dict__, "fill_empty": False}))
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
