"""Stereo pairs from disk: image folders and logs, behind one small interface.

    from terrainmap.sources import open_source

    with open_source("run.mcap") as source:
        print(source.describe())
        for frame in source.frames(start_s=10, max_frames=5):
            ...  # terrainmap.types.StereoFrame

:func:`open_source` guesses the format from the path (first match wins, in this order):

=================  ===================================================================
``mcap``           an ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` + .mcap)
``rosbag2``        a rosbag2 directory in sqlite3 storage (.db3) or compressed (zstd), via ``rosbags``
``ros1-bag``       a ROS 1 ``.bag`` (read chunk by chunk by :mod:`~terrainmap.sources.ros1bag`)
``kitti-raw``      ``image_02/data``, ``image_03/data``, ``calib_cam_to_cam.txt`` up to two levels up
``kitti-odometry`` ``image_2``, ``image_3`` (or grey ``image_0``, ``image_1``), ``calib.txt``, ``times.txt``
``kitti-stereo``   ``image_2|colored_0|image_0`` + partner, ``calib_cam_to_cam/`` or ``calib/``
``middlebury``     ``im0.png``, ``im1.png``, ``calib.txt`` (one scene or a folder of scenes)
``folder``         ``left/``, ``right/``, ``calibration.yaml`` (format in :mod:`.calibration`)
=================  ===================================================================

A rosbag2's ``metadata.yaml`` stands for its folder (:func:`log_path`). A directory of ``.mcap``
files without ``metadata.yaml`` that no layout above matches is read as a
rosbag2 whose recording was cut before it wrote its metadata (its files in name order), and one
of ROS 1 ``.bag`` files as the bags of one recording split by ``rosbag record --split``; a stray
``.mcap`` or ``.bag`` in an image folder does not make the folder a log.

Every source yields uint8 images (RGB or mono, left and right of one size) with a
:class:`~terrainmap.types.StereoCalibration` and, when the source has them, extrinsics.
Bad input raises :class:`~terrainmap.errors.InputError` / ``CalibrationError`` with a one-line
message naming the path or topic.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import ConfigError, InputError, is_whole
from .base import Source
from .folder import GenericFolder
from .kitti import KittiOdometryFolder, KittiRawFolder, KittiStereoFolder
from .log import LogSource, McapSource, Ros1BagSource, Rosbag2Source, split_bags
from .middlebury import MiddleburyFolder
from .readers import bag_metadata

SOURCES: tuple[type[Source], ...] = (
    Rosbag2Source,
    McapSource,
    Ros1BagSource,
    KittiRawFolder,
    KittiOdometryFolder,
    KittiStereoFolder,
    MiddleburyFolder,
    GenericFolder,
)
"""The registry: source classes in the order :func:`open_source` tries them."""

__all__ = ["SOURCES", "Source", "log_path", "open_source", "source_class"]


def log_path(path: str | Path) -> Path:
    """``path``, or the rosbag2 folder where ``path`` is its ``metadata.yaml`` (as ``ros2 bag``
    takes either); :class:`InputError` for an empty path (which ``Path`` would take for the
    current folder) or one that is not a path at all."""
    if not isinstance(path, str | os.PathLike) or str(path) == "":
        raise InputError(f"expected the path of a log or folder, got {path!r}")
    path = Path(path)
    return path.parent if path.name == "metadata.yaml" and path.is_file() else path


def source_class(path: str | Path) -> type[Source]:
    """The source class that reads ``path`` (path guessing only, nothing is opened)."""
    path = log_path(path)
    try:
        exists = path.exists()
    except OSError as exc:  # e.g. a name longer than the file system allows
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not exists:
        raise InputError(f"{path}: does not exist")
    if not (path.is_file() or path.is_dir()):  # reading a FIFO would wait for a writer
        raise InputError(f"{path}: neither a file nor a folder (a device, FIFO or socket); a log is read from a file")
    for cls in SOURCES:
        if cls.matches(path):
            return cls
    if path.is_dir() and any(path.glob("*.mcap")):  # a rosbag2 without metadata.yaml (module docstring)
        return McapSource
    if path.is_dir() and split_bags(path):  # ROS 1 bags split by `rosbag record --split`
        return Ros1BagSource
    listed = bag_metadata(path).get("relative_file_paths") if path.is_dir() else None
    if listed and isinstance(listed, list):  # a rosbag2 whose files are gone (moved, not copied along)
        raise InputError(f"{path}: a rosbag2 folder whose metadata.yaml lists {', '.join(map(str, listed))}, "
                         "none of them in the folder")
    if path.is_dir() and any(path.glob("*.db3")):
        raise InputError(f"{path}: a rosbag2 folder of .db3 files needs its metadata.yaml (`ros2 bag reindex` "
                         "writes it)")
    raise InputError(
        f"{path}: not a known stereo source (expected an .mcap file, a rosbag2 or KITTI/Middlebury folder, "
        "a ROS 1 .bag, or a folder with left/, right/ and calibration.yaml)"
    )


def open_source(
    path: str | Path,
    *,
    left_topic: str | None = None,
    right_topic: str | None = None,
    calibration: str | Path | None = None,
    pair_tolerance_ns: int = 10_000_000,
) -> Source:
    """Open a stereo source, guessing its format from the path.

    Parameters
    ----------
    path : str or Path
        A log file, rosbag2 directory or image folder.
    left_topic, right_topic : str, optional
        Image topics of a log (default: guessed by type and name); an error for image folders.
    calibration : str or Path, optional
        Calibration file (YAML/TOML, KITTI or Middlebury text) overriding the source's own.
    pair_tolerance_ns : int
        Largest stamp difference of a left/right pair in a log, nanoseconds (≥ 0).
    """
    if not is_whole(pair_tolerance_ns) or pair_tolerance_ns < 0:
        raise ConfigError(f"pair tolerance must be a whole number of nanoseconds ≥ 0, got {pair_tolerance_ns!r}")
    path = log_path(path)
    cls = source_class(path)
    if issubclass(cls, LogSource):
        return cls(path, left_topic=left_topic, right_topic=right_topic, calibration=calibration,
                   pair_tolerance_ns=pair_tolerance_ns)
    if left_topic or right_topic:
        raise ConfigError(f"left_topic/right_topic (--left-topic/--right-topic): {path} is an image folder, not a log with topics")
    return cls(path, calibration=calibration)
