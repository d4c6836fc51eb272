"""MCAP output with ROS 2 messages (CDR, profile ``ros2``) for ROS users.

Topics, all in the vehicle frame (``Extrinsics.vehicle_frame_id``: ``base_link``, or
``base_footprint`` where the log's tf has only that) and stamped with the source image's
``stamp_ns``:

- ``/terrainmap/grid_map`` ``grid_map_msgs/msg/GridMap``: layers ``elevation`` (m, NaN = no
  data; the only basic layer), ``slope`` (rad, NaN = no data), ``cost`` (when computed), ``label`` and
  ``valid`` (as floats). Layout: grid_map stores each layer column-major with index (0, 0) at
  the +x, +y corner: row i runs along −x, column j along −y, and the pose is the map centre.
  So the terrainmap cell ``[ix, iy]`` is grid_map cell ``(i, j) = (m0−1−ix, m1−1−iy)``, at flat
  position ``j·m0 + i`` of each layer's data (``dim[0]`` = ``column_index`` of size m1,
  ``dim[1]`` = ``row_index`` of size m0, as grid_map_ros writes it).
- ``/terrainmap/costmap`` ``nav_msgs/msg/OccupancyGrid`` (when the cost is computed): the
  ``cost`` layer as nav2 reads an occupancy grid, ``round(100 · cost)`` in 0..100 (100 = a
  confirmed obstacle's footprint or ground at least ``cost.max_slope_deg`` steep), −1 where the
  cost is unknown; row-major from the cell at ``(x_min, y_min)``, ``width`` = cells along x,
  origin at that cell's corner.
- ``/terrainmap/points`` ``sensor_msgs/msg/PointCloud2``: x, y, z FLOAT32 (7), label UINT32 (6), as
  PCL's ``PointXYZL`` has it; 16 bytes a point.
- ``/terrainmap/obstacles`` ``visualization_msgs/msg/MarkerArray``: a DELETEALL marker, then per
  confirmed obstacle a CUBE (namespace ``obstacles``) and a TEXT_VIEW_FACING label
  (``obstacle_labels``), marker id = track id; and per box of what else occupies the cost map
  (``FrameResult.occupied``) a grey CUBE and label in ``occupied`` and ``occupied_labels``, id n.
- ``/tf`` and ``/tf_static`` ``tf2_msgs/msg/TFMessage``: ``base_link`` → camera frame (edge by edge
  through the frames the log's tf has between them: ``Extrinsics.tf_path``), and on
  ``/tf`` each frame's ``odom → base_link`` where the source gave the vehicle pose.
- metadata record ``terrainmap``: version, config (TOML), the first frame's extrinsics (JSON) and
  ``extrinsics_changes`` (how many later frames moved the camera; each frame's pose is on the
  tf topics), source...

Every channel carries rosbag2's ``offered_qos_profiles`` metadata, so ``ros2 bag play``
publishes with it: reliable, and transient local (latched) for ``/tf_static`` and the costmap.
"""

from __future__ import annotations

import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from ..ros2defs import (
    MARKER_ADD,
    MARKER_CUBE,
    MARKER_DELETEALL,
    MARKER_TEXT_VIEW_FACING,
    POINTFIELD_FLOAT32,
    POINTFIELD_UINT32,
    SCHEMAS,
    grid_map_frame,
    grid_map_layer,
    header,
    offered_qos_profiles,
    pose,
    stamp,
    transform_stamped,
    yaw_quaternion,
)
from ..types import FrameResult, StereoFrame
from .base import (
    METADATA_NAME,
    Box,
    McapSink,
    grid_layers,
    points_record,
    shown_boxes,
)
from .cdr import encode_grid_map, encode_occupancy_grid, point_cloud2_head_tail

LATCHED_TOPICS = frozenset({"/tf_static", "/terrainmap/costmap"})
"""Offered transient local (:class:`Ros2Writer`): tf2's static listener, and map consumers such
as nav2's static layer, subscribe that way and get nothing from a volatile publisher."""


def grid_map_message(result: FrameResult) -> dict:
    """GridMap dict (layer data as numpy arrays, for :func:`~terrainmap.sinks.cdr.encode_grid_map`)."""
    layers = grid_layers(result)
    grid = result.grid.config
    return {
        "header": header(result.stamp_ns, result.extrinsics.vehicle_frame_id),
        "info": grid_map_frame(grid.x_min_m, grid.y_min_m, grid.shape, grid.cell_size_m),
        "layers": list(layers),
        "basic_layers": ["elevation"] if "elevation" in layers else [],
        "data": [grid_map_layer(a) for a in layers.values()],
        "outer_start_index": 0,
        "inner_start_index": 0,
    }


