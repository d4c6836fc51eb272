"""Synthetic scenes for the obstacle, tracking and cost tests: planes, boxes, labelled points."""

from __future__ import annotations

import numpy as np

from terrainmap.config import GridConfig
from terrainmap.types import Label

GRID = GridConfig()


class Plane:
    """A stand-in terrain surface z = z0 + gx·x + gy·y with the RationalSurface methods used."""

    def __init__(self, gx: float = 0.0, gy: float = 0.0, z0: float = 0.0):
        self.gx, self.gy, self.z0 = gx, gy, z0

    def evaluate(self, x, y):
        return self.z0 + self.gx * np.asarray(x) + self.gy * np.asarray(y)

    def on_grid(self, xs, ys):
        return self.evaluate(np.asarray(xs)[:, None], np.asarray(ys)[None, :])


def terrain_points(surface: Plane, spacing: float = 0.1) -> np.ndarray:
    """A lattice of terrain points over the whole grid area, vehicle frame."""
    xs = np.arange(GRID.x_min_m + 0.05, GRID.x_min_m + GRID.length_m, spacing)
    ys = np.arange(GRID.y_min_m + 0.05, GRID.y_min_m + GRID.width_m, spacing)
    x, y = (a.ravel() for a in np.meshgrid(xs, ys, indexing="ij"))
    return np.column_stack([x, y, surface.evaluate(x, y)])


def box_points(surface, center_xy, length, width, height, yaw=0.0, spacing=0.05) -> np.ndarray:
    """Points on the top and sides of a box standing on the surface (its base on the terrain)."""
    u, v = np.meshgrid(
        np.arange(-length / 2, length / 2 + 1e-9, spacing), np.arange(-width / 2, width / 2 + 1e-9, spacing)
    )
    u, v = u.ravel(), v.ravel()
    levels = np.arange(0.3, height + 1e-9, spacing)
    side_u = np.concatenate([np.full_like(levels, -length / 2), np.full_like(levels, length / 2)])
    side_h = np.concatenate([levels, levels])
    uu = np.concatenate([u, side_u])
    vv = np.concatenate([v, np.zeros_like(side_u)])
    hh = np.concatenate([np.full_like(u, height), side_h])
    c, s = np.cos(yaw), np.sin(yaw)
    x = center_xy[0] + uu * c - vv * s
    y = center_xy[1] + uu * s + vv * c
    return np.column_stack([x, y, surface.evaluate(x, y) + hh])


def labelled(surface, *parts: np.ndarray, threshold: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Stack point sets and label them against the surface like the segmentation stage does."""
    points = np.vstack(parts)
    dz = points[:, 2] - surface.evaluate(points[:, 0], points[:, 1])
    labels = np.full(len(points), Label.TERRAIN, np.uint8)
    labels[dz > threshold] = Label.OBSTACLE
    labels[dz < -threshold] = Label.BELOW
    return points.astype(np.float32), labels
