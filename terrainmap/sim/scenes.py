"""Procedural off-road scenes after the paper's Fig. 7, deterministic for a seed.

Every scene is a terrain (a :class:`~terrainmap.sim.heightfield.Heightfield` in the world frame
``odom``, the vehicle starting at x = y = 0 heading along +x), its surface colours and the
obstacles placed in view. All have fine relief (a few cm at 1–8 m) on top of their shape:

- ``flat``: a dirt road with a 0.5 % grade, shallow side ditches and grass; a pedestrian
  walking towards the road who stops at its edge after 2.1 s, a parked car, a pole, rocks.
- ``hills``: rolling hills (±2 m over 15–60 m); a truck, a pedestrian walking, rocks, a pole.
- ``ditch``: a ditch (1.2 m deep) right of the track with a berm beyond it, a berm on the left
  and a shallow cross ditch ahead; a car and a pedestrian close to the left berm (walking
  towards the track, stopping beside it after 2 s), a pole, rocks.
- ``mounds``: gravel mounds (1.5–3.5 m high) beside the track; a pedestrian walking towards the
  track who stops beside it after 2.5 s, a car, rocks and a low wide mound.
- ``canyon``: a gravel floor between 5 m walls that meander; a truck parked ahead on the track,
  which drives off at 6 m/s after 2 s, a pedestrian, rocks.
- ``climb``: a 9 m hill rising from 8 to 53 m ahead (slopes to ~17°) that the camera looks up;
  a drive longer than 20 frames at the default 4 m/s reaches it and climbs it, pitching the
  vehicle and camera (20 frames stop at its foot); a pedestrian walking down towards the
  vehicle who steps off its track after 2 s, rocks, a pole.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .heightfield import Heightfield
from .noise import ValueNoise
from .obstacles import ObstacleSpec

GRAVEL = ((0.56, 0.52, 0.47), (0.44, 0.40, 0.36))
GRASS = ((0.36, 0.45, 0.22), (0.47, 0.43, 0.27))
DIRT_ROAD = (0.52, 0.46, 0.38)


@dataclass
class Scene:
    """A terrain, its look and its obstacles (see the module docstring).

    ``colors``: two RGB colours the terrain albedo blends between (low-frequency noise);
    ``road_half_width_m``: half width of a road band along y = 0 coloured ``DIRT_ROAD``
    (0: none); ``obstacles``: specs with ids 1, 2, ...
    """

    name: str
    terrain: Heightfield
    obstacles: list[ObstacleSpec]
    colors: tuple[tuple[float, float, float], tuple[float, float, float]]
    road_half_width_m: float
    texture: ValueNoise


def _bump(d: np.ndarray, width_m: float) -> np.ndarray:
    return np.exp(-((d / width_m) ** 2))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return x * x * (3 - 2 * x)


def _flat(x, y, relief, rng):
    return 0.005 * x - 0.25 * _bump(np.abs(y) - 5.0, 0.8) + 0.5 * relief(x, y, [40, 15], [0.08, 0.05])


def _hills(x, y, relief, rng):
    return relief(x, y, [60, 30, 15], [2.0, 1.0, 0.35])


def _ditch(x, y, relief, rng):
    z = -1.2 * _bump(y + 5.5, 1.2) + 1.2 * _bump(y + 9.5, 1.5) + 1.5 * _bump(y - 6.5, 1.5)
    return z - 0.6 * _bump(x - 38.0, 1.5) + relief(x, y, [30, 12], [0.3, 0.1])


def _mounds(x, y, relief, rng):
    z = relief(x, y, [30, 10], [0.3, 0.08])
    for _ in range(9):
        radius, height = rng.uniform(3.0, 7.0), rng.uniform(1.5, 3.5)
        cx, cy = rng.uniform(10, 75), rng.choice([-1, 1]) * rng.uniform(radius + 3.0, 28.0)
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / radius**2
        z = z + height * np.clip(1 - r2, 0, None) ** 1.5
    return z


def _canyon(x, y, relief, rng):
    wall = _smoothstep((np.abs(y - 1.5 * np.sin(x / 25.0)) - 5.0) / 3.0)
    return wall * (5.0 + relief(x, y, [12, 5, 2], [1.0, 0.5, 0.25])) + relief(x, y, [20], [0.15])


def _climb(x, y, relief, rng):
    return 9.0 * _smoothstep((x - 8.0) / 45.0) + relief(x, y, [25, 10], [0.4, 0.1])


def _rocks(rng, first_id: int, count: int) -> list[ObstacleSpec]:
    rocks = []
    for k in range(count):
        size = rng.uniform(0.3, 1.0)
        xy = (rng.uniform(8, 30), rng.choice([-1, 1]) * rng.uniform(1.5, 6.0))
        dims = (size * rng.uniform(1.0, 1.5), size * rng.uniform(0.8, 1.2), size * rng.uniform(0.5, 0.8))
        rocks.append(ObstacleSpec(first_id + k, "rock", xy, dims, yaw_rad=rng.uniform(0, np.pi)))
    return rocks


def _obstacles(name: str, rng: np.random.Generator) -> list[ObstacleSpec]:
    """Hand-placed obstacles of each scene (ids from 1) plus random rocks."""
    # (kind, start xy, yaw, velocity, turns): the walkers that would reach the vehicle's track as
    # it comes near (in a drive of the default 50 frames) stop at the roadside, or step off the
    # track, after 2 s (so the first 20 frames, those of the README's drives, are as before); the
    # canyon's truck, parked on the track, drives off ahead of the vehicle after 2 s, faster than
    # the default 4 m/s (a longer drive would run into it).
    placed = {
        "flat": [("pedestrian", (14, 4.5), 0.0, (0.0, -1.3), ((2.1, (0.0, 0.0)),)),
                 ("car", (24, -3.5), 0.1, None, ()),
                 ("pole", (11, 4.8), 0.0, None, ())],
        "hills": [("truck", (30, 5.0), 0.3, None, ()),
                  ("pedestrian", (18, -3.0), 0.0, (0.6, 0.9), ()),
                  ("pole", (12, -4.0), 0.0, None, ())],
        "ditch": [("car", (21, 3.6), 0.05, None, ()),
                  ("pedestrian", (15, 3.2), 0.0, (0.0, -0.7), ((2.0, (0.0, 0.0)),)),
                  ("pole", (12, -2.5), 0.0, None, ())],
        "mounds": [("pedestrian", (13, 5.0), 0.0, (0.0, -1.2), ((2.5, (0.0, 0.0)),)),
                   ("car", (26, -5.0), -0.2, None, ()),
                   ("mound", (20, 3.0), 0.4, None, ())],
        "canyon": [("truck", (32, 0.5), 0.05, None, ((2.0, (6.0, 0.0)),)),
                   ("pedestrian", (18, -2.0), 0.0, None, ())],
        "climb": [("pedestrian", (26, 1.0), 0.0, (-1.0, 0.0), ((2.0, (0.0, 1.0)), (3.5, (0.0, 0.0)))),
                  ("pole", (16, -3.5), 0.0, None, ())],
    }[name]
    specs = [
        ObstacleSpec(i + 1, kind, xy, yaw_rad=yaw, velocity_mps=vel or (0.0, 0.0), turns=turns)
        for i, (kind, xy, yaw, vel, turns) in enumerate(placed)
    ]
    return specs + _rocks(rng, len(specs) + 1, 3)


SHAPES: dict[str, tuple[Callable, tuple, float]] = {
    "flat": (_flat, GRASS, 3.0),
    "hills": (_hills, GRASS, 0.0),
    "ditch": (_ditch, GRAVEL, 0.0),
    "mounds": (_mounds, GRAVEL, 0.0),
    "canyon": (_canyon, GRAVEL, 0.0),
    "climb": (_climb, GRASS, 0.0),
}
"""scene name → (height function of (x, y, relief, rng), colours, road half width in m)."""

SCENES = tuple(SHAPES)


MAX_SCENE_CELLS = 5_000_000
"""Most cells of a scene's height grid (:func:`grid_size`): a drive of 2.3 km at 0.2 m, about
0.7 GB of memory while the scene is built."""


def grid_size(length_m: float, resolution_m: float = 0.2, half_width_m: float = 40.0) -> tuple[float, float]:
    """Cells (nx, ny) of the height grid :func:`build_scene` makes for a drive of ``length_m``
    (whole numbers as floats; inf for an endless drive)."""
    return np.ceil((length_m + 115.0) / resolution_m), np.ceil(2 * half_width_m / resolution_m)


def build_scene(
    name: str, seed: int, *, length_m: float, resolution_m: float = 0.2, half_width_m: float = 40.0
) -> Scene:
    """Build scene ``name`` for a drive of ``length_m`` along +x from the origin.

    The height grid spans x ∈ [−15, length_m + 100] and y ∈ [−half_width_m, half_width_m] at
    ``resolution_m``. Raises :class:`~terrainmap.errors.ConfigError` for an unknown name.
    """
    if name not in SHAPES:
        raise ConfigError(f"--scene: unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    shape, colors, road = SHAPES[name]
    rng = np.random.default_rng([seed, SCENES.index(name)])
    relief_noise = ValueNoise(rng)
    texture = ValueNoise(rng)
    x_min, y_min = -15.0, -half_width_m
    nx, ny = (int(n) for n in grid_size(length_m, resolution_m, half_width_m))
    x = x_min + (np.arange(nx) + 0.5) * resolution_m
    y = y_min + (np.arange(ny) + 0.5) * resolution_m
    grid_x, grid_y = np.meshgrid(x, y, indexing="ij")

    def relief(px, py, wavelengths, amplitudes):
        return relief_noise.fbm(px, py, wavelengths, amplitudes).astype(np.float64)

    z = shape(grid_x, grid_y, relief, rng) + relief(grid_x, grid_y, [8, 3, 1], [0.06, 0.03, 0.015])
    terrain = Heightfield(z.astype(np.float32), x_min, y_min, resolution_m)
    return Scene(name, terrain, _obstacles(name, rng), colors, road, texture)
