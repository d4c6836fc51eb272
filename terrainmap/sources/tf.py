"""A minimal transform tree, enough to find the camera's pose in the vehicle frame (and the right
camera's in the left's, where the camera infos do not give the baseline).

Edges are stored child → (parent, T_parent_child) as 4×4 homogeneous matrices, so
``p_parent = T_parent_child @ p_child``. The first transform seen for a child wins: the camera
mount is static, and only the edges between the camera and the vehicle frame matter here.
"""

from __future__ import annotations

import itertools
import logging
from bisect import bisect_left

import cv2
import numpy as np

from ..types import Extrinsics

logger = logging.getLogger(__name__)

VEHICLE_FRAMES = ("base_link", "base_footprint")

CAMERA_BODY_M = 0.25
"""A frame above the camera (not a vehicle frame) that holds it closer to its origin than this is
taken for the camera's own body (a stereo camera's driver tree), not for the vehicle."""
WORLD_FRAMES = ("map", "odom", "world", "earth")


def usable(translation, quaternion_xyzw) -> bool:
    """Whether a transform is finite with a quaternion that is not (near) zero: logs do carry
    broken ones, which are skipped rather than turned into a rotation."""
    q = np.asarray(quaternion_xyzw, float)
    return bool(np.isfinite(translation).all() and np.isfinite(q).all() and np.abs(q).max() > 1e-6)


