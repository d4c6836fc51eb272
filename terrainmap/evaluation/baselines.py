"""Ground-estimation methods a user would otherwise pick, run on the same points as terrainmap.

Every method maps a point cloud (N×3, vehicle frame, metres) to a :class:`MethodOutput`:
terrain elevation on the grid (NaN where the method says nothing), slope where it has a surface,
and a per-point terrain/obstacle label. Methods whose package is missing are reported by
:func:`available_methods` and skipped, never faked.

Given the stereo rig of the points (``camera``), the methods that label points against a surface
(the single fit, the plane, the lowest-point grid) use terrainmap's labelling thresholds with
their stereo floors, and the single fit terrainmap's grid (eq. 1 with the rig's noise taken out
of σ): what then differs from terrainmap is only how the surface is estimated.

- ``terrainmap``: the full estimator (Algorithm V-B.1) with its point labels; its elevation as
  ``terrainmap process`` writes it, NaN in the cells with no data (:func:`as_written`).
- ``bspline_single``: one unweighted, non-rational fit of the same net (the paper's Fig. 5a), on
  the same cells.
- ``ransac_plane``: a RANSAC plane through the points (the flat-ground assumption).
- ``lowest_point``: the lowest point of each cell, slope by finite differences (:func:`gradient`).
- ``patchworkpp``: Patchwork++ ground segmentation (``pip install pypatchworkpp``); elevation is
  the mean height of its ground points per cell, slope by finite differences.
- ``csf``: Cloth Simulation Filter (``pip install cloth-simulation-filter``), likewise.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache

import numpy as np

from ..config import Config
from ..grid import cell_centers, cell_index, quantize
from ..pipeline import map_points
from ..segmentation import label_points, thresholds
from ..slope import slope_angle
from ..terrain import fitter_for
from ..types import Extrinsics, Label, StereoCamera


@dataclass
class MethodOutput:
    """``elevation`` (m0, m1) metres, NaN where unknown; ``slope`` (m0, m1) radians or None;
    ``point_labels`` (N,) uint8 :class:`Label` or None."""

    elevation: np.ndarray
    slope: np.ndarray | None
    point_labels: np.ndarray | None


Method = Callable[..., MethodOutput]
"""``method(points, config, extrinsics=None, camera=None) -> MethodOutput``."""


def _labels(points, elevation, gx, gy, config: Config, camera: StereoCamera | None, index=None) -> np.ndarray:
    """terrainmap's point labels against a surface (its thresholds, with the rig's floors)."""
    limits = thresholds(config.grid, config.segmentation, camera, elevation, gx, gy)
    return label_points(points, elevation, gx, gy, config.grid, config.segmentation, index=index, limits=limits)


def _from_surface(
    points, elevation, gx, gy, config: Config, camera: StereoCamera | None, valid: np.ndarray | None = None
) -> MethodOutput:
    """A surface's output: its elevation (:func:`as_written` where ``valid`` is given), slope and
    the points labelled against it."""
    written = elevation if valid is None else as_written(elevation, valid)
    return MethodOutput(written, slope_angle(gx, gy), _labels(points, elevation, gx, gy, config, camera))


def as_written(elevation: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """A spline's elevation (m0, m1) as terrainmap writes it: NaN in the cells that are not
    ``valid`` (no point in or beside them), where the surface only extrapolates."""
    return np.where(valid, elevation, np.nan)


def terrainmap_output(result) -> MethodOutput:
    """terrainmap's :class:`MethodOutput` from its FrameResult: elevation :func:`as_written`."""
    layers = result.layers
    return MethodOutput(as_written(layers["elevation"], layers["valid"]), layers["slope"], result.point_labels)


def terrainmap_method(points, config: Config, extrinsics=None, camera=None) -> MethodOutput:
    return terrainmap_output(map_points(points, config, camera=camera))


def bspline_single(points, config: Config, extrinsics=None, camera=None) -> MethodOutput:
    grid = quantize(points, config.grid, camera=camera)
    t = config.terrain
    fit = fitter_for(config.grid, t.control_points_x, t.control_points_y, t.degree)
    R = np.ones(fit.shape)
    Q = fit.fit(grid.z, np.where(grid.observed, 1.0, np.where(grid.valid, t.filled_weight, 0.0)), R, t.smoothness)
    return _from_surface(points, *fit.evaluate_with_gradient(Q, R), config, camera, valid=grid.valid)  # terrainmap's cells


def ransac_plane(points, config: Config, extrinsics=None, camera=None, *, iterations: int = 200,
                 threshold_m: float = 0.1, seed: int = 0) -> MethodOutput:
    idx = cell_index(points, config.grid)
    pts = np.asarray(points, float)[idx < config.grid.shape[0] * config.grid.shape[1]]
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), min(len(pts), 20_000), replace=False)]
    best, best_count = None, -1
    for _ in range(iterations):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if abs(n[2]) < 1e-9:
            continue
        count = np.count_nonzero(np.abs((sample - a) @ n) / np.linalg.norm(n) < threshold_m)
        if count > best_count:
            best, best_count = (a, n), count
    a, n = best
    inliers = sample[np.abs((sample - a) @ n) / np.linalg.norm(n) < threshold_m]
    A = np.column_stack([inliers[:, 0], inliers[:, 1], np.ones(len(inliers))])
    gx, gy, c = np.linalg.lstsq(A, inliers[:, 2], rcond=None)[0]
    xs, ys = cell_centers(config.grid)
    elevation = c + gx * xs[:, None] + gy * ys[None, :]
    full = np.ones_like(elevation)
    return _from_surface(points, elevation, gx * full, gy * full, config, camera)


