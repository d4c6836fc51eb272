"""Vectorised ray casting of the height field and the obstacle solids, one camera at a time.

Rays are ``p(t) = origin + t·d`` with ``d`` the pixel's direction ``((u−cx)/fx, (v−cy)/fy, 1)``
rotated to the world frame, so the ray parameter ``t`` *is* the depth along the optical axis
(the ``32FC1`` depth of ROS REP 118).

Terrain (:func:`march_terrain`): march forward in steps that grow with ``t`` (3 %), or longer where
the ray is so high above the ground that the steepest slope of the terrain cannot reach it
(a Lipschitz bound, as in sphere tracing), until the ray drops below the surface, then pin the crossing with a few Illinois regula-falsi steps. Coarse to fine: every
8th pixel is marched from the camera; each full-resolution ray starts at 0.9 × the nearest hit of
the 3×3 coarse rays around it, so most rays need two or three steps. A ray that starts below the
surface (a near bump the coarse rays missed) is marched again from the camera. Rays leave as sky
when they go past ``t_max_m`` (a crossing found by the step that passes it is kept: up to 3 %
beyond) or climb above the highest node.

Obstacles (:func:`intersect_solids`): exact ray–box (slab) and ray–ellipsoid intersection in each
solid's own frame, only for the pixels inside the solid's projected bounding rectangle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter

from .heightfield import Heightfield
from .obstacles import ObstacleBox

logger = logging.getLogger(__name__)

COARSE = 8
"""Pixel spacing of the coarse pass."""
T_NEAR_M = 0.2
"""Rays start this far from the camera; those that start below the terrain there (ground nearer
than this, under a camera a hand's width above it) march again from ``T_CLOSEST_M``."""
T_CLOSEST_M = 0.001
STEP_REL = 0.03
STEP_MIN_M = 0.02
REFINE_STEPS = 5
START_FRACTION = 0.9
"""Full-resolution rays start at this fraction of the nearest coarse hit around them."""


@dataclass
class Hits:
    """What each pixel's ray hit, arrays (H, W[, k]).

    ``depth`` float32 metres along the optical axis (``inf`` for sky); ``label`` uint8
    (0 sky, 1 terrain, 2 obstacle); ``instance`` uint8 (obstacle id, 0 elsewhere); ``points``
    float32 (H, W, 3) world hit points; ``normal`` float32 (H, W, 3) world unit normals;
    ``texture_uv`` float32 (H, W, 2) surface coordinates for texturing (world x, y on the terrain,
    solid-fixed coordinates on obstacles, so textures move with them); ``dirs`` the rays.
    """

    depth: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    texture_uv: np.ndarray
    dirs: np.ndarray
    """(H, W, 3) float32 world ray directions (optical-axis component 1)."""


def _above(terrain: Heightfield, origin, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Height of ray points above the terrain, (N,) float32 (negative below); d is (3+, N)."""
    return origin[2] + t * d[2] - terrain.height(origin[0] + t * d[0], origin[1] + t * d[1])


def march_terrain(
    terrain: Heightfield, origin: np.ndarray, d: np.ndarray, t_start: np.ndarray, t_max_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """First terrain crossing of each ray at or after ``t_start``.

    Parameters
    ----------
    origin : (3,) float32, world metres.  d : (3, N) float32 ray directions (world), by component.
    t_start : (N,) float32, where each march begins (must not be below the surface to be exact).

    Returns
    -------
    t_hit : (N,) float32, ``inf`` where the ray reaches the sky.
    started_below : (N,) bool, rays that were already below the surface at ``t_start``.
    """
    n = d.shape[1]
    t_hit = np.full(n, np.inf, np.float32)
    lo, hi = np.zeros(n, np.float32), np.zeros(n, np.float32)
    f_lo, f_hi = np.ones(n, np.float32), -np.ones(n, np.float32)
    idx = np.flatnonzero(t_start < t_max_m)
    t = t_start[idx].astype(np.float32)
    # rows: dx, dy, dz, and the Lipschitz bound: the surface rises at most max_slope per metre,
    # so a ray f above it cannot reach it within f / (max_slope·|d_xy| − d_z) (safe long steps).
    rays = np.empty((4, idx.size), np.float32)
    rays[:3] = d[:, idx]
    rays[3] = np.maximum(np.float32(terrain.max_slope) * np.hypot(rays[0], rays[1]) - rays[2], np.float32(1e-3))
    f = _above(terrain, origin, rays, t)
    started_below = np.zeros(n, bool)
    started_below[idx[f <= 0]] = True
    keep = f > 0
    idx, t, rays, f = idx[keep], t[keep], rays[:, keep], f[keep]
    z_top = np.float32(terrain.z_max_m)
    while idx.size:
        t_next = np.maximum(t * np.float32(1 + STEP_REL) + np.float32(STEP_MIN_M), t + f / rays[3])
        f_next = _above(terrain, origin, rays, t_next)
        hit = f_next <= 0
        h = idx[hit]
        lo[h], hi[h], f_lo[h], f_hi[h] = t[hit], t_next[hit], f[hit], f_next[hit]
        t_hit[h] = 0  # marked; refined below
        gone = (t_next >= t_max_m) | ((rays[2] >= 0) & (origin[2] + t_next * rays[2] > z_top))
        keep = ~(hit | gone)
        idx, t, rays, f = idx[keep], t_next[keep], rays[:, keep], f_next[keep]
    hit = np.flatnonzero(t_hit == 0)
    t_hit[hit] = _refine(terrain, origin, d[:, hit], lo[hit], hi[hit], f_lo[hit], f_hi[hit])
    return t_hit, started_below


def _refine(terrain, origin, d, lo, hi, f_lo, f_hi) -> np.ndarray:
    """Illinois regula falsi on brackets ``f(lo) > 0 >= f(hi)``; returns the crossing, (N,) float32.

    (When the same end is kept twice, its value is halved, so both ends converge.)"""
    last_below = np.zeros(lo.shape, bool)
    last_above = np.zeros(lo.shape, bool)
    for _ in range(REFINE_STEPS):
        t = lo - f_lo * (hi - lo) / (f_hi - f_lo)
        f = _above(terrain, origin, d, t)
        below = f <= 0
        f_lo = np.where(below & last_below, f_lo * np.float32(0.5), f_lo)
        f_hi = np.where(~below & last_above, f_hi * np.float32(0.5), f_hi)
        hi, f_hi = np.where(below, t, hi), np.where(below, f, f_hi)
        lo, f_lo = np.where(below, lo, t), np.where(below, f_lo, f)
        last_below, last_above = below, ~below
    return lo - f_lo * (hi - lo) / (f_hi - f_lo)


def terrain_depth(terrain: Heightfield, origin: np.ndarray, dirs: np.ndarray, t_max_m: float) -> np.ndarray:
    """Terrain hit depth for every pixel, coarse to fine (module docstring). dirs: (H, W, 3)."""
    h, w, _ = dirs.shape
    near = np.float32(T_NEAR_M)
    coarse_dirs = dirs[COARSE // 2 :: COARSE, COARSE // 2 :: COARSE]
    ch, cw, _ = coarse_dirs.shape
    flat = np.ascontiguousarray(coarse_dirs.reshape(-1, 3).T)
    coarse = _march_from_camera(terrain, origin, flat, t_max_m)
    start = minimum_filter(coarse.reshape(ch, cw), size=3, mode="nearest") * np.float32(START_FRACTION)
    start = np.repeat(np.repeat(start, COARSE, axis=0), COARSE, axis=1)
    start = np.pad(start, ((0, max(0, h - start.shape[0])), (0, max(0, w - start.shape[1]))), mode="edge")
    start = np.maximum(start[:h, :w].ravel(), near)
    flat = np.ascontiguousarray(dirs.reshape(-1, 3).T)
    t_hit, below = march_terrain(terrain, origin, flat, start, t_max_m)
    if below.any():
        again = np.flatnonzero(below)
        logger.debug("%d rays started below the terrain; marched again from the camera", again.size)
        t_hit[again] = _march_from_camera(terrain, origin, flat[:, again], t_max_m)
    return t_hit.reshape(h, w)


def _march_from_camera(terrain: Heightfield, origin: np.ndarray, dirs: np.ndarray, t_max_m: float) -> np.ndarray:
    """:func:`march_terrain` of ``dirs`` (3, N) from ``T_NEAR_M``, and from ``T_CLOSEST_M`` for the
    rays that start below the terrain there; (N,) float32 depths."""
    t_hit, below = march_terrain(terrain, origin, dirs, np.full(dirs.shape[1], T_NEAR_M, np.float32), t_max_m)
    if below.any():
        again = np.flatnonzero(below)
        t_hit[again], _ = march_terrain(terrain, origin, dirs[:, again], np.full(again.size, T_CLOSEST_M), t_max_m)
    return t_hit


def _rectangle(box: ObstacleBox, origin, rotation_world_cam, fx, fy, cx, cy, h, w):
    """Pixel rectangle (v0, v1, u0, u1) that holds the solid's image, or None when out of view."""
    corners_cam = (box.corners_world() - origin) @ rotation_world_cam
    z = corners_cam[:, 2]
    if (z <= 0).all():
        return None
    if (z <= 0.05).any():
        return 0, h, 0, w
    u = fx * corners_cam[:, 0] / z + cx
    v = fy * corners_cam[:, 1] / z + cy
    u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, w)
    v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, h)
    return (v0, v1, u0, u1) if u0 < u1 and v0 < v1 else None


