"""Data passed between the pipeline stages (the contracts of docs/DESIGN §2).

Frames follow ROS REP-103: vehicle frame ``base_link`` x forward, y left, z up (origin on the
ground under the camera unless extrinsics say otherwise); camera optical frame x right, y down,
z forward. Units: metres, radians, nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from .errors import InputError


class Label(IntEnum):
    """Per-point and per-cell labels (uint8 in every output)."""

    UNKNOWN = 0
    TERRAIN = 1
    OBSTACLE = 2  # above the terrain surface (outlier above)
    BELOW = 3  # below the terrain surface (hole, ditch, or a gross stereo error)


@dataclass(frozen=True)
class StereoCalibration:
    """Intrinsics of a stereo pair.

    When ``rectified`` is true, both images are already rectified and the pinhole model is
    ``fx, fy, cx, cy`` (left camera) with ``baseline_m``; ``cx_right`` may differ from ``cx``
    (then disparity is offset by ``cx - cx_right``, KITTI-style) and ``doffs`` is Middlebury's
    disparity offset in pixels (``Z = f·B / (d + doffs)``).

    When ``rectified`` is false, ``K_left, K_right`` (3×3), ``dist_left, dist_right``
    (OpenCV distortion vectors), ``R`` (3×3) and ``T`` (3, metres) give the right camera
    relative to the left (OpenCV ``stereoRectify`` convention: x_right = R·x_left + T); the stereo
    stage rectifies and derives the pinhole model itself.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    cx_right: float | None = None
    doffs: float = 0.0
    rectified: bool = True
    K_left: np.ndarray | None = None
    K_right: np.ndarray | None = None
    dist_left: np.ndarray | None = None
    dist_right: np.ndarray | None = None
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    source: str = ""
    """Where it came from (file path or topic), for messages and output metadata."""

    def key(self) -> tuple:
        """Its values as a hashable tuple (arrays as bytes): equal keys, the same calibration."""
        return tuple(np.asarray(v).tobytes() if isinstance(v, np.ndarray) else v for v in vars(self).values())


@dataclass(frozen=True)
class Extrinsics:
    """Pose of the left camera optical frame in the vehicle frame.

    ``p_vehicle = rotation @ p_camera + translation``; ``rotation`` is 3×3, ``translation`` 3
    (metres). ``source`` records what was used: ``"tf"``, ``"calibration"``, ``"estimated"``
    (ground fit on the data) or ``"default"``.
    """

    rotation: np.ndarray
    translation: np.ndarray
    source: str = "default"
    camera_frame_id: str = "camera_optical"
    vehicle_frame_id: str = "base_link"
    tf_path: tuple[tuple[str, str, np.ndarray], ...] = ()
    """Where the log's tf has frames between the vehicle frame and the camera frame: its edges
    from the vehicle frame down, ``(parent, child, T_parent_child)`` (4×4), whose product is this
    pose. Outputs republish these edges rather than one vehicle → camera transform, which would
    give the camera frame a second parent beside the log's tree."""

    def to_dict(self) -> dict:
        return {
            "rotation": np.asarray(self.rotation, float).tolist(),
            "translation_m": np.asarray(self.translation, float).tolist(),
            "source": self.source,
            "camera_frame_id": self.camera_frame_id,
            "vehicle_frame_id": self.vehicle_frame_id,
        }


@dataclass
class StereoFrame:
    """One synchronised stereo pair as a source yields it.

    ``left``/``right`` are H×W (mono) or H×W×3 (RGB order) uint8 images of the same size.
    ``extrinsics`` is None when the source has none (the pipeline then estimates them).
    ``vehicle_pose`` is ``world_from_vehicle`` (4×4, metres) in the log's odometry frame at the
    pair's stamp, from its dynamic tf (``odom → base_link``), or None; obstacles are then tracked
    in that frame.
    """

    index: int
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    calibration: StereoCalibration
    extrinsics: Extrinsics | None = None
    frame_id: str = "camera_optical"
    source: str = ""
    """Human-readable origin (file names or topics), for messages."""
    vehicle_pose: np.ndarray | None = None
    odometry_frame_id: str = "odom"
    """The frame ``vehicle_pose`` is given in (the parent of the vehicle frame in the log's tf)."""


