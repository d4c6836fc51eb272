"""What every output sink shares: the :class:`Sink` protocol and the MCAP sink life cycle.

A sink receives ``write(frame, result)`` once per processed frame and ``close()`` once at the
end, in a ``finally``: ``close`` must leave a finalised file (summary and index) holding every
frame written so far, even when the run failed part way, and may be called again safely.
Threads may share a sink: its calls take turns (:func:`one_at_a_time`), each frame written whole.
Where the file itself cannot be written (a full disk), :class:`McapSink` cuts it back to its
last whole frame and ends it there without a summary, so that it still reads back.

:class:`McapSink` implements that life cycle for the MCAP flavours; subclasses only say how a
frame becomes messages (``_write_frame``) and how the file is finished (``_finish``). The helpers
below turn a :class:`~terrainmap.types.FrameResult` into the plain arrays both flavours pack.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer, Metadata
from mcap.writer import MCAP0_MAGIC

from ..config import Config, check_config
from ..errors import ConfigError, InputError, TerrainmapError, brief, counted, is_whole
from ..ros2defs import quaternion_from_matrix
from ..types import Extrinsics, FrameResult, Obstacle, StereoFrame

log = logging.getLogger(__name__)

METADATA_NAME = "terrainmap"
GRID_LAYERS = ("elevation", "slope", "cost", "label", "valid")
"""Layers written to the grid messages, in this order, where present (``cost`` is optional)."""
FLOAT_LAYERS = frozenset({"elevation", "slope", "cost"})
"""float32 layers; the others (``label``, ``valid``) are written as uint8."""
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "u1")])
"""Packed point record of the Foxglove flavour: 13 bytes, x, y, z in metres (vehicle frame), Label
(the ROS 2 flavour's label is 4 bytes wide: ``mcap_ros2.CLOUD2_DTYPE``)."""
OBSTACLE_RGBA = {"positive": (1.0, 0.35, 0.1, 0.85), "negative": (0.3, 0.3, 1.0, 0.85)}
"""Box colour by :attr:`Obstacle.kind`."""
OCCUPIED_RGBA = (0.6, 0.6, 0.6, 0.5)
"""Box colour of what occupies the cost map without being a confirmed obstacle of the frame."""


def output_path(what: str, path) -> Path:
    """``path`` as a Path; :class:`InputError` naming ``what`` (an output) where it is no path."""
    if not isinstance(path, str | os.PathLike):
        raise InputError(f"{what}: expected a file path, got {brief(path)}")
    return Path(path)


def one_at_a_time(method):
    """A sink method whose calls from several threads take turns (on the sink's ``_lock``, an
    RLock: a signal handler that closes the sink within a write of its own thread does not wait for
    ever; :meth:`McapSink.close` refuses that close, which fails the write, and a close after it
    ends the file with the frame before)."""

    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return locked


def check_frame(what: str, frame: StereoFrame, result: FrameResult | None, bits: int, *, failed: bool = False) -> None:
    """:class:`InputError` naming ``what`` (an output) unless ``frame`` is a StereoFrame and
    ``result`` its FrameResult (``failed``: a frame the pipeline could not process, which has none),
    the frame's index is a whole number, the result is that frame's (the same index and stamp) and
    the stamp a whole number of nanoseconds in [0, 2^bits)."""
    if not isinstance(frame, StereoFrame) or not (failed or isinstance(result, FrameResult)):
        raise InputError(f"{what}: expected a StereoFrame and its FrameResult, got {type(frame).__name__} and "
                         f"{type(result).__name__}")
    result = frame if failed else result  # (a failed frame's own index and stamp)
    if not is_whole(frame.index):
        raise InputError(f"{what}: the frame index must be a whole number, got {frame.index!r}")
    for stamp in {frame.stamp_ns, result.stamp_ns}:
        if not is_whole(stamp) or not 0 <= stamp < 2**bits:
            raise InputError(f"{what}: frame {result.index}: the stamp must be a whole number of nanoseconds in "
                             f"[0, 2^{bits}), got {stamp!r}")
    if (frame.index, frame.stamp_ns) != (result.index, result.stamp_ns):
        raise InputError(f"{what}: the result of frame {result.index!r} (stamp {result.stamp_ns!r} ns) given with "
                         f"frame {frame.index!r} (stamp {frame.stamp_ns!r} ns): a result goes with its own frame")


def _to_disk(file) -> None:
    """Flush ``file`` and have the OS write it to the device: the output of a finished (or cut
    back) run then survives a power cut right after, as on a vehicle whose power is switched off."""
    file.flush()
    os.fsync(file.fileno())


def _utf8(value) -> str:
    """``str(value)`` that UTF-8 can encode: a path whose name is not UTF-8 reaches Python with
    surrogate escapes, which would break the MCAP metadata record; they are written as ``\\udcff``."""
    return str(value).encode("utf-8", "backslashreplace").decode("utf-8")


@runtime_checkable
class Sink(Protocol):
    """Receives each processed frame; ``close`` finalises the output (idempotent) and sets
    ``finished`` once the output is complete and readable. A sink may also have
    ``failed(frame, error)``, which the runner calls for a frame the pipeline could not process
    (:class:`~terrainmap.errors.FrameError`): the Rerun recording marks it on its timeline; an
    MCAP writes nothing for it (the latest messages' stamps say how old they are)."""

    path: Path
    finished: bool

    def write(self, frame: StereoFrame, result: FrameResult) -> None: ...

    def close(self) -> None: ...


class McapSink:
    """Life cycle of an MCAP output: open, write frames, always finish (once), context manager.

    Parameters
    ----------
    path : str or Path
        Output ``.mcap`` file (overwritten).
    config : Config
        Effective configuration, stored as TOML in the ``terrainmap`` metadata record.
    metadata : mapping of str to str, optional
        Extra entries for the metadata record (e.g. ``{"source": "<input path>"}``).
    """

    def __init__(self, path: str | Path, *, config: Config, metadata: Mapping[str, str] | None = None):
        self._lock = threading.RLock()
        self.path = output_path("MCAP output", path)
        check_config(f"MCAP output {path}", config)  # before the file is created: its TOML goes into the metadata
        self._config = config
        if metadata is not None and not isinstance(metadata, Mapping):
            raise ConfigError(f"MCAP output {path}: metadata must be a mapping of names to texts, got "
                              f"{type(metadata).__name__}")
        self._metadata = {_utf8(k): _utf8(v) for k, v in (metadata or {}).items()}
        self._extrinsics: Extrinsics | None = None  # the first frame's
        self._extrinsics_changes = 0  # frames whose camera pose differs from the frame before's
        self._camera: tuple | None = None  # camera_transforms of the frame being written
        self._last_static: tuple | None = None
        self.frames_written = 0
        self._closed = False
        self._writing = False  # within write(): a close() then is refused
        self._failed: BaseException | None = None  # what stopped the file being written, part way into a frame
        self.finished = False
        try:
            self._stream = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise InputError(f"cannot create MCAP output {self.path}: {exc.strerror or exc}") from exc
        try:
            self._open(self._stream)
            self._stream.flush()  # the header on disk: where a file cut back before any frame ends
        except BaseException as exc:
            with contextlib.suppress(OSError):  # closing flushes what failed again
                self._stream.close()
            if not isinstance(exc, OSError):
                raise
            self.path.resolve().unlink(missing_ok=True)  # not even a header: no MCAP at all (a link's target)
            raise InputError(f"cannot write MCAP output {self.path}: {exc.strerror or exc}") from exc
        self._whole = self._stream.tell()  # where the last whole frame ends (the header, before any)

    def _open(self, stream) -> None:
        raise NotImplementedError

    def _point_stride(self, result: FrameResult) -> int:
        """Every how many points the frame's point cloud keeps (``config.mcap.max_points``)."""
        return point_stride(len(result.points_vehicle), self._config.mcap.max_points)

    def _write_frame(self, frame: StereoFrame, result: FrameResult) -> None:
        raise NotImplementedError

    def _finish(self, metadata: dict[str, str]) -> None:
        raise NotImplementedError

    @one_at_a_time
    def write(self, frame: StereoFrame, result: FrameResult) -> None:
        """Write all messages of one frame, stamped ``frame.stamp_ns``."""
        if self._closed:
            raise TerrainmapError(f"MCAP output {self.path} is already closed")
        if self._failed is not None:
            raise TerrainmapError(f"MCAP output {self.path} failed in an earlier frame ({self._failed})")
        check_frame(f"MCAP output {self.path}", frame, result, 64)  # before any message of the frame is written
        if np.shape(result.point_labels) != (len(result.points_vehicle),):
            raise TerrainmapError(f"frame {result.index}: {len(result.points_vehicle)} points but point labels "
                                  f"of shape {np.shape(result.point_labels)}")
        check_layers(result)  # before the frame's first message (its /tf) is written
        camera = camera_transforms(result.extrinsics)
        if self._extrinsics is None:
            self._extrinsics = result.extrinsics
        self._extrinsics_changes += self._camera not in (None, camera)
        self._camera = camera
        self._writing = True
        try:
            self._write_frame(frame, result)
            # The frame's chunk goes to the file now, so that a later failure can keep every
            # frame before it (_cut_back). `_writer._writer`: the flavour writer's mcap writer.
            self._writer._writer.flush()
        except BaseException as exc:  # part of the frame may be written or buffered: close() cuts it off
            self._failed = exc
            if isinstance(exc, OSError):
                raise InputError(f"cannot write MCAP output {self.path}: {exc.strerror or exc}") from exc
            raise
        finally:
            self._writing = False
        self.frames_written += 1
        self._whole = self._stream.tell()

    @one_at_a_time
    def close(self) -> None:
        """Write the metadata record, summary and index, and close the file. Safe to call twice."""
        if self._closed:
            return
        if self._writing:  # a signal handler's, within a write of this thread (one_at_a_time)
            raise TerrainmapError(f"MCAP output {self.path}: close() while a frame is being written; close it after")
        self._closed = True
        failed_in_frame = self._failed
        try:
            if self._failed is None:
                self._finish(self._metadata_record())
                _to_disk(self._stream)
        except OSError as exc:  # disk full, device gone: the summary could not be written
            self._failed = exc
        finally:
            try:
                self._stream.close()
            except OSError as exc:
                self._failed = self._failed or exc
        if isinstance(self._failed, OSError):
            what = "write" if self._failed is failed_in_frame else "finish"
            raise InputError(f"cannot {what} MCAP output {self.path}: {self._failed.strerror or self._failed}; "
                             f"{self._cut_back()}") from self._failed
        if self._failed is not None:  # the run's own error says what went wrong
            log.warning("MCAP output %s: %s", self.path, self._cut_back())
            return
        self.finished = True
        log.info("wrote %s to %s", counted(self.frames_written, "frame"), self.path)

    def _cut_back(self) -> str:
        """Cut the file back to the end of its last whole frame and end it there with the metadata
        record and a footer without summary (a valid MCAP that readers read from start to end),
        or without the metadata where there is no room for it. Returns what the file holds now."""
        error: OSError | None = None
        for metadata in (True, False):
            ending = RecordBuilder()
            if metadata:
                Metadata(name=METADATA_NAME, metadata=self._metadata_record()).write(ending)
            DataEnd(data_section_crc=0).write(ending)  # 0: no CRC computed
            Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(ending)
            ending.write(MCAP0_MAGIC)
            try:
                with open(self.path, "r+b") as file:
                    file.truncate(self._whole)
                    file.seek(self._whole)
                    file.write(ending.end())
                    _to_disk(file)
                break
            except OSError as exc:
                error = exc
        else:
            return f"it could not be cut back to its last whole frame ({error.strerror or error}) and is damaged"
        n = self.frames_written
        if n == 0:
            return "cut back to its header (no frame in it)"
        first = "its first frame, which reads" if n == 1 else f"its first {n} frames, which read"
        return f"cut back to {first} back without an index"

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __del__(self) -> None:
        # A sink dropped without close() (no `with`): finished, not left without its summary.
        if getattr(self, "_whole", None) is not None and not self._closed:
            with contextlib.suppress(Exception):
                self.close()

    def _metadata_record(self) -> dict[str, str]:
        from .. import __version__

        record = {"version": __version__, "config": self._config.to_toml(), "frames": str(self.frames_written)}
        if self._extrinsics is not None:
            record["extrinsics"] = json.dumps(self._extrinsics.to_dict())
            record["extrinsics_changes"] = str(self._extrinsics_changes)
        return {**record, **self._metadata}

    def _transforms(self, frame: StereoFrame, result: FrameResult) -> list[tuple[str, tuple]]:
        """``(topic, transforms)`` pairs to write for this frame (transforms as :func:`camera_transforms`).

        Estimated extrinsics may change every frame and go on ``/tf``; fixed ones (from tf, a
        calibration file or the defaults) go on ``/tf_static`` when first seen or changed. The
        vehicle's pose in the odometry frame, where the source gave one, goes on ``/tf``. Those
        the log's tf gave are left out with ``mcap.log_transforms`` off.
        """
        out = []
        camera = self._camera  # set by write() for this frame
        log_transforms = self._config.mcap.log_transforms
        if result.extrinsics.source == "estimated":
            out.append(("/tf", camera))
        elif camera != self._last_static and (log_transforms or result.extrinsics.source != "tf"):
            self._last_static = camera
            out.append(("/tf_static", camera))
        if frame.vehicle_pose is not None and log_transforms:
            out.append(("/tf", (vehicle_transform(frame, result.extrinsics),)))
        return out


def camera_transforms(extrinsics: Extrinsics) -> tuple[tuple[str, str, tuple, tuple], ...]:
    """``(parent, child, translation_m (x, y, z), rotation (x, y, z, w))`` of the camera in the
    vehicle frame, or of each edge of the log's tf between them (``extrinsics.tf_path``)."""
    if extrinsics.tf_path:
        return tuple(_transform(parent, child, T[:3, :3], T[:3, 3]) for parent, child, T in extrinsics.tf_path)
    return (_transform(extrinsics.vehicle_frame_id, extrinsics.camera_frame_id, extrinsics.rotation,
                       extrinsics.translation),)


def vehicle_transform(frame: StereoFrame, extrinsics: Extrinsics) -> tuple[str, str, tuple, tuple]:
    """``(parent, child, translation_m, rotation (x, y, z, w))`` of the vehicle frame in the log's
    odometry frame at this frame's stamp (``frame.vehicle_pose`` must be given)."""
    T = np.asarray(frame.vehicle_pose, float)
    return _transform(frame.odometry_frame_id, extrinsics.vehicle_frame_id, T[:3, :3], T[:3, 3])


def _transform(parent: str, child: str, rotation, translation) -> tuple[str, str, tuple, tuple]:
    return parent, child, tuple(float(v) for v in np.asarray(translation, float).reshape(3)), quaternion_from_matrix(
        np.asarray(rotation, float))


def check_layers(result: FrameResult) -> None:
    """:class:`TerrainmapError` when a layer to write has another shape than the grid."""
    shape = tuple(result.grid.config.shape)
    for name in GRID_LAYERS:
        if name in result.layers and np.shape(result.layers[name]) != shape:
            raise TerrainmapError(f"frame {result.index}: layer '{name}' has shape {np.shape(result.layers[name])}, "
                                  f"grid is {shape}")


def grid_layers(result: FrameResult) -> dict[str, np.ndarray]:
    """The grid layers to write, in :data:`GRID_LAYERS` order, as (m0, m1) float32 / uint8 arrays.

    Elevation and slope are NaN where the cell is not ``valid`` (no data: the surface only
    extrapolates there), as grid_map expects.

    Raises
    ------
    TerrainmapError
        A layer's shape differs from the grid's.
    """
    check_layers(result)
    layers = {name: np.asarray(result.layers[name]).astype(np.float32 if name in FLOAT_LAYERS else np.uint8, copy=False)
              for name in GRID_LAYERS if name in result.layers}
    if "valid" in layers:
        for name in ("elevation", "slope"):
            if name in layers:
                layers[name] = np.where(layers["valid"] > 0, layers[name], np.float32(np.nan))
    return layers


def point_stride(n: int, max_points: int) -> int:
    """Keep every k-th of ``n`` points so that at most ``max_points`` remain (0: all, k = 1)."""
    return 1 if max_points <= 0 else max(1, -(-n // max_points))


def points_record(result: FrameResult, head: bytes, tail: bytes = b"", stride: int = 1,
                  dtype: np.dtype = POINT_DTYPE) -> bytearray:
    """``head`` + every ``stride``-th point packed as a ``dtype`` record (:data:`POINT_DTYPE`, or
    one whose little-endian unsigned label is wider) + ``tail``, in one buffer.

    Both flavours serialize a point cloud as a small header, the packed points and (ROS 2) a
    trailing field; packing straight into the final buffer saves two 4 MB copies per frame at
    300k points. x, y, z go in as one 12-byte run per point (twice as fast as field by field).
    """
    points = np.ascontiguousarray(result.points_vehicle[::stride], dtype="<f4").reshape(-1, 3)
    n, step = len(points), dtype.itemsize
    record = bytearray(len(head) + n * step + len(tail))  # zeros: a wider label's high bytes stay 0
    record[: len(head)] = head
    record[len(record) - len(tail) :] = tail
    raw = np.frombuffer(record, np.uint8, count=n * step, offset=len(head)).reshape(n, step)
    raw[:, :12] = points.view(np.uint8)
    raw[:, 12] = result.point_labels[::stride]
    return record


SLOPE_RANGE_RAD = (0.0, np.radians(30.0))
"""Slopes coloured from green (flat) to red (this steep and over) by both viewers' surfaces."""


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Values → RGB uint8 on a green–yellow–red ramp (NaN grey), shape (..., 3)."""
    t = np.clip((np.nan_to_num(values, nan=lo) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = np.stack([np.clip(2 * t, 0, 1), np.clip(2 - 2 * t, 0, 1), np.full_like(t, 0.15)], axis=-1)
    out = (255 * rgb).astype(np.uint8)
    out[np.isnan(values)] = (128, 128, 128)
    return out


def surface_triangles(valid: np.ndarray) -> np.ndarray:
    """Triangles (k, 3) uint32 of a mesh over the (m0, m1) lattice of cell centres (vertex
    ``ix·m1 + iy``), two a square of four centres: those whose three corners hold data (``valid``)."""
    all_of_them = _triangles(*valid.shape)
    return all_of_them[valid.ravel()[all_of_them].all(axis=1)]


@functools.lru_cache(maxsize=4)  # one per grid shape
def _triangles(m0: int, m1: int) -> np.ndarray:
    """Two triangles per grid square of an (m0, m1) vertex lattice, (2·(m0−1)·(m1−1), 3) uint32."""
    i = (np.arange(m0 - 1)[:, None] * m1 + np.arange(m1 - 1)[None, :]).ravel()
    return np.concatenate([np.stack([i, i + m1, i + 1], 1), np.stack([i + 1, i + m1, i + m1 + 1], 1)]).astype(np.uint32)


class Box(NamedTuple):
    """A box the outputs draw: ``group`` "obstacle" (a confirmed obstacle, ``number`` its track id)
    or "occupied" (what else occupies the cost map, ``number`` counting from 0 in the frame)."""

    group: str
    number: int
    obstacle: Obstacle
    rgba: tuple[float, float, float, float]
    text: str


def shown_boxes(result: FrameResult) -> list[Box]:
    """The boxes every output draws: the confirmed tracks (a detection seen in one frame only, or
    a track not yet confirmed, is not an obstacle; :mod:`terrainmap.tracking`), coloured by kind
    and labelled ``"<track id> <kind> <height> m"``; then, in grey, what else occupies the cost
    map (:attr:`FrameResult.occupied`): ``"part of <track id>"`` for a cluster taken for part of
    one of the frame's confirmed obstacles (it has that obstacle's track id), ``"<track id>
    unseen"`` for a confirmed obstacle missed in the last frames, at its predicted place (its own
    track id, none of the frame's obstacles')."""
    boxes = [Box("obstacle", o.track_id, o, OBSTACLE_RGBA.get(o.kind, OCCUPIED_RGBA),
                 f"{o.track_id} {o.kind} {o.height_m:.2f} m") for o in result.obstacles if o.confirmed]
    shown = {box.number for box in boxes}
    for k, o in enumerate(result.occupied):
        text = f"part of {o.track_id}" if o.track_id in shown else f"{o.track_id} unseen"
        boxes.append(Box("occupied", k, o, OCCUPIED_RGBA, text))
    return boxes
