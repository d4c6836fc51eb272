"""Obstacles of the simulated scenes: what they are, where they stand at a time, how rays hit them.

An obstacle is a solid standing upright on the terrain: an oriented box (pedestrian, car, truck,
pole) or an ellipsoid (rock, low wide mound). :class:`ObstacleSpec` is the scene's description
(start position, size, velocity); :meth:`ObstacleSpec.at` places it on the terrain at a time and
gives the :class:`ObstacleBox` that is both rendered and written as ground truth.

Placement: a box's bottom is 5 cm below the lowest terrain point under its footprint and its
top ``height_m`` above the terrain at its centre; an ellipsoid is centred on the lowest of the
terrain heights at its centre and at its four axis ends, with vertical semi-axis the nominal
height (so about its upper half shows, less on sloping ground). The truth height of either is
that of its top above the terrain at its centre. Moving obstacles keep their heading along
their velocity (and the last one while they stand).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .heightfield import Heightfield

KINDS: dict[str, tuple[str, tuple[float, float, float], tuple[float, float, float]]] = {
    "pedestrian": ("box", (0.35, 0.5, 1.8), (0.22, 0.26, 0.45)),
    "car": ("box", (4.3, 1.8, 1.5), (0.62, 0.12, 0.10)),
    "truck": ("box", (8.0, 2.6, 3.5), (0.85, 0.64, 0.12)),
    "pole": ("box", (0.15, 0.15, 3.0), (0.72, 0.72, 0.70)),
    "rock": ("ellipsoid", (0.7, 0.6, 0.5), (0.42, 0.40, 0.38)),
    "mound": ("ellipsoid", (4.0, 3.0, 0.5), (0.50, 0.42, 0.32)),
}
"""kind → (shape, default (length, width, height) in metres, base colour RGB in [0, 1])."""

_CORNERS = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)], np.float32)


@dataclass(frozen=True)
class ObstacleBox:
    """One obstacle at one time, world frame (``odom``).

    ``center_m`` (3,) centre of the solid; ``size_m`` (3,) its extent along its own x (heading
    ``yaw_rad`` about world z), y and z; the solid is the box itself (``shape == "box"``) or the
    ellipsoid inscribed in it (``"ellipsoid"``). ``height_m``: its top's height above the terrain
    at its centre (an ellipsoid sunk on sloping ground stands less than its nominal size).
    ``velocity_mps`` (3,) world velocity. ``id`` ≥ 1 is stable over the frames.
    """

    id: int
    kind: str
    shape: str
    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float
    height_m: float
    velocity_mps: np.ndarray

    def rotation(self) -> np.ndarray:
        """(3, 3) rotation of the solid's frame in the world frame (yaw about z)."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_local(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) in the solid's frame (origin at its centre), (N, 3)."""
        return (np.asarray(points_world, np.float64) - self.center_m) @ self.rotation()

    def corners_world(self) -> np.ndarray:
        """The 8 corners of the bounding box, (8, 3) world metres."""
        return (_CORNERS * self.size_m) @ self.rotation().T + self.center_m

    def intersect(self, origin: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Entry of rays ``origin + t·d`` (d: (N, 3) world) into the solid.

        Returns ``t`` (N,) float32 (``inf`` for a miss or a solid behind the camera), the
        world unit normal (N, 3) and the hit point in the solid's frame (N, 3), both float32.
        """
        rot = self.rotation().astype(np.float32)
        o = (np.asarray(origin, np.float32) - self.center_m.astype(np.float32)) @ rot
        dl = d @ rot
        half = (self.size_m / 2).astype(np.float32)
        if self.shape == "box":
            t, normal = _slab(o, dl, half)
        else:
            t, normal = _ellipsoid(o, dl, half)
        local = o + np.where(np.isfinite(t), t, 0)[:, None] * dl
        return t, (normal @ rot.T).astype(np.float32), local.astype(np.float32)


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray–box entry (box centred at the origin, half extents ``half``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (-half - o) * inv, (half - o) * inv
    t_in_axis = np.fmin(t1, t2)
    t_in = np.nanmax(t_in_axis, axis=1)
    t_out = np.nanmin(np.fmax(t1, t2), axis=1)
    ok = (t_in <= t_out) & (t_in > 0)
    axis = np.nanargmax(np.where(np.isnan(t_in_axis), -np.inf, t_in_axis), axis=1)
    normal = np.zeros_like(d)
    normal[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    return np.where(ok, t_in, np.inf).astype(np.float32), normal


def _ellipsoid(o: np.ndarray, d: np.ndarray, semi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray–ellipsoid entry (centred at the origin, semi-axes ``semi``)."""
    os_, ds = o / semi, d / semi
    a = np.einsum("ij,ij->i", ds, ds)
    b = 2 * ds @ os_
    c = float(os_ @ os_) - 1
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    ok = (disc >= 0) & (t > 0)
    p = o + np.where(ok, t, 0)[:, None] * d
    normal = p / (semi * semi)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return np.where(ok, t, np.inf).astype(np.float32), normal


@dataclass(frozen=True)
class ObstacleSpec:
    """An obstacle of a scene: ``kind`` (a key of :data:`KINDS`), start ``xy_m`` (world, at
    time 0), ``size_m`` (length, width, height above ground; default the kind's), ``yaw_rad``,
    ``velocity_mps`` (vx, vy; zero for a static obstacle) and ``turns``: later changes of
    velocity, ``(time_s, (vx, vy))`` in time order (a walker that stops at the roadside or steps
    off the vehicle's track as it comes near: a real log holds no obstacle inside the vehicle)."""

    id: int
    kind: str
    xy_m: tuple[float, float]
    size_m: tuple[float, float, float] | None = None
    yaw_rad: float = 0.0
    velocity_mps: tuple[float, float] = (0.0, 0.0)
    turns: tuple[tuple[float, tuple[float, float]], ...] = ()

    def __post_init__(self):
        times = [t for t, _ in self.turns]
        if times != sorted(times) or any(t < 0 for t in times):
            raise ValueError(f"obstacle {self.id}: turns must come in time order from 0 s, got times {times}")

    @property
    def shape(self) -> str:
        return KINDS[self.kind][0]

    @property
    def color(self) -> tuple[float, float, float]:
        return KINDS[self.kind][2]

    def motion(self, time_s: float) -> tuple[np.ndarray, np.ndarray, float]:
        """World position (x, y) m, velocity (vx, vy) m/s and heading (rad) at ``time_s``: the
        heading of the latest motion (``yaw_rad`` before any), kept while standing."""
        xy, velocity, start, yaw = np.array(self.xy_m, float), np.array(self.velocity_mps, float), 0.0, self.yaw_rad
        for turn_s, next_velocity in ((0.0, self.velocity_mps), *self.turns):
            if turn_s > time_s:
                break
            xy += velocity * (turn_s - start)
            start, velocity = turn_s, np.array(next_velocity, float)
            if velocity.any():
                yaw = float(np.arctan2(velocity[1], velocity[0]))
        return xy + velocity * (time_s - start), velocity, yaw

    def at(self, terrain: Heightfield, time_s: float) -> ObstacleBox:
        """The obstacle placed on ``terrain`` at ``time_s`` (module docstring)."""
        length, width, height = self.size_m or KINDS[self.kind][1]
        (x, y), velocity, yaw = self.motion(time_s)
        c, s = np.cos(yaw), np.sin(yaw)
        if self.shape == "box":
            dx = np.array([-1, -1, 1, 1, 0]) * length / 2
            dy = np.array([-1, 1, -1, 1, 0]) * width / 2
        else:
            dx = np.array([-1, 1, 0, 0, 0]) * length / 2
            dy = np.array([0, 0, -1, 1, 0]) * width / 2
        ground = terrain.height(x + c * dx - s * dy, y + s * dx + c * dy).astype(float)
        if self.shape == "box":
            bottom, top = ground.min() - 0.05, ground[-1] + height
            center_z, size_z = (bottom + top) / 2, top - bottom
        else:
            center_z, size_z = ground.min(), 2 * height
        return ObstacleBox(
            id=self.id,
            kind=self.kind,
            shape=self.shape,
            center_m=np.array([x, y, center_z]),
            size_m=np.array([length, width, size_z]),
            yaw_rad=yaw,
            height_m=float(center_z + size_z / 2 - ground[-1]),
            velocity_mps=np.array([velocity[0], velocity[1], 0.0]),
        )
