"""ROS 2 message definitions (schema text) for writing and reading CDR MCAP without a ROS install.

:data:`SCHEMAS` maps a full type name (``sensor_msgs/msg/Image``) to the concatenated ``.msg``
text that MCAP's ``ros2msg`` schema encoding expects: the type's own fields first, then every
dependency after a line of 80 ``=`` and ``MSG: pkg/Type``. Dependencies are written
``MSG: std_msgs/Header`` (not ``std_msgs/msg/Header``): Rerun and some other readers fail on
the long form. Field definitions follow ROS 2 Humble (``Marker`` with texture and mesh file
fields, ``CameraInfo`` with lower-case ``d, k, r, p``, ``grid_map_msgs`` 2.x).

The helpers build the plain dicts that ``mcap_ros2.writer.Writer.write_message`` encodes::

    header(stamp_ns, "base_link") -> {"stamp": {"sec": ..., "nanosec": ...}, "frame_id": ...}
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

SEPARATOR = "=" * 80

_PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)

# Bodies of every message used, keyed by short name "pkg/Type". Dependencies are found by parsing.
_BODIES: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a",
    "std_msgs/MultiArrayDimension": "string label\nuint32 size\nuint32 stride",
    "std_msgs/MultiArrayLayout": "MultiArrayDimension[] dim\nuint32 data_offset",
    "std_msgs/Float32MultiArray": "MultiArrayLayout layout\nfloat32[] data",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "sensor_msgs/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "RegionOfInterest roi"
    ),
    "sensor_msgs/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n"
        "uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count"
    ),
    "sensor_msgs/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
        "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense"
    ),
    "grid_map_msgs/GridMapInfo": (
        "float64 resolution\nfloat64 length_x\nfloat64 length_y\ngeometry_msgs/Pose pose"
    ),
    "grid_map_msgs/GridMap": (
        "std_msgs/Header header\nGridMapInfo info\nstring[] layers\nstring[] basic_layers\n"
        "std_msgs/Float32MultiArray[] data\nuint16 outer_start_index\nuint16 inner_start_index"
    ),
    "nav_msgs/MapMetaData": (
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n"
        "geometry_msgs/Pose origin"
    ),
    "nav_msgs/OccupancyGrid": "std_msgs/Header header\nMapMetaData info\nint8[] data",
    "visualization_msgs/UVCoordinate": "float32 u\nfloat32 v",
    "visualization_msgs/MeshFile": "string filename\nuint8[] data",
    "visualization_msgs/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n"
        "int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n"
        "int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\n"
        "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n"
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\nbool frame_locked\ngeometry_msgs/Point[] points\n"
        "std_msgs/ColorRGBA[] colors\nstring texture_resource\nsensor_msgs/CompressedImage texture\n"
        "UVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\nMeshFile mesh_file\n"
        "bool mesh_use_embedded_materials"
    ),
    "visualization_msgs/MarkerArray": "Marker[] markers",
}

# Numbering of sensor_msgs/PointField.datatype (differs from foxglove.PackedElementField's).
POINTFIELD_UINT32 = 6
POINTFIELD_FLOAT32 = 7
# visualization_msgs/Marker constants used by the writers.
MARKER_CUBE = 1
MARKER_TEXT_VIEW_FACING = 9
MARKER_ADD = 0
MARKER_DELETEALL = 3


def _field_type(line: str, package: str) -> str | None:
    """Fully qualified ``pkg/Type`` of a complex field line, None for primitives, constants, comments."""
    code = line.split("#")[0]
    words = code.split()
    if len(words) < 2 or "=" in code:
        return None
    base = words[0].split("[")[0].split("<=")[0]
    if base in _PRIMITIVES:
        return None
    return base if "/" in base else f"{package}/{base}"


def _qualified_body(short_name: str) -> str:
    """Body of a message with every complex field type written ``pkg/Type`` (readers differ on
    how they resolve package-relative names inside dependency sections)."""
    package = short_name.split("/")[0]
    lines = []
    for line in _BODIES[short_name].splitlines():
        full = _field_type(line, package)
        if full is not None and "/" not in line.split()[0]:
            line = f"{package}/{line.lstrip()}"
        lines.append(line)
    return "\n".join(lines)


def _all_dependencies(short_name: str) -> list[str]:
    """Every dependency of a message, depth first, each once, the message itself excluded."""
    ordered: list[str] = []

    def visit(name: str) -> None:
        package = name.split("/")[0]
        for line in _BODIES[name].splitlines():
            dep = _field_type(line, package)
            if dep is not None and dep not in ordered:
                ordered.append(dep)
                visit(dep)

    visit(short_name)
    return ordered


def schema_text(type_name: str) -> str:
    """Concatenated ``.msg`` text of ``type_name`` (``pkg/msg/Type`` or ``pkg/Type``) and its dependencies.

    Raises
    ------
    KeyError
        The type is not one terrainmap defines.
    """
    short = type_name.replace("/msg/", "/")
    parts = [_qualified_body(short)]
    parts += [f"{SEPARATOR}\nMSG: {dep}\n{_qualified_body(dep)}" for dep in _all_dependencies(short)]
    return "\n".join(parts) + "\n"


SCHEMAS: dict[str, str] = {
    name: schema_text(name)
    for name in (
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CompressedImage",
        "sensor_msgs/msg/CameraInfo",
        "sensor_msgs/msg/PointCloud2",
        "sensor_msgs/msg/PointField",
        "tf2_msgs/msg/TFMessage",
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/TransformStamped",
        "grid_map_msgs/msg/GridMap",
        "nav_msgs/msg/OccupancyGrid",
        "visualization_msgs/msg/Marker",
        "visualization_msgs/msg/MarkerArray",
        "std_msgs/msg/Float32MultiArray",
    )
}
"""Full type name → schema text, for ``Writer.register_msgdef(name, SCHEMAS[name])``."""


def offered_qos_profiles(latched: bool, depth: int = 10) -> str:
    """rosbag2's ``offered_qos_profiles`` channel metadata (a YAML list of one profile), which the
    MCAP ``ros2`` profile asks for and ``ros2 bag play`` publishes each topic with: reliable,
    keep last (depth 1 latched, else ``depth``: 100 for ``/tf``, as tf2's broadcaster offers),
    and transient local where ``latched`` (``/tf_static``,
    maps: subscribers that join later, such as tf2's static listener, still get the last
    message; a volatile publisher would not even connect to them) or volatile. Enum values
    are rmw's (history 1 keep last, reliability 1 reliable, durability 1 transient local / 2
    volatile, liveliness 1 automatic); durations 0 are rmw's "unspecified" (the default)."""
    zero = "\n    sec: 0\n    nsec: 0"
    return (
        f"- history: 1\n  depth: {1 if latched else depth}\n  reliability: 1\n  durability: {1 if latched else 2}\n"
        f"  deadline:{zero}\n  lifespan:{zero}\n  liveliness: 1\n  liveliness_lease_duration:{zero}\n"
        "  avoid_ros_namespace_conventions: false"
    )


