"""Fast CDR encoders for the ROS 2 messages with big arrays: ``grid_map_msgs/msg/GridMap``,
``nav_msgs/msg/OccupancyGrid`` and ``sensor_msgs/msg/PointCloud2``.

mcap-ros2-support encodes ``float32[]`` one element at a time (~9 ms for five 68×44 layers)
and copies a 4 MB ``uint8[]`` twice; here the arrays go in as raw little-endian bytes. Encoding is plain CDR as ROS 2 writes it:
a 4-byte encapsulation header (CDR_LE), then each field aligned to its own size, counted from
the end of that header. The schemas are those of :data:`terrainmap.ros2defs.SCHEMAS`.
"""

from __future__ import annotations

import struct

import numpy as np

_CDR_LE = b"\x00\x01\x00\x00"


class CdrBuffer:
    """Little-endian CDR writer with alignment (the few primitives GridMap needs)."""

    def __init__(self):
        self._parts: list[bytes] = []
        self._size = 0

    def _put(self, data: bytes) -> None:
        self._parts.append(data)
        self._size += len(data)

    def _align(self, n: int) -> None:
        pad = -self._size % n
        if pad:
            self._put(b"\x00" * pad)

    def pack(self, fmt: str, *values) -> None:
        """Write primitives of one size (``fmt`` a :mod:`struct` code like ``"d"`` or ``"3d"``)."""
        data = struct.pack("<" + fmt, *values)
        self._align(struct.calcsize("<" + fmt[-1]))
        self._put(data)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.pack("I", len(data))
        self._put(data)

    def strings(self, texts: list[str]) -> None:
        self.pack("I", len(texts))
        for text in texts:
            self.string(text)

    def array(self, values: np.ndarray, dtype: str) -> None:
        """A sequence of one primitive of at most 4 bytes (``dtype``: ``"<f4"``, ``"i1"``...)."""
        data = np.ascontiguousarray(values, dtype=dtype)
        self.pack("I", data.size)
        self._put(data.tobytes())  # aligned after the 4-byte count

    def pose(self, pose: dict) -> None:
        """A ``geometry_msgs/Pose`` dict (see :func:`terrainmap.ros2defs.pose`)."""
        position, orientation = pose["position"], pose["orientation"]
        self.pack("3d", position["x"], position["y"], position["z"])
        self.pack("4d", orientation["x"], orientation["y"], orientation["z"], orientation["w"])

    def header(self, header: dict) -> None:
        """A ``std_msgs/Header`` dict (see :func:`terrainmap.ros2defs.header`)."""
        self.pack("iI", header["stamp"]["sec"], header["stamp"]["nanosec"])
        self.string(header["frame_id"])

    def getvalue(self) -> bytes:
        return _CDR_LE + b"".join(self._parts)


def encode_grid_map(msg: dict) -> bytes:
    """CDR bytes of a GridMap given as the same nested dict mcap_ros2 would take.

    ``msg["data"]`` items are ``{"layout": {"dim": [...], "data_offset": int}, "data": array}``
    with the float32 data as a numpy array (any shape, written in C order).
    """
    buf = CdrBuffer()
    buf.header(msg["header"])
    info = msg["info"]
    buf.pack("3d", info["resolution"], info["length_x"], info["length_y"])
    buf.pose(info["pose"])
    buf.strings(msg["layers"])
    buf.strings(msg["basic_layers"])
    buf.pack("I", len(msg["data"]))
    for array in msg["data"]:
        buf.pack("I", len(array["layout"]["dim"]))
        for dim in array["layout"]["dim"]:
            buf.string(dim["label"])
            buf.pack("II", dim["size"], dim["stride"])
        buf.pack("I", array["layout"]["data_offset"])
        buf.array(array["data"], "<f4")
    buf.pack("HH", msg["outer_start_index"], msg["inner_start_index"])
    return buf.getvalue()


def encode_occupancy_grid(msg: dict) -> bytes:
    """CDR bytes of an OccupancyGrid given as the nested dict mcap_ros2 would take, with
    ``msg["data"]`` an int8 numpy array (row-major: ``width`` cells along x per row)."""
    buf = CdrBuffer()
    buf.header(msg["header"])
    info = msg["info"]
    buf.pack("iI", info["map_load_time"]["sec"], info["map_load_time"]["nanosec"])
    buf.pack("f", info["resolution"])
    buf.pack("II", info["width"], info["height"])
    buf.pose(info["origin"])
    buf.array(msg["data"], "i1")
    return buf.getvalue()


def point_cloud2_head_tail(msg: dict) -> tuple[bytes, bytes]:
    """CDR of a PointCloud2 dict split around its point data: ``(bytes before, bytes after)``.

    ``msg`` holds every field but ``data``; the caller puts the ``row_step · height`` data bytes
    between the two parts (the length prefix is already in the head; ``is_dense`` is the tail).
    """
    buf = CdrBuffer()
    buf.header(msg["header"])
    buf.pack("II", msg["height"], msg["width"])
    buf.pack("I", len(msg["fields"]))
    for field in msg["fields"]:
        buf.string(field["name"])
        buf.pack("I", field["offset"])
        buf.pack("B", field["datatype"])
        buf.pack("I", field["count"])
    buf.pack("?", msg["is_bigendian"])
    buf.pack("II", msg["point_step"], msg["row_step"])
    buf.pack("I", msg["row_step"] * msg["height"])
    return buf.getvalue(), struct.pack("?", msg["is_dense"])
