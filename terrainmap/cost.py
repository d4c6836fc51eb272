r"""Traversability cost (paper step 5: slope and occupancy fused into one cost per cell).

For every grid cell (arrays ``(m0, m1)``, indexed ``[ix, iy]``)::

    cost = max( s(θ / θ_max),  s(h / h_max),  occ )                 where the cell has data
    cost = 1                                                         where occupied, data or not
    cost = NaN                                                       elsewhere (unknown)

    s(t) = 3·t'² − 2·t'³  with  t' = clip(t, 0, 1)                   (smoothstep ramp)

* ``θ`` is the terrain slope (the ``slope`` layer, radians) and ``θ_max`` is
  ``cost.max_slope_deg``: flat ground costs 0, ``θ ≥ θ_max`` costs 1, with a ramp that is
  flat at both ends (so gentle slopes cost little and the cost saturates smoothly);
* ``h`` is the step height (metres, see :func:`step_height`), the largest height difference of
  the terrain relief between the cell and its observed 8-neighbours, and ``h_max`` is
  ``cost.max_step_m``; the term is 0 where the step is NaN (cells filled from neighbours
  hold no sample of their own) and everywhere when no ``step`` array is given;
* ``occ`` is 1 where a **confirmed** obstacle's footprint, grown by ``cost.clearance_m``,
  reaches the cell (the pipeline passes the tracker's parts of confirmed tracks and the
  confirmed tracks missed in the last ``cost.occupied_misses`` frames as confirmed obstacles
  too: :attr:`~terrainmap.tracking.ObstacleTracker.parts`,
  :meth:`~terrainmap.tracking.ObstacleTracker.coasting`): the distance between the oriented footprint rectangle and the cell's square
  is at most ``clearance_m`` (so a footprint touching a cell, at a corner too, occupies it even
  with no clearance), and 0 elsewhere;
* "has data" is the ``valid`` mask where slope and elevation are finite.

Each term lies in [0, 1], so the cost does too; it never decreases when the slope, the step
or the occupied area grows.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .config import CostConfig, GridConfig, check_section
from .errors import InputError
from .grid import check_shapes
from .types import Obstacle


def smoothstep(t: np.ndarray) -> np.ndarray:
    """``s(t) = 3t² − 2t³`` of ``t`` clipped to [0, 1]; NaN stays NaN."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def traversability_cost(
    elevation: np.ndarray,
    slope: np.ndarray,
    valid: np.ndarray,
    grid_config: GridConfig,
    obstacles: list[Obstacle],
    config: CostConfig,
    *,
    step: np.ndarray | None = None,
) -> np.ndarray:
    """Traversability cost of every cell, ``(m0, m1)`` float32 in [0, 1], NaN where unknown.

    Parameters
    ----------
    elevation : (m0, m1) float array
        Terrain height at the cell centres, metres (only its shape and finiteness are used).
    slope : (m0, m1) float array
        Terrain slope, radians.
    valid : (m0, m1) bool array
        Cells with terrain data (observed or filled).
    grid_config : GridConfig
    obstacles : list of Obstacle
        Tracked obstacles, vehicle frame; only those with ``confirmed`` true occupy cells.
    config : CostConfig
    step : (m0, m1) float array, optional
        Step height per cell, metres (:func:`step_height`); NaN counts as no step.

    Raises
    ------
    InputError
        A layer does not have the grid's shape, or a confirmed obstacle's box is not finite.
    ConfigError
        ``config`` or ``grid_config`` does not validate.
    """
    check_section(config, CostConfig)
    check_section(grid_config, GridConfig)
    try:
        obstacles = list(obstacles)
    except TypeError:
        raise InputError(f"traversability_cost: obstacles must be Obstacles (a list), got {type(obstacles).__name__}") from None
    shape = grid_config.shape
    layers = {"elevation": elevation, "slope": slope, "valid": valid}
    if step is not None:
        layers["step"] = step
    for name, layer in layers.items():
        if np.shape(layer) != shape:
            raise InputError(f"cost: layer {name!r} has shape {np.shape(layer)}, expected the grid's {shape}")
    known = np.asarray(valid, bool) & np.isfinite(slope) & np.isfinite(elevation)
    cost = smoothstep(np.abs(slope) / np.deg2rad(config.max_slope_deg))
    if step is not None:
        step_m = np.nan_to_num(np.asarray(step, float), nan=0.0)
        cost = np.maximum(cost, smoothstep(step_m / config.max_step_m))
    occupied = occupancy(obstacles, grid_config, config.clearance_m)
    cost = np.where(occupied, 1.0, np.where(known, cost, np.nan))
    return cost.astype(np.float32)


