"""ROS 2 messages of a simulated log, both ways: dicts for ``mcap_ros2``'s writer and back.

Kept in one place so that the writer (:mod:`terrainmap.sim.mcap_log`) and the truth reader
(:mod:`terrainmap.sim.truth`) cannot drift apart. Layouts:

- obstacles: one ``visualization_msgs/Marker`` per obstacle, ``ns`` = kind, ``id`` = obstacle
  id (stable over frames), ``type`` CUBE (box) or SPHERE (ellipsoid), ``pose`` = centre and yaw,
  ``scale`` = size (m), frame ``odom``.
- terrain: ``grid_map_msgs/GridMap`` with one layer ``elevation`` in frame ``odom``; grid_map's
  layout is column-major with index (0, 0) at the +x, +y corner, so node ``[ix, iy]`` is at flat
  position ``(ny−1−iy)·nx + (nx−1−ix)``; the pose is the map centre.
- images: ``sensor_msgs/Image`` (``mono8``, ``rgb8``, ``32FC1`` little-endian).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..ros2defs import grid_map_frame, grid_map_layer, header, pose, quaternion_from_matrix, yaw_quaternion
from .heightfield import Heightfield
from .obstacles import KINDS, ObstacleBox

MARKER_CUBE, MARKER_SPHERE = 1, 2
ENCODINGS = {"mono8": (np.uint8, 1), "rgb8": (np.uint8, 3), "32FC1": (np.dtype("<f4"), 1)}


def image_message(image: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    """``sensor_msgs/Image`` dict of a uint8 (H, W) / (H, W, 3) or float32 (H, W) image."""
    h, w = image.shape[:2]
    encoding = "32FC1" if image.dtype == np.float32 else ("rgb8" if image.ndim == 3 else "mono8")
    data = np.ascontiguousarray(image, dtype=ENCODINGS[encoding][0]).tobytes()
    return {
        "header": header(stamp_ns, frame_id), "height": h, "width": w, "encoding": encoding,
        "is_bigendian": 0, "step": len(data) // h, "data": data,
    }


def image_array(msg, topic: str) -> np.ndarray:
    """The array of a decoded ``sensor_msgs/Image`` (mono8, rgb8 or 32FC1)."""
    if msg.encoding not in ENCODINGS:
        raise InputError(f"{topic}: image encoding {msg.encoding!r} is not one of {', '.join(ENCODINGS)}")
    dtype, channels = ENCODINGS[msg.encoding]
    flat = np.frombuffer(bytes(msg.data), dtype=dtype)
    if flat.size != msg.height * msg.width * channels:
        raise InputError(f"{topic}: image data holds {flat.size} values, not {msg.height}×{msg.width}×{channels}")
    return flat.reshape((msg.height, msg.width, channels) if channels > 1 else (msg.height, msg.width))


def marker_array_message(boxes: list[ObstacleBox], stamp_ns: int, frame_id: str) -> dict:
    """``visualization_msgs/MarkerArray`` dict of the obstacles (module docstring)."""
    markers = []
    for box in boxes:
        r, g, b = KINDS[box.kind][2]
        sx, sy, sz = (float(v) for v in box.size_m)
        markers.append({
            "header": header(stamp_ns, frame_id), "ns": box.kind, "id": box.id,
            "type": MARKER_CUBE if box.shape == "box" else MARKER_SPHERE, "action": 0,
            "pose": pose(box.center_m, yaw_quaternion(box.yaw_rad)),
            "scale": {"x": sx, "y": sy, "z": sz}, "color": {"r": r, "g": g, "b": b, "a": 0.8},
            "frame_locked": False,
        })
    return {"markers": markers}


def obstacles_from_markers(msg, terrain: Heightfield, velocities: dict[int, np.ndarray]) -> list[ObstacleBox]:
    """Obstacles of a decoded MarkerArray; ``velocities`` by id (from the log's metadata)."""
    boxes = []
    for m in msg.markers:
        q = m.pose.orientation
        yaw = float(2 * np.arctan2(q.z, q.w))
        center = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
        size = np.array([m.scale.x, m.scale.y, m.scale.z])
        shape = "box" if m.type == MARKER_CUBE else "ellipsoid"
        ground = float(terrain.height(center[0], center[1]))
        height = center[2] + size[2] / 2 - ground  # top above the terrain at the centre, as ObstacleBox
        boxes.append(ObstacleBox(
            id=int(m.id), kind=m.ns, shape=shape, center_m=center, size_m=size, yaw_rad=yaw,
            height_m=float(height), velocity_mps=velocities.get(int(m.id), np.zeros(3)),
        ))
    return boxes


def pose_message(rotation: np.ndarray, position: np.ndarray, stamp_ns: int, frame_id: str) -> dict:
    """``geometry_msgs/PoseStamped`` dict."""
    return {"header": header(stamp_ns, frame_id), "pose": pose(position, quaternion_from_matrix(rotation))}


def grid_map_message(terrain: Heightfield, stamp_ns: int, frame_id: str) -> dict:
    """``grid_map_msgs/GridMap`` dict with the ``elevation`` layer (module docstring)."""
    layer = grid_map_layer(terrain.z)
    layer["data"] = layer["data"].tolist()  # mcap_ros2's encoder takes lists
    return {
        "header": header(stamp_ns, frame_id),
        "info": grid_map_frame(terrain.x_min_m, terrain.y_min_m, terrain.shape, terrain.resolution_m),
        "layers": ["elevation"], "basic_layers": ["elevation"],
        "data": [layer], "outer_start_index": 0, "inner_start_index": 0,
    }


def heightfield_from_grid_map(msg, topic: str) -> Heightfield:
    """The terrain of a decoded GridMap written by :func:`grid_map_message`."""
    if "elevation" not in msg.layers:
        raise InputError(f"{topic}: GridMap has no 'elevation' layer (layers: {', '.join(msg.layers)})")
    if len(msg.data) != len(msg.layers):
        raise InputError(f"{topic}: GridMap has {len(msg.layers)} layers but {len(msg.data)} data arrays")
    info = msg.info
    res = info.resolution
    numbers = (res, info.length_x, info.length_y, info.pose.position.x, info.pose.position.y)
    if not (np.isfinite(numbers).all() and res > 0 and info.length_x >= res and info.length_y >= res):
        raise InputError(f"{topic}: GridMap of {info.length_x:g}×{info.length_y:g} m at {res:g} m resolution is no grid")
    nx, ny = round(info.length_x / res), round(info.length_y / res)
    values = np.asarray(msg.data[msg.layers.index("elevation")].data, dtype=np.float32)
    if values.size != nx * ny or msg.outer_start_index or msg.inner_start_index:
        raise InputError(f"{topic}: elevation layer is not a plain {nx}×{ny} grid")
    z = values.reshape(ny, nx).T[::-1, ::-1]
    x_min = info.pose.position.x - info.length_x / 2
    y_min = info.pose.position.y - info.length_y / 2
    return Heightfield(z, x_min, y_min, res)
