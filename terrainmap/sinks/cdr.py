"""A fast CDR encoder for ``grid_map_msgs/msg/GridMap``.

mcap-ros2-support encodes ``float32[]`` one element at a time (~9 ms for five 68×44 layers);
here the layers go in as raw little-endian bytes. Encoding is plain CDR as ROS 2 writes it:
a 4-byte encapsulation header (CDR_LE), then each field aligned to its own size, counted from
the end of that header. The schema is :data:`terrainmap.ros2defs.SCHEMAS` ``["grid_map_msgs/msg/GridMap"]``.
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

    def float32_array(self, values: np.ndarray) -> None:
        data = np.ascontiguousarray(values, dtype="<f4").tobytes()
        self.pack("I", len(data) // 4)
        self._put(data)  # already 4-aligned after the count

    def getvalue(self) -> bytes:
        return _CDR_LE + b"".join(self._parts)


def encode_grid_map(msg: dict) -> bytes:
    """CDR bytes of a GridMap given as the same nested dict mcap_ros2 would take.

    ``msg["data"]`` items are ``{"layout": {"dim": [...], "data_offset": int}, "data": array}``
    with the float32 data as a numpy array (any shape, written in C order).
    """
    buf = CdrBuffer()
    header = msg["header"]
    buf.pack("iI", header["stamp"]["sec"], header["stamp"]["nanosec"])
    buf.string(header["frame_id"])
    info = msg["info"]
    position, orientation = info["pose"]["position"], info["pose"]["orientation"]
    buf.pack("3d", info["resolution"], info["length_x"], info["length_y"])
    buf.pack("3d", position["x"], position["y"], position["z"])
    buf.pack("4d", orientation["x"], orientation["y"], orientation["z"], orientation["w"])
    buf.strings(msg["layers"])
    buf.strings(msg["basic_layers"])
    buf.pack("I", len(msg["data"]))
    for array in msg["data"]:
        buf.pack("I", len(array["layout"]["dim"]))
        for dim in array["layout"]["dim"]:
            buf.string(dim["label"])
            buf.pack("II", dim["size"], dim["stride"])
        buf.pack("I", array["layout"]["data_offset"])
        buf.float32_array(array["data"])
    buf.pack("HH", msg["outer_start_index"], msg["inner_start_index"])
    return buf.getvalue()