def quaternion_to_matrix(q_xyzw) -> np.ndarray:
    """3×3 rotation matrix of a quaternion given as (x, y, z, w); normalised first."""
    q = np.asarray(q_xyzw, float)
    q = q / (np.abs(q).max() or 1.0)  # first to about 1: the norm of a quaternion of 1e200 overflows
    x, y, z, w = q / (np.linalg.norm(q) or 1.0)
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
        self._broken: set[tuple[str, str]] = set()  # warned about once each

    def __len__(self) -> int:
        return len(self._parent)

    def add(self, parent: str, child: str, translation, quaternion_xyzw) -> None:
        """Record ``child``'s pose in ``parent`` (leading '/' of ROS 1 frame ids is dropped)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not child or not parent or child == parent or child in self._parent:
            return
        if not usable(translation, quaternion_xyzw):
            if (parent, child) not in self._broken:
                self._broken.add((parent, child))
                logger.warning("tf: the transform %s → %s is not finite or its quaternion is zero; ignored", parent, child)
            return
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
        """Pose of ``camera_frame`` in ``base_link`` (else ``base_footprint``, else the highest
        ancestor below the world frames of REP-105, ``map``, ``odom``, ``world``, ``earth``, which
        move with respect to the vehicle).

        None when the tree knows no such frame above the camera frame, or when that highest
        ancestor holds the camera within :data:`CAMERA_BODY_M` of its origin: the camera's own
        body frame (``camera_link`` of a RealSense or ZED driver's tree, published alone), in
        which the pose would put the camera at height 0, turned as the camera is (a warning says
        so; the pose is then estimated from the ground).
        """
        chain = self.chain(camera_frame)
        body = list(itertools.takewhile(lambda name: name not in WORLD_FRAMES, chain))
        target = next((name for name in VEHICLE_FRAMES if name in chain), body[-1] if body else chain[0])
        if target == chain[0]:
            return None
        T = self._up_to(chain, target)
        if target not in VEHICLE_FRAMES and np.linalg.norm(T[:3, 3]) < CAMERA_BODY_M:
            logger.warning("tf: the camera frame %s lies %.2f m from the origin of %s, the highest frame above it "
                           "(no base_link or base_footprint): taken for the camera's own body, not the vehicle; "
                           "the camera pose is estimated from the ground", chain[0], np.linalg.norm(T[:3, 3]), target)
            return None
        edges = tuple((self._parent[child][0], child, self._parent[child][1]) for child in chain[: chain.index(target)])
        return Extrinsics(
            rotation=T[:3, :3],
            translation=T[:3, 3],
            source="tf",
            camera_frame_id=chain[0],
            vehicle_frame_id=target,
            tf_path=edges[::-1] if len(edges) > 1 else (),
        )

    def _up_to(self, chain: list[str], ancestor: str) -> np.ndarray:
        """``T_ancestor_frame`` (4×4) of ``chain[0]``, ``ancestor`` being in its ``chain``."""
        T = np.eye(4)
        for child in chain[: chain.index(ancestor)]:
            T = self._parent[child][1] @ T
        return T

    def relative(self, frame: str, other: str) -> np.ndarray | None:
        """``T_frame_other`` (4×4): the pose of ``other`` in ``frame``, through their nearest
        common ancestor; None when they have none (or are the same frame)."""
        chain, other_chain = self.chain(frame), self.chain(other)
        common = next((name for name in chain if name in other_chain), None)
        if common is None or chain[0] == other_chain[0]:
            return None
        return np.linalg.inv(self._up_to(chain, common)) @ self._up_to(other_chain, common)


class VehiclePoses:
    """Recent poses of the vehicle (``base_link`` / ``base_footprint``) in an odometry frame,
    from the dynamic tf (``odom → base_link``), looked up at image stamps.

    ``at(stamp)`` interpolates between the two poses around the stamp, the translation linearly
    and the rotation along the shortest arc (slerp: a vehicle turning at 60°/s turns 6° between
    10 Hz poses, which at 20 m moves an obstacle 2 m); a stamp outside the known poses but within
    ``tolerance_ns`` of the nearest gets the motion between the two nearest carried on to it, for
    at most their own time apart (at 4 m/s, the nearest pose alone would be 40 cm off 100 ms
    away), the one pose where only one is known; else None. The first odometry frame and vehicle frame seen are kept (poses
    between others are ignored), and poses older than ``horizon_ns`` before the newest are forgotten, so memory
    stays bounded. Two poses in a row stamped more than ``horizon_ns`` before the newest, the
    second later than the first, are a clock that went back and runs again (a reset): the poses
    before them are dropped, with a warning. One such pose alone, or repeated, is a stale message
    and ignored, as are poses stamped 0 or broken (one warning for those).
    """

    def __init__(self, tolerance_ns: int = 100_000_000, horizon_ns: int = 2_000_000_000):
        self.tolerance_ns, self.horizon_ns = tolerance_ns, horizon_ns
        self.parent: str | None = None
        self.child: str | None = None
        """The vehicle frame the poses are of: the first one seen (``base_link`` or ``base_footprint``)."""
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._back: int | None = None  # the stamp of a pose just before, far before the newest
        self._warned_broken = False

    @property
    def newest_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def reach(self, stamp_ns: int) -> bool:
        """Whether :meth:`at` has all the poses it uses for ``stamp_ns``: one at or after it, and a
        second, so that a stamp before the first pose gets their motion carried back to it."""
        return len(self._stamps) >= 2 and self._stamps[-1] >= stamp_ns

    def add(self, stamp_ns: int, parent: str, child: str, translation, quaternion_xyzw) -> None:
        """Record one transform; only ``odometry frame → vehicle frame`` ones are kept."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if (child not in VEHICLE_FRAMES or parent in VEHICLE_FRAMES or parent != (self.parent or parent)
                or child != (self.child or child)):
            return
        if not usable(translation, quaternion_xyzw) or stamp_ns == 0:  # broken, or never stamped
            if not self._warned_broken:
                self._warned_broken = True
                logger.warning("odometry: a pose %s → %s is not finite, has a zero quaternion or no stamp; such poses "
                               "are ignored", parent, child)
            return
        if self._stamps and stamp_ns <= self._stamps[-1]:
            far_back = self._stamps[-1] - stamp_ns > self.horizon_ns
            running = self._back is not None and stamp_ns > self._back  # later than the last far-back one
            self._back = stamp_ns if far_back else None
            if not (far_back and running):
                return  # out of order or repeated (poses are kept in time order), or one stale pose
            logger.warning("odometry: the clock went back %.1f s (a reset?); the poses before are dropped",
                           (self._stamps[-1] - stamp_ns) / 1e9)
            self._stamps.clear()
            self._poses.clear()
        self._back = None
        self.parent, self.child = parent, child
        self._stamps.append(int(stamp_ns))
        self._poses.append(homogeneous(quaternion_to_matrix(quaternion_xyzw), translation))
        old = bisect_left(self._stamps, stamp_ns - self.horizon_ns)
        del self._stamps[:old], self._poses[:old]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """``world_from_vehicle`` (4×4) at ``stamp_ns``, or None (see the class docstring)."""
        stamps, n = self._stamps, len(self._stamps)
        k = bisect_left(stamps, stamp_ns)  # the first pose at or after the stamp
        if not 0 < k < n:  # outside the known poses
            if n == 0 or abs(stamps[min(k, n - 1)] - stamp_ns) > self.tolerance_ns:
                return None
            if n == 1:
                return self._poses[0].copy()
            k = min(max(k, 1), n - 1)  # the two nearest, carried on beyond them
        t0, t1 = stamps[k - 1], stamps[k]
        a = min(max((stamp_ns - t0) / (t1 - t0), -1.0), 2.0)  # carried on at most their own gap beyond them
        before, after = self._poses[k - 1], self._poses[k]
        pose = before.copy()
        turn, _ = cv2.Rodrigues(before[:3, :3].T @ after[:3, :3])  # axis × angle
        pose[:3, :3] = before[:3, :3] @ cv2.Rodrigues(a * turn)[0]
        pose[:3, 3] = (1 - a) * before[:3, 3] + a * after[:3, 3]
        return pose
