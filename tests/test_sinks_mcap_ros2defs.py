"""terrainmap.ros2defs: schema text checked against rosbags' own ROS 2 Humble store and mcap_ros2."""

from __future__ import annotations

import io

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from terrainmap.errors import InputError
from terrainmap.ros2defs import SCHEMAS, SEPARATOR, header, quaternion_from_matrix, stamp, transform_stamped

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_schema_fields_match_ros2_humble(name):
    types = get_types_from_msg(SCHEMAS[name], name)
    for type_name, (_consts, fields) in types.items():
        if type_name in HUMBLE.fielddefs:  # grid_map_msgs is not in the store
            assert [f[0] for f in fields] == [f[0] for f in HUMBLE.fielddefs[type_name][1]], type_name


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_dependencies_use_short_form_and_appear_once(name):
    text = SCHEMAS[name]
    assert "/msg/" not in text
    sections = [part.split("\n", 2)[1] for part in text.split(SEPARATOR)[1:]]
    assert all(s.startswith("MSG: ") for s in sections)
    assert len(sections) == len(set(sections))


def test_gridmap_schema_has_ros2_fields():
    fields = get_types_from_msg(SCHEMAS["grid_map_msgs/msg/GridMap"], "grid_map_msgs/msg/GridMap")
    names = [f[0] for f in fields["grid_map_msgs/msg/GridMap"][1]]
    assert names == ["header", "info", "layers", "basic_layers", "data", "outer_start_index", "inner_start_index"]
    info = [f[0] for f in fields["grid_map_msgs/msg/GridMapInfo"][1]]
    assert info == ["resolution", "length_x", "length_y", "pose"]


def test_mcap_ros2_round_trip_of_a_transform():
    buf = io.BytesIO()
    writer = Writer(buf)
    schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", SCHEMAS["tf2_msgs/msg/TFMessage"])
    tf = transform_stamped(1_700_000_000_123_456_789, "base_link", "cam", [1.0, 2.0, 3.0], [0, 0, 0.6, 0.8])
    writer.write_message("/tf", schema, {"transforms": [tf]}, log_time=1, publish_time=1)
    writer.finish()
    buf.seek(0)
    (_, _, _, msg), = make_reader(buf, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
    t = msg.transforms[0]
    assert (t.header.stamp.sec, t.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert t.header.frame_id == "base_link" and t.child_frame_id == "cam"
    assert (t.transform.translation.y, t.transform.rotation.z, t.transform.rotation.w) == (2.0, 0.6, 0.8)


def test_stamp_and_header():
    assert stamp(-1) == {"sec": -1, "nanosec": 999_999_999}
    assert header(2_000_000_001, "x") == {"stamp": {"sec": 2, "nanosec": 1}, "frame_id": "x"}
    assert stamp((2**31 - 1) * 10**9)["sec"] == 2**31 - 1
    with pytest.raises(InputError, match="int32 seconds.*--flavor foxglove"):
        stamp(2**31 * 10**9)  # 2038-01-19 03:14:08 UTC


def test_quaternion_from_matrix_matches_scipy():
    rotations = Rotation.random(200, random_state=0)
    special = Rotation.from_matrix([np.eye(3), np.diag([1, -1, -1]), np.diag([-1, 1, -1]), np.diag([-1, -1, 1])])
    for r in list(rotations) + list(special):
        ref = r.as_quat()
        ref = -ref if ref[3] < 0 else ref
        np.testing.assert_allclose(quaternion_from_matrix(r.as_matrix()), ref, atol=1e-9)