def occupancy_grid_message(result: FrameResult) -> dict | None:
    """OccupancyGrid dict of the ``cost`` layer (data an int8 numpy array, for
    :func:`~terrainmap.sinks.cdr.encode_occupancy_grid`), None where the frame has no cost."""
    if "cost" not in result.layers:
        return None
    cost = np.asarray(result.layers["cost"], np.float32)  # its shape checked by grid_map_message
    grid = result.grid.config
    occupancy = np.full(cost.shape, -1, np.int8)
    known = np.isfinite(cost)
    occupancy[known] = np.rint(100 * np.clip(cost[known], 0, 1))
    return {
        "header": header(result.stamp_ns, result.extrinsics.vehicle_frame_id),
        "info": {
            "map_load_time": stamp(result.stamp_ns),
            "resolution": grid.cell_size_m,
            "width": cost.shape[0],
            "height": cost.shape[1],
            "origin": pose((grid.x_min_m, grid.y_min_m, 0.0)),
        },
        "data": occupancy.T.ravel(),  # [iy, ix]: rows along y, each row along x
    }


CLOUD2_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
"""PointCloud2 point record, 16 bytes: the label is uint32 as in PCL's ``PointXYZL``, whose
``pcl::fromROSMsg`` matches fields by name and datatype (a uint8 label reads as 0 there), and the
floats of every point stay 4-byte aligned."""


def encode_point_cloud2(result: FrameResult, stride: int = 1) -> bytearray:
    """CDR bytes of a PointCloud2: one row of packed (x, y, z float32, label uint32) points, every
    ``stride``-th of the frame's."""
    n, step = len(result.points_vehicle[::stride]), CLOUD2_DTYPE.itemsize
    ros_type = {"f": POINTFIELD_FLOAT32, "u": POINTFIELD_UINT32}
    fields = [
        {"name": name, "offset": CLOUD2_DTYPE.fields[name][1], "datatype": ros_type[CLOUD2_DTYPE[name].kind],
         "count": 1}
        for name in CLOUD2_DTYPE.names
    ]
    head, tail = point_cloud2_head_tail(
        {
            "header": header(result.stamp_ns, result.extrinsics.vehicle_frame_id),
            "height": 1,
            "width": n,
            "fields": fields,
            "is_bigendian": False,
            "point_step": step,
            "row_step": step * n,
            "is_dense": bool(np.isfinite(result.points_vehicle[::stride]).all()),
        }
    )
    return points_record(result, head, tail, stride=stride, dtype=CLOUD2_DTYPE)


_NAMESPACES = {"obstacle": ("obstacles", "obstacle_labels"), "occupied": ("occupied", "occupied_labels")}
"""Marker namespaces (cubes, texts) of each group of :class:`~.base.Box`."""


def _markers(box: Box, stamp_ns: int, frame_id: str) -> list[dict]:
    obstacle = box.obstacle
    center = np.asarray(obstacle.center_m, float)
    size = np.asarray(obstacle.size_m, float)
    r, g, b, a = box.rgba
    cubes, texts = _NAMESPACES[box.group]
    common = {"header": header(stamp_ns, frame_id), "id": box.number, "action": MARKER_ADD}
    cube = {
        **common,
        "ns": cubes,
        "type": MARKER_CUBE,
        "pose": pose(center, yaw_quaternion(obstacle.yaw_rad)),
        "scale": {"x": size[0], "y": size[1], "z": size[2]},
        "color": {"r": r, "g": g, "b": b, "a": a},
    }
    text = {
        **common,
        "ns": texts,
        "type": MARKER_TEXT_VIEW_FACING,
        "pose": pose(center + [0.0, 0.0, size[2] / 2 + 0.3]),
        "scale": {"x": 0.0, "y": 0.0, "z": 0.4},
        "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0},
        "text": box.text,
    }
    return [cube, text]


