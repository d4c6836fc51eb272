"""Calibration files: terrainmap's YAML/TOML format, KITTI ``calib*.txt`` and Middlebury ``calib.txt``.

terrainmap's own format (``calibration.yaml``, ``.yml`` or ``.toml``)::

    width: 640          # pixels
    height: 480
    fx: 500.0           # rectified pinhole of the left camera, pixels
    fy: 500.0
    cx: 320.0
    cy: 240.0
    baseline_m: 0.30
    cx_right: 320.0     # optional, default cx
    doffs: 0.0          # optional (Middlebury-style disparity offset, px)
    rectified: true     # optional, default true; when false give K_left, K_right (3x3),
                        # dist_left, dist_right (lists), R (3x3), T ([x, y, z] m, right wrt left)
                        # instead of fx ... doffs: the images are rectified with those
    extrinsics:         # optional: left camera optical frame in the vehicle frame (base_link)
      translation_m: [0.0, 0.0, 1.5]
      rotation: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]   # or quaternion_xyzw: [x, y, z, w]

Calibrations read from KITTI/Middlebury text may not know the image size (``width = height = 0``);
:func:`fit_to_image` fills it in from the first image and checks it otherwise.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import re
import tomllib
from pathlib import Path

import numpy as np
import yaml

from ..errors import CalibrationError, brief
from ..extrinsics import MAX_MOUNT_M, is_rotation
from ..stereo import check_calibration as stereo_check
from ..stereo import matching_pinhole
from ..types import Extrinsics, StereoCalibration
from .tf import quaternion_to_matrix, usable

logger = logging.getLogger(__name__)

_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy", "baseline_m")
_UNRECTIFIED = ("K_left", "K_right", "dist_left", "dist_right", "R", "T")
_KNOWN = (*_REQUIRED, "cx_right", "doffs", "rectified", "extrinsics", *_UNRECTIFIED)


def check_calibration(calib: StereoCalibration) -> StereoCalibration:
    """:func:`terrainmap.stereo.check_calibration` for a file that may not state the image size."""
    return stereo_check(calib, size_known=False)


def fit_to_image(calib: StereoCalibration, shape: tuple[int, ...], image_name: str) -> StereoCalibration:
    """Fill in an unknown image size from ``shape`` (H, W[, C]) (with a warning where the principal
    point lies far from the image's centre) or check a known one."""
    height, width = int(shape[0]), int(shape[1])
    if calib.width == 0 and calib.height == 0:
        if abs(calib.cx - width / 2) > width / 4 or abs(calib.cy - height / 2) > height / 4:
            _warn_off_centre(calib.source, calib.cx, calib.cy, width, height)
        return dataclasses.replace(calib, width=width, height=height)
    if (calib.width, calib.height) != (width, height):
        raise CalibrationError(
            f"{calib.source}: calibration is for {calib.width}×{calib.height} images but {image_name} is {width}×{height}"
        )
    return calib


@functools.lru_cache(maxsize=16)  # once per calibration and image size, not once per pair
def _warn_off_centre(source: str, cx: float, cy: float, width: int, height: int) -> None:
    """A calibration that does not state its image size, whose principal point lies far from the
    centre of the images it is given (a quarter of their size or more): likely another camera's."""
    logger.warning("%s: the principal point (%.1f, %.1f) lies far from the centre of the %d×%d images it is "
                   "used for; is the calibration for these images?", source, cx, cy, width, height)


def from_projections(
    P_left: np.ndarray, P_right: np.ndarray, *, source: str, width: int = 0, height: int = 0
) -> StereoCalibration:
    """Rectified pinhole from two 3×4 projection matrices (KITTI and ROS conventions).

    ``baseline_m = (P_left[0,3] − P_right[0,3]) / fx``; ``cx_right`` is set when the principal
    points differ.
    """
    P_left, P_right = (np.asarray(P, float).reshape(3, 4) for P in (P_left, P_right))
    fx = float(P_left[0, 0])
    baseline_m = float((P_left[0, 3] - P_right[0, 3]) / fx) if fx else 0.0
    cx_right = float(P_right[0, 2])
    return check_calibration(
        StereoCalibration(
            width=int(width),
            height=int(height),
            fx=fx,
            fy=float(P_left[1, 1]),
            cx=float(P_left[0, 2]),
            cy=float(P_left[1, 2]),
            baseline_m=baseline_m,
            cx_right=None if math.isclose(cx_right, P_left[0, 2]) else cx_right,
            source=source,
        )
    )


def read_key_values(path: Path, separator: str) -> dict[str, str]:
    """``key<separator> value`` lines of a text file (KITTI uses ':', Middlebury '=')."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read the calibration file ({exc})") from None
    pairs = (line.split(separator, 1) for line in lines if separator in line)
    return {key.strip(): value.strip() for key, value in pairs}


def _numbers(text: str) -> np.ndarray:
    return np.array([float(v) for v in re.split(r"[\s;,\[\]]+", text) if v], float)


def kitti_calibration(path: Path, keys: tuple[str, str] | None = None) -> StereoCalibration:
    """Calibration from a KITTI text file: ``P_rect_02/03`` (cam_to_cam), else ``P2/P3`` (object,
    odometry, stereo 2012), or the two given keys (e.g. ``("P0", "P1")`` for the grey cameras)."""
    values = read_key_values(path, ":")
    candidates = [keys] if keys else [("P_rect_02", "P_rect_03"), ("P2", "P3")]
    for left_key, right_key in candidates:
        if left_key in values and right_key in values:
            size_key = f"S_rect_{left_key[-2:]}"
            try:
                P_left, P_right = _numbers(values[left_key]), _numbers(values[right_key])
            except ValueError:
                raise CalibrationError(f"{path}: {left_key}/{right_key} are not numbers") from None
            try:
                size = _numbers(values.get(size_key, "0 0"))
                width, height = (_whole(v) for v in size[:2]) if size.size >= 2 else (0, 0)
            except (ValueError, OverflowError):
                raise CalibrationError(f"{path}: {size_key} must be the image width and height in pixels") from None
            if P_left.size != 12 or P_right.size != 12:
                raise CalibrationError(f"{path}: {left_key} and {right_key} must have 12 values each")
            return from_projections(P_left, P_right, source=str(path), width=width, height=height)
    wanted = " or ".join("/".join(k) for k in candidates)
    raise CalibrationError(f"{path}: no {wanted} projection matrices in this KITTI calibration file")


def middlebury_calibration(path: Path) -> StereoCalibration:
    """Calibration from a Middlebury ``calib.txt`` (cam0/cam1 matrices, doffs, baseline in mm)."""
    values = read_key_values(path, "=")

    def field(key: str, parse, what: str, default=None):
        if key not in values:
            if default is not None:
                return default
            raise CalibrationError(f"{path}: Middlebury calibration lacks {key!r}")
        try:
            return parse(values[key])
        except ValueError:
            raise CalibrationError(f"{path}: {key} must be {what}, got {brief(values[key])}") from None

    def matrix(text: str) -> np.ndarray:
        return _numbers(text).reshape(3, 3)

    K0 = field("cam0", matrix, "a 3×3 matrix [fx 0 cx; 0 fy cy; 0 0 1]")
    baseline_mm = field("baseline", float, "a number of millimetres")
    if not 1 <= baseline_mm <= 1e5:  # False for NaN; Middlebury gives millimetres, not metres
        raise CalibrationError(f"{path}: baseline must be 1..100000 mm (Middlebury's unit), got {baseline_mm:g}")
    calib = check_calibration(StereoCalibration(
        width=field("width", _whole, "a whole number of pixels", 0),
        height=field("height", _whole, "a whole number of pixels", 0),
        fx=float(K0[0, 0]),
        fy=float(K0[1, 1]),
        cx=float(K0[0, 2]),
        cy=float(K0[1, 2]),
        baseline_m=baseline_mm / 1000.0,
        doffs=field("doffs", float, "a number of pixels", 0.0),
        source=str(path),
    ))
    K1 = field("cam1", matrix, "a 3×3 matrix [fx 0 cx; 0 fy cy; 0 0 1]") if "cam1" in values else None
    if K1 is not None and not (np.isclose(K1[0, 0], K0[0, 0], rtol=0.01) and abs(K1[0, 2] - K0[0, 2] - calib.doffs) <= 0.5):
        logger.warning("%s: cam1 (fx %g, cx %g) is not cam0 shifted by doffs %g (fx %g, cx %g): not one rectified "
                       "pair? cam0 and doffs are used", path, K1[0, 0], K1[0, 2], calib.doffs, K0[0, 0], K0[0, 2])
    return calib


def _number(data: dict, key: str, path: Path) -> float:
    """``data[key]`` as a float, or :class:`CalibrationError` naming the key (a YAML ``true`` is
    not a number here)."""
    value = data[key]
    try:
        if isinstance(value, bool):
            raise TypeError
        return float(value)  # a text too: PyYAML reads 1e3 (no dot) as one
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{path}: {key} must be a number, got {brief(value)}") from None


def _whole(text) -> int:
    """A whole number of pixels from a text value (ValueError otherwise, also for 1242.7)."""
    value = float(text)
    if not value.is_integer():
        raise ValueError(f"{text!r} is not a whole number")
    return int(value)


def _array(data: dict, key: str, shape: tuple[int, ...] | None, path: Path, needed_when: str = "") -> np.ndarray:
    """``data[key]`` as a finite float array of ``shape``; a missing key is reported as required
    ``needed_when`` (e.g. "as rectified is false")."""
    try:
        value = np.asarray(data[key], float)
        value = value.reshape(shape) if shape else value.ravel()
        if not np.isfinite(value).all():
            raise ValueError
        return value
    except KeyError:
        raise CalibrationError(f"{path}: {key!r} is required {needed_when}".rstrip()) from None
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{path}: {key!r} must be a list of finite numbers of shape {shape or '(n,)'}") from None


def extrinsics_from_dict(data: dict, path: Path) -> Extrinsics:
    """The ``extrinsics:`` section: ``translation_m`` and ``rotation`` (3×3) or ``quaternion_xyzw``."""
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: 'extrinsics' must be a table with translation_m and rotation")
    unknown = sorted(set(data) - {"translation_m", "rotation", "quaternion_xyzw"}, key=str)
    if unknown:
        logger.warning("%s: ignoring unknown keys in extrinsics: %s (known: translation_m, rotation, quaternion_xyzw)",
                       path, ", ".join(map(str, unknown)))
    translation = _array(data, "translation_m", (3,), path, "in extrinsics")  # (at the origin: a camera on the ground)
    if np.abs(translation).max() > MAX_MOUNT_M:
        raise CalibrationError(f"{path}: extrinsics translation_m must be within 1 km, got {translation.tolist()}")
    if "quaternion_xyzw" in data:
        quaternion = _array(data, "quaternion_xyzw", (4,), path)
        if not usable(translation, quaternion):
            raise CalibrationError(f"{path}: extrinsics quaternion_xyzw must not be zero")
        rotation = quaternion_to_matrix(quaternion)
    else:
        rotation = _array(data, "rotation", (3, 3), path, "in extrinsics (or quaternion_xyzw)")
    if not is_rotation(rotation):
        raise CalibrationError(f"{path}: extrinsics rotation is not a rotation matrix")
    return Extrinsics(rotation=rotation, translation=translation, source="calibration")


def _load_table(path: Path) -> dict:
    try:
        if path.suffix.lower() == ".toml":
            return tomllib.loads(path.read_text())
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError, tomllib.TOMLDecodeError, RecursionError) as exc:
        # RecursionError: lists nested thousands deep
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationError(f"{path}: cannot parse the calibration file ({reason})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: calibration file must hold a mapping of keys (width, height, fx...)")
    return data


def terrainmap_calibration(path: Path) -> tuple[StereoCalibration, Extrinsics | None]:
    """Read terrainmap's YAML/TOML calibration format (see the module docstring)."""
    data = _load_table(path)
    rectified = data.get("rectified", True)
    if not isinstance(rectified, bool):
        raise CalibrationError(f"{path}: rectified must be true or false, got {brief(rectified)}")
    unknown = sorted(set(data) - set(_KNOWN), key=str)
    # `fx:` with no value is missing too; raw images' pinhole comes from K, dist, R and T instead
    missing = [key for key in _REQUIRED[: None if rectified else 2] if data.get(key) is None]
    if missing:
        also = f" (and {', '.join(map(str, unknown))} is no key of this format)" if unknown else ""
        raise CalibrationError(f"{path}: missing calibration keys: {', '.join(missing)}{also}")
    if unknown:  # a misspelt optional key would otherwise pass unnoticed
        logger.warning("%s: ignoring unknown calibration keys: %s (known: %s)", path, ", ".join(map(str, unknown)),
                       ", ".join(_KNOWN))
    numbers = {key: _number(data, key, path) for key in (*_REQUIRED, "doffs", "cx_right") if data.get(key) is not None}
    for key in ("width", "height"):
        if not numbers[key].is_integer():
            raise CalibrationError(f"{path}: {key} must be a whole number of pixels, got {brief(data[key])}")
        numbers[key] = int(numbers[key])
    cx_right = numbers.pop("cx_right", None)
    extra = {} if rectified else {
        key: _array(data, key, (3, 3) if key in ("K_left", "K_right", "R") else (3,) if key == "T" else None, path,
                    "as rectified is false")
        for key in _UNRECTIFIED
    }
    if not rectified:  # the matcher rectifies with K, dist, R and T: a pinhole given beside them is unused
        unused = [key for key in (*_REQUIRED[2:], "cx_right", "doffs") if data.get(key) is not None]
        if unused:
            logger.warning("%s: %s not used: with rectified false the rectified pinhole is derived from K_left, "
                           "K_right, dist_left, dist_right, R and T", path, ", ".join(unused))
        K = extra["K_left"].reshape(3, 3)  # nominal values; `info` shows the derived ones
        numbers.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], baseline_m=math.hypot(*extra["T"].ravel()), doffs=0.0)
        cx_right = None
    calib = StereoCalibration(
        **numbers,
        cx_right=cx_right,
        rectified=rectified,
        source=str(path),
        **extra,
    )
    extrinsics = extrinsics_from_dict(data["extrinsics"], path) if data.get("extrinsics") is not None else None
    return check_calibration(calib), extrinsics


