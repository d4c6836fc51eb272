"""Terrain inlier/outlier segmentation of points and cells against the surface.

A point at height z over (x, y) is TERRAIN when ``−below ≤ z − S(x, y) ≤ above``, OBSTACLE above
that and BELOW under it, with both thresholds growing with range r = ‖(x, y)‖ by
``threshold_per_m · r`` (stereo noise grows with distance). Points outside the grid area are
UNKNOWN.

Where the stereo camera is known (:class:`StereoCamera`), each cell's thresholds are also at
least the height change a disparity error of ``disparity_tolerance_px`` (above) or
``below_tolerance_px`` (below; wider, as SGBM puts ground points low) makes there. A point
at camera depth Z along the ray ``ρ = p − c`` (c the camera centre) moves by
``Δp = ρ · Z · Δd / (f·B)`` for a disparity error Δd, which changes its height above the
tangent plane ``S ≈ c₀ + gx·x + gy·y`` by ``Δh = (ρz − gx·ρx − gy·ρy) · Z · Δd / (f·B)``. On flat
ground 20 m ahead of a camera 1.8 m up with f·B = 150 px·m that is 0.24 m per pixel; on a 17°
slope facing the camera, 1.0 m per pixel: a fixed threshold there calls stereo noise an obstacle.
The cell centre and the surface there stand in for the points of the cell. Where the camera's
image is known, both tolerances grow towards its left and right sides, where SGBM errs more:
linearly over ``side_band`` of its width on each side, to ``1 + side_gain`` times at the side (the
cell's column is that of its centre at the surface's height).

For speed, S under a point comes from the exact spline value and analytic gradient at the
centre of the point's cell (first-order Taylor: a few table lookups per point, no spline
evaluation): the error is at most ``½ · max|∂²S| · d²`` with d ≤ cell/√2 the distance to the
centre. On the synthetic benchmark cloud the median error is 0.3 mm and 99 % of points are within
4 mm of exact evaluation, all outside the four corner cells within 5 cm (in the corners, where
the clamped spline bends most, up to ~10 cm); a test checks this.
"""

from __future__ import annotations

import numpy as np

from .config import GridConfig, SegmentationConfig, check_section
from .grid import HeightGrid, as_points, cell_centers, cell_index, check_shapes, neighbour_sum
from .types import Label, StereoCamera


