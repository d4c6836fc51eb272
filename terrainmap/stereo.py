"""Stereo front end (paper Sec. III): rectification, SGM disparity, reprojection to 3D points.

One :class:`StereoMatcher` per calibration caches everything that does not change between frames:
the rectification maps (when the calibration is not rectified yet), the OpenCV ``StereoSGBM``
matcher and the per-pixel ray grid used by :meth:`StereoMatcher.reproject`::

    matcher = StereoMatcher(frame.calibration, config.stereo)
    result = matcher.compute(frame.left, frame.right)        # disparity, rectified image, pinhole
    points_cam, pixels = matcher.reproject(result.disparity)
    points_vehicle = to_vehicle(points_cam, extrinsics)

Disparity convention: ``d = u_left − u_right`` as SGBM measures it on the rectified pair; depth is
``Z = fx·B / (d + doffs)`` with the effective ``doffs = calibration.doffs + (cx_right − cx)``
(KITTI-style different principal points and Middlebury's ``doffs`` are the same offset and add up).

Threads: OpenCV runs SGBM on all cores by default (the ``sgbm_3way`` mode halves its time with 2
threads, see :class:`~terrainmap.config.StereoConfig`). :class:`StereoMatcher` may be called from
several threads at once; the runner matches two frames at a time and divides OpenCV's thread count
between them for the run (:func:`terrainmap.runner.run`). A program that processes frames in
several worker processes should call ``cv2.setNumThreads(1)`` in each worker.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from .config import StereoConfig, check_section
from .errors import CalibrationError, InputError, brief
from .extrinsics import is_rotation
from .types import Extrinsics, StereoCalibration, StereoCamera

log = logging.getLogger(__name__)

_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


@dataclass(frozen=True)
class RectifiedPinhole:
    """The pinhole model of the rectified left camera, the one disparities and points refer to.

    ``fx, fy, cx, cy`` in pixels, ``baseline_m`` in metres, ``doffs`` the disparity offset in pixels
    (``Z = fx·baseline_m / (d + doffs)``), ``width × height`` the image size in pixels.
    ``rectifying_rotation``: R1 of ``cv2.stereoRectify``, 9 floats row-major, the turn from the
    left camera's frame into the rectified camera's (``p_rect = R1·p_cam``) where terrainmap
    rectified the images itself; None where they came rectified (no turn).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    doffs: float
    width: int
    height: int
    rectifying_rotation: tuple[float, ...] | None = None


def rectified_camera(extrinsics: Extrinsics, pinhole: RectifiedPinhole) -> Extrinsics:
    """The pose in the vehicle frame of the camera that took the rectified image (``pinhole``), from
    the left camera's ``extrinsics``: ``R·R1ᵀ``; ``extrinsics`` itself where there is no turn."""
    if pinhole.rectifying_rotation is None:
        return extrinsics
    r1 = np.reshape(pinhole.rectifying_rotation, (3, 3))
    return replace(extrinsics, rotation=np.asarray(extrinsics.rotation, np.float64) @ r1.T, tf_path=())  # (no tf frame)


def rig_camera(pinhole: RectifiedPinhole, extrinsics: Extrinsics) -> StereoCamera:
    """The :class:`~terrainmap.types.StereoCamera` (noise geometry and image columns, vehicle frame)
    of disparities taken with ``pinhole`` by the left camera at ``extrinsics``."""
    rectified = rectified_camera(extrinsics, pinhole)
    return StereoCamera.from_rig(pinhole.fx, pinhole.baseline_m, rectified, pinhole.cx, pinhole.width)


@dataclass
class StereoResult:
    """One matched pair.

    ``disparity``: H×W float32, pixels, NaN where SGBM found no valid match.
    ``image``: the rectified left image, H×W or H×W×3 uint8 as given (RGB stays RGB).
    ``pinhole``: the rectified camera model the disparity refers to.
    ``grey``: the rectified left image as matched, H×W uint8 (``image`` itself when mono).
    """

    disparity: np.ndarray
    image: np.ndarray
    pinhole: RectifiedPinhole
    grey: np.ndarray


PLAUSIBLE = {"fx": (1.0, 1e6, "pixels"), "fy": (1.0, 1e6, "pixels"), "baseline_m": (1e-3, 100.0, "m")}
"""Ranges that a stereo camera's focal lengths and baseline fall in (:func:`check_calibration`)."""
MAX_FIELD_OF_VIEW_DEG = 150.0
"""Horizontal field of view past which a calibration is warned about (a focal length in mm, say)."""
WIDE_BASELINE_M = 3.0
"""Baseline past which a calibration is warned about (one in cm, say)."""
MAX_SKEW = 1e-3
"""Skew (K[0][1]) as a fraction of fx past which a camera matrix is warned about (half a pixel at
fx = 500 px): OpenCV's rectification ignores it."""
_NUMBER = (int, float, np.integer, np.floating)
_CALIBRATION_KINDS = {
    **dict.fromkeys(("width", "height"), ((int, np.integer), "an integer")),
    **dict.fromkeys(("fx", "fy", "cx", "cy", "baseline_m", "doffs"), (_NUMBER, "a number")),
    "cx_right": ((*_NUMBER, type(None)), "a number or None"),
    "rectified": ((bool, np.bool_), "true or false"),
}
"""Field → (accepted types, how a message names them) of a :class:`StereoCalibration` (never a bool
for a number: Python's True is an int)."""
MAX_SIDE_PX, MAX_PIXELS = 16384, 2**26
"""The largest image a calibration may describe: the matcher's per-pixel tables (16 bytes a pixel)
and SGBM's buffers are allocated for it before any image is seen."""


