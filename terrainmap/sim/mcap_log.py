"""Write a simulated drive as a ROS 2 MCAP log (CDR, profile ``ros2``), like a real robot's.

Topics (every message of a frame is logged at, and stamped with, the frame's stamp):

=================================  ==================================  ===============================
``/stereo/left/image_rect``        ``sensor_msgs/msg/Image``           mono8 or rgb8, ``left_camera_optical``
``/stereo/right/image_rect``       ``sensor_msgs/msg/Image``           ``right_camera_optical``
``/stereo/{left,right}/camera_info`` ``sensor_msgs/msg/CameraInfo``    right ``P[0,3] = −fx·B``
``…/image_rect/compressed``        ``sensor_msgs/msg/CompressedImage`` PNG, instead of the raw images
                                                                       when ``compressed=True``
``/tf_static``                     ``tf2_msgs/msg/TFMessage``          base_link → left → right camera
``/tf``                            ``tf2_msgs/msg/TFMessage``          odom → base_link (true pose)
``/truth/terrain``                 ``grid_map_msgs/msg/GridMap``       once; layer ``elevation``, odom
``/truth/pose``                    ``geometry_msgs/msg/PoseStamped``   base_link in odom
``/truth/obstacles``               ``visualization_msgs/msg/MarkerArray`` boxes, odom
``/truth/left/depth``              ``sensor_msgs/msg/Image``           32FC1 m along the optical axis, +inf sky
``/truth/left/label``              ``sensor_msgs/msg/Image``           mono8: 0 sky, 1 terrain, 2 obstacle
``/truth/left/instance``           ``sensor_msgs/msg/Image``           mono8: obstacle id, 0 elsewhere
=================================  ==================================  ===============================

Channels carry rosbag2's QoS metadata (:func:`terrainmap.ros2defs.offered_qos_profiles`):
``/tf_static`` and ``/truth/terrain`` latched.

Metadata record ``terrainmap.sim``: key ``scene``, the JSON description of the simulation
(scene, seed, rig, obstacles with velocities, terrain grid), see :func:`terrainmap.sim.simulate.describe`.
Message layouts are in :mod:`terrainmap.sim.messages`.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import cv2
import numpy as np
from mcap.writer import CompressionType

from ..ros2defs import SCHEMAS, header, quaternion_from_matrix, transform_stamped
from ..sinks.mcap_ros2 import Ros2Writer
from .messages import grid_map_message, image_message, marker_array_message, pose_message
from .render import SimFrame
from .rig import LEFT_FRAME, RIGHT_FRAME, VEHICLE_FRAME, WORLD_FRAME, CameraRig
from .scenes import Scene

METADATA_NAME = "terrainmap.sim"
TRUTH_TOPICS = {
    "/truth/terrain": "grid_map_msgs/msg/GridMap",
    "/truth/pose": "geometry_msgs/msg/PoseStamped",
    "/truth/obstacles": "visualization_msgs/msg/MarkerArray",
    "/truth/left/depth": "sensor_msgs/msg/Image",
    "/truth/left/label": "sensor_msgs/msg/Image",
    "/truth/left/instance": "sensor_msgs/msg/Image",
}
"""The ground-truth topics and their types (the reader requires all of them)."""
LATCHED_TOPICS = frozenset({"/tf_static", "/truth/terrain"})
"""Written once and offered transient local, as a robot's static transforms and maps are."""


