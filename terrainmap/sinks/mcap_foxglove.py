"""MCAP output with Foxglove protobuf schemas (the default flavour): opens in Foxglove with no setup.

Topics, all in the vehicle frame (``Extrinsics.vehicle_frame_id``: ``base_link``, or
``base_footprint`` where the log's tf has only that) and stamped with the source image's
``stamp_ns`` (log time, publish time and message timestamp):

- ``/terrainmap/grid`` ``foxglove.Grid``: fields ``elevation`` (float32, m, NaN = no data),
  ``slope`` (float32, rad, NaN = no data), ``cost`` (float32, when computed), ``label`` (uint8 Label),
  ``valid`` (uint8 0/1). Layout: foxglove.Grid is row-major with rows along y and columns along
  x, so ``column_count = m0`` and the cell at byte offset ``(iy·m0 + ix)·cell_stride`` is the
  terrainmap cell ``[ix, iy]``, centred at ``(x_min + (ix+½)c, y_min + (iy+½)c)``; the pose is
  the grid's corner ``(x_min_m, y_min_m, 0)`` with identity orientation.
- ``/terrainmap/surface`` ``foxglove.SceneUpdate``: entity ``terrain``, a triangle list over the
  cell centres at the surface's elevation where the cells hold data, coloured by slope (green 0°
  to red ≥ 30°): foxglove.Grid is drawn flat, this is the surface in 3D (:func:`surface_message`).
- ``/terrainmap/points`` ``foxglove.PointCloud``: x, y, z float32 and uint8 ``label``.
- ``/terrainmap/obstacles`` ``foxglove.SceneUpdate``: deletes all previous entities, then one
  entity per confirmed obstacle (id ``obstacle/<track id>``) with a cube (coloured by kind) and a
  text ``"<id> <kind> <height> m"``, and a grey one per box of what else occupies the cost map
  (id ``occupied/<n>``, text ``"part of <id>"`` or ``"<id> unseen"``; ``FrameResult.occupied``).
- ``/tf`` and ``/tf_static`` ``foxglove.FrameTransforms``: ``base_link`` → camera frame (edge by edge
  through the frames the log's tf has between them: ``Extrinsics.tf_path``), and on
  ``/tf`` each frame's ``odom → base_link`` where the source gave the vehicle pose (so Foxglove
  can show the drive in the odometry frame).
- metadata record ``terrainmap``: version, config (TOML), the first frame's extrinsics (JSON) and
  ``extrinsics_changes`` (how many later frames moved the camera; each frame's pose is on the
  tf topics), source...
"""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.well_known import MessageEncoding
from mcap.writer import CompressionType
from mcap_protobuf.schema import register_schema
from mcap_protobuf.writer import Writer

from ..grid import cell_centers
from ..ros2defs import yaw_quaternion
from ..types import FrameResult, StereoFrame
from .base import (
    FLOAT_LAYERS,
    METADATA_NAME,
    POINT_DTYPE,
    SLOPE_RANGE_RAD,
    Box,
    McapSink,
    colormap,
    grid_layers,
    points_record,
    shown_boxes,
    surface_triangles,
)

FLOAT32 = PackedElementField.FLOAT32  # 7
UINT8 = PackedElementField.UINT8  # 1 (ROS numbers UINT8 as 2)


def _timestamp(stamp_ns: int) -> Timestamp:
    sec, nanos = divmod(int(stamp_ns), 1_000_000_000)
    return Timestamp(seconds=sec, nanos=nanos)


def _pose(position, quaternion=(0.0, 0.0, 0.0, 1.0)) -> Pose:
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = quaternion
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def _fields(dtype: np.dtype) -> list[PackedElementField]:
    return [
        PackedElementField(name=name, offset=dtype.fields[name][1], type=FLOAT32 if dtype[name].kind == "f" else UINT8)
        for name in dtype.names
    ]


def grid_message(result: FrameResult) -> Grid:
    """``foxglove.Grid`` of the result's layers (see the module docstring for the layout)."""
    layers = grid_layers(result)
    grid = result.grid.config
    m0, _ = grid.shape
    dtype = np.dtype([(name, "<f4" if name in FLOAT_LAYERS else "u1") for name in layers])
    cells = np.empty(grid.shape[::-1], dtype=dtype)  # (m1, m0): rows along y, columns along x
    for name, array in layers.items():
        cells[name] = array.T
    return Grid(
        timestamp=_timestamp(result.stamp_ns),
        frame_id=result.extrinsics.vehicle_frame_id,
        pose=_pose((grid.x_min_m, grid.y_min_m, 0.0)),
        column_count=m0,
        cell_size=Vector2(x=grid.cell_size_m, y=grid.cell_size_m),
        row_stride=m0 * dtype.itemsize,
        cell_stride=dtype.itemsize,
        fields=_fields(dtype),
        data=cells.tobytes(),
    )


