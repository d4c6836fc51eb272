"""A minimal transform tree, enough to find the camera's pose in the vehicle frame.

Edges are stored child → (parent, T_parent_child) as 4×4 homogeneous matrices, so
``p_parent = T_parent_child @ p_child``. The first transform seen for a child wins: the camera
mount is static, and only the edges between the camera and the vehicle frame matter here.
"""

from __future__ import annotations

import numpy as np

from ..types import Extrinsics

VEHICLE_FRAMES = ("base_link", "base_footprint")


def quaternion_to_matrix(q_xyzw) -> np.ndarray:
    """3×3 rotation matrix of a quaternion given as (x, y, z, w); normalised first."""
    x, y, z, w = np.asarray(q_xyzw, float) / (np.linalg.norm(q_xyzw) or 1.0)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def homogeneous(rotation: np.ndarray, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = np.asarray(translation, float)
    return T


class TransformTree:
    """Static (first-seen) transforms between named frames."""

    def __init__(self) -> None:
        self._parent: dict[str, tuple[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._parent)

    def add(self, parent: str, child: str, translation, quaternion_xyzw) -> None:
        """Record ``child``'s pose in ``parent`` (leading '/' of ROS 1 frame ids is dropped)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if child and parent and child != parent and child not in self._parent:
            self._parent[child] = (parent, homogeneous(quaternion_to_matrix(quaternion_xyzw), translation))

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root (cycles are cut)."""
        chain = [frame.lstrip("/")]
        while chain[-1] in self._parent and self._parent[chain[-1]][0] not in chain:
            chain.append(self._parent[chain[-1]][0])
        return chain

    def resolves(self, frame: str) -> bool:
        """True when ``frame`` reaches a vehicle frame (base_link / base_footprint)."""
        return any(name in VEHICLE_FRAMES for name in self.chain(frame))

    def extrinsics(self, camera_frame: str) -> Extrinsics | None:
        """Pose of ``camera_frame`` in ``base_link`` (else ``base_footprint``, else the root).

        None when the tree knows no parent of the camera frame.
        """
        chain = self.chain(camera_frame)
        if len(chain) == 1:
            return None
        target = next((name for name in VEHICLE_FRAMES if name in chain), chain[-1])
        T = np.eye(4)
        for child in chain[: chain.index(target)]:
            T = self._parent[child][1] @ T
        return Extrinsics(
            rotation=T[:3, :3],
            translation=T[:3, 3],
            source="tf",
            camera_frame_id=chain[0],
            vehicle_frame_id=target,
        )
