"""Ground truth of one simulated frame on terrainmap's grid, in the vehicle frame (for :mod:`.accuracy`).

The simulator's terrain is a height function of world (``odom``) x, y; the maps are in
``base_link``, which pitches and rolls with the ground. The true height *under a cell* is taken
along base_link's z axis through the cell centre ``(x, y)``: the ``h`` for which the point
``p = pose @ (x, y, h)`` lies on the terrain, ``p_z = terrain(p_x, p_y)``. Solved by fixed-point
iteration ``h ← (terrain(p_x, p_y) − pose_z(x, y, 0)) / R_zz`` from ``h = 0``; each step
shrinks the error by about ``tilt · slope`` (a few percent), so four steps leave well under a
millimetre.

A cell is *observed* in a frame when it holds at least ``min_pixels`` truth terrain pixels
(label 1) of the left camera, back-projected with the truth depth through the true extrinsics;
cells seen only through obstacles or not at all are not observed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import GridConfig
from ..grid import cell_centers, cell_index
from ..sim.truth import Truth, TruthFrame
from ..types import StereoCalibration

TERRAIN_PIXEL = 1
"""Truth label of terrain pixels (0 sky, 1 terrain, 2 obstacle)."""


@dataclass
class TruthObstacle:
    """A truth obstacle in the vehicle frame: ``center_m`` (3,), ``size_m`` (3,) box extent along
    its heading ``yaw_rad`` (about base z), ``height_m`` of its top above the terrain at its
    centre, ``pixels`` (its pixels
    that both cameras see, :func:`truth_obstacles`) and ``range_m`` (horizontal distance of the
    centre)."""

    id: int
    kind: str
    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float
    height_m: float
    pixels: int

    @property
    def range_m(self) -> float:
        return float(np.hypot(self.center_m[0], self.center_m[1]))

    def contains_xy(self, xy_m: np.ndarray, margin_m: float) -> np.ndarray:
        """Whether points ``xy_m`` (N, 2) lie in the footprint dilated by ``margin_m``, (N,) bool."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        d = np.asarray(xy_m, float).reshape(-1, 2) - self.center_m[:2]
        along, across = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
        return (np.abs(along) <= self.size_m[0] / 2 + margin_m) & (np.abs(across) <= self.size_m[1] / 2 + margin_m)


@dataclass
class GridTruth:
    """Truth of one frame on the grid, all (m0, m1) indexed [ix, iy] (see :mod:`terrainmap.grid`).

    ``observed`` bool: see the module docstring. ``height_m`` float64: true terrain under each cell
    centre along base z. ``slope_rad``: true slope of the cell, ``atan`` of the cell-mean gradient
    ``((h(x+c/2, y) − h(x−c/2, y))/c, (h(x, y+c/2) − h(x, y−c/2))/c)`` in the vehicle frame (the
    terrain at the map's resolution; the simulated relief has centimetre bumps at 1 m that no
    0.5 m map represents). ``range_m``: horizontal distance of the cell centre.
    ``obstacles``: the frame's truth obstacles, vehicle frame.
    """

    observed: np.ndarray
    height_m: np.ndarray
    slope_rad: np.ndarray
    range_m: np.ndarray
    obstacles: list[TruthObstacle]


def height_along_z(truth: Truth, pose_world_base: np.ndarray, x_m, y_m, iterations: int = 4) -> np.ndarray:
    """True terrain height (m, float64) under vehicle-frame points ``(x_m, y_m)`` along base z.

    ``pose_world_base`` is the 4×4 pose of base_link in odom; see the module docstring.
    """
    x_m, y_m = np.broadcast_arrays(np.asarray(x_m, float), np.asarray(y_m, float))
    rot, trans = pose_world_base[:3, :3], pose_world_base[:3, 3]
    base = rot[:, 0, None] * x_m.ravel() + rot[:, 1, None] * y_m.ravel() + trans[:, None]  # (3, N) at h = 0
    h = np.zeros(x_m.size)
    for _ in range(iterations):
        p = base + rot[:, 2, None] * h
        h = (truth.height(p[0], p[1]).astype(float) - base[2]) / rot[2, 2]
    return h.reshape(x_m.shape)


