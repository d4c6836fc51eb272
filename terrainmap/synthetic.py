"""Synthetic terrain for tests and the benchmark (the stereo simulator lives in :mod:`terrainmap.sim`).

``rolling_terrain`` is a smooth off-road height field (metres, vehicle frame);
``cloud`` samples it like a 640×480 stereo frame would (density falling with range, noise,
a few box obstacles); ``grid_samples`` draws one noisy sample per grid cell with gross outliers
and empty cells, the setting of the core accuracy target.
"""

from __future__ import annotations

import numpy as np

from .config import GridConfig
from .errors import InputError, is_whole
from .grid import HeightGrid, _fill, cell_centers


def rolling_terrain(x, y) -> np.ndarray:
    """Rolling hills with a gentle climb: heights in metres, slopes up to ~12°."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return 0.8 * np.sin(x / 6.0) + 0.5 * np.cos(y / 5.0) + 0.3 * np.sin((x + y) / 4.0) + 0.02 * x


BOXES = ((12.0, 3.0, 1.2, 1.8), (20.0, -4.0, 2.5, 1.5), (27.0, 2.0, 0.6, 1.0))
"""(x, y, width, height) of the benchmark's obstacles, metres."""


def cloud(n_points: int = 300_000, *, grid: GridConfig | None = None, noise_m: float = 0.03, seed: int = 0):
    """A stereo-like cloud over ``rolling_terrain`` with box obstacles: (N, 3) float32, vehicle frame.

    Range is drawn so that density falls roughly with 1/r² like a camera's, within the grid area.
    The points come in the order a camera 1.8 m up delivers them, 480 image rows from far to near,
    each read left to right: runs of consecutive points share a grid cell as in a real frame,
    which matters to the speed of the per-cell sums (:data:`terrainmap.grid._LANES`).
    """
    if not is_whole(n_points) or n_points < 0:
        raise InputError(f"cloud: n_points must be a whole number >= 0, got {n_points!r}")
    grid = grid or GridConfig()
    rng = np.random.default_rng(seed)
    x0, x1 = grid.x_min_m, grid.x_min_m + grid.length_m
    x = x0 + (x1 - x0) * rng.random(n_points) ** 2
    y = grid.y_min_m + grid.width_m * rng.random(n_points)
    z = rolling_terrain(x, y) + rng.normal(0, noise_m, n_points)
    for bx, by, w, h in BOXES:
        inside = (np.abs(x - bx) < w / 2) & (np.abs(y - by) < w / 2)
        z[inside] += rng.uniform(0, h, inside.sum())
    far, near = np.arctan2(1.8, x1), np.arctan2(1.8, x0)  # depression angles of the area's ends
    row = np.floor((np.arctan2(1.8, x) - far) / (near - far) * 479.999)
    order = np.lexsort((-y, row))
    return np.column_stack([x, y, z])[order].astype(np.float32)


def grid_samples(
    grid: GridConfig | None = None,
    *,
    noise_m: float = 0.03,
    outlier_fraction: float = 0.1,
    outlier_max_m: float = 2.0,
    empty_fraction: float = 0.3,
    seed: int = 0,
) -> tuple[HeightGrid, np.ndarray]:
    """One sample per cell of ``rolling_terrain`` with noise, gross outliers 0.2 m (or
    ``outlier_max_m`` where lower) to ``outlier_max_m`` above the ground and empty cells (filled
    from neighbours as in Sec. IV). Returns the grid and the true heights."""
    grid = grid or GridConfig()
    rng = np.random.default_rng(seed)
    xs, ys = cell_centers(grid)
    truth = rolling_terrain(xs[:, None], ys[None, :])
    z = truth + rng.normal(0, noise_m, truth.shape)
    outliers = rng.random(truth.shape) < outlier_fraction
    z[outliers] += rng.uniform(min(0.2, outlier_max_m), outlier_max_m, outliers.sum())
    count = (rng.random(truth.shape) >= empty_fraction).astype(np.int64)
    z = np.where(count > 0, z, 0.0)
    return _fill(z, z.copy(), count, grid), truth
