"""Stereo pairs from logs: MCAP files, rosbag2 directories (MCAP or sqlite3 storage) and ROS 1 bags.

Images: ROS 2/1 ``sensor_msgs/msg/Image`` and ``CompressedImage``, Foxglove ``RawImage`` and
``CompressedImage``. Calibration: ``sensor_msgs/msg/CameraInfo`` or ``foxglove.CameraCalibration``
matched to each image topic by namespace (or a calibration file). Extrinsics: the tf tree
(``tf2_msgs/msg/TFMessage``, ``foxglove.FrameTransform(s)``) from ``base_link`` (else
``base_footprint``, else the root) to the left image's frame. Vehicle poses: the dynamic tf
from an odometry frame to ``base_link`` / ``base_footprint`` (:class:`~terrainmap.sources.tf.VehiclePoses`),
looked up at each pair's stamp (``StereoFrame.vehicle_pose``), so obstacles are tracked over ground.

Calibration, the first left image (for its frame id) and the transforms are read at open, each
through the topic index, so they are found whatever part of the log ``frames()`` selects. Then
``frames()`` streams the two image topics (and the dynamic tf) once, pairs them by header stamp
(:class:`~terrainmap.sources.pairing.StereoPairer`, bounded buffers; with odometry a pair waits up
to ``POSE_WAIT_NS`` of log time for the pose after its stamp) and decodes images only for the
pairs it yields: memory stays bounded for a log of any length.
"""

from __future__ import annotations

import itertools
import logging
import math
from abc import abstractmethod
from collections import deque
from collections.abc import Iterator
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from ..errors import CalibrationError, DamagedImageError, InputError, NoStereoError
from ..types import Extrinsics, StereoCalibration, StereoFrame
from . import calibration as calib_io
from . import messages as msgs
from .base import PairRef, Source, extrinsics_entry, natural_key
from .images import stereo_pair
from .pairing import StereoPairer
from .readers import MCAP_MAGIC, McapLog, Rosbag2Bag, SplitLog, bag_metadata
from .ros1bag import MAGIC as ROS1_MAGIC
from .ros1bag import Ros1Bag
from .tf import TransformTree, VehiclePoses
from .topics import calibration_topic, rectified_name, side_tokens, stereo_topics

logger = logging.getLogger(__name__)

MAX_DYNAMIC_TF_MESSAGES = 1000
"""How many non-static tf messages are read at most while looking for the camera's parent frames."""

CLOCKS_APART_NS = 3600 * 1_000_000_000
"""A stereo pair this far from the odometry's newest pose is taken for stamped by another clock
(time since boot against Unix time, say), which is warned about once."""

POSE_WAIT_NS = 1_000_000_000
"""How long (log time) a stereo pair waits for the vehicle pose after its stamp before it is
yielded with the poses known by then."""

UNSTAMPED_PREFIX = 5
"""Images whose topic's first this many messages are stamped 0 are taken as never stamped."""

CALIBRATION_TRIES = 5
"""How many of a calibration topic's first messages are tried for one that is usable."""


def _info_error(message, topic: str) -> CalibrationError | None:
    """Why a camera info message cannot serve (:func:`~terrainmap.sources.messages.camera_info`), or None."""
    try:
        msgs.camera_info(message, topic)
    except CalibrationError as exc:
        return exc
    return None


def _starts_with(path: Path, magic: bytes) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(magic)) == magic
    except OSError:
        return False


