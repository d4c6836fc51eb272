import math

import numpy as np
import pytest

from terrainmap.errors import InputError
from terrainmap.evaluation import artificial_obstacle as ao

HEIGHTS = ao.PAPER_HEIGHTS_M


@pytest.fixture(scope="module")
def results():
    return ao.run(ao.grid_of_scenarios(ao.PAPER_NETS, (0.8, 2.0, 4.0, 8.0, 12.0), HEIGHTS))


def _worst(results, net, width):
    return max(r.max_deviation_pct for r in results if r.control_points == net and r.width_m == width)


def test_thin_obstacle_barely_moves_the_25x25_surface(results):
    for r in results:
        if r.control_points == 25 and r.width_m == 0.8:
            assert r.max_deviation_pct < 5.0, r


def test_deviation_grows_with_width(results):
    for net in ao.PAPER_NETS:
        worst = [_worst(results, net, w) for w in (0.8, 2.0, 4.0, 8.0, 12.0)]
        assert all(b >= a - 1.0 for a, b in zip(worst, worst[1:])), worst  # 1-point slack for grid effects
        assert worst[-1] > 50 > worst[0]


def test_never_nan_and_no_overshoot_beyond_150_percent(results):
    for r in results:
        assert math.isfinite(r.max_deviation_pct) and 0 <= r.max_deviation_pct <= 150, r


def test_few_control_points_make_a_more_rigid_surface(results):
    assert _worst(results, 5, 8.0) < _worst(results, 25, 8.0)


def test_box_is_added_where_asked():
    base = ao.flat_base(ao.PAPER_GRID)
    with_box = ao.add_box(base, (11.0, 0.0), 2.0, 1.5)
    raised = with_box[:, 2] > 0
    assert np.all(np.abs(with_box[raised, 0] - 11.0) <= 1.0) and np.all(np.abs(with_box[raised, 1]) <= 1.0)
    assert raised.sum() == 16 * 16  # 2 m at 4 samples per 0.5 m cell


@pytest.mark.parametrize("position, height", [((50.0, 0.0), 1.0), ((11.0, 0.0), 1e6)])
def test_a_box_the_grid_never_sees_is_an_error_not_zero_percent(position, height):
    """Outside the area, or with its top above grid.z_max_m, the box would leave the surface
    untouched and score a misleading 0 %."""
    with pytest.raises(InputError, match="leaves no point in the grid"):
        ao.run([ao.Scenario(5, 2.0, height)], position_xy=position)


def test_the_deviation_is_the_largest_over_the_area_as_a_percentage_of_the_height():
    """Fig. 6's measure: max |S_with − S_without| over the lattice, in % of h (not a mean or a percentile)."""
    from dataclasses import replace

    from terrainmap.config import TerrainConfig

    (result,) = ao.run([ao.Scenario(5, 4.0, 2.0)])
    terrain = replace(TerrainConfig(), control_points_x=5, control_points_y=5)
    base = ao.flat_base(ao.PAPER_GRID)
    without, _ = ao._surface_on_lattice(base, ao.PAPER_GRID, terrain, 5)
    with_box, _ = ao._surface_on_lattice(ao.add_box(base, (11.0, 0.0), 4.0, 2.0), ao.PAPER_GRID, terrain, 5)
    deviation = np.abs(with_box - without)
    assert result.max_deviation_m == pytest.approx(deviation.max())
    assert result.max_deviation_pct == pytest.approx(100 * deviation.max() / 2.0)


def test_a_base_with_gaps_is_scored_on_the_cells_that_hold_its_points_with_its_rig(monkeypatch):
    """A base scene from a log covers part of the area: the deviation is taken over the cells
    that hold its points, not over the cells filled from their neighbours, and its rig gives the
    grid eq. 1's noise discount, as in the pipeline."""
    from dataclasses import replace

    from terrainmap.config import TerrainConfig
    from terrainmap.grid import quantize
    from terrainmap.types import StereoCamera

    base = ao.flat_base(ao.PAPER_GRID)
    base = base[(base[:, 0] < 15.0) & (np.abs(base[:, 1]) < 6.0)]  # seen nearer than 15 m, 6 m to each side
    grid = quantize(base, ao.PAPER_GRID)
    assert (grid.valid & ~grid.observed).any()  # cells filled at the edge of the seen part
    _, mask = ao._surface_on_lattice(base, ao.PAPER_GRID, replace(TerrainConfig(), control_points_x=5,
                                                                   control_points_y=5), 5)
    step = ao.PAPER_GRID.cell_size_m / 5
    xs = ao.PAPER_GRID.x_min_m + np.arange(mask.shape[0]) * step
    ys = ao.PAPER_GRID.y_min_m + np.arange(mask.shape[1]) * step
    assert xs[mask.any(1)].max() < 15.0 and -6.0 <= ys[mask.any(0)].min() and ys[mask.any(0)].max() < 6.0
    cameras = []
    monkeypatch.setattr(ao, "quantize", lambda points, grid, camera=None: cameras.append(camera) or
                        quantize(points, grid, camera=camera))
    camera = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)
    (seen,) = ao.run([ao.Scenario(5, 2.0, 1.0)], base_points=base, camera=camera)
    assert seen.max_deviation_pct > 0 and cameras == [camera, camera]
