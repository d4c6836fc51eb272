"""Obstacle extraction: synthetic planes with boxes and ditches, filters, many tiny clusters."""

from __future__ import annotations

import numpy as np
import pytest
from obstacle_scenes import GRID, Plane, box_points, labelled, terrain_points

from terrainmap.config import ConfigError, GridConfig, ObstacleConfig
from terrainmap.errors import InputError
from terrainmap.obstacles import extract_obstacles, terrain_at
from terrainmap.types import Label


def test_box_on_flat_ground_is_one_positive_obstacle():
    plane = Plane()
    box = box_points(plane, (10.0, 2.0), 1.5, 1.0, 1.2)
    points, labels = labelled(plane, terrain_points(plane), box)
    (obstacle,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert obstacle.kind == "positive"
    assert obstacle.track_id == -1 and not obstacle.confirmed
    np.testing.assert_allclose(obstacle.center_m[:2], [10.0, 2.0], atol=0.05)
    np.testing.assert_allclose(obstacle.center_m[2], 0.6, atol=0.05)  # from the ground to the top
    np.testing.assert_allclose(sorted(obstacle.size_m[:2]), [1.0, 1.5], atol=0.06)
    assert obstacle.size_m[2] == pytest.approx(1.2, abs=0.02)
    assert obstacle.height_m == pytest.approx(1.2, abs=1e-3)
    assert obstacle.point_count == int((labels == Label.OBSTACLE).sum())
    nearest = np.linalg.norm(box[box[:, 2] > 0.25], axis=1).min()
    assert obstacle.range_m == pytest.approx(nearest, abs=1e-4)


def test_reused_cell_index_gives_the_same_obstacles():
    """The pipeline hands over the grid stage's cell index instead of computing it again."""
    from terrainmap.grid import cell_index

    plane = Plane()
    points, labels = labelled(
        plane, terrain_points(plane), box_points(plane, (10.0, 2.0), 1.5, 1.0, 1.2),
        box_points(plane, (18.0, -4.0), 0.6, 0.6, 1.8),
    )
    plain = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    reused = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(), index=cell_index(points, GRID))
    assert len(plain) == len(reused) == 2
    for a, b in zip(plain, reused, strict=True):
        np.testing.assert_array_equal(np.r_[a.center_m, a.size_m], np.r_[b.center_m, b.size_m])
        assert (a.yaw_rad, a.height_m, a.point_count, a.range_m) == (b.yaw_rad, b.height_m, b.point_count, b.range_m)
    with pytest.raises(InputError, match="index"):
        extract_obstacles(points, labels, GRID, plane, ObstacleConfig(), index=np.zeros(3, int))