def check_calibration(calibration: StereoCalibration, *, size_known: bool = True) -> StereoCalibration:
    """Return ``calibration``, or raise :class:`CalibrationError` (one line, naming its source and
    the problem) if it is unusable. ``size_known=False`` accepts an image size of 0×0, for
    calibration files that do not state it (the first image fills it in)."""
    if not isinstance(calibration, StereoCalibration):
        raise CalibrationError(f"expected a StereoCalibration, got {type(calibration).__name__}")
    name = calibration.source or "stereo calibration"
    for field, (kinds, kind_name) in _CALIBRATION_KINDS.items():
        value = getattr(calibration, field)
        if not isinstance(value, kinds) or (isinstance(value, bool) and field != "rectified"):
            raise CalibrationError(f"{name}: {field} must be {kind_name}, got {brief(value)}")
    for field, value in (
        ("fx", calibration.fx),
        ("fy", calibration.fy),
        ("baseline_m", calibration.baseline_m),
    ):
        if not (math.isfinite(value) and value > 0):
            swapped = " (left and right swapped?)" if field == "baseline_m" and value < 0 else ""
            raise CalibrationError(f"{name}: {field} must be > 0, got {value}{swapped}")
        _check_plausible(name, field, value)
    for field in ("cx", "cy", "doffs", "cx_right"):
        value = getattr(calibration, field)
        if value is not None and not (math.isfinite(value) and abs(value) < 1e6):
            raise CalibrationError(f"{name}: {field} must be a finite number of pixels, got {value}")
    unknown = not size_known and calibration.width == 0 and calibration.height == 0
    if not unknown and (calibration.width <= 0 or calibration.height <= 0):
        raise CalibrationError(
            f"{name}: image size must be positive, got {calibration.width}×{calibration.height}"
        )
    if max(calibration.width, calibration.height) > MAX_SIDE_PX or calibration.width * calibration.height > MAX_PIXELS:
        raise CalibrationError(f"{name}: image size must be at most {MAX_SIDE_PX} px a side and {MAX_PIXELS} pixels "
                               f"(a {MAX_PIXELS / 1e6:.0f} MP camera), got {calibration.width}×{calibration.height}")
    if not calibration.rectified:
        for field, shape in (("K_left", (3, 3)), ("K_right", (3, 3)), ("R", (3, 3)), ("T", (3,))):
            value = getattr(calibration, field)
            if value is None or np.asarray(value).size != math.prod(shape):
                raise CalibrationError(
                    f"{name}: rectified is false, so {field} must be given with shape {shape}"
                )
        length = math.hypot(*np.asarray(calibration.T, float).ravel())  # no overflow for huge T
        if not (math.isfinite(length) and length > 0):
            raise CalibrationError(f"{name}: T must be a non-zero finite translation (the baseline)")
        low, high, unit = PLAUSIBLE["baseline_m"]
        if not low <= length <= high:
            raise CalibrationError(f"{name}: T (the baseline) must be {low:g}..{high:g} {unit} long, got {length:g}")
        if not is_rotation(calibration.R):
            raise CalibrationError(f"{name}: R must be a rotation matrix (orthonormal, determinant 1)")
        for side in ("left", "right"):
            _check_camera_matrix(np.asarray(getattr(calibration, f"K_{side}"), float).reshape(3, 3), f"{name}: K_{side}")
            dist = getattr(calibration, f"dist_{side}")
            if dist is not None and np.size(dist) not in (4, 5, 8, 12, 14):
                raise CalibrationError(f"{name}: dist_{side} must hold 4, 5, 8, 12 or 14 coefficients "
                                       f"(OpenCV's models), got {np.size(dist)}")
            if dist is not None and not np.all(np.abs(dist) < 1e6):  # False for NaN too
                raise CalibrationError(f"{name}: dist_{side} must hold finite coefficients below 1e6, got "
                                       f"{np.ravel(dist).tolist()}")
        if not unknown:  # a pair that cannot be rectified is refused where it is read, not at its first frame
            _stereo_rectify(calibration)
        K = np.asarray(calibration.K_left, float).reshape(3, 3)
        fx, cx, cy, baseline_m = K[0, 0], K[0, 2], K[1, 2], length
    else:
        fx, cx, cy, baseline_m = calibration.fx, calibration.cx, calibration.cy, calibration.baseline_m
    if not unknown:
        _warn_unlikely(name, float(fx), float(cx), float(cy), int(calibration.width), int(calibration.height),
                       float(baseline_m))
    return calibration


