"""Rerun recordings (``terrainmap process --rrd OUT.rrd``): every stage of every frame.

One explicit :class:`rerun.RecordingStream` saved to the ``.rrd`` with a default blueprint: the
3D view of the vehicle surroundings (points coloured by label, the terrain surface coloured by
slope, grid samples before and after equalization, obstacle boxes), the left image with the
labels drawn on it, the depth image, and plots of per-stage times and fit statistics.

Entity tree (``world`` is the log's odometry frame where the source gives the vehicle's pose,
else the vehicle frame itself; z up)::

    world                         ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/vehicle                 Transform3D: the vehicle frame (base_link) in the odometry frame,
                                  per frame (only where the source gives the pose; else identity)
    world/vehicle/camera          Transform3D (camera pose) + Pinhole, logged on the frame where
                                  they first hold (and again where they change); image, labels
    world/vehicle/points          Points3D, class ids = Label (AnnotationContext on world, static)
    world/vehicle/grid/samples    grid samples before equalization (eq. 1, valid cells)
    world/vehicle/grid/equalized  samples after the last equalization
    world/vehicle/terrain/slope   Mesh3D over the valid cells' centres, coloured by slope (0–30°)
    world/vehicle/terrain/elevation  the same mesh coloured by elevation, lowest to highest drawn so
                                  far in the run (hidden in the blueprint)
    world/vehicle/terrain/cost    the same mesh coloured by traversability cost (hidden)
    world/vehicle/obstacles       Boxes3D of the confirmed obstacles, "id kind height" labels
    world/vehicle/occupied        Boxes3D, grey, of what else occupies the cost map ("part of id",
                                  "id unseen"; FrameResult.occupied)
    world/vehicle/camera/image/labels  SegmentationImage: each point's Label at its pixel, the
                                  pixels without a point transparent (class NO_POINT)
    depth                         DepthImage (metres, from the disparity; 0, no data, outside
                                  the stereo.min_range_m..max_range_m that points are kept in)
    log                           TextLog: a warning for each frame that failed, and why (its
                                  results cleared: the views show nothing there, not the frame before)
    timings/<stage>               Scalars, ms
    stats/fit/<name>              Scalars: iterations, mean_error_m
    stats/counts/<name>           Scalars: points, cells, obstacles (confirmed tracks), detections
                                  (the frame's obstacles as the tracker reports them, confirmed or not)

Everything the pipeline computes is logged in the vehicle frame, as computed; the per-frame
vehicle transform places it in the odometry frame, so the 3D view follows the drive.

Timelines: ``frame`` (sequence, the frame index) and ``stamp`` (the source image's time).
Written for rerun-sdk 0.41 (pinned); the files open in the Rerun viewer 0.41.
"""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..config import Config, check_config
from ..errors import InputError, TerrainmapError
from ..grid import cell_centers
from ..ros2defs import yaw_quaternion
from ..stereo import rectified_camera
from ..types import FrameResult, Label, StereoFrame
from .base import (
    SLOPE_RANGE_RAD,
    check_frame,
    colormap,
    one_at_a_time,
    output_path,
    point_stride,
    shown_boxes,
    surface_triangles,
)

LABEL_COLORS = {
    Label.UNKNOWN: (140, 140, 140),
    Label.TERRAIN: (60, 180, 75),
    Label.OBSTACLE: (230, 25, 75),
    Label.BELOW: (0, 130, 200),
}
NO_POINT = 255
"""Class id of the label image's pixels that hold no point: transparent (the image shows through),
where the classes of :data:`LABEL_COLORS` are drawn over it."""
VEHICLE = "world/vehicle"
"""Entity of the vehicle frame; everything computed per frame is logged under it."""
RESULTS = ("points", "grid", "terrain", "obstacles", "occupied", "camera/image/labels")
"""Entities under :data:`VEHICLE` that a failed frame clears (with ``depth``)."""