def test_rotated_box_on_tilted_plane_height_is_above_the_surface():
    plane = Plane(gx=np.tan(np.deg2rad(10)), gy=-0.05, z0=0.4)
    yaw = np.deg2rad(30)
    box = box_points(plane, (15.0, -3.0), 3.0, 1.0, 0.8, yaw=yaw)
    points, labels = labelled(plane, terrain_points(plane), box)
    (obstacle,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert obstacle.yaw_rad == pytest.approx(yaw, abs=np.deg2rad(2))
    np.testing.assert_allclose(obstacle.size_m[:2], [3.0, 1.0], atol=0.06)
    np.testing.assert_allclose(obstacle.center_m[:2], [15.0, -3.0], atol=0.05)
    # Box top is 0.8 m above the plane; the plane rises 0.53 m across the box's x extent.
    assert obstacle.height_m == pytest.approx(0.8, abs=0.02)


def test_ditch_is_a_negative_obstacle_with_its_depth():
    plane = Plane(gy=0.02)
    ground = terrain_points(plane)
    ditch = (np.abs(ground[:, 0] - 20.0) < 0.6) & (np.abs(ground[:, 1]) < 3.0)
    ground[ditch, 2] -= 0.7
    points, labels = labelled(plane, ground)
    (obstacle,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert obstacle.kind == "negative"
    assert obstacle.height_m == pytest.approx(0.7, abs=1e-3)
    # The box spans from the deepest point (low side of the tilted ditch) up to the terrain.
    ground_z = plane.evaluate(*obstacle.center_m[:2])
    assert obstacle.size_m[2] == pytest.approx(ground_z - points[ditch, 2].min(), abs=1e-4)
    assert obstacle.center_m[2] == pytest.approx(ground_z - obstacle.size_m[2] / 2, abs=1e-6)
    np.testing.assert_allclose(obstacle.center_m[:2], [20.0, 0.0], atol=0.1)
    assert extract_obstacles(points, labels, GRID, plane, ObstacleConfig(negative=False)) == []
    # A ditch is held to min_depth_m, not to the positive obstacles' min_height_m.
    assert len(extract_obstacles(points, labels, GRID, plane, ObstacleConfig(min_height_m=1.0))) == 1
    assert extract_obstacles(points, labels, GRID, plane, ObstacleConfig(min_depth_m=0.8)) == []


def test_obstacles_come_positive_first_each_kind_sorted_by_range():
    """A box far out to the side is found (labelled) before a nearer one straight ahead: the
    result is still in range order, and a pit nearer than both comes after them."""
    plane = Plane()
    ground = terrain_points(plane)
    pit = (np.abs(ground[:, 0] - 8.0) < 0.6) & (np.abs(ground[:, 1]) < 1.0)
    ground[pit, 2] -= 0.7
    side = box_points(plane, (12.0, -9.0), 1.0, 1.0, 1.0)  # 15 m away, at a lower x
    ahead = box_points(plane, (14.0, 0.0), 1.0, 1.0, 1.0)  # 13.5 m away
    points, labels = labelled(plane, ground, side, ahead)
    found = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert [o.kind for o in found] == ["positive", "positive", "negative"]
    np.testing.assert_allclose([o.center_m[0] for o in found[:2]], [14.0, 12.0], atol=0.1)
    assert found[0].range_m < found[1].range_m


def test_frame_without_obstacles_gives_none():
    plane = Plane(gx=0.1)
    points, labels = labelled(plane, terrain_points(plane))
    assert extract_obstacles(points, labels, GRID, plane, ObstacleConfig()) == []
    empty = np.zeros((0, 3), np.float32)
    assert extract_obstacles(empty, np.zeros(0, np.uint8), GRID, plane, ObstacleConfig()) == []


def test_separate_boxes_are_separate_and_diagonal_neighbours_join():
    plane = Plane()
    a = box_points(plane, (8.0, 0.0), 0.8, 0.8, 1.0)
    b = box_points(plane, (8.0, 4.0), 0.8, 0.8, 1.0)
    points, labels = labelled(plane, a, b)
    found = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert sorted(round(o.center_m[1]) for o in found) == [0, 4]
    # Two single-cell clusters touching at a corner are one cluster (8-connectivity).
    corner = np.array([[10.25, 0.25, 1.0]] * 6 + [[10.75, 0.75, 1.0]] * 6)
    labels = np.full(len(corner), Label.OBSTACLE, np.uint8)
    (joined,) = extract_obstacles(corner, labels, GRID, plane, ObstacleConfig(min_points=1))
    assert joined.point_count == 12


@pytest.mark.parametrize(
    ("field", "value", "kept"),
    [
        ("min_height_m", 1.1, False),
        ("min_height_m", 0.9, True),
        ("min_points", 10_000, False),
        ("min_cells", 20, False),
    ],
)
def test_filters(field, value, kept):
    plane = Plane()
    points, labels = labelled(plane, box_points(plane, (10.0, 0.0), 1.0, 1.0, 1.0))
    found = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(**{field: value}))
    assert len(found) == int(kept)


def test_a_cluster_of_exactly_min_points_is_kept():
    """``min_points`` is the fewest points an obstacle may have ("fewer are dropped")."""
    plane = Plane()
    points, labels = labelled(plane, box_points(plane, (10.0, 0.0), 1.0, 1.0, 1.0))
    (obstacle,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    config = ObstacleConfig(min_points=obstacle.point_count)
    assert len(extract_obstacles(points, labels, GRID, plane, config)) == 1
    config = ObstacleConfig(min_points=obstacle.point_count + 1)
    assert extract_obstacles(points, labels, GRID, plane, config) == []


def test_min_cell_points_drops_sparse_cells():
    plane = Plane()
    sparse = np.array([[10.25, 0.25, 1.0], [10.75, 0.25, 1.0]])  # one point in each of two cells
    labels = np.full(2, Label.OBSTACLE, np.uint8)
    assert len(extract_obstacles(sparse, labels, GRID, plane, ObstacleConfig(min_points=1, min_cell_points=1))) == 1
    assert (
        extract_obstacles(sparse, labels, GRID, plane, ObstacleConfig(min_points=1, min_cell_points=2)) == []
    )


def test_thousands_of_tiny_clusters_are_each_found():
    plane = Plane()
    m0, m1 = GRID.shape
    ix, iy = np.meshgrid(np.arange(0, m0, 2), np.arange(0, m1, 2), indexing="ij")
    n_clusters = ix.size  # isolated cells: every other cell along both axes
    x = GRID.x_min_m + (ix.ravel() + 0.5) * GRID.cell_size_m
    y = GRID.y_min_m + (iy.ravel() + 0.5) * GRID.cell_size_m
    rng = np.random.default_rng(1)
    per_cluster = 5
    jitter = rng.uniform(-0.2, 0.2, (per_cluster * n_clusters, 2))
    pts = np.column_stack(
        [np.repeat(x, per_cluster) + jitter[:, 0], np.repeat(y, per_cluster) + jitter[:, 1]]
    )
    pts = np.column_stack([pts, rng.uniform(0.4, 1.0, len(pts))])
    labels = np.full(len(pts), Label.OBSTACLE, np.uint8)
    config = ObstacleConfig(min_points=1)
    found = extract_obstacles(pts, labels, GRID, plane, config)  # its speed: `terrainmap bench`
    assert n_clusters > 700 and len(found) == n_clusters
    assert all(o.point_count == per_cluster for o in found)
    assert extract_obstacles(pts, labels, GRID, plane, ObstacleConfig(min_points=6)) == []


def test_points_outside_the_area_are_ignored():
    plane = Plane()
    outside = box_points(plane, (-5.0, 0.0), 1.0, 1.0, 1.0)
    points, labels = labelled(plane, outside)
    assert extract_obstacles(points, labels, GRID, plane, ObstacleConfig()) == []


def test_bad_input_raises_input_error():
    with pytest.raises(InputError, match="N×3"):
        extract_obstacles(np.zeros((4, 2)), np.zeros(4, np.uint8), GRID, Plane(), ObstacleConfig())
    with pytest.raises(InputError, match="labels"):
        extract_obstacles(np.zeros((4, 3)), np.zeros(3, np.uint8), GRID, Plane(), ObstacleConfig())


def test_terrain_at_is_exact_on_a_plane():
    plane = Plane(gx=0.3, gy=-0.2, z0=1.0)
    xs, ys = np.random.default_rng(0).uniform([2.5, -10.7], [35.7, 10.7], (500, 2)).T
    elevation = plane.on_grid(
        GRID.x_min_m + (np.arange(68) + 0.5) * 0.5, GRID.y_min_m + (np.arange(44) + 0.5) * 0.5
    )
    got = terrain_at(xs, ys, elevation, GRID)
    np.testing.assert_allclose(got, plane.evaluate(xs, ys), atol=1e-9)


def test_terrain_at_is_bilinear_between_cell_centres_and_clamped_beyond():
    """Against scipy's bilinear interpolation over the cell centres, the points clamped to them."""
    from scipy.interpolate import RegularGridInterpolator

    rng = np.random.default_rng(5)
    elevation = rng.normal(size=GRID.shape)
    cx = GRID.x_min_m + (np.arange(GRID.shape[0]) + 0.5) * GRID.cell_size_m
    cy = GRID.y_min_m + (np.arange(GRID.shape[1]) + 0.5) * GRID.cell_size_m
    xs = rng.uniform(GRID.x_min_m - 2, cx[-1] + 2, 2000)  # inside, in the outer half cells and beyond
    ys = rng.uniform(GRID.y_min_m - 2, cy[-1] + 2, 2000)
    expected = RegularGridInterpolator((cx, cy), elevation)(np.column_stack([np.clip(xs, cx[0], cx[-1]), np.clip(ys, cy[0], cy[-1])]))
    np.testing.assert_allclose(terrain_at(xs, ys, elevation, GRID), expected, atol=1e-9)


def test_terrain_at_on_a_grid_one_cell_long():
    """One row of cells: linear along y between the cell centres, constant along x and beyond the ends."""
    grid = GridConfig(x_min_m=2.0, length_m=0.5, y_center_m=0.0, width_m=2.0, cell_size_m=0.5)  # 1 × 4 cells
    elevation = np.array([[0.0, 1.0, 3.0, 4.0]])  # centres at y = -0.75, -0.25, 0.25, 0.75
    got = terrain_at(np.array([1.0, 2.25, 9.0, 2.25, 2.25]), np.array([-0.5, 0.0, 0.25, -5.0, 5.0]), elevation, grid)
    np.testing.assert_allclose(got, [0.5, 2.0, 3.0, 0.0, 4.0])


@pytest.mark.parametrize(
    ("field", "value"),
    [("min_height_m", 0), ("min_depth_m", 0), ("min_points", 0), ("min_cells", 0), ("min_cell_points", 0),
     ("split_min_length_m", 0), ("split_gap_fraction", 1.0), ("split_min_part", -0.1),
     ("tall_height_m", 0), ("tall_min_share", 1.5)],
)
def test_config_rejects_nonsense(field, value):
    with pytest.raises(ConfigError, match=f"obstacles.{field}"):
        ObstacleConfig(**{field: value}).validate()


def _smeared_pair(rng, per_cell):
    """A person (0.5 m, 1.8 m tall) at 14 m and a car (4 × 1.8 m) 6 m behind it, with as many
    points as a camera gives each, joined by a trail of stereo-smeared points between them
    (``per_cell`` per 0.5 m cell, 1.2 m up)."""
    plane = Plane()
    person = box_points(plane, (14.0, 3.0), 0.5, 0.5, 1.8)
    car = box_points(plane, (22.0, 3.0), 4.0, 1.8, 1.5, spacing=0.1)
    trail_x = np.repeat(np.arange(14.3, 20.0, 0.5), per_cell)
    trail_x += rng.uniform(-0.2, 0.2, trail_x.size)
    trail = np.column_stack([trail_x, np.full_like(trail_x, 3.0), np.full_like(trail_x, 1.2)])
    return plane, labelled(plane, terrain_points(plane), person, car, trail)


# 3 per cell is a thin trail; 15 is as dense, relative to the person, as the simulated ditch's
# smear (12–17 % of the person's fullest 0.5 m stretch).
@pytest.mark.parametrize("per_cell", [3, 15])
def test_smear_between_two_obstacles_is_cut(per_cell):
    plane, (points, labels) = _smeared_pair(np.random.default_rng(0), per_cell)
    (merged,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(split_gap_fraction=0))
    assert merged.point_count == int((labels == Label.OBSTACLE).sum())  # one cluster, centred on neither:
    assert min(abs(merged.center_m[0] - 14.0), abs(merged.center_m[0] - 22.0)) > 1.0
    person, car = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    np.testing.assert_allclose(person.center_m[:2], [14.0, 3.0], atol=0.15)
    np.testing.assert_allclose(car.center_m[:2], [22.0, 3.0], atol=0.15)
    assert person.height_m == pytest.approx(1.8, abs=0.01) and car.height_m == pytest.approx(1.5, abs=0.01)
    assert person.point_count + car.point_count < int((labels == Label.OBSTACLE).sum())  # the trail is dropped


def test_a_cluster_shorter_than_split_min_length_is_never_split():
    """The person-smear-car cluster is about 10 m long: split with a 9 m minimum, whole with 11 m."""
    plane, (points, labels) = _smeared_pair(np.random.default_rng(0), 3)
    assert len(extract_obstacles(points, labels, GRID, plane, ObstacleConfig(split_min_length_m=9.0))) == 2
    (whole,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(split_min_length_m=11.0))
    assert whole.point_count == int((labels == Label.OBSTACLE).sum())


def test_small_obstacle_smeared_into_a_tall_one_is_cut_off():
    """A 0.5 m rock 3.5 m behind a 3 m pole, joined to it by smear: the rock holds under 10 % of
    their cluster (as in the simulated ditch) and is still cut off as an obstacle of its own."""
    plane = Plane()
    pole = box_points(plane, (11.0, -2.5), 0.3, 0.3, 3.0, spacing=0.011)
    rock = box_points(plane, (14.5, -2.5), 0.6, 0.6, 0.5, spacing=0.06)
    trail_x = np.repeat(np.arange(11.4, 14.1, 0.5), 8) + np.random.default_rng(0).uniform(-0.2, 0.2, 48)
    trail = np.column_stack([trail_x, np.full_like(trail_x, -2.5), np.full_like(trail_x, 0.45)])
    points, labels = labelled(plane, terrain_points(plane), pole, rock, trail)
    assert len(rock) < 0.1 * int((labels == Label.OBSTACLE).sum())
    (merged,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(split_min_part=0.1))
    assert merged.point_count == int((labels == Label.OBSTACLE).sum())
    found_pole, found_rock = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    np.testing.assert_allclose(found_pole.center_m[:2], [11.0, -2.5], atol=0.1)
    np.testing.assert_allclose(found_rock.center_m[:2], [14.5, -2.5], atol=0.15)
    assert found_rock.height_m == pytest.approx(0.5, abs=0.01)
    # Each part counts its own cells: the pole's 4 are too few for min_cells 5, the cluster's were not.
    (only,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(min_cells=5))
    assert only.point_count == found_rock.point_count


def test_long_dense_obstacle_is_not_split():
    plane = Plane()
    wall = box_points(plane, (12.0, -2.0), 8.0, 0.6, 1.0)  # evenly dense along its 8 m
    points, labels = labelled(plane, terrain_points(plane), wall)
    (found,) = extract_obstacles(points, labels, GRID, plane, ObstacleConfig())
    assert found.size_m[0] == pytest.approx(8.0, abs=0.06)


def test_boxes_found_on_the_real_terrain_estimate():
    """End to end with the core: synthetic cloud → grid → surface → labels → obstacles."""
    from terrainmap.config import SegmentationConfig, TerrainConfig
    from terrainmap.grid import quantize
    from terrainmap.segmentation import label_points
    from terrainmap.synthetic import BOXES, cloud
    from terrainmap.terrain import estimate_terrain

    points = cloud(150_000, seed=3)
    estimate = estimate_terrain(quantize(points, GRID), TerrainConfig())
    labels = label_points(
        points, estimate.elevation, estimate.dz_dx, estimate.dz_dy, GRID, SegmentationConfig()
    )
    found = [
        o
        for o in extract_obstacles(points, labels, GRID, estimate.surface, ObstacleConfig())
        if o.kind == "positive"
    ]
    for bx, by, width, height in BOXES:
        near = [o for o in found if np.hypot(o.center_m[0] - bx, o.center_m[1] - by) < width / 2 + 0.3]
        assert len(near) == 1, (bx, by, [o.center_m for o in found])
        assert near[0].height_m == pytest.approx(height, abs=0.25)


def test_box_ignores_a_sparse_smeared_tail():
    """Stereo smears far obstacles along the viewing ray: a few stray points behind a compact
    object must not stretch its box or pull its centre off the object."""
    from terrainmap.obstacles import Segments, _robust_extent

    rng = np.random.default_rng(0)
    compact = rng.uniform(-0.5, 0.5, 400)  # a 1 m object
    tail = np.linspace(0.5, 6.0, 12)  # sparse smear up to 6 m behind it
    cid = np.zeros(len(compact) + len(tail), int)
    npts = np.array([len(cid)], float)
    centre, half = _robust_extent(np.concatenate([compact, tail]), Segments(cid, 1), npts)
    assert abs(centre[0]) < 0.6 and half[0] < 1.1  # the plain extent would give centre 2.75, half 3.25
    centre, half = _robust_extent(compact, Segments(np.zeros(400, int), 1), np.array([400.0]))
    assert half[0] == pytest.approx(0.5, abs=0.01) and abs(centre[0]) < 0.05  # compact: full extent kept


def test_segments_reduce_each_cluster_like_a_loop():
    """Segments over points sorted by cluster gives each cluster's count, sum, minimum, maximum,
    run and per-point spread as a loop over the clusters would, empty clusters included."""
    from terrainmap.obstacles import Segments

    rng = np.random.default_rng(3)
    cid = np.sort(rng.choice([0, 2, 3, 6], 200))  # clusters 1, 4, 5 and 7 hold no point
    values = rng.normal(size=cid.size)
    per = Segments(cid, 8)
    members = [values[cid == c] for c in range(8)]
    np.testing.assert_array_equal(per.sum(), [m.size for m in members])
    np.testing.assert_allclose(per.sum(values), [m.sum() for m in members], atol=1e-12)
    np.testing.assert_array_equal(per.reduce(np.minimum, values), [m.min() if m.size else np.inf for m in members])
    np.testing.assert_array_equal(per.reduce(np.maximum, values), [m.max() if m.size else -np.inf for m in members])
    for c in range(8):
        np.testing.assert_array_equal(values[per.run(c)], members[c])
    np.testing.assert_array_equal(per.spread(np.arange(8) * 10), cid * 10)


def test_a_square_cluster_gets_an_axis_aligned_box_whatever_the_rounding():
    """A cluster without a major axis (points on a square lattice: equal spreads in x and y, no
    covariance) gets yaw 0, not an angle set by rounding noise, wherever it lies."""
    from terrainmap.obstacles import Segments, _principal_axes

    lattice = np.stack(np.meshgrid(np.arange(9) * 0.1, np.arange(9) * 0.1), -1).reshape(-1, 2)
    for offset in (0.0, 7.3, 13.37):
        x, y = (lattice + offset).T
        yaw, _, _ = _principal_axes(x, y, Segments(np.zeros(x.size, int), 1), np.array([x.size]))
        assert yaw[0] == 0.0


@pytest.mark.parametrize("seed", range(40))
@pytest.mark.parametrize("width", [2.0, 1.8, 1.0])
def test_a_square_footprint_gets_a_box_that_holds_it_at_any_yaw(seed, width):
    """Points spread evenly over a 2 m × ``width`` footprint at a random yaw: with no clear major
    axis the covariance's axis is noise (up to 44° off for a square), and a box along it cut the
    corners off (up to 7 % of the points outside, by 0.28 m). The box now holds every point of
    the cluster (those in cells of at least ``min_cell_points``) within 3 cm, and a square or
    nearly square one lies along the footprint's sides within 4.5° (the search's 3° steps, chosen
    on 200 of the points), its length along the yaw."""
    from terrainmap.grid import cell_index

    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi / 2, np.pi / 2)
    u, v = rng.uniform(-1.0, 1.0, 800), rng.uniform(-width / 2, width / 2, 800)
    c, s = np.cos(yaw), np.sin(yaw)
    points = np.column_stack([15 + u * c - v * s, 2 + u * s + v * c, rng.uniform(0.05, 1.5, 800)])
    config = ObstacleConfig()
    (obstacle,) = extract_obstacles(points, np.full(800, Label.OBSTACLE, np.uint8), GRID, None, config,
                                    elevation=np.zeros(GRID.shape))
    index = cell_index(points, GRID)
    kept = np.bincount(index)[index] >= config.min_cell_points
    assert obstacle.point_count == kept.sum()
    c, s = np.cos(obstacle.yaw_rad), np.sin(obstacle.yaw_rad)
    d = points[kept, :2] - obstacle.center_m[:2]
    along, across = np.abs(d @ [c, s]), np.abs(d @ [-s, c])
    assert (along <= obstacle.size_m[0] / 2 + 0.03).all() and (across <= obstacle.size_m[1] / 2 + 0.03).all()
    assert obstacle.size_m[0] >= obstacle.size_m[1]
    assert -np.pi / 2 < obstacle.yaw_rad <= np.pi / 2
    if width > 1.5:
        assert np.degrees(abs((obstacle.yaw_rad - yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)) <= 4.5


def test_points_stacked_at_one_spot_give_an_axis_aligned_box_of_no_size():
    """A pole seen as one column of points: yaw 0 and sizes 0, not an angle and a negative size
    set by rounding, wherever it stands."""
    for x, y in ((15.3, 0.7), (33.1, -9.9), (7.77, 3.33)):
        points = np.column_stack([np.full(12, x), np.full(12, y), np.linspace(0.1, 1.0, 12)])
        config = ObstacleConfig(min_points=1, min_cells=1, min_cell_points=1)
        (obstacle,) = extract_obstacles(points, np.full(12, Label.OBSTACLE, np.uint8), GRID, None, config,
                                        elevation=np.zeros(GRID.shape))
        assert obstacle.yaw_rad == 0.0 and (obstacle.size_m[:2] == 0).all()


def _cell_counts(points: np.ndarray) -> np.ndarray:
    """All points per grid cell, as ``HeightGrid.count`` holds them."""
    from terrainmap.grid import cell_index

    n = GRID.shape[0] * GRID.shape[1]
    return np.bincount(cell_index(points, GRID), minlength=n + 1)[:n].reshape(GRID.shape)


def test_tall_clusters_must_hold_their_cells():
    """Stereo mismatches standing 1.5 m up from the ground (a few points among the ground's 25 per
    cell) are no obstacle once the cells' point counts are given; a tall box, which holds most of
    its cells' points, stays, and so does a low rock holding as small a share (the test is for
    clusters at least ``tall_height_m`` tall)."""
    plane = Plane()
    rng = np.random.default_rng(0)
    stray = np.column_stack([rng.uniform(14.0, 15.0, 24), rng.uniform(-4.0, -3.0, 24), rng.uniform(1.3, 1.7, 24)])
    box = box_points(plane, (10.0, 2.0), 1.0, 1.0, 1.2)
    rock = box_points(plane, (18.0, 5.0), 1.0, 1.0, 0.5, spacing=0.25)
    points, labels = labelled(plane, terrain_points(plane), stray, box, rock)
    counts = _cell_counts(points)
    for part, (x0, y0) in ((stray, (14.0, -4.0)), (rock, (17.5, 4.5))):  # each covers 2×2 cells
        ix, iy = int((x0 - GRID.x_min_m) / 0.5), int((y0 - GRID.y_min_m) / 0.5)
        share = (part[:, 2] > 0.25).sum() / counts[ix : ix + 2, iy : iy + 2].sum()
        assert share < 0.25  # both well under tall_min_share
    config = ObstacleConfig(min_points=10)
    found = {(round(o.center_m[0]), round(o.center_m[1])): o for o in extract_obstacles(
        points, labels, GRID, plane, config, cell_counts=counts)}
    assert set(found) == {(10, 2), (18, 5)}
    assert found[(18, 5)].height_m == pytest.approx(0.5, abs=0.01)
    assert len(extract_obstacles(points, labels, GRID, plane, config)) == 3  # without the counts
    off = ObstacleConfig(min_points=10, tall_min_share=0)
    assert len(extract_obstacles(points, labels, GRID, plane, off, cell_counts=counts)) == 3


def test_low_clusters_on_steep_ground_are_dropped_tall_ones_stay():
    """With ``steep`` cells (slope past the cost's limit), a low cluster lying mostly in them is
    the ground's relief (a berm's crest standing above a lagging surface) and is dropped; a tall
    box there stays (the surface climbs cars and trucks too), and so does a low one on drivable
    ground, and everything when the cells are not given."""
    plane = Plane()
    crest = box_points(plane, (12.0, 5.0), 2.0, 0.5, 0.55)  # low and long, like a berm's crest
    truck = box_points(plane, (12.0, -5.0), 3.0, 2.0, 2.5)
    rock = box_points(plane, (20.0, 0.0), 1.0, 1.0, 0.55)
    points, labels = labelled(plane, terrain_points(plane), crest, truck, rock)
    steep = np.zeros(GRID.shape, bool)
    for x0, y0, x1, y1 in ((10.5, 3.5, 13.5, 6.5), (10.0, -6.5, 14.0, -3.5)):  # the berm's and the truck's cells
        steep[int((x0 - GRID.x_min_m) / 0.5) : int((x1 - GRID.x_min_m) / 0.5),
              int((y0 - GRID.y_min_m) / 0.5) : int((y1 - GRID.y_min_m) / 0.5)] = True  # fmt: skip

    def centres(**kwargs):
        found = extract_obstacles(points, labels, GRID, plane, ObstacleConfig(), **kwargs)
        return {(round(o.center_m[0]), round(o.center_m[1])) for o in found if o.kind == "positive"}

    assert centres() == {(12, 5), (12, -5), (20, 0)}
    assert centres(steep=steep) == {(12, -5), (20, 0)}
    assert centres(steep=np.zeros(GRID.shape, bool)) == centres()


def test_terrain_layers_of_the_wrong_shape_or_none_or_not_finite_are_named():
    points = np.array([[10.0, 0.0, 1.0]])
    labels = np.array([Label.OBSTACLE], np.uint8)
    with pytest.raises(InputError, match="give the terrain as elevation"):
        extract_obstacles(points, labels, GRID, None, ObstacleConfig())
    with pytest.raises(InputError, match=r"obstacles: elevation must have shape"):
        extract_obstacles(points, labels, GRID, None, ObstacleConfig(), elevation=np.zeros((3, 3)))
    with pytest.raises(InputError, match=r"obstacles: cell_counts must have shape"):
        extract_obstacles(points, labels, GRID, None, ObstacleConfig(), elevation=np.zeros(GRID.shape),
                          cell_counts=np.zeros((3, 3)))
    holed = np.zeros(GRID.shape)
    holed[10, 10] = np.nan  # a written layer read back: it would void every cluster near the hole
    with pytest.raises(InputError, match=r"obstacles: elevation must be finite in every cell"):
        extract_obstacles(points, labels, GRID, None, ObstacleConfig(), elevation=holed)


def test_past_max_points_the_largest_clusters_are_thinned_alike():
    """A dense frame (more points above the terrain than ``max_points``): the largest clusters'
    shapes, heights and counts come from about one in k of their points and match those from all of
    them, while a small obstacle keeps every point (the same box to the bit); under the cap
    nothing changes. Smear cut off (the split) and the tall-share test work on the thinned points."""
    import warnings
    from dataclasses import replace

    plane = Plane()
    person = box_points(plane, (14.0, 3.0), 0.5, 0.5, 1.8, spacing=0.01)
    car = box_points(plane, (22.0, 3.0), 4.0, 1.8, 1.5, spacing=0.03)
    trail_x = np.repeat(np.arange(14.3, 20.0, 0.5), 60) + np.random.default_rng(0).uniform(-0.2, 0.2, 720)
    trail = np.column_stack([trail_x, np.full_like(trail_x, 3.0), np.full_like(trail_x, 1.2)])
    crate = box_points(plane, (10.0, -4.0), 1.2, 0.8, 1.0, spacing=0.02)
    pole = box_points(plane, (16.0, -6.0), 0.2, 0.2, 1.5, spacing=0.1)
    points, labels = labelled(plane, terrain_points(plane), person, car, trail, crate, pole)
    counts = _cell_counts(points)
    above = int((labels == Label.OBSTACLE).sum())
    assert above > 10_000

    def boxes(max_points):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # clusters left with no point: no division warnings
            found = extract_obstacles(points, labels, GRID, plane, replace(ObstacleConfig(), max_points=max_points),
                                      cell_counts=counts)
        return {(round(o.center_m[0]), round(o.center_m[1])): o for o in found}

    full = boxes(0)
    assert set(full) == {(14, 3), (22, 3), (10, -4), (16, -6)}  # the trail cut off
    same = boxes(above)
    for key, o in full.items():
        assert (o.center_m.tolist(), o.size_m.tolist(), o.point_count) == (
            same[key].center_m.tolist(), same[key].size_m.tolist(), same[key].point_count)
    for cap in (5_000, 1_000):
        thinned = boxes(cap)
        assert set(thinned) == set(full)
        for key, o in thinned.items():
            np.testing.assert_allclose(o.center_m, full[key].center_m, atol=0.1)
            np.testing.assert_allclose(o.size_m, full[key].size_m, atol=0.15)
            assert o.height_m == pytest.approx(full[key].height_m, abs=0.05)
            assert o.point_count == pytest.approx(full[key].point_count, rel=0.1)
        small = thinned[(16, -6)]
        assert (small.center_m.tolist(), small.point_count) == (full[(16, -6)].center_m.tolist(), full[(16, -6)].point_count)


@pytest.mark.parametrize(("sizes", "budget", "strides"), [
    ([10, 20, 30], 0, [1, 1, 1]),  # no limit
    ([10, 20, 30], 60, [1, 1, 1]),  # they fit
    ([10, 20, 300], 130, [1, 1, 3]),  # the largest thinned to the 100 left
    ([10, 200, 300], 110, [1, 4, 6]),  # the two largest share 100: 50 each
    ([500], 5, [100]),
])
def test_thinning_keeps_small_clusters_whole_and_fits_the_budget(sizes, budget, strides):
    from terrainmap.obstacles import _thinning

    assert _thinning(np.array(sizes), budget).tolist() == strides