class LogSource(Source):
    """Stereo pairs from a log through a message reader (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        *,
        left_topic: str | None = None,
        right_topic: str | None = None,
        calibration: str | Path | None = None,
        pair_tolerance_ns: int = 10_000_000,
    ):
        super().__init__(path)
        self._fitted_shape = self._stale_shape = None  # image shapes: the last that fitted its calibration, the last skipped
        self.reader = self._open_reader()
        try:
            self._read_log(left_topic, right_topic, calibration, pair_tolerance_ns)
        except BaseException:  # a reader that holds the log open (a temporary folder) lets go of it
            self.close()
            raise

    def _read_log(self, left_topic, right_topic, calibration, pair_tolerance_ns) -> None:
        """Find the stereo topics, the calibration and the camera pose (see the module docstring)."""
        try:
            self.left_topic, self.right_topic = stereo_topics(self.reader.types, left_topic, right_topic, str(self.path))
        except InputError as exc:
            damage, reason = self.reader.damage, str(exc).removeprefix(f"{self.path}: ")
            raise NoStereoError(f"{damage}; before it, {reason}" if damage else str(exc), self._contents()) from None
        if self.left_topic == self.right_topic:
            raise InputError(f"{self.path}: left and right topic are the same ({self.left_topic})")
        self.pair_tolerance_ns = int(pair_tolerance_ns)
        # (damage before the right topic's first message is left for frames() to meet, as it was)
        firsts = {t: self._first(t, UNSTAMPED_PREFIX, lenient=t == self.right_topic)
                  for t in (self.left_topic, self.right_topic)}
        self._image_frames = tuple(msgs.frame_id(firsts[t][0]) if firsts[t] else "camera_optical"
                                   for t in (self.left_topic, self.right_topic))
        self.frame_id = self._image_frames[0]
        # A driver that never sets the header stamp (0 on its first UNSTAMPED_PREFIX images): both
        # cameras' images are then paired and placed by log time, one clock for both.
        self._unstamped = [t for t, first in firsts.items() if first and not any(map(msgs.stamp_ns, first))]
        override = calib_io.load_calibration_file(calibration) if calibration else None
        self._static_tf_topics, self.odometry_topics = self._tf_topics()
        tree = self._tree = self._tf_tree()
        self._stereo_tf_read = False  # (_stereo_pose)
        self.calibration_topics: tuple[str | None, str | None] = (None, None)
        self.calibration_error: CalibrationError | None = None
        self.calibration: StereoCalibration | None = override[0] if override else self._log_calibration()
        given = override[1] if override else None
        if given is not None:  # a calibration file names no frames: the camera's is the images'
            given = replace(given, camera_frame_id=self.frame_id)
        self.extrinsics: Extrinsics | None = given or tree.extrinsics(self.frame_id)

    @abstractmethod
    def _open_reader(self) -> McapLog | Rosbag2Bag | Ros1Bag:
        """The message reader of ``self.path``."""

    def close(self) -> None:
        close = getattr(self.reader, "close", None)  # a reader that keeps its log open
        if close is not None:
            close()
        super().close()

    def _first(self, topic: str, n: int = 1, *, lenient: bool = False) -> list:
        """The first ``n`` messages of ``topic`` (fewer where it has fewer, or where damage ends the
        read after the first, or, ``lenient``, before it: the damage is for ``frames()`` to meet)."""
        stream, found = self.reader.messages([topic]), []
        try:
            for _, _, message in itertools.islice(stream, n):
                found.append(message)
        except InputError:
            if not (found or lenient):
                raise
        finally:
            stream.close()
        return found

    def _log_calibration(self) -> StereoCalibration | None:
        topics = [t for t, kind in self.reader.types.items() if kind in msgs.CALIBRATION_TYPES]
        sides = side_tokens(self.left_topic, self.right_topic)
        left = calibration_topic(self.left_topic, topics, side=sides)
        right = calibration_topic(self.right_topic, topics, exclude=left, side=sides and sides[::-1])
        self.calibration_topics = (left, right)
        try:
            if left is None or right is None:
                raise CalibrationError(
                    f"{self.path}: no camera calibration topic for {self.left_topic} and {self.right_topic} "
                    f"(calibration topics: {', '.join(topics) or 'none'}); pass --calibration"
                )
            infos = [self._first(t, CALIBRATION_TRIES) for t in (left, right)]
            if not all(infos):
                raise CalibrationError(f"{self.path}: {left} or {right} holds no readable message; pass --calibration")
            chosen = []  # the first usable info of each side (a driver may publish an empty one first)
            for found, topic in zip(infos, (left, right), strict=True):
                errors = [_info_error(message, topic) for message in found]
                if all(errors):  # they name the topic: name the log too
                    more = f" (nor is any of the {len(found) - 1} messages after it)" if len(found) > 1 else ""
                    raise CalibrationError(f"{self.path}: {errors[0]}{more}") from errors[0]
                chosen.append(found[errors.index(None)])
            try:
                return self._calibration_of(*chosen)
            except CalibrationError as exc:
                raise CalibrationError(f"{self.path}: {exc}") from exc
        except CalibrationError as exc:
            self.calibration_error = exc
            return None

    def _calibration_of(self, left_msg, right_msg) -> StereoCalibration:
        """The stereo calibration of a left and a right camera info message (``calibration_topics``)."""
        left, right = self.calibration_topics
        left_info, right_info = msgs.camera_info(left_msg, left), msgs.camera_info(right_msg, right)
        if left_info["frame_id"] == right_info["frame_id"]:  # infos naming no frame of their own (or one
            left_info["frame_id"], right_info["frame_id"] = self._image_frames  # for both): the images'
        no_baseline = left_info["P"][0, 3] == right_info["P"][0, 3]  # (then tf's pose of the right camera is used)
        return msgs.calibration_from_infos(
            left_info,
            right_info,
            rectified_images=rectified_name(self.left_topic),
            source=f"{left} + {right}",
            right_in_left=self._stereo_pose(left_info["frame_id"], right_info["frame_id"]) if no_baseline else None,
        )

    def _calibration_after(
        self, current: StereoCalibration, infos: dict, stamp_ns: int, warned: bool
    ) -> tuple[StereoCalibration, bool]:
        """The calibration of the newest left and right camera infos (``infos``: calibration topic →
        message), with a warning where it differs from ``current``; ``current`` where it does not
        or is unusable (warned about once: ``warned`` says whether it was; returned too)."""
        try:
            new = self._calibration_of(*(infos[t] for t in self.calibration_topics))
        except CalibrationError as exc:
            if not warned:
                logger.warning("%s: a camera info at %.3f s is unusable, the calibration before is kept (%s)",
                               self.path, stamp_ns / 1e9, exc)
            return current, True
        if new.key() != current.key():
            logger.warning("%s: the camera calibration changes at %.3f s (%s, was %s); the frames after use it",
                           self.path, stamp_ns / 1e9, _brief(new), _brief(current))
            return new, warned
        return current, warned

    def _tf_topics(self) -> tuple[list[str], list[str]]:
        """The log's (static, dynamic) tf topics, told apart by name."""
        tf_topics = sorted(t for t, kind in self.reader.types.items() if kind in msgs.TF_TYPES)
        return [t for t in tf_topics if "static" in t], [t for t in tf_topics if "static" not in t]

    def _tf_tree(self) -> TransformTree:
        """The static transforms, and the dynamic ones of the first ``MAX_DYNAMIC_TF_MESSAGES``
        messages where the static ones do not place the camera."""
        tree = TransformTree()
        for topics, limit in ((self._static_tf_topics, None), (self.odometry_topics, MAX_DYNAMIC_TF_MESSAGES)):
            if topics and not tree.resolves(self.frame_id):
                self._read_transforms(tree, topics, limit, lambda: tree.resolves(self.frame_id))
        return tree

    def _read_transforms(self, tree: TransformTree, topics: list[str], limit: int | None, enough) -> None:
        """Add the transforms of the first ``limit`` messages of ``topics`` (all: None) to ``tree``,
        stopping early once ``enough()`` (with a limit)."""
        stream = self.reader.messages(topics)
        try:
            for topic, _, msg in itertools.islice(stream, limit):
                for _, *transform in msgs.transforms(msg, self.reader.types[topic]):
                    tree.add(*transform)
                if limit and enough():
                    break
        except InputError as exc:  # a damaged log (reader.damage): keep the transforms read before it
            logger.warning("reading transforms: %s", exc)
        finally:
            stream.close()

    def _stereo_pose(self, left: str, right: str) -> np.ndarray | None:
        """tf's pose of camera frame ``right`` in ``left`` (4×4), for camera infos that give no
        baseline; where the transforms read do not relate them, the first ``MAX_DYNAMIC_TF_MESSAGES``
        dynamic ones are read for it (ROS 1's static_transform_publisher sends it on ``/tf``), once."""
        pose = self._tree.relative(left, right)
        if pose is None and self.odometry_topics and not self._stereo_tf_read:
            self._stereo_tf_read = True
            self._read_transforms(self._tree, self.odometry_topics, MAX_DYNAMIC_TF_MESSAGES,
                                  lambda: self._tree.relative(left, right) is not None)
            pose = self._tree.relative(left, right)
        return pose

    def _pairs(self) -> Iterator[PairRef]:
        if self.calibration is None:
            raise self.calibration_error
        pairer = StereoPairer(self.pair_tolerance_ns, same=msgs.same_data)
        poses = VehiclePoses()
        self._clocks_told = False  # (_pair_ref: images and odometry on different clocks, said once)
        pending: deque = deque()  # (log time made, pair): pairs waiting for the pose after their stamp
        index, warned = 0, False  # warned: of an unusable camera info, once
        if self._unstamped:
            logger.warning("%s: %s has images with no header stamp (0); both cameras' images are paired and "
                           "placed by log time", self.path, " and ".join(self._unstamped))
        # The camera infos are followed too (unless a calibration file is given): a calibration that
        # changes part way applies to the pairs made after a left and a right info of it, paired by
        # stamp as the images are; where one side is a single message (latched), with that one.
        calibration, info_topics = self.calibration, [t for t in self.calibration_topics if t]
        infos, info_pairer = {}, StereoPairer(self.pair_tolerance_ns)
        latched = [t for t in info_topics if self.reader.counts.get(t) == 1]
        topics = [self.left_topic, self.right_topic, *self.odometry_topics, *info_topics]
        failed: list[Exception] = []

        def messages():  # a log that ends in damage: the pairs waiting for a pose are given first
            try:
                yield from self.reader.messages(topics)
            except Exception as exc:
                failed.append(exc)

        for topic, log_time_ns, msg in messages():
            if topic in self.odometry_topics:  # (then the pairs waiting for it below, not at the next image)
                for transform in msgs.transforms(msg, self.reader.types[topic]):
                    poses.add(*transform)
            else:
                stamp_ns = log_time_ns if self._unstamped else msgs.stamp_ns(msg) or log_time_ns
                if topic in info_topics:
                    if latched:  # one side is a single message: each new info goes with the other's newest
                        infos[topic] = msg
                        ready = len(infos) == 2
                    else:  # both republished: paired by stamp, as the images are
                        made = info_pairer.push(info_topics.index(topic), stamp_ns, msg)
                        ready = made is not None
                        if ready:
                            infos = dict(zip(info_topics, made[1:], strict=True))
                    if ready:
                        calibration, warned = self._calibration_after(calibration, infos, stamp_ns, warned)
                else:
                    pair = pairer.push(0 if topic == self.left_topic else 1, stamp_ns, msg)
                    if pair is not None:
                        pending.append((log_time_ns, (index, *pair, calibration)))
                        index += 1
            # With odometry, a pair waits for the poses around its stamp, or for a second of log time.
            while pending and (not self.odometry_topics or poses.reach(pending[0][1][1])
                               or log_time_ns - pending[0][0] >= POSE_WAIT_NS):
                yield self._pair_ref(pending.popleft()[1], poses)
        while pending:
            yield self._pair_ref(pending.popleft()[1], poses)
        if failed:
            raise failed[0]
        pairer.finish()
        if pairer.dropped:
            full = (f"; {pairer.overflowed} of them left a full pairing buffer: one camera's images are logged "
                    f"over {pairer.max_buffer} messages behind the other's") if pairer.overflowed else ""
            half = pairer.half_period_ns
            within = (f"{self.pair_tolerance_ns / 1e6:.1f} ms (--pair-tolerance-ms)" if half is None or
                      half > self.pair_tolerance_ns else
                      f"{half / 1e6:.1f} ms, half the cameras' frame period (--pair-tolerance-ms "
                      f"{self.pair_tolerance_ns / 1e6:.1f})")
            missed = pairer.offset_ns or 0
            hint = (f"; the cameras' stamps lie about {missed / 1e6:.1f} ms apart: --pair-tolerance-ms "
                    f"{math.ceil(missed * 1.25 / 1e6)} would pair them"
                    if missed > self.pair_tolerance_ns and (half is None or missed < half) else "")
            logger.warning("%s: %d of %d image messages had no partner within %s%s%s",
                           self.path, pairer.dropped, pairer.pushed, within, full, hint)
        if pairer.repeated:
            logger.warning("%s: %d image messages repeated the message before them on their topic, stamp and "
                           "image (duplicates), and were skipped", self.path, pairer.repeated)

    def _pair_ref(self, pair: tuple, poses: VehiclePoses) -> PairRef:
        index, stamp_ns = pair[:2]
        pose = poses.at(stamp_ns)
        if pose is None and poses.newest_ns is not None and abs(stamp_ns - poses.newest_ns) > CLOCKS_APART_NS:
            if not self._clocks_told:
                self._clocks_told = True
                logger.warning("%s: the stereo pair stamped %.3f s has no vehicle pose: the odometry (%s) is stamped "
                               "around %.3f s; are the images and the tf stamped by different clocks? Obstacles are "
                               "tracked in the vehicle frame where no pose is found", self.path, stamp_ns / 1e9,
                               ", ".join(self.odometry_topics), poses.newest_ns / 1e9)
        if pose is not None and self.extrinsics is not None and poses.child != self.extrinsics.vehicle_frame_id:
            # odom → base_footprint poses, the camera mounted on base_link: the pose of base_link
            mount = self._tree.relative(poses.child, self.extrinsics.vehicle_frame_id)
            pose = pose if mount is None else pose @ mount
        load = partial(self._load, *pair, vehicle_pose=pose, odometry_frame_id=poses.parent or "odom")
        return PairRef(index, stamp_ns, load)

    def _load(
        self, index: int, stamp_ns: int, left_msg, right_msg, calibration: StereoCalibration, *,
        vehicle_pose=None, odometry_frame_id="odom"
    ) -> StereoFrame | None:
        types = self.reader.types
        try:
            left = msgs.image_array(left_msg, types[self.left_topic], self.left_topic)
            right = msgs.image_array(right_msg, types[self.right_topic], self.right_topic)
            left, right = stereo_pair(left, right, self.left_topic, self.right_topic)
        except DamagedImageError as exc:  # one bad image: that pair is lost, the run goes on
            self._skip_damaged(f"{self.path}: stereo pair at {stamp_ns / 1e9:.3f} s", exc)
            return None
        except InputError as exc:  # an encoding or size it cannot read, images of two sizes
            raise InputError(f"{self.path}: {exc}") from exc
        try:
            calibration = calib_io.fit_to_image(calibration, left.shape, self.left_topic)
        except CalibrationError as exc:
            # Drivers log a camera's info after its image: the first pair of images of a new size
            # still holds the old calibration. One such pair is skipped; a second, or a size that
            # never fitted, means the calibration does not follow the images.
            if self._fitted_shape in (None, left.shape) or self._stale_shape == left.shape:
                raise CalibrationError(f"{self.path}: {exc}") from exc
            self._stale_shape = left.shape
            self._skip_damaged(f"{self.path}: stereo pair at {stamp_ns / 1e9:.3f} s", exc, "images of a new size "
                               "before their camera infos")
            return None
        self._fitted_shape = left.shape
        return StereoFrame(
            index=index,
            stamp_ns=stamp_ns,
            left=left,
            right=right,
            calibration=calibration,
            extrinsics=self.extrinsics,
            frame_id=msgs.frame_id(left_msg),
            source=f"{self.path} {self.left_topic} + {self.right_topic}",
            vehicle_pose=vehicle_pose,
            odometry_frame_id=odometry_frame_id,
        )

    def skipped(self) -> list[str]:
        return [*self.reader.skipped, *self._damaged]

    def _contents(self) -> dict:
        """What the log holds, whatever its topics: format, files, damage, topics."""
        counts, span = self.reader.counts, self.reader.span_ns
        return {
            "format": self.format,
            "path": str(self.path),
            "files": [str(p) for p in self.reader.paths],
            "duration_s": None if span is None else (span[1] - span[0]) / 1e9,  # of all its messages
            # in the file as a whole, else the parts skipped so far (reading its calibration and tf)
            "damage": self.reader.damage or "; ".join(self.reader.skipped) or None,
            "topics": [{"topic": t, "type": k, "count": counts.get(t)} for t, k in sorted(self.reader.types.items())],
        }

    def describe(self) -> dict:
        counts = self.reader.counts
        sides = [counts.get(self.left_topic), counts.get(self.right_topic)]
        pairs = None if None in sides else min(sides)  # (unknown: an MCAP without its statistics)
        return {
            **self._contents(),
            "left_topic": self.left_topic,
            "right_topic": self.right_topic,
            "frames": pairs,
            "frames_note": "at most; from message counts, pairs are matched by stamp" if pairs is not None
            else "unknown: the MCAP has no message counts (no statistics record)",
            "frame_id": self.frame_id,
            "calibration_topics": list(self.calibration_topics),
            "calibration": calib_io.summary(self.calibration) or f"missing: {self.calibration_error}",
            "extrinsics": extrinsics_entry(self.extrinsics),
            "odometry_topics": self.odometry_topics,
        }


