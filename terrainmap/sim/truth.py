"""Read the ground truth of a simulated log (MCAP or folder), frame by frame, in bounded memory.

    from terrainmap.sim.truth import open_truth

    with open_truth("drive.mcap") as truth:
        z = truth.height(x_world, y_world)          # terrain without obstacles, odom frame
        for frame in truth.frames():                # streamed, one frame in memory at a time
            frame.stamp_ns, frame.depth, frame.label, frame.obstacles, frame.pose_world_base()

World frame ``odom`` (z up). ``truth.extrinsics`` is the left camera optical frame in
``base_link`` and ``truth.calibration`` the rectified pinhole model, so a depth pixel (u, v, Z)
maps to ``p_cam = Z·((u−cx)/fx, (v−cy)/fy, 1)``, ``p_base = R·p_cam + t`` and
``p_world = pose_world_base() @ [p_base, 1]``. Frames are yielded in stamp order. The layouts
read are those written by :mod:`terrainmap.sim.mcap_log` and :mod:`terrainmap.sim.folder_log`.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..bspline import xy_arrays
from ..errors import InputError
from ..sources.readers import MCAP_MAGIC, summary_section
from ..sources.tf import quaternion_to_matrix, usable
from ..types import Extrinsics, StereoCalibration
from .heightfield import Heightfield
from .mcap_log import METADATA_NAME, TRUTH_TOPICS
from .messages import heightfield_from_grid_map, image_array, obstacles_from_markers
from .obstacles import ObstacleBox, ObstacleSpec
from .simulate import SimConfig

FRAME_TOPICS = tuple(t for t in TRUTH_TOPICS if t != "/truth/terrain")


@dataclass
class TruthFrame:
    """Ground truth of one frame (arrays as in :class:`terrainmap.sim.render.SimFrame`)."""

    index: int
    stamp_ns: int
    rotation_world_base: np.ndarray
    position_world_base: np.ndarray
    obstacles: list[ObstacleBox]
    depth: np.ndarray
    label: np.ndarray
    instance: np.ndarray

    def __post_init__(self) -> None:
        """Reject damaged truth (wrong shapes, non-finite pose) before it meets the scoring."""
        if np.shape(self.rotation_world_base) != (3, 3) or np.shape(self.position_world_base) != (3,):
            raise ValueError("vehicle pose must be a 3×3 rotation and a 3-vector")
        if not (np.isfinite(self.rotation_world_base).all() and np.isfinite(self.position_world_base).all()):
            raise ValueError("vehicle pose is not finite")
        if np.shape(self.depth) != np.shape(self.label) or np.shape(self.label) != np.shape(self.instance):
            raise ValueError("depth, label and instance images differ in size")
        for box in self.obstacles:
            numbers = np.concatenate([box.center_m, box.size_m, [box.yaw_rad, box.height_m]])
            if not (np.isfinite(numbers).all() and np.all(np.asarray(box.size_m) > 0)):
                raise ValueError(f"obstacle {box.id} is not a finite box of positive size")

    def pose_world_base(self) -> np.ndarray:
        """4×4 pose of base_link in odom (``p_world = T @ p_base``)."""
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = self.rotation_world_base, self.position_world_base
        return pose


class Truth:
    """Ground truth of one log; iterate :meth:`frames`. Use as a context manager."""

    def __init__(self, path: Path, terrain: Heightfield, description: dict, frames_fn):
        self.path = path
        self.terrain = terrain
        self.description = description
        self.config = SimConfig(**description["config"])
        self.config.validate()  # a damaged description (a text or 0 for the focal length) is named, not scored
        rig = self.config.rig()
        self.calibration: StereoCalibration = rig.calibration(source=str(path))
        self.extrinsics: Extrinsics = rig.extrinsics()
        self._motions = [
            ObstacleSpec(o["id"], o["kind"], tuple(o["xy_m"]), velocity_mps=tuple(o["velocity_mps"]),
                         turns=tuple((t, tuple(v)) for t, v in o.get("turns", ())))  # (none in logs before turns)
            for o in description["obstacles"]
        ]
        self._frames_fn = frames_fn

    def velocities(self, index: int) -> dict[int, np.ndarray]:
        """Each obstacle's world velocity (vx, vy, 0) m/s in frame ``index``, by id."""
        return {m.id: np.array([*m.motion(index / self.config.fps)[1], 0.0]) for m in self._motions}

    def height(self, x, y) -> np.ndarray:
        """Terrain height (m, float32) at world (odom) points ``(x, y)`` (broadcastable arrays, m),
        obstacles excluded; NaN where x or y is not finite."""
        x, y = xy_arrays("Truth.height", x, y)
        finite = np.isfinite(x) & np.isfinite(y)
        height = self.terrain.height(np.where(finite, x, 0.0), np.where(finite, y, 0.0))
        return np.where(finite, height, np.float32(np.nan))

    def frames(self) -> Iterator[TruthFrame]:
        return self._frames_fn(self)

    def __enter__(self) -> Truth:
        return self

    def __exit__(self, *exc) -> None:
        return None