def stamp(stamp_ns: int) -> dict:
    """``builtin_interfaces/Time`` dict of a time in nanoseconds (non-negative nanosec part).

    Raises :class:`InputError` for a time its int32 seconds cannot hold (before 1901 or after
    2038-01-19 03:14:07 UTC)."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise InputError(
            f"stamp {stamp_ns} ns lies outside what ROS 2's builtin_interfaces/Time (int32 seconds) holds, "
            "1901–2038; write --flavor foxglove instead"
        )
    return {"sec": sec, "nanosec": nanosec}


def header(stamp_ns: int, frame_id: str) -> dict:
    """``std_msgs/Header`` dict."""
    return {"stamp": stamp(stamp_ns), "frame_id": frame_id}


def pose(position_m, quaternion_xyzw=(0.0, 0.0, 0.0, 1.0)) -> dict:
    """``geometry_msgs/Pose`` dict from a position (3,) in metres and a quaternion (x, y, z, w)."""
    x, y, z = (float(v) for v in position_m)
    qx, qy, qz, qw = (float(v) for v in quaternion_xyzw)
    return {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def transform_stamped(stamp_ns: int, parent: str, child: str, translation_m, quaternion_xyzw) -> dict:
    """``geometry_msgs/TransformStamped`` dict: pose of frame ``child`` in frame ``parent``."""
    p = pose(translation_m, quaternion_xyzw)
    return {
        "header": header(stamp_ns, parent),
        "child_frame_id": child,
        "transform": {"translation": p["position"], "rotation": p["orientation"]},
    }


def yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of a rotation by ``yaw_rad`` about z."""
    return (0.0, 0.0, float(np.sin(yaw_rad / 2)), float(np.cos(yaw_rad / 2)))


def quaternion_from_matrix(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` (w ≥ 0) of a 3×3 rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    diag = np.diag(m)
    k = int(np.argmax(np.r_[trace, diag]))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + trace)
        x, y, z = (m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]) / (4 * w)
    else:
        i = k - 1
        j, n = (i + 1) % 3, (i + 2) % 3
        q = np.empty(3)
        q[i] = 0.5 * np.sqrt(max(1.0 + 2 * m[i, i] - trace, 0.0))
        q[j] = (m[j, i] + m[i, j]) / (4 * q[i])
        q[n] = (m[n, i] + m[i, n]) / (4 * q[i])
        w = (m[n, j] - m[j, n]) / (4 * q[i])
        x, y, z = q
    quat = np.array([x, y, z, w]) / np.linalg.norm([x, y, z, w])
    if quat[3] < 0:
        quat = -quat
    return tuple(float(v) for v in quat)


def grid_map_frame(x_min_m: float, y_min_m: float, shape: tuple[int, int], resolution_m: float) -> dict:
    """``grid_map_msgs/GridMapInfo`` of a grid of ``shape`` = (cells along x, along y) whose corner
    is (x_min_m, y_min_m): grid_map puts the pose at the map centre."""
    nx, ny = shape
    center = (x_min_m + nx * resolution_m / 2, y_min_m + ny * resolution_m / 2, 0.0)
    return {"resolution": resolution_m, "length_x": nx * resolution_m, "length_y": ny * resolution_m,
            "pose": pose(center)}


def grid_map_layer(values: np.ndarray) -> dict:
    """A GridMap layer (``std_msgs/Float32MultiArray``) from an array indexed [ix, iy] (x, y up).

    grid_map stores column-major from the +x, +y corner: cell [ix, iy] goes to index
    (i, j) = (nx−1−ix, ny−1−iy), stored at data[j][i]. ``data`` is a float32 numpy array."""
    nx, ny = values.shape
    layout = {
        "dim": [
            {"label": "column_index", "size": ny, "stride": nx * ny},
            {"label": "row_index", "size": nx, "stride": nx},
        ],
        "data_offset": 0,
    }
    return {"layout": layout, "data": np.ascontiguousarray(values[::-1, ::-1].T, dtype=np.float32).ravel()}