@lru_cache(maxsize=16)  # once per calibration, not once per frame
def _warn_unlikely(name: str, fx: float, cx: float, cy: float, width: int, height: int, baseline_m: float) -> None:
    """Warn about values within the checked ranges that are likely a slip all the same (a unit, a
    calibration of other images), which would only end in "no ground" later."""
    if not (0 <= cx <= width and 0 <= cy <= height):
        log.warning("%s: the principal point (%g, %g) lies outside the %d×%d images; is the calibration for these "
                    "images?", name, cx, cy, width, height)
    field_of_view = 2 * math.degrees(math.atan(width / (2 * fx)))
    if field_of_view > MAX_FIELD_OF_VIEW_DEG:
        log.warning("%s: a focal length of %g px gives the %d px wide images a field of view of %.0f°, more than "
                    "a rectified pinhole shows; is it in pixels (not mm)?", name, fx, width, field_of_view)
    if baseline_m > WIDE_BASELINE_M:
        log.warning("%s: a baseline of %g m is unusually wide for a stereo rig; is it in metres (not cm)?",
                    name, baseline_m)


def _check_camera_matrix(K: np.ndarray, name: str) -> None:
    """:class:`CalibrationError` naming ``name`` unless ``K`` is a camera matrix ``[[fx, s, cx],
    [0, fy, cy], [0, 0, 1]]`` with focal lengths in :data:`PLAUSIBLE` and the rest finite pixels."""
    upper = abs(K[1, 0]) <= 1e-9 * abs(K[1, 1])  # zero, up to a text file's rounding
    if not (np.all(np.abs(K) < 1e6) and np.allclose(K[2], [0, 0, 1]) and upper):  # < 1e6: False for NaN
        raise CalibrationError(f"{name} must be a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] of finite "
                               f"pixels, got {K.tolist()}")
    _check_plausible(name, "fx", K[0, 0])
    _check_plausible(name, "fy", K[1, 1])
    if abs(K[0, 1]) > MAX_SKEW * K[0, 0]:
        _warn_skew(name, float(K[0, 1]))


@lru_cache(maxsize=16)  # once per camera matrix, not once per frame
def _warn_skew(name: str, skew: float) -> None:
    log.warning("%s has a skew of %g px (K[0][1]), which OpenCV's rectification ignores: the images are rectified "
                "as if it were 0", name, skew)


def _check_plausible(name: str, field: str, value: float) -> None:
    """:class:`CalibrationError` naming ``name`` and ``field`` unless ``value`` lies in its
    :data:`PLAUSIBLE` range: a wrong unit or a typo, which would only end in "no ground" later."""
    low, high, unit = PLAUSIBLE[field]
    if not low <= value <= high:
        raise CalibrationError(f"{name}: {field} must be within {low:g}..{high:g} {unit}, got {value:g}")


def matching_pinhole(calibration: StereoCalibration) -> RectifiedPinhole:
    """The rectified pinhole the stereo stage matches and reprojects with: the calibration's own
    ``fx, fy, cx, cy, baseline_m`` where the images are rectified, else the one that
    ``cv2.stereoRectify`` derives from ``K, dist, R, T`` (:class:`CalibrationError` where it cannot)."""
    return _stereo_rectify(calibration)[-1] if not calibration.rectified else _given_pinhole(calibration)


def _rectification(calibration: StereoCalibration) -> tuple[tuple, tuple, RectifiedPinhole]:
    """``cv2.stereoRectify`` + ``initUndistortRectifyMap``: maps for left and right, and the new
    pinhole (with R1, the rotation from the left camera's frame into the rectified one, where it
    turns at all)."""
    (K1, D1, R1, P1), (K2, D2, R2, P2), pinhole = _stereo_rectify(calibration)
    size = (calibration.width, calibration.height)
    try:
        maps_left = cv2.initUndistortRectifyMap(K1, D1, R1, P1, size, cv2.CV_16SC2)
        maps_right = cv2.initUndistortRectifyMap(K2, D2, R2, P2, size, cv2.CV_16SC2)
    except cv2.error as exc:
        raise CalibrationError(
            f"{calibration.source or 'stereo calibration'}: cannot rectify ({exc.err})"
        ) from None
    return maps_left, maps_right, pinhole