@dataclass
class Obstacle:
    """One obstacle (step 5 of the paper), in the vehicle frame.

    ``center_m`` is the centre of its oriented bounding box (x, y, z), ``size_m`` its
    (length along ``yaw_rad``, width, height) and ``height_m`` its top above the terrain surface
    (depth below it for ``kind == "negative"``), metres. ``range_m`` is the distance from the
    vehicle origin to the cluster's nearest point (not to the centre), ``point_count`` the points
    it holds. ``track_id`` is -1 before tracking; ``confirmed`` says whether its track has been
    seen in ``tracking.confirm_hits`` frames (only confirmed tracks are obstacles to the outputs
    and the cost); ``velocity_mps`` is the track's estimated velocity (vx, vy, 0), m/s, in vehicle
    axes: over ground where the source gives the vehicle's pose, else relative to the vehicle;
    None before tracking.
    """

    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float
    height_m: float
    point_count: int
    range_m: float
    kind: str = "positive"  # "positive" (standing up) or "negative" (ditch, hole)
    track_id: int = -1
    confirmed: bool = False
    velocity_mps: np.ndarray | None = None


@dataclass
class FrameResult:
    """Everything the pure per-frame core computed for one frame.

    Arrays of points are in the vehicle frame; ``pixels`` holds the (u, v) pixel of each point in
    the (rectified) left image, so labels can be drawn back on it. ``layers`` maps a layer name to
    an m0×m1 array indexed ``[ix, iy]`` (ix along x, iy along y, see :mod:`terrainmap.grid`);
    ``elevation`` and ``slope`` hold the surface at every cell centre, extrapolated where ``valid``
    is false (no point in or beside the cell), where the writers give NaN instead
    (:func:`terrainmap.sinks.base.grid_layers`).
    """

    index: int
    stamp_ns: int
    extrinsics: Extrinsics
    points_vehicle: np.ndarray  # N×3 float32, metres
    pixels: np.ndarray  # N×2 int32, (u, v)
    point_labels: np.ndarray  # N uint8, Label values
    grid: object  # terrainmap.grid.HeightGrid (samples before equalization)
    terrain: object  # terrainmap.terrain.TerrainEstimate (surface, equalized samples, weights, ...)
    layers: dict[str, np.ndarray] = field(default_factory=dict)
    disparity: np.ndarray | None = None  # H×W float32 px, NaN where invalid
    image: np.ndarray | None = None  # rectified left image (the frame's own array where it came rectified)
    pinhole: object | None = None  # terrainmap.stereo.RectifiedPinhole of image and disparity
    obstacles: list[Obstacle] = field(default_factory=list)  # tracked, confirmed or not (Obstacle.confirmed)
    stats: dict[str, float] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    occupied: list[Obstacle] = field(default_factory=list)
    """What else occupies the ``cost`` layer, vehicle frame: clusters taken for parts of one of
    this frame's confirmed obstacles (with its ``track_id``), and confirmed obstacles missed in the
    last frames (``cost.occupied_misses``), at their predicted places (their own ``track_id``,
    none of this frame's obstacles')."""