def intersect_solids(hits: Hits, boxes: list[ObstacleBox], origin, dirs, rotation_world_cam, intrinsics) -> None:
    """Overwrite ``hits`` where an obstacle solid is nearer than what the ray hit so far."""
    fx, fy, cx, cy = intrinsics
    h, w, _ = dirs.shape
    for box in boxes:
        rect = _rectangle(box, origin, rotation_world_cam, fx, fy, cx, cy, h, w)
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        d = dirs[v0:v1, u0:u1].reshape(-1, 3)
        t, normal, local = box.intersect(origin, d)
        current = hits.depth[v0:v1, u0:u1].reshape(-1)
        nearer = np.flatnonzero(t < current)
        if not nearer.size:
            continue
        rows, cols = nearer // (u1 - u0) + v0, nearer % (u1 - u0) + u0
        tn = t[nearer]
        hits.depth[rows, cols] = tn
        hits.label[rows, cols] = 2
        hits.instance[rows, cols] = box.id
        hits.points[rows, cols] = origin + tn[:, None] * d[nearer]
        hits.normal[rows, cols] = normal[nearer]
        local = local[nearer]
        hits.texture_uv[rows, cols] = np.stack([local[:, 0] + local[:, 2], local[:, 1] - local[:, 2]], axis=1)