def encode_points(result: FrameResult, stride: int = 1) -> bytearray:
    """Serialized ``foxglove.PointCloud`` with x, y, z (float32, m, vehicle frame) and uint8
    ``label`` of every ``stride``-th point, built without protobuf copying the point data.

    Protobuf's own serializer takes ~10 ms for 300k points (4 MB); here the small fields are
    serialized by protobuf and the ``data`` field (bytes, number 6) is appended by hand
    (wire format: tag, varint length, bytes; fields may come in any order).
    """
    head = PointCloud(
        timestamp=_timestamp(result.stamp_ns),
        frame_id=result.extrinsics.vehicle_frame_id,
        pose=_pose((0.0, 0.0, 0.0)),
        point_stride=POINT_DTYPE.itemsize,
        fields=_fields(POINT_DTYPE),
    ).SerializeToString()
    size = len(result.points_vehicle[::stride]) * POINT_DTYPE.itemsize
    return points_record(result, head + _field_head(PointCloud.DESCRIPTOR.fields_by_name["data"].number, size),
                         stride=stride)


def _field_head(number: int, size: int) -> bytes:
    """The tag and varint length of a length-delimited protobuf field (a message, bytes) of ``size`` bytes."""
    return bytes([number << 3 | 2]) + _varint(size)


def _message_field(number: int, data: bytes) -> bytes:
    """A length-delimited protobuf field with its tag and length."""
    return _field_head(number, len(data)) + data


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _entity(box: Box, stamp: Timestamp, frame_id: str) -> SceneEntity:
    obstacle = box.obstacle
    center = np.asarray(obstacle.center_m, float)
    size = np.asarray(obstacle.size_m, float)
    r, g, b, a = box.rgba
    top = center + [0.0, 0.0, size[2] / 2 + 0.3]
    return SceneEntity(
        timestamp=stamp,
        frame_id=frame_id,
        id=f"{box.group}/{box.number}",
        cubes=[
            CubePrimitive(
                pose=_pose(center, yaw_quaternion(obstacle.yaw_rad)),
                size=Vector3(x=size[0], y=size[1], z=size[2]),
                color=Color(r=r, g=g, b=b, a=a),
            )
        ],
        texts=[
            TextPrimitive(
                pose=_pose(top),
                billboard=True,
                font_size=14.0,
                scale_invariant=True,
                color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                text=box.text,
            )
        ],
    )


_POINT3 = np.dtype({"names": ["tag", "size", "tx", "x", "ty", "y", "tz", "z"],
                    "formats": ["u1", "u1", "u1", "<f8", "u1", "<f8", "u1", "<f8"],
                    "offsets": [0, 1, 2, 3, 11, 12, 20, 21], "itemsize": 29})
"""A ``foxglove.Point3`` (x, y, z doubles: fields 1–3) as field 2 of a TriangleListPrimitive."""
_COLOR = np.dtype({"names": ["tag", "size", "tr", "r", "tg", "g", "tb", "b", "ta", "a"],
                   "formats": ["u1", "u1", "u1", "<f8", "u1", "<f8", "u1", "<f8", "u1", "<f8"],
                   "offsets": [0, 1, 2, 3, 11, 12, 20, 21, 29, 30], "itemsize": 38})
"""A ``foxglove.Color`` (r, g, b, a doubles: fields 1–4) as field 4 of a TriangleListPrimitive."""