class McapSource(LogSource):
    """An ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` + ``.mcap`` files; a directory
    of ``.mcap`` files without ``metadata.yaml``, as a recording that was killed leaves it, is read
    as one too when no image-folder layout matches it, see :func:`terrainmap.sources.source_class`)."""

    @classmethod
    def matches(cls, path: Path) -> bool:
        if path.is_dir():
            return (path / "metadata.yaml").is_file() and any(path.glob("*.mcap"))
        return path.suffix.lower() == ".mcap" or _starts_with(path, MCAP_MAGIC)

    @property
    def format(self) -> str:
        return "rosbag2" if self.path.is_dir() else "mcap"

    def _open_reader(self) -> McapLog:
        return McapLog(self.path)


class Rosbag2Source(LogSource):
    """A rosbag2 directory (``metadata.yaml``) in sqlite3 storage (``.db3`` files) or with compressed
    files (``.mcap.zstd``, ``.db3.zstd``) or messages (``compression_mode: message``), read through
    ``rosbags`` (:class:`~terrainmap.sources.readers.Rosbag2Bag`); uncompressed MCAP storage is
    :class:`McapSource`'s."""

    format = "rosbag2"

    @classmethod
    def matches(cls, path: Path) -> bool:
        if not (path / "metadata.yaml").is_file():
            return False
        if any(path.glob("*.db3")) or any(path.glob("*.zstd")):
            return True
        return str(bag_metadata(path).get("compression_mode") or "").lower() in ("message", "file")

    def _open_reader(self) -> Rosbag2Bag:
        return Rosbag2Bag(self.path)


