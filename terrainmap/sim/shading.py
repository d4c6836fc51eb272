"""From ray hits to camera images: textured, lit surfaces, a sky, haze, and sensor effects.

Surfaces are Lambertian under a fixed sun plus ambient light, with an albedo textured by
multi-octave value noise in surface coordinates (world x, y on the terrain; solid-fixed
coordinates on obstacles), so a surface point has the same brightness in both cameras and
stereo matching has texture to lock on to. Octaves finer than the pixel footprint fade out; the
footprint is ``distance / f / max(cos incidence, 0.6)``: foreshortening only partly counted, which
keeps the horizontal detail SGBM needs (a full 1/cos blurred mid-range ground and doubled SGBM's
median error, 0.54 → 0.23 px on ``mounds``). An octave fades from 4 footprints down to 2, while a
pixel's box filter keeps 64 % of a wavelength of 2 pixels: the texture is blurrier than that of an
ideal camera, as lens blur and motion make a real one's. ``detail`` 2 halves the footprint; SGBM's
bias on ground 10–20 m away then falls from −0.24 to −0.06 px and its errors over a pixel from
10 % to 1 % (simulated flat, hills and mounds drives).
The terrain blends two scene colours at low frequency (and a dirt road band where the scene has
one); obstacles take their kind's colour. The sky is a gradient from a pale horizon to a blue
zenith; distant surfaces fade into the horizon colour (haze). :func:`expose` then applies
vignetting (``1 − k·r²``, r = 1 at the image corners), Gaussian pixel noise and 8-bit quantisation.
"""

from __future__ import annotations

import numpy as np

from .raycast import Hits
from .scenes import DIRT_ROAD, Scene

SUN_DIRECTION = np.array([-0.45, 0.35, 0.82]) / np.linalg.norm([-0.45, 0.35, 0.82])
"""Unit vector towards the sun, world frame (behind-left of the vehicle, high)."""
AMBIENT = 0.35
DIFFUSE = 0.75
HORIZON = np.array([0.80, 0.84, 0.88], np.float32)
ZENITH = np.array([0.42, 0.58, 0.86], np.float32)
HAZE_M = 350.0
DETAIL_WAVELENGTHS_M = (2.0, 0.7, 0.25, 0.09, 0.03)
DETAIL_AMPLITUDES = (0.12, 0.15, 0.2, 0.25, 0.25)


def _terrain_base(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Low-frequency terrain colour (N, 3) at world points (N, 3)."""
    x, y = points[:, 0], points[:, 1]
    mix = np.clip(0.5 + 0.6 * scene.texture.fbm(x, y, (9.0, 3.0), (0.7, 0.3)), 0, 1)[:, None]
    a, b = (np.array(c, np.float32) for c in scene.colors)
    color = a + (b - a) * mix
    if scene.road_half_width_m > 0:
        road = np.clip(scene.road_half_width_m + 0.5 - np.abs(y), 0, 1)[:, None]
        color = color + (np.array(DIRT_ROAD, np.float32) - color) * road
    return color


def shade(
    hits: Hits, scene: Scene, colors_by_id: dict[int, tuple[float, float, float]], focal_px: float, detail: float = 1.0
):
    """Linear RGB image (H, W, 3) float32 in about [0, 1] of one camera's hits. ``detail`` divides
    the texture's footprint (:class:`~terrainmap.sim.SimConfig` ``texture_detail``)."""
    h, w = hits.depth.shape
    d = hits.dirs.reshape(-1, 3)
    ray_norm = np.linalg.norm(d, axis=1)
    elevation = np.clip(d[:, 2] / ray_norm, 0, 1)[:, None]
    image = HORIZON + (ZENITH - HORIZON) * np.sqrt(elevation)
    surf = np.flatnonzero(hits.label.ravel() > 0)
    if surf.size:
        image[surf] = _shade_surfaces(hits, scene, colors_by_id, focal_px * detail, surf, d[surf], ray_norm[surf])
    return image.reshape(h, w, 3).astype(np.float32)


def _shade_surfaces(hits, scene, colors_by_id, focal_px, surf, d, ray_norm) -> np.ndarray:
    label = hits.label.ravel()[surf]
    normal = hits.normal.reshape(-1, 3)[surf]
    distance = hits.depth.ravel()[surf] * ray_norm
    cos_incidence = np.abs(np.einsum("ij,ij->i", normal, d)) / ray_norm
    footprint = (distance / focal_px / np.maximum(cos_incidence, 0.6)).astype(np.float32)
    uv = hits.texture_uv.reshape(-1, 2)[surf]
    base = np.empty((surf.size, 3), np.float32)
    terrain = label == 1
    base[terrain] = _terrain_base(scene, hits.points.reshape(-1, 3)[surf[terrain]])
    palette = np.zeros((256, 3), np.float32)
    for obstacle_id, color in colors_by_id.items():
        palette[obstacle_id] = color
    base[~terrain] = palette[hits.instance.ravel()[surf[~terrain]]]
    detail = scene.texture.fbm(uv[:, 0], uv[:, 1], DETAIL_WAVELENGTHS_M, DETAIL_AMPLITUDES, footprint_m=footprint)
    light = AMBIENT + DIFFUSE * np.maximum(normal @ SUN_DIRECTION.astype(np.float32), 0)
    color = base * ((1 + detail) * light)[:, None]
    haze = (1 - np.exp(-distance / HAZE_M))[:, None].astype(np.float32)
    return color + (HORIZON - color) * haze


def expose(
    rgb: np.ndarray, rng: np.random.Generator, *, noise_dn: float, vignetting: float, mono: bool
) -> np.ndarray:
    """8-bit camera image from linear RGB (H, W, 3): vignetting, noise (σ = ``noise_dn`` grey
    levels), rounding. Returns (H, W) uint8 when ``mono`` (Rec. 601 luma), else (H, W, 3)."""
    h, w, _ = rgb.shape
    if mono:
        rgb = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    gain = 235.0 * (1 - vignetting * r2)
    image = rgb * (gain if mono else gain[..., None])
    if noise_dn > 0:
        image = image + rng.normal(0.0, noise_dn, image.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