def lowest_point(points, config: Config, extrinsics=None, camera=None) -> MethodOutput:
    m0, m1 = config.grid.shape
    idx = cell_index(points, config.grid)
    zmin = np.full(m0 * m1 + 1, np.inf)
    np.minimum.at(zmin, idx, np.asarray(points[:, 2], float))
    elevation = np.where(np.isfinite(zmin[:-1]), zmin[:-1], np.nan).reshape(m0, m1)
    gx, gy = gradient(elevation, config.grid.cell_size_m)
    labels = _labels(points, *(np.nan_to_num(a) for a in (elevation, gx, gy)), config, camera, index=idx)
    labels[np.isnan(np.append(elevation.ravel(), np.nan)[idx])] = Label.UNKNOWN
    return MethodOutput(elevation, slope_angle(gx, gy), labels)


def gradient(elevation: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """d elevation / dx and / dy ((m0, m1) each, m/m) of a grid with empty (NaN) cells: central
    differences where both neighbours along the axis have a value, one-sided where one has, NaN
    where neither has (``np.gradient`` gives NaN beside every empty cell, which would leave the
    cells at the edges of the data without slope while they count for the elevation)."""
    result = []
    for axis in (0, 1):
        e = np.moveaxis(np.asarray(elevation, float), axis, 0)
        ahead = np.full_like(e, np.nan)
        ahead[:-1] = (e[1:] - e[:-1]) / step_m
        behind = np.full_like(e, np.nan)
        behind[1:] = ahead[:-1]
        both = (ahead + behind) / 2
        g = np.where(np.isnan(both), np.where(np.isnan(ahead), behind, ahead), both)
        result.append(np.moveaxis(g, 0, axis))
    return result[0], result[1]


def _ground_to_output(points, ground: np.ndarray, config: Config) -> MethodOutput:
    """Per-point ground mask → labels and a mean-height elevation per cell."""
    m0, m1 = config.grid.shape
    idx = cell_index(points, config.grid)
    g = ground & (idx < m0 * m1)
    count = np.bincount(idx[g], minlength=m0 * m1 + 1)[:-1]
    total = np.bincount(idx[g], weights=np.asarray(points[g, 2], float), minlength=m0 * m1 + 1)[:-1]
    elevation = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(m0, m1)
    gx, gy = gradient(elevation, config.grid.cell_size_m)
    labels = np.where(ground, Label.TERRAIN, Label.OBSTACLE).astype(np.uint8)
    labels[idx >= m0 * m1] = Label.UNKNOWN
    return MethodOutput(elevation, slope_angle(gx, gy), labels)


@contextmanager
def _quiet_stdout():
    """Silence C++ code that prints to the process's stdout (file descriptor 1)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def patchworkpp(points, config: Config, extrinsics: Extrinsics | None = None, camera=None) -> MethodOutput:
    import pypatchworkpp

    height = float(np.asarray(extrinsics.translation)[2]) if extrinsics is not None else 1.5
    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.enable_RNR = False  # needs LiDAR intensity
    params.sensor_height = height
    params.max_range = float(np.hypot(config.grid.x_min_m + config.grid.length_m, config.grid.width_m / 2)) + 1
    params.min_range = 0.5
    sensor = np.asarray(points, np.float64) - [0.0, 0.0, height]  # Patchwork++ works in the sensor frame
    with _quiet_stdout():
        estimator = pypatchworkpp.patchworkpp(params)
        estimator.estimateGround(sensor)
    ground = np.zeros(len(points), bool)
    ground[np.asarray(estimator.getGroundIndices(), int)] = True
    return _ground_to_output(points, ground, config)


def csf(points, config: Config, extrinsics=None, camera=None) -> MethodOutput:
    import CSF

    cloth = CSF.CSF()
    cloth.params.bSloopSmooth = True
    cloth.params.cloth_resolution = config.grid.cell_size_m
    cloth.params.class_threshold = config.segmentation.obstacle_height_m
    cloth.setPointCloud(np.asarray(points, np.float64))
    ground_idx, other_idx = CSF.VecInt(), CSF.VecInt()
    with _quiet_stdout():
        cloth.do_filtering(ground_idx, other_idx, exportCloth=False)
    ground = np.zeros(len(points), bool)
    ground[np.asarray(ground_idx, int)] = True
    return _ground_to_output(points, ground, config)


METHODS: dict[str, Method] = {
    "terrainmap": terrainmap_method,
    "bspline_single": bspline_single,
    "ransac_plane": ransac_plane,
    "lowest_point": lowest_point,
    "patchworkpp": patchworkpp,
    "csf": csf,
}
_PACKAGES = {"patchworkpp": "pypatchworkpp", "csf": "CSF"}


def available_methods() -> list[str]:
    """Methods that can run here (the optional ones need their package installed, and importable)."""
    return [m for m in METHODS if m not in _PACKAGES or _importable(_PACKAGES[m])]


@cache
def _importable(package: str) -> bool:
    """Whether ``package`` imports: one that is found but fails to import counts as missing."""
    try:
        importlib.import_module(package)
    except Exception:  # not installed, or a broken build (ImportError, OSError for a missing library...)
        return False
    return True