def surface_message(result: FrameResult) -> bytes:
    """Serialized ``foxglove.SceneUpdate`` with one entity ``terrain``: a triangle list over the
    centres of the cells with data, at the surface's elevation, each vertex coloured by slope
    (green 0° to red ≥ 30°, :data:`~.base.SLOPE_RANGE_RAD`). foxglove.Grid is drawn flat, so this is
    how Foxglove shows the surface in 3D. The 3000 vertices and colours are packed with numpy
    (protobuf's message objects took milliseconds a frame); the wire format is protobuf's."""
    grid = result.grid.config
    xs, ys = cell_centers(grid)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    points = np.zeros(X.size, _POINT3)
    points["tag"], points["size"], points["tx"], points["ty"], points["tz"] = 0x12, 27, 0x09, 0x11, 0x19
    points["x"], points["y"], points["z"] = X.ravel(), Y.ravel(), result.layers["elevation"].ravel()
    rgb = colormap(result.layers["slope"].ravel(), *SLOPE_RANGE_RAD) / 255.0
    colors = np.zeros(X.size, _COLOR)
    colors["tag"], colors["size"], colors["tr"], colors["tg"], colors["tb"], colors["ta"] = 0x22, 36, 9, 0x11, 0x19, 0x21
    colors["r"], colors["g"], colors["b"], colors["a"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], 1.0
    indices = surface_triangles(result.grid.valid).astype("<u4").tobytes()
    primitive = (_message_field(1, Pose(orientation=Quaternion(w=1.0)).SerializeToString()) + points.tobytes()
                 + colors.tobytes() + _message_field(5, indices))
    stamp = _timestamp(result.stamp_ns)
    entity = SceneEntity(timestamp=stamp, frame_id=result.extrinsics.vehicle_frame_id, id="terrain").SerializeToString()
    return _message_field(2, entity + _message_field(12, primitive))  # SceneUpdate.entities, SceneEntity.triangles


def obstacles_message(result: FrameResult) -> SceneUpdate:
    """``foxglove.SceneUpdate`` that deletes every earlier entity and adds this frame's boxes
    (:func:`~.base.shown_boxes`): entity ids ``obstacle/<track id>`` and ``occupied/<n>``."""
    stamp = _timestamp(result.stamp_ns)
    frame_id = result.extrinsics.vehicle_frame_id
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletion.ALL)],
        entities=[_entity(box, stamp, frame_id) for box in shown_boxes(result)],
    )


def transforms_message(stamp_ns: int, transforms: tuple[tuple[str, str, tuple, tuple], ...]) -> FrameTransforms:
    """``foxglove.FrameTransforms`` of ``(parent, child, translation, rotation xyzw)`` tuples."""
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=_timestamp(stamp_ns),
                parent_frame_id=parent,
                child_frame_id=child,
                translation=Vector3(x=x, y=y, z=z),
                rotation=Quaternion(x=qx, y=qy, z=qz, w=qw),
            )
            for parent, child, (x, y, z), (qx, qy, qz, qw) in transforms
        ]
    )


class _Writer(Writer):
    """mcap_protobuf's writer plus ``write_encoded`` for messages serialized here."""

    def write_encoded(self, topic: str, message_type: type, data: bytes | bytearray, log_time: int) -> None:
        if topic not in self._channels:
            schema_id = register_schema(self._writer, message_type)
            self._schemas[topic] = (schema_id, message_type.DESCRIPTOR.full_name)
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=schema_id
            )
        self._writer.add_message(
            channel_id=self._channels[topic], log_time=log_time, data=data, publish_time=log_time, sequence=0
        )


class FoxgloveMcapSink(McapSink):
    """Writes each frame as Foxglove protobuf messages to an MCAP file (see the module docstring).

    Parameters are those of :class:`~terrainmap.sinks.base.McapSink`, plus ``compression``
    (``"lz4"``, ``"zstd"`` or ``"none"``; see :func:`terrainmap.sinks.open_mcap_sink`).
    """

    def __init__(self, path, *, config, metadata=None, compression: str = "lz4"):
        self._compression = CompressionType[compression.upper()]
        super().__init__(path, config=config, metadata=metadata)

    def _open(self, stream) -> None:
        self._writer = _Writer(stream, compression=self._compression)

    def _log(self, topic: str, message, stamp_ns: int) -> None:
        self._writer.write_message(topic, message, log_time=stamp_ns, publish_time=stamp_ns)

    def _write_frame(self, frame: StereoFrame, result: FrameResult) -> None:
        t = frame.stamp_ns
        for topic, transforms in self._transforms(frame, result):
            self._log(topic, transforms_message(t, transforms), t)
        self._log("/terrainmap/grid", grid_message(result), t)
        self._writer.write_encoded("/terrainmap/surface", SceneUpdate, surface_message(result), t)
        points = encode_points(result, self._point_stride(result))
        self._writer.write_encoded("/terrainmap/points", PointCloud, points, t)
        self._log("/terrainmap/obstacles", obstacles_message(result), t)

    def _finish(self, metadata: dict[str, str]) -> None:
        self._writer.add_metadata(METADATA_NAME, metadata)
        self._writer.finish()