def truth_at(frames: Iterator[TruthFrame], stamp_ns: int, log: Path, shape: tuple[int, int]) -> TruthFrame:
    """Advance the (stamp-ordered) truth ``frames`` of ``log`` to the one of ``stamp_ns``, whose
    per-pixel images must have the stereo images' ``shape`` (rows, columns), or
    :class:`InputError` when it has none or another size."""
    for truth_frame in frames:
        if truth_frame.stamp_ns == stamp_ns:
            if truth_frame.depth.shape != tuple(shape):
                size = ["×".join(map(str, s[::-1])) for s in (truth_frame.depth.shape, shape)]  # width × height
                raise InputError(f"{log}: the ground truth of the stereo frame at stamp {stamp_ns} is {size[0]} "
                                 f"pixels, its images {size[1]}")
            return truth_frame
        if truth_frame.stamp_ns > stamp_ns:
            break
    raise InputError(f"{log}: no ground truth for the stereo frame at stamp {stamp_ns}")


class NoTruthError(InputError):
    """The log is readable but holds no ground truth: not written by ``terrainmap simulate``."""


def open_truth(path: str | Path) -> Truth:
    """Open the truth of a log written by ``terrainmap simulate`` (an .mcap file or a folder).

    Raises
    ------
    NoTruthError
        The path is not a simulated log: it lacks truth topics/files (named).
    InputError
        The path does not exist, or its truth is damaged.
    """
    if not isinstance(path, str | Path):
        raise InputError(f"open_truth: path must be a str or Path, got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: does not exist")
    if path.is_dir() and not (path / "truth").exists() and any(path.glob("*.mcap")):  # a rosbag2 folder
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) > 1:
            raise NoTruthError(f"{path}: a log in {len(mcaps)} MCAP files; the ground truth is read from the one "
                               "MCAP file (or folder) that terrainmap simulate writes")
        return _open_mcap(mcaps[0])
    if path.is_dir():
        return _open_folder(path)
    return _open_mcap(path)


def _open_folder(path: Path) -> Truth:
    truth_dir = path / "truth"
    missing = [n for n in ("scene.json", "terrain.npz") if not (truth_dir / n).is_file()]
    if missing:
        raise NoTruthError(f"{path}: no ground truth (missing truth/{', truth/'.join(missing)})")

    def frames(truth: Truth) -> Iterator[TruthFrame]:
        for index, file in enumerate(sorted(truth_dir.glob("[0-9]*.npz"))):
            with _damaged(file), np.load(file) as d:
                boxes = [
                    ObstacleBox(int(i), str(k), str(s), c, z, float(y), float(h), v)
                    for i, k, s, c, z, y, h, v in zip(
                        d["obstacle_id"], d["obstacle_kind"], d["obstacle_shape"], d["obstacle_center_m"],
                        d["obstacle_size_m"], d["obstacle_yaw_rad"], d["obstacle_height_m"],
                        d["obstacle_velocity_mps"], strict=True,
                    )
                ]
                yield TruthFrame(
                    index, int(d["stamp_ns"]), d["rotation_world_base"], d["position_world_base"], boxes,
                    d["depth"], d["label"], d["instance"],
                )

    with _damaged(truth_dir / "terrain.npz"), np.load(truth_dir / "terrain.npz") as data:
        terrain = Heightfield(
            data["elevation"], float(data["x_min_m"]), float(data["y_min_m"]), float(data["resolution_m"])
        )
    with _damaged(truth_dir / "scene.json"):
        return Truth(path, terrain, _description((truth_dir / "scene.json").read_text()), frames)


def _mcap_reader(file):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    return make_reader(file, validate_crcs=True, decoder_factories=[DecoderFactory()])  # damage: an error, not wrong truth


