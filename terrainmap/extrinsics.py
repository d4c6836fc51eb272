"""Camera pose in the vehicle frame: given by a calibration, or estimated from the ground.

Conventions (REP-103): the vehicle frame ``base_link`` has x forward, y left, z up; the camera
optical frame x right, y down, z forward; ``p_vehicle = rotation @ p_cam + translation``.

When nothing gives the pose, :func:`estimate_extrinsics` fits the ground plane to the near points
below the camera (RANSAC, then least squares on the inliers) and defines the vehicle frame from it:
origin on the plane directly below the camera, z up along the plane normal, x forward along the
optical axis projected onto the plane (so yaw is 0 by construction), y left.

Angles (:func:`describe_extrinsics`, :func:`extrinsics_from_pose`): the camera's rotation relative to
a level camera looking along +x, as intrinsic z-y-x (yaw, pitch, roll) angles in the vehicle frame,
right-handed: **pitch > 0 tilts the optical axis down** (towards the ground), **roll > 0 lowers the
camera's right side** (rotation about +x, forward).

On KITTI 2015 pair 000005 the fit gives height 1.62 m, pitch −0.45° (optical axis slightly above
the road plane), roll +1.87° (camera's right side lower than its left relative to the road) on
the ground-truth points, and 1.62 m, −0.45°, +2.15° on SGBM points. The data README quotes
"pitch ≈ 0.5°, roll ≈ −1.9°": the same magnitudes with both signs flipped, i.e. the road plane's
tilt as seen from the camera rather than the camera's tilt relative to the road.

Cost: ~9 ms for 200k–340k points on a 2-core machine (the fit uses at most 10k random near
points), so a pipeline may estimate once per log or every few frames rather than every frame.
"""

from __future__ import annotations

import functools
import logging
import math

import numpy as np

from .config import ExtrinsicsConfig
from .errors import CalibrationError, FrameError
from .types import Extrinsics

log = logging.getLogger(__name__)

_FIT_POINTS = 10000
"""Near points kept (random subset) for the fit: plenty for a plane, and bounds the cost."""
_REFINE_STEPS = 10
"""Most least-squares refinements of the RANSAC plane (each re-selects the inliers)."""

