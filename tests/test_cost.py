"""Traversability cost: the documented formula on hand-built cells, occupancy, steps, invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from obstacle_scenes import GRID, Plane, box_points, labelled, terrain_points

from terrainmap.config import Config, ConfigError, CostConfig, GridConfig
from terrainmap.cost import occupancy, smoothstep, step_height, traversability_cost
from terrainmap.errors import InputError
from terrainmap.grid import cell_centers, quantize
from terrainmap.obstacle_stage import make_tracker, run_obstacle_stage
from terrainmap.segmentation import label_cells
from terrainmap.types import Obstacle

SMALL = GridConfig(x_min_m=0.0, length_m=3.0, width_m=2.0, cell_size_m=0.5)  # 6×4 cells, y ∈ [−1, 1]
SHAPE = SMALL.shape


def obstacle(x: float, y: float, length: float = 0.0, width: float = 0.0, yaw: float = 0.0, confirmed=True):
    return Obstacle(
        center_m=np.array([x, y, 0.5]),
        size_m=np.array([length, width, 1.0]),
        yaw_rad=yaw,
        height_m=1.0,
        point_count=20,
        range_m=float(np.hypot(x, y)),
        confirmed=confirmed,
    )


def cost_of(slope_deg, *, valid=None, step=None, obstacles=(), config=None, grid=SMALL):
    slope = np.broadcast_to(np.deg2rad(np.asarray(slope_deg, float)), grid.shape)
    valid = np.ones(grid.shape, bool) if valid is None else valid
    return traversability_cost(
        np.zeros(grid.shape), slope, valid, grid, list(obstacles), config or CostConfig(), step=step
    )


def test_formula_on_hand_built_cells():
    config = CostConfig(max_slope_deg=20.0, max_step_m=0.4)
    slope = np.array([[0, 10, 20, 30], [5, 0, 0, 0], [0, 0, 0, 0], [0] * 4, [0] * 4, [0] * 4], float)
    step = np.zeros(SHAPE)
    step[1, 1], step[1, 2], step[1, 3] = 0.2, 0.4, np.nan
    valid = np.ones(SHAPE, bool)
    valid[2, 0] = False
    cost = cost_of(slope, valid=valid, step=step, config=config)
    assert cost.dtype == np.float32 and cost.shape == SHAPE
    assert cost[0, 0] == 0  # flat
    assert cost[0, 1] == pytest.approx(0.5)  # half the limit: s(½) = ½
    assert cost[0, 2] == 1 and cost[0, 3] == 1  # at and beyond the limit
    assert cost[1, 0] == pytest.approx(3 * 0.25**2 - 2 * 0.25**3)  # s(¼) = 0.15625
    assert cost[1, 1] == pytest.approx(0.5) and cost[1, 2] == 1  # step at ½ and at the limit
    assert cost[1, 3] == 0  # unknown step counts as none
    assert np.isnan(cost[2, 0])  # no data
    assert smoothstep(0.25) == pytest.approx(cost[1, 0])  # the README's s(t), as a function


def test_cost_is_the_max_of_the_terms():
    cost = cost_of(
        np.full(SHAPE, 10.0), step=np.full(SHAPE, 0.1), config=CostConfig(max_slope_deg=20, max_step_m=0.4)
    )
    np.testing.assert_allclose(cost, max(smoothstep(0.5), smoothstep(0.25)))


def test_confirmed_obstacle_occupies_its_footprint_and_clearance():
    # A point obstacle at a cell centre, no clearance: exactly that cell.
    cost = cost_of(0.0, obstacles=[obstacle(1.25, 0.25)], config=CostConfig(clearance_m=0.0))
    assert np.argwhere(cost == 1).tolist() == [[2, 2]]
    assert np.nansum(cost) == 1
    # 0.5 m clearance reaches the 8 neighbours' centres (≤ 0.5·√2 < 0.5 + 0.25) but no further.
    occupied = occupancy([obstacle(1.25, 0.25)], SMALL, clearance_m=0.5)
    assert occupied.sum() == 9 and occupied[1:4, 1:4].all()


def test_obstacles_may_come_as_any_iterable():
    zeros, ones = np.zeros(SHAPE), np.ones(SHAPE, bool)
    listed = traversability_cost(zeros, zeros, ones, SMALL, [obstacle(1.25, 0.25)], CostConfig())
    generated = traversability_cost(zeros, zeros, ones, SMALL, (o for o in [obstacle(1.25, 0.25)]), CostConfig())
    np.testing.assert_array_equal(generated, listed)


def test_unconfirmed_obstacles_do_not_occupy():
    cost = cost_of(0.0, obstacles=[obstacle(1.25, 0.25, 1.0, 1.0, confirmed=False)])
    assert np.all(cost == 0)


def test_rotated_footprint_occupies_the_cells_it_touches():
    grid = GridConfig(x_min_m=0.0, length_m=5.0, width_m=5.0, cell_size_m=0.5)  # y ∈ [−2.5, 2.5]
    diagonal = obstacle(2.5, 0.0, length=4.0, width=0.1, yaw=np.pi / 4)
    occupied = occupancy([diagonal], grid, clearance_m=0.0)
    ix, iy = np.nonzero(occupied)
    # The footprint's centre line y = x − 2.5 runs through cell centres and the corners they
    # share: the 4 m footprint spans 2.83 m along x, six cells on the line, and it touches the
    # cells beside at those corners (five on each side), so no farther than one cell off the line.
    assert np.sum(ix == iy) == 6 and np.all(np.abs(ix - iy) <= 1) and len(ix) == 16
    assert not occupied[0, -1] and not occupied[-1, 0]  # far corners off the diagonal


def test_a_footprint_near_a_cell_corner_reaches_the_cells_within_the_clearance():
    """A 2 cm footprint 1 cm from the corner its cell [1, 2] shares with three others (at x 1.0,
    y 0.5): the clearance reaches a cell once it reaches its square, not its centre's disc."""
    small = obstacle(0.98, 0.48, length=0.02, width=0.02)
    assert np.argwhere(occupancy([small], SMALL, clearance_m=0.0)).tolist() == [[1, 2]]
    # 1 cm to the two neighbours' edges, 1.4 cm to the diagonal one's corner
    assert np.argwhere(occupancy([small], SMALL, clearance_m=0.012)).tolist() == [[1, 2], [1, 3], [2, 2]]
    assert np.argwhere(occupancy([small], SMALL, clearance_m=0.015)).tolist() == [[1, 2], [1, 3], [2, 2], [2, 3]]