def observed_cells(truth: Truth, frame: TruthFrame, grid: GridConfig, min_pixels: int = 1) -> np.ndarray:
    """Cells holding ≥ ``min_pixels`` truth terrain pixels of the left camera, (m0, m1) bool."""
    cal, ext = truth.calibration, truth.extrinsics
    v, u = np.nonzero((frame.label == TERRAIN_PIXEL) & np.isfinite(frame.depth))
    z = frame.depth[v, u].astype(float)
    points_cam = np.column_stack([(u - cal.cx) / cal.fx * z, (v - cal.cy) / cal.fy * z, z])
    points_base = points_cam @ np.asarray(ext.rotation, float).T + np.asarray(ext.translation, float)
    m0, m1 = grid.shape
    count = np.bincount(cell_index(points_base, grid), minlength=m0 * m1 + 1)[: m0 * m1]
    return (count >= min_pixels).reshape(m0, m1)


def truth_obstacles(frame: TruthFrame, calibration: StereoCalibration) -> list[TruthObstacle]:
    """The frame's truth obstacles in the vehicle frame, with the number of their pixels that both
    cameras see: left-image pixels whose match in the (rectified) right image, column
    ``u − fx·B/Z + doffs``, lies inside it. Stereo can give no point for the others (an obstacle
    at the left edge of the left image that the right camera does not see)."""
    pose = frame.pose_world_base()
    rot, trans = pose[:3, :3], pose[:3, 3]
    v, u = np.nonzero(frame.instance)
    with np.errstate(divide="ignore", invalid="ignore"):
        u_right = u - calibration.fx * calibration.baseline_m / frame.depth[v, u] + calibration.doffs
    both = (u_right >= 0) & (u_right < calibration.width)  # False for NaN
    pixels = np.bincount(frame.instance[v[both], u[both]], minlength=256)
    out = []
    for box in frame.obstacles:
        heading = rot.T @ np.array([np.cos(box.yaw_rad), np.sin(box.yaw_rad), 0.0])
        out.append(TruthObstacle(
            box.id, box.kind, rot.T @ (np.asarray(box.center_m, float) - trans), np.asarray(box.size_m, float),
            float(np.arctan2(heading[1], heading[0])), float(box.height_m), int(pixels[box.id]) if box.id < 256 else 0,
        ))
    return out


def grid_truth(truth: Truth, frame: TruthFrame, grid: GridConfig, *, min_pixels: int = 1) -> GridTruth:
    """Everything :mod:`.accuracy` compares against in one frame (see :class:`GridTruth`)."""
    pose = frame.pose_world_base()
    xs, ys = cell_centers(grid)
    x, y = np.meshgrid(xs, ys, indexing="ij")
    half = grid.cell_size_m / 2
    h = height_along_z(truth, pose, np.stack([x, x + half, x - half, x, x]), np.stack([y, y, y, y + half, y - half]))
    gx, gy = (h[1] - h[2]) / grid.cell_size_m, (h[3] - h[4]) / grid.cell_size_m
    return GridTruth(
        observed=observed_cells(truth, frame, grid, min_pixels),
        height_m=h[0],
        slope_rad=np.arctan(np.hypot(gx, gy)),
        range_m=np.hypot(x, y),
        obstacles=truth_obstacles(frame, truth.calibration),
    )


def depression_depth(truth: Truth, pose_world_base: np.ndarray, center_xy_m, radius_m: float) -> float:
    """How far (m) the true terrain at ``center_xy_m`` (vehicle frame) lies below the plane fitted
    to the true terrain on a ring of ``radius_m`` around it (> 0 for a hole or ditch; slopes cancel)."""
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    rx, ry = center_xy_m[0] + radius_m * np.cos(angles), center_xy_m[1] + radius_m * np.sin(angles)
    ring = height_along_z(truth, pose_world_base, rx, ry)
    a = np.column_stack([np.ones_like(rx), rx, ry])
    coef = np.linalg.lstsq(a, ring, rcond=None)[0]
    centre = height_along_z(truth, pose_world_base, center_xy_m[0], center_xy_m[1])
    return float(coef @ [1.0, center_xy_m[0], center_xy_m[1]] - centre)