def thresholds(
    grid: GridConfig,
    config: SegmentationConfig,
    camera: StereoCamera | None = None,
    elevation: np.ndarray | None = None,
    dz_dx: np.ndarray | None = None,
    dz_dy: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell (above, below) thresholds, (m0, m1) metres each (see the module docstring). The
    stereo term needs ``camera`` and the surface (``elevation`` and its gradient at the cell centres);
    it grows towards the image's sides where ``camera`` knows its columns."""
    check_section(grid, GridConfig)
    check_section(config, SegmentationConfig)  # (a NaN threshold would label every point TERRAIN)
    xs, ys = cell_centers(grid)
    x, y = xs[:, None], ys[None, :]
    grow = config.threshold_per_m * np.hypot(x, y)
    above, below = config.obstacle_height_m + grow, config.below_depth_m + grow
    if camera is not None and (config.disparity_tolerance_px > 0 or config.below_tolerance_px > 0):
        per_px = camera.height_per_px(x, y, elevation, dz_dx, dz_dy)
        if config.side_gain > 0 and camera.has_image:  # SGBM errs more towards the image's sides
            u = camera.column(x, y, elevation)
            border = np.minimum(u + 0.5, camera.width_px - 0.5 - u)  # px to the nearer side (< 0 outside)
            ramp = np.clip(1 - border / (config.side_band * camera.width_px), 0, 1)  # 1 at a side
            per_px = per_px * (1 + config.side_gain * ramp)
        above = np.maximum(above, config.disparity_tolerance_px * per_px)
        below = np.maximum(below, config.below_tolerance_px * per_px)
    return np.broadcast_to(above, grid.shape), np.broadcast_to(below, grid.shape)


def widen_at_edges(
    limits: tuple[np.ndarray, np.ndarray], observed: np.ndarray, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``limits`` (above, below), (m0, m1) metres each, raised by ``margin_m`` at the cells on the
    edge of the ``observed`` area: observed cells with fewer than 8 observed neighbours (cells
    outside the grid count as unobserved)."""
    if margin_m <= 0:
        return limits
    edge = observed & (neighbour_sum(observed.astype(float)) < 7.5)
    return tuple(np.where(edge, limit + margin_m, limit) for limit in limits)


def cell_planes(elevation: np.ndarray, dz_dx: np.ndarray, dz_dy: np.ndarray, grid: GridConfig) -> np.ndarray:
    """Per-cell tangent planes ``S ≈ c + gx·x + gy·y``: a (3, m0·m1 + 1) float32 table of
    (c, gx, gy), flat cell index as in :func:`terrainmap.grid.cell_index`; the extra last column
    (points outside the area) is all zero."""
    xs, ys = cell_centers(grid)
    c = elevation - dz_dx * xs[:, None] - dz_dy * ys[None, :]
    table = np.zeros((3, elevation.size + 1), np.float32)
    table[:, :-1] = np.stack([c, dz_dx, dz_dy]).reshape(3, -1)
    return table


def surface_under_points(points: np.ndarray, planes: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Surface height under each point from :func:`cell_planes`: (N,) float32."""
    c, gx, gy = (planes[k].take(index) for k in range(3))
    return c + gx * points[:, 0] + gy * points[:, 1]


def label_points(
    points_vehicle: np.ndarray,
    elevation: np.ndarray,
    dz_dx: np.ndarray,
    dz_dy: np.ndarray,
    grid: GridConfig,
    config: SegmentationConfig,
    *,
    index: np.ndarray | None = None,
    limits: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Label each point TERRAIN / OBSTACLE / BELOW / UNKNOWN: (N,) uint8 (:class:`Label`).

    Parameters
    ----------
    points_vehicle : (N, 3) float array, metres, vehicle frame.
    elevation, dz_dx, dz_dy : (m0, m1) arrays
        Surface height (m) and analytic gradient at the cell centres
        (:class:`~terrainmap.terrain.TerrainEstimate` has them).
    index : (N,) int array, optional
        :func:`~terrainmap.grid.cell_index` of the points, reused from the grid stage (taken as
        given, not checked).
    limits : (above, below) of (m0, m1) arrays, optional
        Per-cell thresholds from :func:`thresholds` (the fixed ones of ``config`` if omitted).
    """
    with np.errstate(over="ignore"):  # coordinates past float32 become inf: outside the area, UNKNOWN
        pts = np.asarray(as_points(points_vehicle), dtype=np.float32)
    check_section(grid, GridConfig)
    check_shapes("label_points", grid.shape, elevation=elevation, dz_dx=dz_dx, dz_dy=dz_dy)
    check_shapes("label_points", (len(pts),), index=index)
    if index is None:
        index = cell_index(pts, grid)
    above, below = limits or thresholds(grid, config)
    c, gx, gy = cell_planes(elevation, dz_dx, dz_dy, grid)
    unknown = ~np.isfinite(c + gx + gy)
    if unknown.any():  # no surface there: its points go to the outside row and come out UNKNOWN
        index = np.where(unknown[index], elevation.size, index)
    # One row per cell (gx, gy, c + above, c − below), gathered once per point: the thresholds are
    # folded in, so z − gx·x − gy·y is compared with the last two columns.
    table = np.stack([gx, gy, np.append(above.ravel(), 0) + c, np.append(-below.ravel(), 0) + c], axis=1)
    rows = table.astype(np.float32).take(index, axis=0)
    with np.errstate(invalid="ignore"):  # non-finite points (cell index: outside) end up UNKNOWN
        s = pts[:, 2] - rows[:, 0] * pts[:, 0] - rows[:, 1] * pts[:, 1]
        labels = (s > rows[:, 2]).view(np.uint8) + np.uint8(Label.TERRAIN)  # TERRAIN 1, OBSTACLE 2
        labels += (s < rows[:, 3]).view(np.uint8) * np.uint8(Label.BELOW - Label.TERRAIN)  # BELOW 3
    labels *= (index < elevation.size).view(np.uint8)  # UNKNOWN 0 outside the area (and non-finite points)
    return labels


def label_cells(
    grid: HeightGrid,
    elevation: np.ndarray,
    config: SegmentationConfig,
    *,
    limits: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Per-cell labels (m0, m1) uint8: UNKNOWN where no point fell, OBSTACLE where the cell's top
    (``grid.z_top``, mean + σ) rises above the surface by the obstacle threshold,
    BELOW where its eq.-1 sample lies under it by the below threshold, TERRAIN otherwise.
    ``limits``: per-cell (above, below) thresholds as in :func:`label_points`."""
    check_shapes("label_cells", grid.shape, elevation=elevation)
    above, below = limits or thresholds(grid.config, config)
    labels = np.full(grid.shape, Label.TERRAIN, dtype=np.uint8)
    labels[grid.z_top - elevation > above] = Label.OBSTACLE
    labels[grid.z - elevation < -below] = Label.BELOW
    labels[~grid.observed] = Label.UNKNOWN
    return labels


def cells_holding(index: np.ndarray, shape: tuple[int, int], min_points: int) -> np.ndarray:
    """(m0, m1) bool: the cells that hold at least ``min_points`` of the points whose flat cell
    ``index`` (:func:`~terrainmap.grid.cell_index`; ``m0·m1`` outside the area) is given."""
    size = shape[0] * shape[1]
    return (np.bincount(index, minlength=size + 1)[:size] >= min_points).reshape(shape)