def _open_mcap(path: Path) -> Truth:
    try:
        with open(path, "rb") as file:
            if file.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise NoTruthError(f"{path}: not an MCAP file; the ground truth is read from logs that "
                                 "terrainmap simulate writes (MCAP or a folder)")
            if not summary_section(file)[1]:
                raise InputError(f"{path}: damaged log (its summary fails its CRC); scoring needs the whole simulated log")
            file.seek(0)
            reader = _mcap_reader(file)
            try:
                summary = reader.get_summary()
            except Exception:  # noqa: BLE001 - no footer
                summary = None
            if summary is None:
                raise InputError(f"{path}: the log has no summary (cut short, or still being written); "
                                 "scoring needs the whole simulated log")
            topics = {c.topic for c in summary.channels.values()}
            missing = [t for t in TRUTH_TOPICS if t not in topics]
            if missing:
                raise NoTruthError(f"{path}: not a simulated log with ground truth (missing topics {', '.join(missing)})")
            meta = next((m.metadata for m in reader.iter_metadata() if m.name == METADATA_NAME), None)
            if meta is None or "scene" not in meta:
                raise NoTruthError(f"{path}: no '{METADATA_NAME}' metadata record (not written by terrainmap simulate)")
            with _damaged(f"{path}: /truth/terrain"):
                first = next(reader.iter_decoded_messages(topics=["/truth/terrain"]), None)
            if first is None:
                raise InputError(f"{path}: /truth/terrain holds no message")
            terrain = heightfield_from_grid_map(first[3], f"{path}: /truth/terrain")
    except InputError:
        raise
    except Exception as exc:  # mcap raises many kinds of errors on damaged or foreign files
        raise InputError(f"{path}: cannot read as an MCAP log ({exc})") from exc
    with _damaged(f"{path}: the '{METADATA_NAME}' metadata"):
        return Truth(path, terrain, _description(meta["scene"]), _mcap_frames)


@contextmanager
def _damaged(path: Path | str):
    """Turn the errors of reading a damaged truth file into one InputError naming it (or its part)."""
    try:
        yield
    except (OSError, ValueError, KeyError, IndexError, TypeError, EOFError, zipfile.BadZipFile) as exc:  # npz, json on garbage
        raise InputError(f"{path}: damaged ground truth ({type(exc).__name__}: {exc})") from exc


def _description(text: str) -> dict:
    """The scene description JSON that ``terrainmap simulate`` stores (it holds the SimConfig)."""
    description = json.loads(text)
    if not isinstance(description, dict) or not isinstance(description.get("config"), dict):
        raise ValueError("the scene description has no 'config' table")
    return description


def _mcap_frames(truth: Truth) -> Iterator[TruthFrame]:
    """Group the per-frame truth messages by log time (= stamp) and yield complete frames."""
    parts: dict[str, object] = {}
    stamp, index = None, 0
    with _damaged(truth.path), open(truth.path, "rb") as file:
        messages = _mcap_reader(file).iter_decoded_messages(topics=list(FRAME_TOPICS), log_time_order=True)
        for _, channel, message, decoded in _undamaged(messages, truth.path):
            if stamp is not None and message.log_time != stamp:
                yield _mcap_frame(truth, index, stamp, parts)
                parts, index = {}, index + 1
            stamp = message.log_time
            parts[channel.topic] = decoded
        if parts:
            yield _mcap_frame(truth, index, stamp, parts)


def _undamaged(messages: Iterator, path: Path) -> Iterator:
    """``messages``, with any error in reading them (a chunk's CRC, its decompression, a message's
    decoding: mcap and its codecs raise many kinds) one :class:`InputError` naming the log and the
    log time of the last message read before it."""
    last = None
    try:
        for item in messages:
            last = item[2].log_time
            yield item
    except Exception as exc:
        where = "before its first truth message" if last is None else f"after log time {last / 1e9:.3f} s"
        raise InputError(f"{path}: damaged ground truth {where} ({type(exc).__name__}: {exc})") from exc


def _mcap_frame(truth: Truth, index: int, stamp_ns: int, parts: dict) -> TruthFrame:
    missing = [t for t in FRAME_TOPICS if t not in parts]
    if missing:
        raise InputError(f"{truth.path}: frame at stamp {stamp_ns} lacks {', '.join(missing)}")
    p = parts["/truth/pose"].pose
    q = p.orientation
    if not usable((p.position.x, p.position.y, p.position.z), (q.x, q.y, q.z, q.w)):
        raise InputError(f"{truth.path}: /truth/pose at stamp {stamp_ns} is not finite or its quaternion is zero")
    return TruthFrame(
        index=index,
        stamp_ns=int(stamp_ns),
        rotation_world_base=quaternion_to_matrix((q.x, q.y, q.z, q.w)),
        position_world_base=np.array([p.position.x, p.position.y, p.position.z]),
        obstacles=obstacles_from_markers(parts["/truth/obstacles"], truth.terrain, truth.velocities(index)),
        depth=image_array(parts["/truth/left/depth"], "/truth/left/depth"),
        label=image_array(parts["/truth/left/label"], "/truth/left/label"),
        instance=image_array(parts["/truth/left/instance"], "/truth/left/instance"),
    )