def load_calibration_file(path: str | Path) -> tuple[StereoCalibration, Extrinsics | None]:
    """Any supported calibration file, chosen by name: ``.yaml/.yml/.toml`` (terrainmap format),
    Middlebury ``calib.txt`` (has ``cam0=``), or a KITTI ``.txt``."""
    if not isinstance(path, str | Path):
        raise CalibrationError(f"calibration must be the path of a file, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file does not exist")
    if path.suffix.lower() in (".yaml", ".yml", ".toml"):
        return terrainmap_calibration(path)
    if "cam0" in read_key_values(path, "="):
        return middlebury_calibration(path), None
    return kitti_calibration(path), None


def summary(calib: StereoCalibration | None) -> dict | None:
    """The calibration fields a human checks first (for ``describe()``): for raw images
    (``rectified`` false), the pinhole that rectifying them gives, which is what ``process`` uses."""
    if calib is None:
        return None
    pinhole = None if calib.rectified or not calib.width else matching_pinhole(calib)
    return {
        "fx": pinhole.fx if pinhole else calib.fx,
        "fy": pinhole.fy if pinhole else calib.fy,
        "cx": pinhole.cx if pinhole else calib.cx,
        "cy": pinhole.cy if pinhole else calib.cy,
        "cx_right": pinhole.cx + pinhole.doffs if pinhole else calib.cx_right,
        "baseline_m": pinhole.baseline_m if pinhole else calib.baseline_m,
        "doffs": 0.0 if pinhole else calib.doffs,
        "width": calib.width,
        "height": calib.height,
        "rectified": calib.rectified,
        "source": calib.source,
    }