def _stereo_rectify(calibration: StereoCalibration) -> tuple[tuple, tuple, RectifiedPinhole]:
    """``cv2.stereoRectify`` of an unrectified calibration: ``(K, D, R, P)`` of the left and of the
    right camera, and the rectified pinhole; :class:`CalibrationError` for a pair it cannot make
    side-by-side stereo of, naming the calibration's source."""
    size = (calibration.width, calibration.height)
    K1, K2 = (np.asarray(k, np.float64).reshape(3, 3) for k in (calibration.K_left, calibration.K_right))
    D1, D2 = (
        np.zeros(5) if d is None else np.asarray(d, np.float64).ravel()
        for d in (calibration.dist_left, calibration.dist_right)
    )
    R = np.asarray(calibration.R, np.float64).reshape(3, 3)
    T = np.asarray(calibration.T, np.float64).reshape(3, 1)  # OpenCV 5 rejects a flat (3,) T
    try:
        R1, R2, P1, P2, *_ = cv2.stereoRectify(
            K1, D1, K2, D2, size, R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0
        )
    except cv2.error as exc:
        raise CalibrationError(
            f"{calibration.source or 'stereo calibration'}: cannot rectify ({exc.err})"
        ) from None
    T = np.ravel(calibration.T)
    if abs(P2[1, 3]) > abs(P2[0, 3]) or abs(T[2]) > np.hypot(T[0], T[1]):
        raise CalibrationError(
            f"{calibration.source or 'stereo calibration'}: the cameras are not side by side (T = {T.tolist()}); "
            "vertical or forward-looking stereo is not supported"
        )
    if not (np.all(np.isfinite(P1)) and np.all(np.isfinite(P2))):
        raise CalibrationError(
            f"{calibration.source or 'stereo calibration'}: cannot rectify (the rectified cameras are not finite)"
        )
    baseline_m = -P2[0, 3] / P2[0, 0]
    if not baseline_m > 0:
        raise CalibrationError(
            f"{calibration.source or 'stereo calibration'}: the right camera is not to the right of the left "
            f"(rectified baseline {baseline_m:.4f} m): swap the images, or give T as OpenCV's stereoCalibrate "
            "does (the left camera's origin in the right camera's frame: [-B, 0, 0] for a baseline of B m)"
        )
    turn = None if np.allclose(R1, np.eye(3), atol=1e-9) else tuple(np.ravel(R1).tolist())
    pinhole = RectifiedPinhole(
        float(P1[0, 0]), float(P1[1, 1]), float(P1[0, 2]), float(P1[1, 2]), float(baseline_m),
        float(P2[0, 2] - P1[0, 2]), calibration.width, calibration.height, turn,
    )  # fmt: skip
    return (K1, D1, R1, P1), (K2, D2, R2, P2), pinhole


def _given_pinhole(calibration: StereoCalibration) -> RectifiedPinhole:
    cx_right = calibration.cx if calibration.cx_right is None else calibration.cx_right
    return RectifiedPinhole(
        float(calibration.fx), float(calibration.fy), float(calibration.cx), float(calibration.cy),
        float(calibration.baseline_m), float(calibration.doffs + cx_right - calibration.cx),
        calibration.width, calibration.height,
    )  # fmt: skip