def occupancy(obstacles: list[Obstacle], grid_config: GridConfig, clearance_m: float) -> np.ndarray:
    """Cells reached by a confirmed obstacle's footprint grown by ``clearance_m``, (m0, m1) bool.

    A cell is reached when the distance between the obstacle's oriented footprint rectangle
    (``center_m[:2]``, ``size_m[:2]``, ``yaw_rad``) and the cell's square is at most
    ``clearance_m``. Only the cells in each obstacle's bounding window are tested (all obstacles
    at once), so the cost grows with the obstacles' area, not their number times the grid size.
    """
    m0, m1 = grid_config.shape
    c = grid_config.cell_size_m
    occupied = np.zeros(m0 * m1, bool)
    boxes = np.array([[*o.center_m[:2], *o.size_m[:2], o.yaw_rad] for o in obstacles if o.confirmed], float)
    if not len(boxes):
        return occupied.reshape(m0, m1)
    if not np.isfinite(boxes).all():
        raise InputError("cost: a confirmed obstacle's centre, size or yaw is not finite")
    cx, cy, length, width, yaw = boxes.T
    h = c / 2
    radius = np.hypot(length, width) / 2 + clearance_m + h * np.sqrt(2)
    # Window of cell indices whose centres lie within ``radius`` of the centre along each axis.
    fx, fy = (cx - grid_config.x_min_m) / c - 0.5, (cy - grid_config.y_min_m) / c - 0.5
    ix0 = np.clip(np.ceil(fx - radius / c), 0, m0).astype(np.intp)
    ix1 = np.clip(np.floor(fx + radius / c) + 1, 0, m0).astype(np.intp)
    iy0 = np.clip(np.ceil(fy - radius / c), 0, m1).astype(np.intp)
    iy1 = np.clip(np.floor(fy + radius / c) + 1, 0, m1).astype(np.intp)
    wx, wy = np.maximum(ix1 - ix0, 0), np.maximum(iy1 - iy0, 0)
    count = wx * wy
    k = np.repeat(np.arange(len(boxes)), count)  # obstacle of each (obstacle, cell) pair
    j = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    ix, iy = ix0[k] + j // wy[k], iy0[k] + j % wy[k]
    dx = grid_config.x_min_m + (ix + 0.5) * c - cx[k]
    dy = grid_config.y_min_m + (iy + 0.5) * c - cy[k]
    cos, sin = np.cos(yaw[k]), np.sin(yaw[k])
    a, b = length[k] / 2, width[k] / 2
    centre = _to_rectangle(dx, dy, cos, sin, a, b)
    # The square holds the disc of radius h about its centre and lies in the one of radius h·√2:
    # only the pairs in between need the exact test.
    reached = centre <= clearance_m + h
    ring = np.flatnonzero(~reached & (centre <= clearance_m + h * np.sqrt(2)))
    reached[ring] = _square_reaches(dx[ring], dy[ring], cos[ring], sin[ring], a[ring], b[ring], h, clearance_m)
    occupied[(ix * m1 + iy)[reached]] = True
    return occupied.reshape(m0, m1)


def _square_reaches(dx, dy, cos, sin, a, b, h, clearance_m) -> np.ndarray:
    """Whether the axis-aligned square of half-size ``h`` centred at (dx, dy) lies within
    ``clearance_m`` of the rectangle of half-sizes (a, b) at the origin, turned by yaw (cos, sin).
    Two convex polygons overlap when no axis of either separates them; otherwise their distance is
    that of a vertex of one to the other."""
    ac, as_ = np.abs(cos), np.abs(sin)
    separated = (
        (np.abs(dx) > h + a * ac + b * as_)
        | (np.abs(dy) > h + a * as_ + b * ac)
        | (np.abs(dx * cos + dy * sin) > a + h * (ac + as_))
        | (np.abs(dy * cos - dx * sin) > b + h * (ac + as_))
    )
    nearest = np.full(dx.shape, np.inf)
    for sx, sy in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
        corner = _to_rectangle(dx + sx * h, dy + sy * h, cos, sin, a, b)  # the square's corner, to the rectangle
        qx, qy = sx * a * cos - sy * b * sin, sx * a * sin + sy * b * cos  # the rectangle's corner, to the square
        nearest = np.minimum(nearest, np.minimum(corner, _to_rectangle(qx - dx, qy - dy, 1.0, 0.0, h, h)))
    return ~separated | (nearest <= clearance_m)


def _to_rectangle(px, py, cos, sin, a, b) -> np.ndarray:
    """Distance of the points (px, py) to the rectangle of half-sizes (a, b) at the origin, turned
    by yaw (cos, sin); 0 inside."""
    u = np.maximum(np.abs(px * cos + py * sin) - a, 0.0)
    v = np.maximum(np.abs(py * cos - px * sin) - b, 0.0)
    return np.hypot(u, v)


def step_height(samples: np.ndarray, elevation: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Step height per cell, metres, (m0, m1) float64, NaN where not observed.

    The relief ``r = samples − elevation`` is what the smooth terrain surface does not explain
    (kerbs, berms, ruts, rocks). The step of an observed cell is
    ``max |r[n] − r[c]|`` over its observed 8-neighbours ``n`` (0 with none).

    Parameters
    ----------
    samples : (m0, m1) float array
        Grid sample heights, metres (``HeightGrid.z``, eq. 1, before equalization).
    elevation : (m0, m1) float array
        Terrain surface at the cell centres, metres.
    observed : (m0, m1) bool array
        Cells whose sample describes the terrain: holding points of their own
        (``HeightGrid.observed``), less those labelled OBSTACLE in the pipeline.
    """
    check_shapes("step_height", np.shape(samples), elevation=elevation, observed=observed)
    observed = np.asarray(observed, bool) & np.isfinite(samples) & np.isfinite(elevation)
    relief = np.where(observed, np.asarray(samples, float) - elevation, 0.0)
    # size=3: the 3×3 square as two separable 1-D passes (a footprint array takes the general path)
    hi = ndimage.maximum_filter(np.where(observed, relief, -np.inf), size=3, mode="constant", cval=-np.inf)
    lo = ndimage.minimum_filter(np.where(observed, relief, np.inf), size=3, mode="constant", cval=np.inf)
    return np.where(observed, np.maximum(hi - relief, relief - lo), np.nan)