LEVEL_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation camera optical → vehicle of a level camera looking forward (x_v = z_c, y_v = −x_c, z_v = −y_c)."""


MAX_MOUNT_M = 1e3
"""Farthest a camera may sit from the vehicle origin along any axis, metres."""
UP_PITCH_DEG = 30.0
"""A camera pose that looks up more than this, degrees, is warned about: it sees no ground ahead,
most likely a rotation given in another convention (an identity rotation looks straight up).
Down, rolled or upside down a camera may be mounted."""


def extrinsics_from_calibration(
    rotation: np.ndarray, translation: np.ndarray, *, source: str = "calibration", name: str = "extrinsics"
) -> Extrinsics:
    """Extrinsics from a camera-to-vehicle rotation (3×3) and translation (3, metres).

    Raises :class:`CalibrationError` (naming ``name``) unless ``rotation`` is a proper rotation
    (orthonormal within 1e-3, determinant +1), both are finite and the camera lies within
    :data:`MAX_MOUNT_M` of the vehicle origin.
    """
    try:
        R = np.asarray(rotation, np.float64).reshape(3, 3)
        t = np.asarray(translation, np.float64).reshape(3)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{name}: rotation must be 3×3 and translation 3 numbers") from None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise CalibrationError(f"{name}: rotation and translation must be finite")
    if not is_rotation(R):
        raise CalibrationError(f"{name}: rotation is not a proper rotation matrix (orthonormal, det +1)")
    if np.abs(t).max() > MAX_MOUNT_M:  # metres taken for millimetres, or a pose in the wrong frame
        raise CalibrationError(f"{name}: the camera must lie within {MAX_MOUNT_M:g} m of the vehicle origin, "
                               f"got translation {t.tolist()}")
    extrinsics = Extrinsics(rotation=R, translation=t, source=source)
    pitch_deg = describe_extrinsics(extrinsics)["pitch_deg"]
    if pitch_deg < -UP_PITCH_DEG:  # an identity rotation, say: the optical z axis taken for the vehicle's up
        _warn_looking_up(name, round(pitch_deg))
    return extrinsics


@functools.lru_cache(maxsize=64)  # once per pose and source, however often its extrinsics are built
def _warn_looking_up(name: str, pitch_deg: int) -> None:
    log.warning("%s: the camera looks %d° up, where it sees no ground; is the rotation that of the camera's "
                "optical frame (x right, y down, z forward) in the vehicle frame (x forward, y left, z up)?",
                name, -pitch_deg)


def is_rotation(matrix: np.ndarray) -> bool:
    """Whether a 3×3 matrix is a proper rotation: finite, orthonormal within 1e-3, determinant +1."""
    R = np.asarray(matrix, np.float64).reshape(3, 3)
    return bool(np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0)


def extrinsics_from_pose(
    height_m: float,
    pitch_rad: float = 0.0,
    roll_rad: float = 0.0,
    yaw_rad: float = 0.0,
    *,
    source: str = "default",
) -> Extrinsics:
    """Camera ``height_m`` above the vehicle origin, tilted by (yaw, pitch, roll); see the module docstring."""
    body = _rot_z(yaw_rad) @ _rot_y(pitch_rad) @ _rot_x(roll_rad)
    return Extrinsics(rotation=body @ LEVEL_CAMERA, translation=np.array([0.0, 0.0, height_m]), source=source)


def describe_extrinsics(extrinsics: Extrinsics) -> dict[str, float]:
    """``height_m``, ``pitch_deg``, ``roll_deg``, ``yaw_deg`` of the camera, for metadata and messages."""
    body = np.asarray(extrinsics.rotation, float) @ LEVEL_CAMERA.T
    return {
        "height_m": float(np.asarray(extrinsics.translation, float)[2]),
        "pitch_deg": math.degrees(math.asin(float(np.clip(-body[2, 0], -1.0, 1.0)))),
        "roll_deg": math.degrees(math.atan2(body[2, 1], body[2, 2])),
        "yaw_deg": math.degrees(math.atan2(body[1, 0], body[0, 0])),
    }


def estimate_extrinsics(
    points_cam: np.ndarray, config: ExtrinsicsConfig | None = None, rng: np.random.Generator | int | None = 0
) -> Extrinsics:
    """Camera pose from a robust ground-plane fit on near points (``source="estimated"``).

    Parameters
    ----------
    points_cam : (N, 3) float array, metres, left camera optical frame.
    config : ExtrinsicsConfig, optional
        Range, thresholds and RANSAC budget; defaults if omitted.
    rng : numpy Generator or seed
        Drives the RANSAC sampling; the same seed gives the same result.

    Raises
    ------
    FrameError
        ``reason="no_ground"`` with a one-line message when too few near points lie below the
        camera, too few are inliers of any plausible plane, the inliers lie along a line (less than
        0.2 m of spread across it), or the best plane is not a plausible ground (normal tilted more
        than ``max_tilt_deg`` from the camera's −y, camera not above it).
    """
    config = config or ExtrinsicsConfig()
    normal, offset = fit_ground_plane(points_cam, config, np.random.default_rng(rng))
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal  # optical axis projected onto the plane
    forward /= np.linalg.norm(forward)
    rotation = np.stack([forward, np.cross(normal, forward), normal])  # rows: vehicle x, y, z in camera
    extrinsics = Extrinsics(rotation=rotation, translation=np.array([0.0, 0.0, offset]), source="estimated")
    log.debug("estimated extrinsics %s", describe_extrinsics(extrinsics))
    return extrinsics


def fit_ground_plane(
    points_cam: np.ndarray, config: ExtrinsicsConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """Ground plane ``normal · p + offset = 0`` in the camera frame; unit normal pointing up (to −y).

    ``offset`` is then the camera's height above the plane (metres). RANSAC hypotheses from random
    point triples are scored on a random subset of the near points; the best is refined by least
    squares on all its inliers (among at most 10k near points), re-selected until stable.
    Raises ``FrameError("no_ground")`` on failure.
    """
    points = np.asarray(points_cam).reshape(-1, 3)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]  # filter before converting: N may be 300k+
    near = points[(z > 0) & (z < config.near_range_m) & (y > 0) & np.isfinite(x)].astype(np.float64)
    if len(near) < config.min_points:
        raise FrameError(
            "no_ground",
            f"ground fit: only {len(near)} points below the camera nearer than {config.near_range_m} m "
            f"(extrinsics.min_points = {config.min_points})",
        )
    if len(near) > _FIT_POINTS:
        near = near[rng.choice(len(near), _FIT_POINTS, replace=False)]
    sample = near[rng.integers(0, len(near), size=min(len(near), config.sample_size))]
    normal, offset = _ransac(sample, near, config, rng)
    for _ in range(_REFINE_STEPS):  # re-select inliers and refit until the plane stops moving
        inliers = near[np.abs(near @ normal + offset) < config.inlier_threshold_m]
        previous = np.append(normal, offset)
        normal, offset, spread = _least_squares_plane(inliers)
        if np.abs(np.append(normal, offset) - previous).max() < 1e-4:  # 0.006°, 0.1 mm
            break
    if spread < _MIN_SPREAD_M:  # points along one line: every plane through it fits them as well
        raise FrameError(
            "no_ground",
            f"ground fit: the ground points lie along a line (their spread across it is under "
            f"{_MIN_SPREAD_M} m): the plane's tilt about it is unknown",
        )
    fraction = float(np.mean(np.abs(near @ normal + offset) < config.inlier_threshold_m))
    if fraction < config.min_inlier_fraction:
        raise FrameError(
            "no_ground",
            f"ground fit: only {fraction:.0%} of the near points lie on the best plane "
            f"(extrinsics.min_inlier_fraction = {config.min_inlier_fraction:.0%})",
        )
    tilt_deg = math.degrees(math.acos(min(1.0, -normal[1])))
    if tilt_deg > config.max_tilt_deg or offset <= 0:
        raise FrameError(
            "no_ground",
            f"ground fit: implausible ground (normal {tilt_deg:.0f}° from the camera's up axis, "
            f"camera {offset:+.2f} m above it; extrinsics.max_tilt_deg = {config.max_tilt_deg})",
        )
    return normal, float(offset)


_MIN_SPREAD_M = 0.2
"""Least spread (standard deviation, m) of the ground inliers across their narrower direction: a
strip of ground about 0.7 m wide (a line of points tilts the fitted plane at random about it)."""


def _ransac(
    sample: np.ndarray, near: np.ndarray, config: ExtrinsicsConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """Best plausible plane of ``config.iterations`` random triples, scored on ``sample`` (vectorised)."""
    triples = near[rng.integers(0, len(near), size=(config.iterations, 3))]  # (k, 3 points, xyz)
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    normals /= np.where(lengths > 0, lengths, 1.0)[:, None]
    normals *= np.where(normals[:, 1] > 0, -1.0, 1.0)[:, None]  # point up: towards the camera's −y
    offsets = -np.einsum("ij,ij->i", normals, triples[:, 0])
    plausible = (
        (lengths > 0) & (-normals[:, 1] >= math.cos(math.radians(config.max_tilt_deg))) & (offsets > 0)
    )
    if not plausible.any():
        raise FrameError("no_ground", "ground fit: no candidate plane is a plausible ground under the camera")
    distances = sample.astype(np.float32) @ normals.T.astype(np.float32) + offsets.astype(np.float32)
    scores = (np.abs(distances) < config.inlier_threshold_m).sum(axis=0)
    best = int(np.argmax(np.where(plausible, scores, -1)))
    return normals[best], float(offsets[best])


def _least_squares_plane(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Total least-squares plane through ``points`` (normal = least-variance direction), normal up,
    and the points' spread in the plane's narrower direction (standard deviation, m)."""
    if len(points) < 3:
        raise FrameError("no_ground", f"ground fit: only {len(points)} inliers to refine the plane")
    centroid = points.mean(axis=0)
    centred = points - centroid
    variances, axes = np.linalg.eigh(centred.T @ centred / len(points))
    normal = axes[:, 0]  # the eigenvector of the smallest eigenvalue
    if normal[1] > 0:
        normal = -normal
    return normal, float(-normal @ centroid), float(np.sqrt(max(variances[1], 0.0)))


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