def blueprint() -> rrb.Blueprint:
    """The default layout embedded in every recording."""
    hidden = rrb.EntityBehavior(visible=False)  # in the view, a click away
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="terrain",
                origin="/world",
                contents=["+ /world/**"],
                overrides={f"/{VEHICLE}/terrain/elevation": hidden, f"/{VEHICLE}/terrain/cost": hidden},
            ),
            rrb.Vertical(
                rrb.Spatial2DView(name="left image and labels", origin=f"/{VEHICLE}/camera"),
                rrb.Spatial2DView(name="depth", origin="/depth"),
                rrb.TimeSeriesView(name="stage times (ms)", origin="/timings"),
                rrb.TimeSeriesView(name="fit: iterations, mean error (m)", origin="/stats/fit"),
                rrb.TimeSeriesView(name="counts: points, cells, obstacles", origin="/stats/counts"),
                rrb.TextLogView(name="frames that failed", origin="/log"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def _span(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of the finite ``values`` (the cells drawn), (0, 1) when there are none."""
    finite = values[np.isfinite(values)]
    return (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)


_FLUSH_WAIT_S = 5.0
"""How long one flush of :meth:`RerunSink.close` waits for the recording's file, s."""
_STALL_S = 60.0
"""How long the file may stand still, on a disk with room, before its writer is taken for dead, s
(a slow network disk); on a full disk (less than :data:`_FULL_BYTES` free) one wait is enough."""
_FULL_BYTES = 4 << 20
"""Free space under which a recording that stands still counts as stopped by a full disk, bytes
(a write that fails for want of space leaves less than one frame of the recording, about 1 MB)."""


_STUCK: list = []
"""Recording streams whose file writer died (:meth:`RerunSink.close`)."""


def exit_would_hang() -> bool:
    """Whether a recording's file writer died (a full disk): Rerun 0.41 then waits for it for ever
    once the stream is flushed, so that a process exiting normally would not end. The CLI ends
    with ``os._exit`` then, its outputs already closed."""
    return bool(_STUCK)


class RerunSink:
    """Writes a Rerun recording; a :class:`~terrainmap.sinks.base.Sink`.

    Parameters
    ----------
    path : str or Path
        Output ``.rrd`` file (overwritten).
    config : Config
        ``config.rerun.max_points`` caps the points logged per frame (uniform subsampling).
    """

    def __init__(self, path: str | Path, *, config: Config, application_id: str = "terrainmap"):
        self._lock = threading.RLock()
        self.path = output_path("Rerun output", path)
        check_config(f"Rerun output {path}", config)
        if not self.path.parent.is_dir():  # said before a stream exists (Rerun would warn as it drops it)
            raise InputError(f"cannot create Rerun output {self.path}: folder {self.path.parent} does not exist")
        self._config = config
        self._closed = False
        self.finished = False
        self._camera_key: tuple | None = None
        self._elevation_span: tuple[float, float] | None = None  # lowest and highest drawn so far, m
        self.frames_written = 0
        self._rec = rr.RecordingStream(application_id)
        try:
            self._rec.save(str(self.path), default_blueprint=blueprint())
        except Exception as exc:  # rerun reports an unwritable path with its own exception types
            raise InputError(f"cannot create Rerun output {self.path}: {exc}") from exc
        self._rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        context = rr.AnnotationContext([(int(k), k.name.lower(), c) for k, c in LABEL_COLORS.items()]
                                       + [(NO_POINT, "no point", (0, 0, 0, 0))])
        self._rec.log("world", context, static=True)

    @one_at_a_time
    def write(self, frame: StereoFrame, result: FrameResult) -> None:
        check_frame(f"Rerun output {self.path}", frame, result, 63)  # (Rerun's timestamps are signed)
        self._start_frame(frame)
        rec = self._rec
        self._log_camera(frame, result)
        self._log_points(result)
        self._log_terrain(result)
        self._log_obstacles(result)
        for stage, ms in result.timings_ms.items():
            rec.log(f"timings/{stage}", rr.Scalars(ms))
        for name, value in result.stats.items():
            group = "fit" if name in ("iterations", "mean_error_m") else "counts"
            rec.log(f"stats/{group}/{name}", rr.Scalars(value))
        self.frames_written += 1

    @one_at_a_time
    def failed(self, frame: StereoFrame, error: Exception) -> None:
        """A frame the pipeline could not process: its vehicle pose and left image (where the
        source's images are rectified; else none), the results of the frame before cleared (so that
        the views do not pass them off as this frame's), and a warning line under ``log`` naming
        it and why."""
        check_frame(f"Rerun output {self.path}", frame, None, 63, failed=True)
        self._start_frame(frame)
        image = rr.Image(frame.left) if frame.calibration.rectified else rr.Clear(recursive=False)
        self._rec.log(f"{VEHICLE}/camera/image", image)
        for path in RESULTS:
            self._rec.log(f"{VEHICLE}/{path}", rr.Clear(recursive=True))
        self._rec.log("depth", rr.Clear(recursive=False))
        reason = getattr(error, "reason", None)  # a FrameError's, by which the run's summary counts it
        why = f" ({reason})" if reason and reason != str(error) else ""
        self._rec.log("log", rr.TextLog(f"frame {frame.index} failed{why}: {error}", level=rr.TextLogLevel.WARN))

    def _start_frame(self, frame: StereoFrame) -> None:
        """The frame's place on the timelines, and the vehicle's pose where the source gives it."""
        if self._closed:
            raise TerrainmapError(f"Rerun output {self.path} is already closed")
        rec = self._rec
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("stamp", timestamp=np.datetime64(int(frame.stamp_ns), "ns"))  # (numpy's ints too)
        if frame.vehicle_pose is not None:
            pose = np.asarray(frame.vehicle_pose, float)
            rec.log(VEHICLE, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))

    def _log_camera(self, frame: StereoFrame, result: FrameResult) -> None:
        rec = self._rec
        c = _camera_model(frame, result)
        ext = result.extrinsics if result.pinhole is None else rectified_camera(result.extrinsics, result.pinhole)
        pinhole = (c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        key = (pinhole, tuple(np.ravel(ext.translation)), tuple(np.ravel(ext.rotation)))
        if key != self._camera_key:  # on the timelines, not static: each holds from its frame on
            rec.log(
                f"{VEHICLE}/camera",
                rr.Transform3D(translation=np.asarray(ext.translation, float), mat3x3=np.asarray(ext.rotation, float)),
                rr.Pinhole(focal_length=[c.fx, c.fy], principal_point=[c.cx, c.cy], width=c.width, height=c.height,
                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0),
            )
            self._camera_key = key
        if result.image is not None:
            rec.log(f"{VEHICLE}/camera/image", rr.Image(result.image))
            labels = np.full(result.image.shape[:2], NO_POINT, np.uint8)
            labels[result.pixels[:, 1], result.pixels[:, 0]] = result.point_labels
            rec.log(f"{VEHICLE}/camera/image/labels", rr.SegmentationImage(labels, opacity=0.45))
        if result.disparity is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = (c.fx * c.baseline_m / (result.disparity[::2, ::2] + c.doffs)).astype(np.float32)
            stereo = self._config.stereo
            depth[~((depth >= stereo.min_range_m) & (depth <= stereo.max_range_m))] = 0.0  # no point there: no data
            rec.log("depth", rr.DepthImage(depth, meter=1.0, depth_range=[0.0, stereo.max_range_m]))

    def _log_points(self, result: FrameResult) -> None:
        step = point_stride(len(result.points_vehicle), self._config.rerun.max_points)
        points = rr.Points3D(result.points_vehicle[::step], class_ids=result.point_labels[::step], radii=0.03)
        self._rec.log(f"{VEHICLE}/points", points)

    def _log_terrain(self, result: FrameResult) -> None:
        rec = self._rec
        grid = result.grid
        xs, ys = cell_centers(grid.config)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        valid = grid.valid
        for name, z in (("samples", grid.z), ("equalized", result.terrain.samples)):
            color = (255, 255, 255) if name == "samples" else (255, 200, 0)
            samples = rr.Points3D(np.column_stack([X[valid], Y[valid], z[valid]]), radii=0.06, colors=color)
            rec.log(f"{VEHICLE}/grid/{name}", samples)
        layers = result.layers
        vertices = np.column_stack([X.ravel(), Y.ravel(), layers["elevation"].ravel()]).astype(np.float32)
        triangles = surface_triangles(valid)  # cells with data only
        drawn = layers["elevation"][valid]
        drawn = drawn[np.isfinite(drawn)]
        lo, hi = self._elevation_span or _span(drawn)  # one scale for the whole drive, widened where needed
        if drawn.size:
            self._elevation_span = lo, hi = min(lo, float(drawn.min())), max(hi, float(drawn.max()))
        colorings = {
            "slope": colormap(layers["slope"].ravel(), *SLOPE_RANGE_RAD),
            "elevation": colormap(layers["elevation"].ravel(), lo, hi),
        }
        if "cost" in layers:
            colorings["cost"] = colormap(layers["cost"].ravel(), 0.0, 1.0)
        for name, colors in colorings.items():
            mesh = rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles, vertex_colors=colors)
            rec.log(f"{VEHICLE}/terrain/{name}", mesh)

    def _log_obstacles(self, result: FrameResult) -> None:
        boxes = shown_boxes(result)
        for group, path in (("obstacle", "obstacles"), ("occupied", "occupied")):
            shown = [box for box in boxes if box.group == group]
            if not shown:
                self._rec.log(f"{VEHICLE}/{path}", rr.Clear(recursive=False))
                continue
            self._rec.log(
                f"{VEHICLE}/{path}",
                rr.Boxes3D(
                    centers=np.array([b.obstacle.center_m for b in shown]),
                    half_sizes=np.array([b.obstacle.size_m for b in shown]) / 2,
                    quaternions=[yaw_quaternion(b.obstacle.yaw_rad) for b in shown],
                    colors=[b.rgba for b in shown],
                    labels=[b.text for b in shown],
                ),
            )

    @one_at_a_time
    def close(self) -> None:
        """Flush and finish the recording; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self._flush()
            self._rec.disconnect()
        except (RuntimeError, OSError) as exc:  # Rerun's file writer stopped on an error it logged itself
            _STUCK.append(self._rec)  # kept: its destructor would wait for the dead writer (exit_would_hang)
            why = "No space left on device" if self._disk_full() else f"its file writer stopped ({exc})"
            try:  # a recording cut mid-message, without its footer, reads back in no Rerun tool
                self.path.resolve().unlink(missing_ok=True)  # a link's target: the file written
                fate = "the part written is removed"
            except OSError:
                fate = "the part written does not read back"
            raise InputError(f"cannot finish Rerun output {self.path}: {why}; {fate}") from exc
        self._rec = None  # Rerun's destructor sweeps its recordings now, while a signal only asks the run to stop
        self.finished = True

    def _flush(self) -> None:
        """Wait until the recording is on disk. Rerun's flush waits for ever once its file writer
        has died (a full disk), so it is given :data:`_FLUSH_WAIT_S` at a time, for as long as the
        file still grows, or stands still for less than :data:`_STALL_S` on a disk with room;
        RuntimeError then."""
        size, still = None, 0.0
        while True:
            try:
                self._rec.flush(timeout_sec=_FLUSH_WAIT_S)
                return
            except RuntimeError:
                now = self.path.stat().st_size
                if now != size:
                    size, still = now, 0.0
                    continue
                still += _FLUSH_WAIT_S
                if still >= _STALL_S or self._disk_full():
                    raise

    def _disk_full(self) -> bool:
        try:
            return shutil.disk_usage(self.path.parent).free < _FULL_BYTES
        except OSError:  # cannot tell: not taken for full
            return False

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _camera_model(frame: StereoFrame, result: FrameResult):
    """The pinhole of the logged image and disparity: the rectified one (differs from
    ``frame.calibration`` when the input was rectified here), the calibration for results built
    without one."""
    return result.pinhole if result.pinhole is not None else frame.calibration