class Ros1BagSource(LogSource):
    """A ROS 1 bag (v2.0), or a folder of the bags ``rosbag record --split`` writes (read one
    after the other in name order, numbers by value: ``run_2.bag`` before ``run_10.bag``; taken
    for one when no image-folder layout matches it, see :func:`terrainmap.sources.source_class`)."""

    format = "ros1-bag"

    @classmethod
    def matches(cls, path: Path) -> bool:
        return path.is_file() and (path.suffix.lower() == ".bag" or _starts_with(path, ROS1_MAGIC))

    def _open_reader(self) -> Ros1Bag | SplitLog:
        if self.path.is_file():
            return Ros1Bag(self.path)
        return SplitLog(self.path, [Ros1Bag(f) for f in split_bags(self.path)])


def split_bags(folder: Path) -> list[Path]:
    """The ROS 1 bags of ``folder`` in name order, numbers by value, the one ``rosbag record`` was
    still writing when it stopped (``NAME.bag.active``) included, hidden files (``._NAME.bag``,
    macOS's) not."""
    bags = (f for pattern in ("*.bag", "*.bag.active") for f in folder.glob(pattern))
    return sorted((f for f in bags if f.is_file() and not f.name.startswith(".")), key=lambda f: natural_key(f.name))


def _brief(calibration: StereoCalibration) -> str:
    return f"fx {calibration.fx:g} px, baseline {calibration.baseline_m:g} m, {calibration.width}×{calibration.height}"
