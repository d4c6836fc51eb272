"""The simulated vehicle and its stereo camera: intrinsics, mounting, and a pose that follows the terrain.

Frames (REP-103/105): world ``odom`` (z up, z = 0 the terrain's datum; the vehicle starts on the
terrain at x = y = 0 heading along +x), vehicle ``base_link`` (x forward, y left, z up; origin on
the ground plane under the camera), cameras ``left_camera_optical`` / ``right_camera_optical`` (x
right, y down, z forward). The left camera sits ``camera_height_m`` above ``base_link``'s origin,
pitched down by ``pitch_rad``; the right camera is ``baseline_m`` along the left camera's x axis,
same rotation (an ideal rectified pair).

The vehicle's pose at each position is the least-squares plane through the terrain heights
under its four wheels: z from the plane at the origin, x the heading projected onto the plane,
z axis the plane's normal, so the vehicle pitches and rolls with the ground.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import Extrinsics, StereoCalibration
from .heightfield import Heightfield

LEFT_FRAME = "left_camera_optical"
RIGHT_FRAME = "right_camera_optical"
VEHICLE_FRAME = "base_link"
WORLD_FRAME = "odom"

WHEELBASE_M = 2.8
TRACK_M = 1.7

_OPTICAL_IN_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Columns: the optical x (right), y (down), z (forward) axes in base_link, zero pitch."""


@dataclass(frozen=True)
class CameraRig:
    """Stereo camera on the vehicle (see the module docstring); pixels, metres, radians."""

    width: int = 640
    height: int = 480
    focal_px: float = 500.0
    baseline_m: float = 0.3
    camera_height_m: float = 1.8
    pitch_rad: float = np.deg2rad(6.0)

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels, the same for both cameras."""
        return self.focal_px, self.focal_px, (self.width - 1) / 2, (self.height - 1) / 2

    def calibration(self, source: str = "terrainmap simulate") -> StereoCalibration:
        fx, fy, cx, cy = self.intrinsics
        return StereoCalibration(
            width=self.width, height=self.height, fx=fx, fy=fy, cx=cx, cy=cy, baseline_m=self.baseline_m,
            source=source,
        )

    def rotation_base_cam(self) -> np.ndarray:
        """(3, 3) rotation of the camera optical frames in base_link (pitch down about y)."""
        c, s = np.cos(self.pitch_rad), np.sin(self.pitch_rad)
        pitch = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        return pitch @ _OPTICAL_IN_BASE

    def left_in_base(self) -> np.ndarray:
        """Left camera centre in base_link, (3,) metres."""
        return np.array([0.0, 0.0, self.camera_height_m])

    def extrinsics(self) -> Extrinsics:
        """The true mounting: left camera optical frame in base_link."""
        return Extrinsics(
            rotation=self.rotation_base_cam(), translation=self.left_in_base(), source="tf",
            camera_frame_id=LEFT_FRAME, vehicle_frame_id=VEHICLE_FRAME,
        )

    def camera_poses(self, rotation_world_base: np.ndarray, position_world_base: np.ndarray):
        """World poses of both cameras: ``(rotation (3, 3), left centre (3,), right centre (3,))``."""
        rotation = rotation_world_base @ self.rotation_base_cam()
        left = position_world_base + rotation_world_base @ self.left_in_base()
        return rotation, left, left + rotation[:, 0] * self.baseline_m


def vehicle_pose(terrain: Heightfield, x_m: float, y_m: float, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose of base_link in the world on the terrain at ``(x_m, y_m)`` heading ``yaw_rad``.

    Returns ``(rotation (3, 3), position (3,))`` with ``p_world = rotation @ p_base + position``.
    """
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    along = np.array([1, 1, -1, -1]) * WHEELBASE_M / 2
    across = np.array([1, -1, 1, -1]) * TRACK_M / 2
    wx = x_m + c * along - s * across
    wy = y_m + s * along + c * across
    wz = terrain.height(wx, wy).astype(float)
    design = np.column_stack([np.ones(4), wx - x_m, wy - y_m])
    z0, gx, gy = np.linalg.lstsq(design, wz, rcond=None)[0]
    up = np.array([-gx, -gy, 1.0]) / np.sqrt(gx * gx + gy * gy + 1)
    heading = np.array([c, s, 0.0])
    forward = heading - (heading @ up) * up
    forward /= np.linalg.norm(forward)
    rotation = np.column_stack([forward, np.cross(up, forward), up])
    return rotation, np.array([x_m, y_m, z0])
