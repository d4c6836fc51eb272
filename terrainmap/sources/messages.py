"""Reading the fields terrainmap needs from ROS 2, ROS 1 (rosbags) and Foxglove messages.

The three families name things differently (ROS 2 ``header.stamp.nanosec`` and ``k``/``p``,
ROS 1 ``K``/``P``, Foxglove ``timestamp.nanos`` and ``K``/``P``); these helpers hide that.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from ..errors import CalibrationError, InputError, brief
from ..types import StereoCalibration
from . import calibration as calib_io
from .images import decode_compressed, decode_raw

RAW_IMAGE_TYPES = ("sensor_msgs/msg/Image", "foxglove.RawImage")
COMPRESSED_IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage", "foxglove.CompressedImage")
IMAGE_TYPES = RAW_IMAGE_TYPES + COMPRESSED_IMAGE_TYPES
VIDEO_TYPES = ("foxglove.CompressedVideo", "foxglove_msgs/msg/CompressedVideo", "foxglove_msgs/CompressedVideo")
"""Video streams (H.264, H.265, ...): not read; named in the error when a log has only those."""
CALIBRATION_TYPES = ("sensor_msgs/msg/CameraInfo", "foxglove.CameraCalibration")
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage", "foxglove.FrameTransform", "foxglove.FrameTransforms")
"""``tf/tfMessage``: ROS 1's tf (before tf2), as older bags record ``/tf``; the same fields."""