def disparity_range(config: StereoConfig, width: int) -> int:
    """``config.num_disparities``, or when it is 0 (auto) 15 % of ``width`` to the nearest pixel,
    rounded up to a multiple of 16 (at least 16)."""
    return config.num_disparities or max(16, -(-round(0.15 * width) // 16) * 16)


def create_sgbm(config: StereoConfig, width: int) -> cv2.StereoSGBM:
    """The OpenCV matcher configured from ``config`` for images ``width`` pixels wide (P1, P2 scaled
    by the block area, one channel)."""
    area = config.block_size**2
    return cv2.StereoSGBM.create(
        minDisparity=config.min_disparity,
        numDisparities=disparity_range(config, width),
        blockSize=config.block_size,
        P1=config.p1_per_pixel * area,
        P2=config.p2_per_pixel * area,
        disp12MaxDiff=config.disp12_max_diff,
        preFilterCap=config.pre_filter_cap,
        uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window_size,
        speckleRange=config.speckle_range,
        mode=_MODES[config.mode],
    )


_SGBM_SETTINGS = ("MinDisparity", "NumDisparities", "BlockSize", "P1", "P2", "Disp12MaxDiff", "PreFilterCap",
                  "UniquenessRatio", "SpeckleWindowSize", "SpeckleRange", "Mode")


def _settings(sgbm: cv2.StereoSGBM) -> tuple:
    """Every setting of a ``cv2.StereoSGBM``, by its getters."""
    return tuple(getattr(sgbm, f"get{name}")() for name in _SGBM_SETTINGS)


def _copy_of(sgbm: cv2.StereoSGBM) -> cv2.StereoSGBM:
    """A new ``cv2.StereoSGBM`` with the settings of ``sgbm`` (and a work buffer of its own)."""
    copy = cv2.StereoSGBM.create()
    for name, value in zip(_SGBM_SETTINGS, _settings(sgbm), strict=True):
        getattr(copy, f"set{name}")(value)
    return copy


def check_matchable(calibration: StereoCalibration, config: StereoConfig | None = None) -> None:
    """What :class:`StereoMatcher` checks of its arguments, without building it (its tables take a
    second for a large raw camera): :func:`check_calibration`, ``config`` (defaults if None) and
    that its disparity range fits the images. :class:`CalibrationError` or :class:`ConfigError`."""
    check_calibration(calibration)
    config = config or StereoConfig()
    check_section(config, StereoConfig)  # a section built in code: ConfigError, not an OpenCV error
    n = disparity_range(config, calibration.width)
    if not (0 < config.min_disparity + n < calibration.width and n < calibration.width):
        raise CalibrationError(  # OpenCV would crash or search nothing that gives depth
            f"{calibration.source or 'stereo calibration'}: images {calibration.width} px wide cannot be matched "
            f"over disparities {config.min_disparity}..{config.min_disparity + n} px (stereo.min_disparity, "
            "stereo.num_disparities): the range must hold positive disparities and be narrower than the images"
        )


class StereoMatcher:
    """Rectification, SGBM and reprojection for one calibration, with everything cached. Threads
    may call :meth:`compute` at once (each then matches with an SGBM instance of its own).

    Parameters
    ----------
    calibration : StereoCalibration
        Checked here; :class:`CalibrationError` if unusable.
    config : StereoConfig, optional
        SGBM parameters and the depth range of :meth:`reproject`; defaults if omitted.
    """

    def __init__(self, calibration: StereoCalibration, config: StereoConfig | None = None):
        self.calibration = calibration
        self.config = replace(config or StereoConfig())  # a copy: same_setup sees a config changed in place
        check_matchable(calibration, self.config)
        n = disparity_range(self.config, calibration.width)
        self.sgbm = create_sgbm(self.config, calibration.width)
        """The bare ``cv2.StereoSGBM`` (``sgbm.compute(grey_left, grey_right)`` is "SGBM alone"); a
        thread that matches while another is matching with it uses a copy of its settings."""
        # A cv2.StereoSGBM keeps its work buffer between calls: threads matching at once (the
        # runner's workers) must not share one.
        self._matching = threading.Lock()  # held while a thread matches with self.sgbm
        self._spares: list[cv2.StereoSGBM] = []  # copies for the others, kept for the next time
        # config.full_width: columns padded on the left, so that SGBM searches every column whose
        # match can lie left_margin_px inside the right image; the largest disparity kept per column.
        self._pad = max(0, self.config.min_disparity + n - self.config.left_margin_px) if self.config.full_width else 0
        columns = min(calibration.width, self.config.min_disparity + n + self.config.left_margin_px)
        self._max_disparity = np.arange(columns, dtype=np.float32) - self.config.left_margin_px
        if calibration.rectified:
            self._maps = None
            self.pinhole = _given_pinhole(calibration)
        else:
            *self._maps, self.pinhole = _rectification(calibration)
        p = self.pinhole
        u = np.arange(p.width, dtype=np.int32)
        v = np.arange(p.height, dtype=np.int32)
        self._pixels = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)  # (H·W, 2) int32 (u, v)
        self._ray_x = ((self._pixels[:, 0] - p.cx) / p.fx).astype(np.float32)  # X / Z per pixel
        self._ray_y = ((self._pixels[:, 1] - p.cy) / p.fy).astype(np.float32)  # Y / Z per pixel

    def same_setup(self, calibration: StereoCalibration, config: StereoConfig) -> bool:
        """Whether this matcher serves ``calibration`` and ``config`` (so a pipeline can keep it)."""
        return config == self.config and (
            calibration is self.calibration
            or calibration.key() == self.calibration.key()
        )

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Check the pair against the calibration and rectify it (a no-op for rectified input)."""
        self._check_images(left, right)
        if self._maps is None:
            return left, right
        (l1, l2), (r1, r2) = self._maps
        return cv2.remap(left, l1, l2, cv2.INTER_LINEAR), cv2.remap(right, r1, r2, cv2.INTER_LINEAR)

    def match(
        self, left_rect: np.ndarray, right_rect: np.ndarray, first_row: int = 0, last_row: int | None = None
    ) -> np.ndarray:
        """SGBM on a rectified pair → disparity H×W float32 in pixels, NaN where invalid.
        Rows above ``first_row`` are not matched (NaN). With ``config.vertical_passes`` 2, the
        upside-down pass covers the rows above ``last_row`` only (all when None), matching
        :data:`_SECOND_PASS_MARGIN` rows more below them whose single-pass values it leaves, and
        with ``config.vertical_passes_max_range_m`` the rows from the first of near ground down."""
        if first_row > 0:
            disparity = np.full(left_rect.shape[:2], np.nan, np.float32)
            if first_row < len(disparity):  # SGBM fails on no rows
                rest = None if last_row is None else max(last_row - first_row, 0)
                disparity[first_row:] = self.match(left_rect[first_row:], right_rect[first_row:], 0, rest)
            return disparity
        grey = to_grey(left_rect)
        pair = (grey, to_grey(right_rect))
        if self._pad:
            pair = [cv2.copyMakeBorder(image, 0, 0, self._pad, 0, cv2.BORDER_REPLICATE) for image in pair]
        disparity = self._sgbm(pair)
        rows = len(disparity) if last_row is None else min(last_row, len(disparity))
        top = self._second_pass_top(disparity[:rows]) if self.config.vertical_passes == 2 else rows
        if top < rows:  # cancels the single-pass modes' bias on ground (config)
            end = min(rows + _SECOND_PASS_MARGIN, len(disparity))
            start = max(0, top - self.config.block_size)  # the upside-down paths end at its first row
            upside_down = cv2.flip(self._sgbm([cv2.flip(image[start:end], 0) for image in pair]), 0)
            top = top if start else 0  # rows above top, matched only for SGBM's window, keep one pass
            upside_down = upside_down[top - start : rows - start]
            both = disparity[top:rows]
            with np.errstate(invalid="ignore"):  # NaN compares false: pixels only one pass matched drop
                disagree = ~(np.abs(both - upside_down) <= self.config.pass_tolerance_px)
            both += upside_down
            both *= 0.5
            both[disagree] = np.nan
        if self.config.full_width:  # only columns left of min_disparity + n + margin can match too near the edge
            strip = disparity[:, : self._max_disparity.size]
            with np.errstate(invalid="ignore"):
                strip[strip > self._max_disparity] = np.nan
        if self.config.right_margin_px > 0:
            disparity[:, -self.config.right_margin_px :] = np.nan
        if self.config.min_texture > 0:
            disparity[_texture_energy(grey, self.config) < self.config.min_texture**2] = np.nan
        if self.config.fattening_trim_px > 0:
            trim_fattening(disparity, self.config.fattening_jump_px, self.config.fattening_trim_px)
        return disparity

    def _second_pass_top(self, disparity: np.ndarray) -> int:
        """The first row the upside-down pass averages: with ``vertical_passes_max_range_m``, the
        first of ``disparity``'s rows (single pass, H×W pixels) in which at least half the pixels
        lie nearer than that range, else 0; ``len(disparity)`` when no row qualifies."""
        range_m = self.config.vertical_passes_max_range_m
        if range_m <= 0 or len(disparity) == 0:
            return 0
        p = self.pinhole
        with np.errstate(invalid="ignore"):  # NaN compares false: no match is not near
            near = np.count_nonzero(disparity >= p.fx * p.baseline_m / range_m - p.doffs, axis=1)
        rows = np.flatnonzero(near >= 0.5 * disparity.shape[1])
        return int(rows[0]) if rows.size else len(disparity)

    def _sgbm(self, pair) -> np.ndarray:
        """One SGBM call on the (padded) grey pair → H×W float32 pixels, NaN where invalid."""
        if self._matching.acquire(blocking=False):
            try:
                raw = self.sgbm.compute(*pair)
            finally:
                self._matching.release()
        else:  # another thread is matching with self.sgbm: a copy of its settings
            try:
                spare = self._spares.pop()  # (list.pop and append are atomic)
            except IndexError:
                spare = None
            if spare is None or _settings(spare) != _settings(self.sgbm):
                spare = _copy_of(self.sgbm)
            try:
                raw = spare.compute(*pair)
            finally:
                self._spares.append(spare)
        raw = raw[:, self._pad :]  # int16, disparity × 16
        disparity = raw.astype(np.float32)
        disparity *= 1.0 / 16.0
        disparity[raw < self.config.min_disparity * 16] = np.nan
        return disparity

    def compute(self, left: np.ndarray, right: np.ndarray, extrinsics: Extrinsics | None = None) -> StereoResult:
        """Rectify (if needed) and match one pair of uint8 images (H×W mono or H×W×3 RGB).

        With the camera's ``extrinsics`` and ``config.drop_sky``, the sky is found first
        (:func:`sky_mask`): the rows above the first that shows anything else, less a margin
        for SGBM's and the texture test's windows, are not matched at all (15–34 % of the rows
        of the simulated scenes' first frames, that much of SGBM's time), and the sky's
        disparities are dropped.
        """
        left_rect, right_rect = self.rectify(left, right)
        grey = to_grey(left_rect)
        posed = None if extrinsics is None else rectified_camera(extrinsics, self.pinhole)
        sky = None if posed is None or not self.config.drop_sky else sky_mask(grey, self.pinhole, posed, self.config)
        first_row = 0
        if sky is not None:
            all_sky = sky.all(axis=1)
            rows_of_sky = len(sky) if all_sky.all() else int(all_sky.argmin())
            first_row = max(0, rows_of_sky - max(self.config.block_size, self.config.texture_window))
        last_row = None  # the second pass's rows: those that see ground beyond vertical_passes_min_range_m
        if posed is not None and self.config.vertical_passes == 2 and self.config.vertical_passes_min_range_m > 0:
            last_row = len(_beyond(self.pinhole, posed, self.config.vertical_passes_min_range_m))
        result = StereoResult(self.match(grey, right_rect, first_row, last_row), left_rect, self.pinhole, grey)
        if sky is not None:
            result.disparity[sky] = np.nan
        return result

    def sky(self, grey: np.ndarray, extrinsics: Extrinsics) -> np.ndarray:
        """:func:`sky_mask` of a rectified grey left image: H×W bool."""
        return sky_mask(grey, self.pinhole, rectified_camera(extrinsics, self.pinhole), self.config)

    def drop_sky(self, result: StereoResult, extrinsics: Extrinsics) -> None:
        """Set the disparities of the sky to NaN, where :meth:`compute` had no extrinsics yet
        (the first frame of a run that estimates them from its points)."""
        if self.config.drop_sky:
            result.disparity[self.sky(result.grey, extrinsics)] = np.nan

    def reproject(self, disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Disparities → 3D points in the left camera optical frame (x right, y down, z forward).

        ``Z = fx·B / (d + doffs)``, ``X = (u − cx)·Z/fx``, ``Y = (v − cy)·Z/fy``; NaN disparities and
        depths outside ``[min_range_m, max_range_m]`` are skipped (tested on the disparity, so only
        the kept pixels pay for a division; the depth is the rectified camera's, before a raw
        pair's points are turned back into the left camera's frame).

        Returns
        -------
        points_cam : (N, 3) float32, metres, camera optical frame (for a pair rectified here,
            the formulas give the rectified camera's frame, turned back by R1ᵀ into the camera's).
        pixels : (N, 2) int32, the (u, v) pixel of each point in the rectified left image.
        """
        p = self.pinhole
        if disparity.shape != (p.height, p.width):
            raise InputError(f"disparity is {disparity.shape}, the calibration expects {(p.height, p.width)}")
        focal_baseline = np.float32(p.fx * p.baseline_m)
        doffs = np.float32(p.doffs)
        d = disparity.reshape(-1)
        with np.errstate(invalid="ignore"):  # NaN compares false: invalid pixels drop out here
            keep = (d >= focal_baseline / self.config.max_range_m - doffs) & (
                d <= focal_baseline / self.config.min_range_m - doffs
            )
        index = np.flatnonzero(keep)  # take() with indices is ~3x faster than boolean indexing here
        z = focal_baseline / (d.take(index) + doffs)
        points_cam = np.empty((index.size, 3), np.float32)
        np.multiply(self._ray_x.take(index), z, out=points_cam[:, 0])
        np.multiply(self._ray_y.take(index), z, out=points_cam[:, 1])
        points_cam[:, 2] = z
        if p.rectifying_rotation is not None:
            # Rectifying turned the left camera by R1; extrinsics (tf, calibration files) place the
            # camera itself, so points are turned back: rows p_rect @ R1 = (R1ᵀ·p_rect)ᵀ.
            points_cam = points_cam @ np.reshape(p.rectifying_rotation, (3, 3)).astype(np.float32)
        return points_cam, self._pixels.take(index, axis=0)

    def _check_images(self, left: np.ndarray, right: np.ndarray) -> None:
        name = self.calibration.source or "stereo calibration"
        for side, image in (("left", left), ("right", right)):
            if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
                got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
                hint = " (terrainmap.sources.images.stereo_pair makes a 16-bit pair uint8)" if "uint16" in got else ""
                raise InputError(f"{side} image must be a uint8 H×W or H×W×3 array, got {got}{hint}")
            if image.ndim == 3 and image.shape[2] != 3:
                hint = " (give a mono image as H×W: image[..., 0])" if image.shape[2] == 1 else ""
                raise InputError(f"{side} image has {image.shape[2]} channels, expected 3 or an H×W mono image{hint}")
        if left.shape[:2] != right.shape[:2]:
            raise CalibrationError(f"left image is {_size(left)} but right image is {_size(right)}")
        if left.shape[:2] != (self.calibration.height, self.calibration.width):
            raise CalibrationError(
                f"{name}: images are {_size(left)} but the calibration is for "
                f"{self.calibration.width}×{self.calibration.height}"
            )


def trim_fattening(disparity: np.ndarray, jump_px: float, columns: int) -> None:
    """Drop (set NaN, in place) the ``columns`` disparities on the near side of every depth edge
    of an H×W float32 disparity map (pixels): wherever two horizontally neighbouring disparities
    differ by more than ``jump_px``, the larger one and the ``columns − 1`` beyond it, away from
    the edge. SGBM's window carries the near surface's disparity onto the background beside it
    (foreground fattening, ``StereoConfig.fattening_trim_px``); NaN neighbours make no edge."""
    with np.errstate(invalid="ignore"):  # NaN compares false
        step = disparity[:, :-1] - disparity[:, 1:]  # column u minus column u + 1
        near_left, near_right = step > jump_px, step < -jump_px
    drop = np.zeros(disparity.shape, bool)
    edges = step.shape[1]
    for s in range(min(columns, edges)):
        drop[:, : edges - s] |= near_left[:, s:]  # an edge right of column u + s: u is near
        drop[:, 1 + s :] |= near_right[:, : edges - s]  # an edge left of column u − s: u is near
    disparity[drop] = np.nan


def to_vehicle(points_cam: np.ndarray, extrinsics: Extrinsics) -> np.ndarray:
    """Camera optical frame → vehicle frame: ``p_vehicle = R @ p_cam + t``; (N, 3) float32, metres.

    Uses ``cv2.transform`` (SIMD, ~0.1 ms for 250k points; numpy's ``points @ R.T`` takes ~2 ms).
    """
    points = np.ascontiguousarray(points_cam, np.float32).reshape(-1, 3)
    if points.shape[0] == 0:
        return points.copy()
    transform = np.hstack([np.asarray(extrinsics.rotation), np.reshape(extrinsics.translation, (3, 1))])
    return cv2.transform(points.reshape(-1, 1, 3), transform.astype(np.float32)).reshape(-1, 3)


def _texture_energy(grey: np.ndarray, config: StereoConfig) -> np.ndarray:
    """Square of the texture measure of ``config.texture_measure`` per pixel (H×W float32, grey
    levels²), the smallest over the windows within ``config.texture_margin_px`` (a cross-shaped
    erosion: up, down, left and right)."""
    box = (config.texture_window, config.texture_window)
    if config.texture_measure == "x_gradient":
        gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=1)  # I(u+1) − I(u−1)
        energy = cv2.boxFilter(gx * gx, cv2.CV_32F, box) * 0.25
    else:
        energy = _local_variance(grey, config.texture_window)
    if config.texture_margin_px > 0:
        side = 2 * config.texture_margin_px + 1
        energy = cv2.erode(energy, cv2.getStructuringElement(cv2.MORPH_CROSS, (side, side)))
    return energy