def test_occupied_unknown_cell_is_one_and_unknown_elsewhere_is_nan():
    valid = np.zeros(SHAPE, bool)
    cost = cost_of(0.0, valid=valid, obstacles=[obstacle(0.25, -0.75)], config=CostConfig(clearance_m=0.0))
    assert cost[0, 0] == 1 and np.isnan(cost).sum() == cost.size - 1


def _segment_distance(p1, p2, q1, q2):
    """Distance between segments p1p2 and q1q2 ((n, 2) arrays of endpoints): 0 where they cross,
    else the least distance of an endpoint to the other segment."""
    def cross(o, a, b):
        return (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])

    def to_segment(p, a, b):
        ab = b - a
        t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300), 0, 1)
        return np.hypot(*(a + t[:, None] * ab - p).T)

    crossing = (cross(p1, p2, q1) * cross(p1, p2, q2) < 0) & (cross(q1, q2, p1) * cross(q1, q2, p2) < 0)
    d = np.minimum.reduce([to_segment(p1, q1, q2), to_segment(p2, q1, q2), to_segment(q1, p1, p2), to_segment(q2, p1, p2)])
    return np.where(crossing, 0.0, d)


def brute_force_occupancy(obstacles, grid, clearance_m):
    """Reference: every cell's square against every confirmed footprint, as polygons: reached
    where one holds a corner of the other or their edges come within ``clearance_m``."""
    xs, ys = cell_centers(grid)
    x, y = (a.ravel() for a in np.meshgrid(xs, ys, indexing="ij"))
    h = grid.cell_size_m / 2
    square = [np.column_stack([x + sx * h, y + sy * h]) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    occupied = np.zeros(x.size, bool)
    for o in (o for o in obstacles if o.confirmed):
        c, s = np.cos(o.yaw_rad), np.sin(o.yaw_rad)
        a, b = o.size_m[0] / 2, o.size_m[1] / 2
        # cells whose centre is farther from the footprint's centre than its corners are, plus the
        # clearance and the cell's half diagonal, are out of reach
        near = np.flatnonzero(np.hypot(x - o.center_m[0], y - o.center_m[1]) <= np.hypot(a, b) + clearance_m + h * 2**0.5)
        sq = [p[near] for p in square]
        rect = [np.broadcast_to(o.center_m[:2] + np.array([u * c - v * s, u * s + v * c]), (near.size, 2))
                for u, v in ((-a, -b), (a, -b), (a, b), (-a, b))]
        inside_rect = [(np.abs((p - o.center_m[:2]) @ [c, s]) <= a) & (np.abs((p - o.center_m[:2]) @ [-s, c]) <= b)
                       for p in sq]
        inside_square = [(np.abs(q[:, 0] - x[near]) <= h) & (np.abs(q[:, 1] - y[near]) <= h) for q in rect]
        edges = np.minimum.reduce([_segment_distance(sq[i], sq[(i + 1) % 4], rect[j], rect[(j + 1) % 4])
                                   for i in range(4) for j in range(4)])
        occupied[near] |= np.logical_or.reduce(inside_rect + inside_square) | (edges <= clearance_m)
    return occupied.reshape(grid.shape)


@pytest.mark.parametrize("clearance", [0.0, 0.5, 1.3])
def test_windowed_occupancy_matches_brute_force(clearance):
    rng = np.random.default_rng(0)
    params = rng.uniform([0, -13, 0, 0, -3], [38, 13, 4, 2, 3], (200, 5))  # some beyond the area
    many = [
        obstacle(x, y, length, width, yaw, confirmed=bool(i % 5))
        for i, (x, y, length, width, yaw) in enumerate(params)
    ]
    expected = brute_force_occupancy(many, GridConfig(), clearance)
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(occupancy(many, GridConfig(), clearance), expected)


def test_step_height_finds_a_kerb_and_ignores_slopes():
    xs = np.arange(SHAPE[0])[:, None] * 0.5
    elevation = np.broadcast_to(0.2 * xs, SHAPE)  # 11° ramp, explained by the surface
    samples = elevation.copy()
    samples[3:] += 0.15  # a 15 cm kerb between rows 2 and 3
    observed = np.ones(SHAPE, bool)
    observed[0, 0] = False
    step = step_height(samples, elevation, observed)
    assert np.isnan(step[0, 0])
    np.testing.assert_allclose(step[2:4], 0.15)
    np.testing.assert_allclose(step[[0, 1, 4, 5]][~np.isnan(step[[0, 1, 4, 5]])], 0.0, atol=1e-12)


def test_step_height_ignores_unobserved_neighbours():
    """Ground lying evenly below the surface has no step, also beside a cell without a sample of its own."""
    elevation = np.zeros(SHAPE)
    samples = np.full(SHAPE, -0.3)  # relief −0.3 m everywhere
    observed = np.ones(SHAPE, bool)
    observed[2, 2] = False
    samples[2, 2] = 1.0  # no sample of its own: not a step, whatever it holds
    step = step_height(samples, elevation, observed)
    assert np.isnan(step[2, 2])
    np.testing.assert_allclose(step[observed], 0.0, atol=1e-12)


def test_shape_mismatch_raises_input_error():
    with pytest.raises(InputError, match="slope"):
        traversability_cost(np.zeros(SHAPE), np.zeros((3, 3)), np.ones(SHAPE, bool), SMALL, [], CostConfig())


@pytest.mark.parametrize(
    ("field", "value"),
    [("max_slope_deg", 0), ("max_slope_deg", 1e-300), ("max_slope_deg", 90), ("max_step_m", 0), ("max_step_m", 1e-9),
     ("clearance_m", -1)],
)
def test_config_rejects_nonsense(field, value):
    with pytest.raises(ConfigError, match=f"cost.{field}"):
        CostConfig(**{field: value}).validate()


slopes = arrays(np.float64, SHAPE, elements=st.one_of(st.floats(0, np.pi / 2), st.just(np.nan)))
masks = arrays(bool, SHAPE)


@settings(max_examples=60, deadline=None)
@given(
    slope=slopes,
    valid=masks,
    step=arrays(np.float64, SHAPE, elements=st.floats(0, 2)),
    x=st.floats(0, 3),
    y=st.floats(-1, 1),
)
def test_cost_is_in_unit_interval_or_nan_exactly_where_unknown(slope, valid, step, x, y):
    obstacles = [obstacle(x, y)]
    cost = traversability_cost(np.zeros(SHAPE), slope, valid, SMALL, obstacles, CostConfig(), step=step)
    occupied = occupancy(obstacles, SMALL, CostConfig().clearance_m)
    known = valid & np.isfinite(slope)
    finite = np.isfinite(cost)
    assert np.all((cost[finite] >= 0) & (cost[finite] <= 1))
    np.testing.assert_array_equal(finite, known | occupied)


@settings(max_examples=60, deadline=None)
@given(
    base=arrays(np.float64, SHAPE, elements=st.floats(0, np.pi / 2)),
    extra=arrays(np.float64, SHAPE, elements=st.floats(0, 1)),
)
def test_cost_is_monotone_in_slope(base, extra):
    valid = np.ones(SHAPE, bool)
    low = traversability_cost(np.zeros(SHAPE), base, valid, SMALL, [], CostConfig())
    high = traversability_cost(np.zeros(SHAPE), base + extra, valid, SMALL, [], CostConfig())
    assert np.all(high >= low)


def _stage(plane, points, labels, config, tracker, stamp, slope_deg=0.0):
    """run_obstacle_stage on ``points`` over ``plane``: the plane as the terrain, one slope everywhere."""
    grid = quantize(points, GRID)
    elevation = plane.on_grid(*cell_centers(GRID))
    layers = {"elevation": elevation, "slope": np.full(GRID.shape, np.deg2rad(slope_deg)),
              "label": label_cells(grid, elevation, config.segmentation)}
    return run_obstacle_stage(points, labels, grid, layers, stamp, tracker, config)[:2]  # (not what else occupies)


def test_stage_on_a_scene_marks_the_box_once_confirmed_and_never_before():
    """The whole step over two frames: the box costs nothing extra until its track is confirmed,
    then becomes an occupied, clearance-grown patch."""
    plane = Plane(gx=np.tan(np.deg2rad(5)))
    box = box_points(plane, (12.0, 0.0), 1.0, 1.0, 1.0)
    points, labels = labelled(plane, terrain_points(plane, spacing=0.2), box)
    config = Config()
    config.cost.clearance_m = 0.4  # reaches the squares of cells up to 0.4 m from the footprint
    tracker = make_tracker(config)
    slope_cost = smoothstep(5 / 25)
    ix, iy = int((12.0 - GRID.x_min_m) / 0.5), int((0.0 - GRID.y_min_m) / 0.5)
    (first,), cost = _stage(plane, points, labels, config, tracker, 0, slope_deg=5)
    assert not first.confirmed
    np.testing.assert_allclose(cost, slope_cost, atol=0.02)  # tentative: no trace of the box
    (box,), cost = _stage(plane, points, labels, config, tracker, 10**8, slope_deg=5)
    assert box.confirmed
    occupied = cost == 1
    # The box's own 2×2 cells and one ring of neighbours (their squares within 0.4 m of the footprint;
    # the next ring's about 0.5 m away).
    assert occupied[ix - 2 : ix + 2, iy - 2 : iy + 2].all() and occupied.sum() == 16
    np.testing.assert_allclose(cost[~occupied], slope_cost, atol=0.02)


def test_a_cluster_taken_for_part_of_a_confirmed_obstacle_occupies_its_cells_too():
    """A person standing 1.1 m behind a parked car, no taller than it, lies in the car's shadow:
    the tracker takes the cluster for the car's far side (no track of its own), but its cells
    still cost 1, as the car's do."""
    plane = Plane()
    car = box_points(plane, (12.0, 0.0), 4.0, 1.8, 1.5)
    person = box_points(plane, (15.35, 0.0), 0.5, 0.5, 1.4)
    config = Config()
    tracker = make_tracker(config)
    for stamp, parts in ((0, [car]), (10**8, [car]), (2 * 10**8, [car, person])):
        obstacles, cost = _stage(plane, *labelled(plane, terrain_points(plane, spacing=0.2), *parts), config,
                                 tracker, stamp)
    (track,) = obstacles
    assert track.confirmed and track.center_m[0] == pytest.approx(12.0, abs=0.1)
    (part,) = tracker.parts
    assert part.track_id == track.track_id and part.center_m[0] == pytest.approx(15.35, abs=0.1)
    ix, iy = int((15.35 - GRID.x_min_m) / 0.5), int((0.0 - GRID.y_min_m) / 0.5)
    assert np.all(cost[ix - 1 : ix + 2, iy - 1 : iy + 1] == 1)  # the person's cells, beyond the car's clearance
    assert cost[int((17.0 - GRID.x_min_m) / 0.5), iy] == 0


@pytest.mark.parametrize("occupied_misses", [3, 0])
def test_a_confirmed_obstacle_missed_for_a_few_frames_keeps_occupying_its_cells(occupied_misses):
    """A detection flickers: a confirmed box missed in a frame is not reported, but its cells stay
    occupied through ``cost.occupied_misses`` missed frames in a row, then no longer."""
    plane = Plane()
    config = Config()
    config.cost.occupied_misses = occupied_misses
    tracker = make_tracker(config)
    ground = labelled(plane, terrain_points(plane, spacing=0.2))
    scene = labelled(plane, terrain_points(plane, spacing=0.2), box_points(plane, (12.0, 0.0), 1.0, 1.0, 1.0))
    ix, iy = int((12.0 - GRID.x_min_m) / 0.5), int((0.0 - GRID.y_min_m) / 0.5)
    occupied = []
    for k, (points, labels) in enumerate([scene, scene, ground, ground, ground, ground]):
        obstacles, cost = _stage(plane, points, labels, config, tracker, k * 10**8)
        assert [o.confirmed for o in obstacles] == ([False] if k == 0 else [True] if k == 1 else [])
        occupied.append(bool(cost[ix, iy] == 1))
    assert occupied == [False, True] + [True] * occupied_misses + [False] * (4 - occupied_misses)


def test_low_relief_on_ground_too_steep_to_drive_is_no_obstacle_and_the_cost_is_the_same():
    """``obstacles.drop_on_steep_ground``: on a 30° bank (past ``cost.max_slope_deg``) a low bump
    gives no obstacle, and the cost layer is what it is with the option off and the bump confirmed
    and occupying cells: the slope alone already costs 1 there."""
    plane = Plane(gy=np.tan(np.deg2rad(30)))
    bump = box_points(plane, (12.0, 0.0), 2.0, 0.5, 0.55)
    points, labels = labelled(plane, terrain_points(plane, spacing=0.2), bump)
    results = {}
    for drop in (True, False):
        config = Config()
        config.obstacles.drop_on_steep_ground = drop
        tracker = make_tracker(config)
        for stamp in (0, 10**8):
            results[drop] = _stage(plane, points, labels, config, tracker, stamp, slope_deg=30)
    assert results[True][0] == []
    (bump_track,) = results[False][0]
    assert bump_track.confirmed and bump_track.height_m == pytest.approx(0.55, abs=0.02)
    np.testing.assert_array_equal(results[True][1], results[False][1])
    assert np.all(results[True][1][np.isfinite(results[True][1])] == 1)


def test_step_height_names_a_layer_of_the_wrong_shape():
    with pytest.raises(InputError, match=r"step_height: elevation must have shape \(3, 3\), got \(3, 4\)"):
        step_height(np.zeros((3, 3)), np.zeros((3, 4)), np.ones((3, 3), bool))


def test_a_bad_grid_or_an_obstacle_that_is_not_finite_is_refused():
    zeros, valid = np.zeros(SHAPE), np.ones(SHAPE, bool)
    with pytest.raises(ConfigError, match="grid.cell_size_m"):
        traversability_cost(zeros, zeros, valid, GridConfig(cell_size_m=-1.0), [], CostConfig())
    lost = Obstacle(np.array([np.nan, 0.0, 0.5]), np.ones(3), 0.0, 1.0, 20, 5.0, track_id=1, confirmed=True)
    with pytest.raises(InputError, match="confirmed obstacle's centre, size or yaw is not finite"):
        traversability_cost(zeros, zeros, valid, SMALL, [lost], CostConfig())