def normalize_type(name: str) -> str:
    """``sensor_msgs/Image`` (ROS 1 style) → ``sensor_msgs/msg/Image``; others unchanged."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def stamp_ns(msg) -> int:
    """Header stamp (ROS) or ``timestamp`` (Foxglove) in nanoseconds."""
    if hasattr(msg, "header"):
        stamp = msg.header.stamp
        return int(stamp.sec) * 1_000_000_000 + int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))
    return int(msg.timestamp.seconds) * 1_000_000_000 + int(msg.timestamp.nanos)


def frame_id(msg) -> str:
    """The message's frame id without a leading '/'; ``camera_optical`` where the driver left it
    empty (a transform to an unnamed frame is one tf2 ignores and Foxglove cannot name) or the
    message has none (Foxglove's image and calibration schemas before August 2022)."""
    name = str(msg.header.frame_id if hasattr(msg, "header") else getattr(msg, "frame_id", "")).lstrip("/")
    return name or "camera_optical"


def image_array(msg, msg_type: str, topic: str) -> np.ndarray:
    """Decode an image message into an RGB / mono array (uint8 or uint16)."""
    if msg_type in COMPRESSED_IMAGE_TYPES:
        if "compresseddepth" in str(getattr(msg, "format", "")).lower():  # a depth map behind a 12-byte header
            raise InputError(f"{topic}: a compressedDepth image (format {msg.format!r}) is a depth map, not a "
                             "camera image; choose the cameras' image topics")
        return decode_compressed(msg.data, topic)
    return decode_raw(
        msg.data,
        width=int(msg.width),
        height=int(msg.height),
        step=int(msg.step),
        encoding=str(msg.encoding),
        name=topic,
        big_endian=bool(getattr(msg, "is_bigendian", False)),
    )


def _field(msg, name: str) -> np.ndarray:
    """``k`` (ROS 2) or ``K`` (ROS 1, Foxglove) as a float array."""
    return np.asarray(getattr(msg, name.lower()) if hasattr(msg, name.lower()) else getattr(msg, name), float)


PINHOLE_DISTORTION_MODELS = frozenset({"plumb_bob", "rational_polynomial", ""})
"""Distortion models OpenCV's pinhole model applies with the coefficients in ROS's order
(REP 104; ``""``: unset, taken as plumb_bob). ``equidistant`` (fisheye) and others are not."""


def camera_info(msg, topic: str) -> dict:
    """K (3×3), D, distortion model, R (3×3), P (3×4), width, height, frame id of a CameraInfo /
    CameraCalibration, for the images as published: a CameraInfo's region of interest and
    binning (``roi``, ``binning_x/y``: the images are a window of the calibrated resolution,
    downsampled) are applied as ROS's image_geometry does, the window's offset taken off the
    principal points, then x and y divided by the binning; ``roi`` is True when a window was applied."""
    K, D, R, P = (_field(msg, name) for name in ("K", "D", "R", "P"))
    if K.size != 9:
        raise CalibrationError(f"{topic}: camera calibration without a 3×3 K matrix")
    info = {
        "K": K.reshape(3, 3),
        "D": D.ravel() if D.size else np.zeros(5),  # empty: no distortion
        "model": str(getattr(msg, "distortion_model", "") or ""),
        "R": R.reshape(3, 3) if R.size == 9 and R.any() else np.eye(3),  # all zero: not set (monocular)
        "P": P.reshape(3, 4) if P.size == 12 else None,
        "width": int(msg.width),
        "height": int(msg.height),
        "frame_id": frame_id(msg),
    }
    if info["P"] is None or not info["P"][0, 0]:
        raise CalibrationError(f"{topic}: camera calibration without a projection matrix P")
    return _window(info, msg, topic)


def _window(info: dict, msg, topic: str) -> dict:
    """``info`` for the region of interest and binning of a CameraInfo (:func:`camera_info`);
    unchanged for a message without them (Foxglove) or with the defaults (no window, binning 0 or 1)."""
    roi = getattr(msg, "roi", None)
    x0, y0, width, height = (int(getattr(roi, name, 0)) for name in ("x_offset", "y_offset", "width", "height"))
    bx, by = (max(int(getattr(msg, name, 0)), 1) for name in ("binning_x", "binning_y"))
    windowed = width > 0 and height > 0 and (x0, y0, width, height) != (0, 0, info["width"], info["height"])
    if not windowed and bx == by == 1:
        return info
    size = (width, height) if windowed else (info["width"], info["height"])
    if size[0] and (size[0] < bx or size[1] < by):
        raise CalibrationError(f"{topic}: binning {bx}×{by} leaves no pixel of the {size[0]}×{size[1]} image")
    if windowed and info["width"] and (x0 + width > info["width"] or y0 + height > info["height"]):
        raise CalibrationError(f"{topic}: region of interest {width}×{height} at ({x0}, {y0}) reaches outside the "
                               f"calibrated {info['width']}×{info['height']} image")
    K, P = info["K"].copy(), info["P"].copy()
    if windowed:
        K[:2, 2] -= (x0, y0)
        P[:2, 2] -= (x0, y0)
    K[0], P[0] = K[0] / bx, P[0] / bx
    K[1], P[1] = K[1] / by, P[1] / by
    return {**info, "K": K, "P": P, "width": size[0] // bx, "height": size[1] // by, "roi": windowed}


def calibration_from_infos(
    left: dict, right: dict, *, rectified_images: bool, source: str, right_in_left: np.ndarray | None = None
) -> StereoCalibration:
    """Stereo calibration from the left and right camera infos (ROS stereo convention).

    Rectified images (``image_rect*`` topics, or no distortion and no rectifying rotation R):
    pinhole from P, baseline
    ``(P_left[0,3] − P_right[0,3]) / fx`` (= ``−P_right[0,3]/P_right[0,0]`` in ROS).
    Raw distorted images: ``rectified=False`` with K, D and the right camera's pose wrt the left,
    ``R = R_rᵀ R_l``, ``T = −R_rᵀ (B, 0, 0)`` (R_l, R_r: the rectifying rotations of the infos).

    Where the right P's Tx equals the left's (two cameras calibrated one by one), the stereo
    geometry comes from ``right_in_left``, the 4×4 pose of the right camera's frame in the left's
    (from tf): raw images (undistorted ones too) take its rotation and translation as the pair's R,
    T and are rectified with them; images of ``rectified_images`` topics must already be a
    rectified pair: a shift along +x (the baseline, off the axis by at most 1 % of it), turned by
    less than half a pixel at fx, with rows that agree (cy and fy within half a pixel).
    """
    sizes = [(info["width"], info["height"]) for info in (left, right)]
    if all(any(size) for size in sizes) and sizes[0] != sizes[1]:  # (0, 0): a driver that leaves it unset
        raise CalibrationError(f"{source}: the left camera info is {left['width']}×{left['height']} px but the "
                               f"right one {right['width']}×{right['height']}: not one stereo pair")
    for side, info in (("left", left), ("right", right)):
        for key, what in (("P", "projection P"), ("R", "rectifying rotation R")):
            if not np.all(np.isfinite(info[key])):
                raise CalibrationError(f"{source}: the {side} camera info's {what} is not finite: {info[key].tolist()}")
    from_tf = left["P"][0, 3] == right["P"][0, 3]  # a driver that leaves Tx at 0 (mono calibrations)
    # Undistorted cameras calibrated one by one are no rectified pair: rectify them with tf's pose.
    rectified = rectified_images or not from_tf and all(
        not np.any(info["D"]) and np.allclose(info["R"], np.eye(3), atol=1e-9) for info in (left, right)
    )
    if rectified and not np.allclose(np.diag(right["P"])[:2], np.diag(left["P"])[:2], rtol=0.01):
        raise CalibrationError(f"{source}: the left and right projections P have different focal lengths "
                               f"(fx {left['P'][0, 0]:g} and {right['P'][0, 0]:g}, fy {left['P'][1, 1]:g} and "
                               f"{right['P'][1, 1]:g} px): not one rectified stereo pair")
    if rectified and abs(right["P"][1, 2] - left["P"][1, 2]) > 0.5:  # a rectified pair's rows line up
        raise CalibrationError(f"{source}: the left and right projections P have principal points at different rows "
                               f"(cy {left['P'][1, 2]:g} and {right['P'][1, 2]:g} px): not one rectified stereo pair")
    if from_tf:
        right = {**right, "P": _right_projection(left, right, right_in_left, rectified, source)}
    for side, info in (("left", left), ("right", right)):
        if rectified and info.get("roi") and np.any(info["D"]):
            raise CalibrationError(
                f"{source}: the {side} camera info has a region of interest and distortion: where its window lies "
                "in rectified images is not known; use the raw image topics or --calibration"
            )
        if not rectified and np.any(info["D"]) and info["model"] not in PINHOLE_DISTORTION_MODELS:
            raise CalibrationError(
                f"{source}: the {side} camera's distortion model {brief(info['model'])} is not supported for "
                f"rectifying raw images (only {', '.join(sorted(PINHOLE_DISTORTION_MODELS - {''}))}); "
                "use rectified image topics or --calibration"
            )
    if from_tf:
        source += f", stereo pose from tf ({left['frame_id']} → {right['frame_id']})"
    calib = calib_io.from_projections(
        left["P"], right["P"], source=source, width=left["width"], height=left["height"]
    )
    if rectified:
        return calib
    if from_tf:  # p_right = R·p_left + T (OpenCV's stereo R, T)
        R, T = right_in_left[:3, :3].T, -right_in_left[:3, :3].T @ right_in_left[:3, 3]
    else:
        R, T = right["R"].T @ left["R"], -right["R"].T @ np.array([calib.baseline_m, 0.0, 0.0])
    return calib_io.check_calibration(dataclasses.replace(  # the distortion and R, T checked too: where they come in
        calib, rectified=False, K_left=left["K"], K_right=right["K"], dist_left=left["D"], dist_right=right["D"], R=R, T=T
    ))


def _right_projection(left: dict, right: dict, right_in_left: np.ndarray | None, rectified: bool, source: str):
    """The right camera's P with Tx = left Tx − fx·B, B from ``right_in_left`` (see
    :func:`calibration_from_infos`), or :class:`CalibrationError` saying why not."""
    frames = f"{left['frame_id']} → {right['frame_id']}"
    if right_in_left is None:
        raise CalibrationError(
            f"{source}: the right camera's projection P has the same Tx as the left, so the baseline is unknown "
            f"(ROS stereo: Tx = −fx·baseline), and tf does not relate the cameras' frames ({frames}); "
            "pass --calibration with baseline_m"
        )
    t = right_in_left[:3, 3]
    angle = np.arccos(np.clip((np.trace(right_in_left[:3, :3]) - 1) / 2, -1, 1))
    (fx, fy, cy), (fy_right, cy_right) = left["P"][[0, 1, 1], [0, 1, 2]], right["P"][1, 1:3]
    aligned = np.hypot(t[1], t[2]) <= 0.01 * t[0] and fx * angle <= 0.5 and abs(fy_right - fy) <= 0.5  # cy: checked before
    if not (t[0] > 0 and (not rectified or aligned)):
        raise CalibrationError(
            f"{source}: tf places the right camera at ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m turned by "
            f"{np.degrees(angle):.2f}° from the left ({frames}), with cy {cy:g} and {cy_right:g} px: not "
            + ("a rectified pair (rows half a pixel apart at most); use the raw image topics, which terrainmap "
               "rectifies with this pose, or --calibration" if rectified else "to its right; pass --calibration")
        )
    P = right["P"].copy()
    P[0, 3] = left["P"][0, 3] - left["P"][0, 0] * float(np.linalg.norm(t) if not rectified else t[0])
    return P


def same_data(a, b) -> bool:
    """Whether two image messages (ROS or Foxglove, raw or compressed) hold the same bytes."""
    return bytes(a.data) == bytes(b.data)


def transforms(msg, msg_type: str) -> Iterator[tuple[int, str, str, list[float], list[float]]]:
    """(stamp ns, parent, child, translation xyz, quaternion xyzw) of each transform in a TF message."""
    if msg_type in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"):
        for t in msg.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            yield stamp_ns(t), t.header.frame_id, t.child_frame_id, [tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]
        return
    for t in msg.transforms if msg_type == "foxglove.FrameTransforms" else [msg]:
        tr, q = t.translation, t.rotation
        # a rotation left unset (a mount that only shifts) is no rotation, as Foxglove draws it
        xyzw = [q.x, q.y, q.z, q.w] if t.HasField("rotation") else [0.0, 0.0, 0.0, 1.0]
        yield stamp_ns(t), t.parent_frame_id, t.child_frame_id, [tr.x, tr.y, tr.z], xyzw
