"""One simulated frame: place the vehicle and the obstacles, ray-cast both cameras, expose.

Frame ``i`` is at time ``i / fps`` seconds; the vehicle is then ``speed_mps · i / fps`` metres
along +x from the origin, posed on the terrain (:func:`~terrainmap.sim.rig.vehicle_pose`), and
stamped ``START_STAMP_NS`` plus that time. Each camera's pixel noise comes from its own random
stream seeded by ``(seed, i, camera)``, so any frame renders the same whatever was rendered before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import raycast
from .obstacles import ObstacleBox
from .rig import CameraRig, vehicle_pose
from .scenes import Scene
from .shading import expose, shade

START_STAMP_NS = 1_700_000_000_000_000_000
"""Stamp of frame 0 (2023-11-14T22:13:20Z), fixed so that logs are reproducible."""
T_MAX_M = 400.0
"""Rays that hit nothing within this depth are sky."""


@dataclass
class SimFrame:
    """A rendered stereo pair with its ground truth.

    ``left``, ``right``: (H, W) or (H, W, 3) uint8. ``depth``: (H, W) float32 metres along the left
    camera's optical axis, ``inf`` for sky. ``label``: (H, W) uint8, 0 sky, 1 terrain, 2 obstacle.
    ``instance``: (H, W) uint8 obstacle id (0 elsewhere). ``rotation_world_base`` (3, 3) and
    ``position_world_base`` (3,): the vehicle pose in ``odom``. ``obstacles``: the solids at this time.
    """

    index: int
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    rotation_world_base: np.ndarray
    position_world_base: np.ndarray
    obstacles: list[ObstacleBox]


@dataclass
class Renderer:
    """Renders frames of one scene with one camera rig (module docstring)."""

    scene: Scene
    rig: CameraRig
    speed_mps: float = 4.0
    fps: float = 10.0
    noise_dn: float = 2.0
    vignetting: float = 0.15
    texture_detail: float = 1.0
    mono: bool = True
    seed: int = 0

    def stamp_ns(self, index: int) -> int:
        return START_STAMP_NS + round(index * 1e9 / self.fps)

    def frame(self, index: int) -> SimFrame:
        time_s = index / self.fps
        rotation_base, position_base = vehicle_pose(self.scene.terrain, self.speed_mps * time_s, 0.0, 0.0)
        boxes = [spec.at(self.scene.terrain, time_s) for spec in self.scene.obstacles]
        colors = {spec.id: spec.color for spec in self.scene.obstacles}
        rotation_cam, left_origin, right_origin = self.rig.camera_poses(rotation_base, position_base)
        images, left_hits = [], None
        for camera, origin in enumerate((left_origin, right_origin)):
            hits = raycast.cast(
                self.scene.terrain, boxes, origin, rotation_cam, self.rig.intrinsics,
                (self.rig.width, self.rig.height), T_MAX_M,
            )
            rgb = shade(hits, self.scene, colors, self.rig.focal_px, self.texture_detail)
            rng = np.random.default_rng([self.seed, index, camera])
            images.append(expose(rgb, rng, noise_dn=self.noise_dn, vignetting=self.vignetting, mono=self.mono))
            left_hits = left_hits or hits
        return SimFrame(
            index=index,
            stamp_ns=self.stamp_ns(index),
            left=images[0],
            right=images[1],
            depth=left_hits.depth,
            label=left_hits.label,
            instance=left_hits.instance,
            rotation_world_base=rotation_base,
            position_world_base=position_base,
            obstacles=boxes,
        )