def camera_info(rig: CameraRig, stamp_ns: int, frame_id: str, baseline_m: float) -> dict:
    """``sensor_msgs/CameraInfo`` of one rectified camera; ``baseline_m`` 0 for the left one."""
    fx, fy, cx, cy = rig.intrinsics
    return {
        "header": header(stamp_ns, frame_id), "height": rig.height, "width": rig.width,
        "distortion_model": "plumb_bob", "d": [0.0] * 5,
        "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
        "p": [fx, 0.0, cx, -fx * baseline_m, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0, "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


class McapLog:
    """Context manager writing frames to ``path`` (module docstring); ``compressed``: PNG images."""

    def __init__(self, path: str | Path, scene: Scene, rig: CameraRig, description: dict, *, compressed: bool = False):
        self.path = Path(path)
        self.scene, self.rig, self.compressed = scene, rig, compressed
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Ros2Writer(self._file, compression=CompressionType.ZSTD, latched=LATCHED_TOPICS)
        self._schemas: dict[str, object] = {}
        self._writer.add_metadata(METADATA_NAME, {"scene": json.dumps(description)})
        self._started = False

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def discard(self) -> None:
        """Remove the file, a link's target (after a write failed: without its summary it is damaged)."""
        with contextlib.suppress(OSError):
            self._file.close()
        self.path.resolve().unlink(missing_ok=True)

    def _log(self, topic: str, type_name: str, message: dict, stamp_ns: int) -> None:
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_msgdef(type_name, SCHEMAS[type_name])
        self._writer.write_message(topic, self._schemas[type_name], message, log_time=stamp_ns, publish_time=stamp_ns)

    def _write_static(self, stamp_ns: int) -> None:
        rig = self.rig
        transforms = [
            transform_stamped(stamp_ns, VEHICLE_FRAME, LEFT_FRAME, rig.left_in_base(),
                              quaternion_from_matrix(rig.rotation_base_cam())),
            transform_stamped(stamp_ns, LEFT_FRAME, RIGHT_FRAME, (rig.baseline_m, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        ]
        self._log("/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": transforms}, stamp_ns)
        self._log("/truth/terrain", TRUTH_TOPICS["/truth/terrain"],
                  grid_map_message(self.scene.terrain, stamp_ns, WORLD_FRAME), stamp_ns)

    def _write_image(self, side: str, image: np.ndarray, stamp_ns: int, frame_id: str) -> None:
        topic = f"/stereo/{side}/image_rect"
        if not self.compressed:
            self._log(topic, "sensor_msgs/msg/Image", image_message(image, stamp_ns, frame_id), stamp_ns)
            return
        bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        png = cv2.imencode(".png", bgr)[1].tobytes()
        message = {"header": header(stamp_ns, frame_id), "format": "png", "data": png}
        self._log(f"{topic}/compressed", "sensor_msgs/msg/CompressedImage", message, stamp_ns)

    def write(self, frame: SimFrame) -> None:
        """Write one frame: camera topics, the true pose on /tf, and the truth topics."""
        t = frame.stamp_ns
        if not self._started:
            self._write_static(t)
            self._started = True
        base_tf = transform_stamped(t, WORLD_FRAME, VEHICLE_FRAME, frame.position_world_base,
                                    quaternion_from_matrix(frame.rotation_world_base))
        self._log("/tf", "tf2_msgs/msg/TFMessage", {"transforms": [base_tf]}, t)
        for side, image, frame_id, baseline in (
            ("left", frame.left, LEFT_FRAME, 0.0), ("right", frame.right, RIGHT_FRAME, self.rig.baseline_m)
        ):
            self._log(f"/stereo/{side}/camera_info", "sensor_msgs/msg/CameraInfo",
                      camera_info(self.rig, t, frame_id, baseline), t)
            self._write_image(side, image, t, frame_id)
        self._log("/truth/pose", TRUTH_TOPICS["/truth/pose"],
                  pose_message(frame.rotation_world_base, frame.position_world_base, t, WORLD_FRAME), t)
        self._log("/truth/obstacles", TRUTH_TOPICS["/truth/obstacles"],
                  marker_array_message(frame.obstacles, t, WORLD_FRAME), t)
        for name, image in (("depth", frame.depth), ("label", frame.label), ("instance", frame.instance)):
            self._log(f"/truth/left/{name}", "sensor_msgs/msg/Image", image_message(image, t, LEFT_FRAME), t)