def _local_variance(grey: np.ndarray, side: int) -> np.ndarray:
    """Grey-level variance over the side × side window around each pixel: H×W float32."""
    mean = cv2.boxFilter(grey, cv2.CV_32F, (side, side))
    return cv2.sqrBoxFilter(grey, cv2.CV_32F, (side, side)) - mean * mean


_SECOND_PASS_MARGIN = 32
"""Rows matched below the last row of a partial upside-down pass (:meth:`StereoMatcher.match`): its
cost paths start at the strip's lower edge, and these rows give them room before the rows it keeps."""

_SKY_WINDOW = 5
"""Side of the window over which a sky pixel must be flat, pixels. A pixel is flat only when its
window misses the skyline, so growing the flat region by the half-width reaches exactly to it."""


def sky_mask(grey: np.ndarray, pinhole: RectifiedPinhole, extrinsics: Extrinsics, config: StereoConfig) -> np.ndarray:
    """The pixels of the rectified left image that see sky: H×W bool.

    Sky is the region of flat pixels (grey-level standard deviation over a 5×5 window below
    ``config.min_texture``) that reaches the top row of the image through flat pixels above the
    horizon, grown by the window's half-width up to the skyline. "Above the horizon" means the ray
    would meet level ground under the camera no nearer than ``config.sky_beyond_m`` (horizontal
    distance), if at all: sky just above a crest ahead or above distant terrain lower than the
    vehicle still counts. The bound keeps flat ground and dark or saturated objects out even
    where they touch the sky along an image border; flat regions closed in by texture (a car's
    panel, a wall) are not reached.

    Parameters
    ----------
    grey : H×W uint8
        The rectified left image.
    pinhole : RectifiedPinhole
        Its camera model.
    extrinsics : Extrinsics
        The camera's pose in the vehicle frame (its rotation orients the rays, its height sets
        the horizon's margin).
    config : StereoConfig
        ``min_texture`` (0 finds no sky) and ``sky_beyond_m``.
    """
    above = _beyond(pinhole, extrinsics, config.sky_beyond_m)
    sky = np.zeros(grey.shape, bool)
    rows = len(above)  # the rows below hold no pixel above the horizon
    if rows == 0:
        return sky
    window = grey[: min(rows + _SKY_WINDOW, grey.shape[0])]
    flat = _local_variance(window, _SKY_WINDOW) < np.float32(config.min_texture) ** 2
    flat = flat[:rows] & above
    count, labels = cv2.connectedComponents(flat.view(np.uint8), connectivity=8)
    reaches_top = np.zeros(count, bool)
    reaches_top[labels[0]] = True
    reaches_top[0] = False  # label 0: the pixels that are not flat
    grown = np.zeros(window.shape, np.uint8)
    grown[:rows] = reaches_top[labels]
    sky[: len(window)] = cv2.dilate(grown, np.ones((_SKY_WINDOW, _SKY_WINDOW), np.uint8)).view(bool)  # half-width
    return sky