def cast(
    terrain: Heightfield,
    boxes: list[ObstacleBox],
    origin: np.ndarray,
    rotation_world_cam: np.ndarray,
    intrinsics: tuple[float, float, float, float],
    size: tuple[int, int],
    t_max_m: float,
) -> Hits:
    """Cast one camera's rays into the scene.

    Parameters
    ----------
    origin : (3,) camera centre in the world frame, metres.
    rotation_world_cam : (3, 3) rotation of the camera optical frame in the world frame.
    intrinsics : (fx, fy, cx, cy) pixels.  size : (width, height) pixels.
    """
    width, height = size
    fx, fy, cx, cy = intrinsics
    origin = np.asarray(origin, np.float32)
    u = (np.arange(width, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
    v = (np.arange(height, dtype=np.float32) - np.float32(cy)) / np.float32(fy)
    rays_cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.float32(1)), axis=-1)
    dirs = (rays_cam @ rotation_world_cam.T.astype(np.float32)).astype(np.float32)
    depth = terrain_depth(terrain, origin, dirs, t_max_m)
    terrain_hit = np.isfinite(depth)
    points = origin + np.where(terrain_hit, depth, 0)[..., None] * dirs
    normal = np.zeros_like(points)
    normal[terrain_hit] = terrain.normal(points[terrain_hit, 0], points[terrain_hit, 1])
    hits = Hits(
        depth=depth,
        label=terrain_hit.astype(np.uint8),
        instance=np.zeros((height, width), np.uint8),
        points=points.astype(np.float32),
        normal=normal,
        texture_uv=points[..., :2].astype(np.float32),
        dirs=dirs,
    )
    intersect_solids(hits, boxes, origin, dirs, rotation_world_cam, intrinsics)
    return hits
