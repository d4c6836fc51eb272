"""The simulated terrain: a fine height grid and the one height function everything uses.

The terrain is a float32 grid of heights (metres) in the world frame ``odom`` (z up), indexed
like :mod:`terrainmap.grid`: ``z[ix, iy]`` is the height at the node
``(x_min_m + (ix + ½)·res, y_min_m + (iy + ½)·res)``. Between nodes the surface is the bilinear
interpolation of the four surrounding nodes; outside the grid the nearest edge node continues
(coordinates are clamped). The renderer, the vehicle pose and the truth reader all call
:meth:`Heightfield.height`, so the written truth is exactly the surface that was rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Heightfield:
    """Bilinear height function over a float32 grid (see the module docstring).

    Parameters
    ----------
    z : (nx, ny) float32 array
        Node heights, metres, indexed ``[ix, iy]`` (ix along world x, iy along world y).
    x_min_m, y_min_m : float
        Lower edges of the grid; node ``(ix, iy)`` sits at the cell centre.
    resolution_m : float
        Node spacing, metres.
    """

    z: np.ndarray
    x_min_m: float
    y_min_m: float
    resolution_m: float
    _normals: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.z = np.ascontiguousarray(self.z, dtype=np.float32)
        if self.z.ndim != 2 or min(self.z.shape) < 2:
            raise ValueError(f"height grid must be 2-D with at least 2×2 nodes, got {self.z.shape}")
        if not (np.isfinite(self.z).all() and np.isfinite([self.x_min_m, self.y_min_m]).all()):
            raise ValueError("height grid and its origin must be finite")
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ValueError(f"height grid resolution must be > 0 m, got {self.resolution_m}")
        self.z_max_m = float(self.z.max())
        # Within a cell the bilinear gradient is a blend of node differences, so this bounds it.
        step_x = float(np.abs(np.diff(self.z, axis=0)).max())
        step_y = float(np.abs(np.diff(self.z, axis=1)).max())
        self.max_slope = float(np.hypot(step_x, step_y)) / self.resolution_m + 1e-3
        """Upper bound of the surface gradient (rise per metre), for safe ray-marching steps."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.z.shape

    def _cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat index of the lower-left node and the fractions (fx, fy) of each query point."""
        nx, ny = self.z.shape
        inv = np.float32(1.0 / self.resolution_m)
        gx = np.clip((np.asarray(x, np.float32) - np.float32(self.x_min_m)) * inv - 0.5, 0, nx - 1)
        gy = np.clip((np.asarray(y, np.float32) - np.float32(self.y_min_m)) * inv - 0.5, 0, ny - 1)
        ix = np.minimum(gx.astype(np.int32), nx - 2)
        iy = np.minimum(gy.astype(np.int32), ny - 2)
        return ix * ny + iy, gx - ix, gy - iy

    def _interpolate(self, values: np.ndarray, x, y) -> np.ndarray:
        """Bilinear interpolation of node ``values`` (nx, ny, ...) at world (x, y)."""
        flat = values.reshape(self.z.size, *values.shape[2:])
        k, fx, fy = self._cells(x, y)
        ny = self.z.shape[1]
        if values.ndim == 3:
            fx, fy = fx[..., None], fy[..., None]
        a, b, c, d = flat[k], flat[k + ny], flat[k + 1], flat[k + ny + 1]
        return a + (b - a) * fx + (c - a) * fy + (a - b - c + d) * (fx * fy)

    def height(self, x, y) -> np.ndarray:
        """Terrain height (float32, metres) at world points ``(x, y)`` (arrays of one shape)."""
        return self._interpolate(self.z, x, y)

    def normal(self, x, y) -> np.ndarray:
        """Unit surface normals (..., 3) float32 at world ``(x, y)`` (interpolated node normals)."""
        if self._normals is None:
            gx, gy = np.gradient(self.z.astype(np.float64), self.resolution_m)
            n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
            self._normals = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
        n = self._interpolate(self._normals, x, y)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def node_coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """Node coordinates ``(x (nx,), y (ny,))`` in metres, world frame."""
        nx, ny = self.z.shape
        r = self.resolution_m
        return self.x_min_m + (np.arange(nx) + 0.5) * r, self.y_min_m + (np.arange(ny) + 0.5) * r