def _beyond(pinhole: RectifiedPinhole, extrinsics: Extrinsics, range_m: float) -> np.ndarray:
    """:func:`_above_horizon` of the camera ``pinhole`` posed by ``extrinsics``."""
    return _above_horizon(pinhole, np.asarray(extrinsics.rotation, np.float64).tobytes(),
                          float(extrinsics.translation[2]), range_m)


@lru_cache(maxsize=8)
def _above_horizon(pinhole: RectifiedPinhole, rotation: bytes, height_m: float, max_range_m: float) -> np.ndarray:
    """Which pixels look above the horizon of :func:`sky_mask`: bool (R, W), the image's first R
    rows, R the last row holding such a pixel plus one (0 rows when none does). Cached: it depends
    only on the camera, which a run keeps."""
    r = np.frombuffer(rotation).reshape(3, 3)
    u = (np.arange(pinhole.width) - pinhole.cx) / pinhole.fx
    v = (np.arange(pinhole.height) - pinhole.cy) / pinhole.fy
    ray_x, ray_y, ray_z = (row[0] * u[None, :] + row[1] * v[:, None] + row[2] for row in r)  # vehicle frame
    above = ray_z > -max(height_m, 0.0) / max_range_m * np.hypot(ray_x, ray_y)
    rows = np.flatnonzero(above.any(axis=1))
    above = above[: rows[-1] + 1 if rows.size else 0]
    above.setflags(write=False)
    return above


def to_grey(image: np.ndarray) -> np.ndarray:
    """The image as one uint8 channel (RGB converted), as SGBM matches it."""
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _size(image: np.ndarray) -> str:
    return f"{image.shape[1]}×{image.shape[0]}"