def marker_array_message(result: FrameResult) -> dict:
    """MarkerArray dict: DELETEALL, then a cube and a text marker per box
    (:func:`~.base.shown_boxes`): namespaces ``obstacles``/``obstacle_labels`` with id = track id,
    and ``occupied``/``occupied_labels`` with id = n."""
    frame_id = result.extrinsics.vehicle_frame_id
    markers = [{"header": header(result.stamp_ns, frame_id), "action": MARKER_DELETEALL}]
    for box in shown_boxes(result):
        markers += _markers(box, result.stamp_ns, frame_id)
    return {"markers": markers}


def tf_message(stamp_ns: int, transforms: tuple[tuple[str, str, tuple, tuple], ...]) -> dict:
    """TFMessage dict of ``(parent, child, translation, rotation xyzw)`` tuples."""
    return {"transforms": [transform_stamped(stamp_ns, *transform) for transform in transforms]}


class Ros2Writer(Writer):
    """mcap_ros2's writer whose channels carry rosbag2's QoS metadata
    (:func:`~terrainmap.ros2defs.offered_qos_profiles`; transient local for the ``latched``
    topics), plus ``write_encoded`` for messages this package encodes itself."""

    def __init__(self, output, *, compression: CompressionType, latched: frozenset[str] = frozenset()):
        super().__init__(output, compression=compression)
        self._latched = latched

    def _channel(self, topic: str, schema: Schema) -> int:
        if topic not in self._channel_ids:
            self._channel_ids[topic] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema.id,
                metadata={"offered_qos_profiles": offered_qos_profiles(topic in self._latched,
                                                                       100 if topic == "/tf" else 10)},
            )
        return self._channel_ids[topic]

    def write_message(self, topic: str, schema: Schema, message, log_time=None, publish_time=None, sequence=0):
        self._channel(topic, schema)  # registered here, with its QoS, before mcap_ros2 would
        super().write_message(topic, schema, message, log_time, publish_time, sequence)

    def write_encoded(self, topic: str, schema: Schema, data: bytes | bytearray, log_time: int) -> None:
        self._writer.add_message(
            channel_id=self._channel(topic, schema), log_time=log_time, publish_time=log_time, sequence=0, data=data
        )


class Ros2McapSink(McapSink):
    """Writes each frame as ROS 2 CDR messages to an MCAP file (see the module docstring).

    Parameters are those of :class:`~terrainmap.sinks.base.McapSink`, plus ``compression``
    (``"lz4"``, ``"zstd"`` or ``"none"``; see :func:`terrainmap.sinks.open_mcap_sink`).
    """

    def __init__(self, path, *, config, metadata=None, compression: str = "lz4"):
        self._compression = CompressionType[compression.upper()]
        self._schemas: dict[str, Schema] = {}
        super().__init__(path, config=config, metadata=metadata)

    def _open(self, stream) -> None:
        self._writer = Ros2Writer(stream, compression=self._compression, latched=LATCHED_TOPICS)

    def _schema(self, type_name: str) -> Schema:
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_msgdef(type_name, SCHEMAS[type_name])
        return self._schemas[type_name]

    def _log(self, topic: str, type_name: str, message: dict, stamp_ns: int) -> None:
        self._writer.write_message(
            topic, self._schema(type_name), message, log_time=stamp_ns, publish_time=stamp_ns
        )

    def _write_frame(self, frame: StereoFrame, result: FrameResult) -> None:
        t = frame.stamp_ns
        for topic, transforms in self._transforms(frame, result):
            self._log(topic, "tf2_msgs/msg/TFMessage", tf_message(t, transforms), t)
        grid_schema = self._schema("grid_map_msgs/msg/GridMap")
        self._writer.write_encoded("/terrainmap/grid_map", grid_schema, encode_grid_map(grid_map_message(result)), t)
        costmap = occupancy_grid_message(result)
        if costmap is not None:
            schema = self._schema("nav_msgs/msg/OccupancyGrid")
            self._writer.write_encoded("/terrainmap/costmap", schema, encode_occupancy_grid(costmap), t)
        cloud_schema = self._schema("sensor_msgs/msg/PointCloud2")
        points = encode_point_cloud2(result, self._point_stride(result))
        self._writer.write_encoded("/terrainmap/points", cloud_schema, points, t)
        self._log("/terrainmap/obstacles", "visualization_msgs/msg/MarkerArray", marker_array_message(result), t)

    def _finish(self, metadata: dict[str, str]) -> None:
        self._writer.add_metadata(METADATA_NAME, metadata)
        self._writer.finish()