@dataclass(frozen=True)
class StereoCamera:
    """The stereo rig's noise geometry, vehicle frame: the centre ``center_m`` (3,) and unit optical
    axis ``axis`` (3,) of the camera the disparities refer to (the rectified left camera), and
    ``focal_baseline`` = f·B (px·m). A point at camera depth Z along the ray ``ρ = p − c`` moves by
    ``Δp = ρ · Z · Δd / (f·B)`` for a disparity error Δd; the grid (eq. 1 noise), segmentation
    (thresholds) and tracking use it.

    Where the image is known (:meth:`from_rig` with ``width_px``, :attr:`has_image`): ``right`` (3,)
    the unit vector of the image's x axis, ``fx_px``, ``cx_px`` and ``width_px`` the rectified left
    camera's focal length, principal column and width (px), for :meth:`column`."""

    center_m: np.ndarray
    axis: np.ndarray
    focal_baseline: float
    right: np.ndarray | None = None
    fx_px: float = 0.0
    cx_px: float = 0.0
    width_px: int = 0

    def __post_init__(self) -> None:
        # Built once a frame: a rig of no baseline or a NaN centre would silently label every point terrain
        vectors = {"center_m": self.center_m, "axis": self.axis, **({"right": self.right} if self.right is not None else {})}
        for name, value in vectors.items():
            if np.shape(value) != (3,) or not np.all(np.isfinite(value)):
                raise InputError(f"StereoCamera: {name} must be 3 finite numbers, got {value!r}")
        if not (np.isfinite(self.focal_baseline) and self.focal_baseline > 0) or not np.any(self.axis):
            raise InputError(f"StereoCamera: needs focal_baseline > 0 and an axis, got {self.focal_baseline!r}, {self.axis!r}")
        if self.right is not None and not (np.isfinite(self.fx_px) and self.fx_px > 0 and np.isfinite(self.cx_px)):
            raise InputError(f"StereoCamera: fx_px must be > 0 and cx_px finite, got {self.fx_px!r}, {self.cx_px!r}")

    @classmethod
    def from_rig(
        cls, fx_px: float, baseline_m: float, extrinsics, cx_px: float | None = None, width_px: int = 0
    ) -> StereoCamera:
        """From the rectified focal length, the baseline and the pose of the rectified left camera,
        an :class:`~terrainmap.types.Extrinsics`; with ``width_px`` > 0, its image columns too
        (``cx_px`` the principal column, the image's centre if omitted)."""
        rotation = np.asarray(extrinsics.rotation, float)
        rig = (np.asarray(extrinsics.translation, float), rotation[:, 2], float(fx_px * baseline_m))
        if width_px <= 0:
            return cls(*rig)
        cx = (width_px - 1) / 2 if cx_px is None else float(cx_px)
        return cls(*rig, rotation[:, 0], float(fx_px), cx, int(width_px))

    @property
    def has_image(self) -> bool:
        """Whether the image's columns are known (:meth:`column` works)."""
        return self.right is not None and self.width_px > 0

    def _ray(self, x, y, z) -> tuple:
        """``(ρx, ρy, ρz, Z)``: the ray from the camera centre to the points and their camera depth."""
        rx, ry, rz = x - self.center_m[0], y - self.center_m[1], z - self.center_m[2]
        return rx, ry, rz, rx * self.axis[0] + ry * self.axis[1] + rz * self.axis[2]

    def column(self, x, y, z) -> np.ndarray:
        """Image column u (px) where the points (x, y, z) (vehicle frame, m; arrays broadcast) appear:
        ``u = cx + fx · (ρ·right)/(ρ·axis)``, ``cx`` for points not in front of the camera.
        Needs :attr:`has_image`."""
        if not self.has_image:
            raise InputError("StereoCamera.column needs the image's columns (from_rig with width_px)")
        rx, ry, rz, depth = self._ray(x, y, z)
        across = rx * self.right[0] + ry * self.right[1] + rz * self.right[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(depth > 0, self.cx_px + self.fx_px * across / depth, self.cx_px)

    def height_per_px(self, x, y, z, dz_dx, dz_dy) -> np.ndarray:
        """|Δh| per pixel of disparity error (m/px), the height change above the plane of gradient
        (dz_dx, dz_dy) through the points (x, y, z): ``Z · |ρz − gx·ρx − gy·ρy| / (f·B)``; arrays
        broadcast together. With a zero gradient, the change of z itself."""
        rx, ry, rz, depth = self._ray(x, y, z)
        return np.maximum(depth, 0.0) * np.abs(rz - dz_dx * rx - dz_dy * ry) / self.focal_baseline

    def shift_per_px(self, points: np.ndarray) -> np.ndarray:
        """How far points (N, 3) move along their rays per pixel of disparity error, ``ρ·Z/(f·B)``:
        (N, 3) metres per pixel, vehicle frame (the error of stereo depth grows as Z²)."""
        ray = np.asarray(points, float).reshape(-1, 3) - self.center_m
        depth = np.maximum(ray @ self.axis, 0.0)
        return ray * (depth / self.focal_baseline)[:, None]
