"""KITTI folder layouts: stereo 2012/2015 and object, raw drives, odometry sequences.

- Stereo 2015 / object / stereo 2012: ``image_2/ image_3/`` (or 2012's ``colored_0/ colored_1/``
  or grey ``image_0/ image_1/``) with one calibration file per scene in ``calib_cam_to_cam/``
  (``P_rect_02``, ``P_rect_03``) or ``calib/`` (``P0``..``P3``); pair files ``NNNNNN_10.png``
  (and ``_11``) or ``NNNNNN.png`` use ``NNNNNN.txt``.
- Raw drive: ``image_02/data/ image_03/data/``, ``image_02/timestamps.txt`` and
  ``calib_cam_to_cam.txt`` in the drive folder or one or two folders up.
- Odometry sequence: ``image_2/ image_3/`` with ``P2``, ``P3`` of ``calib.txt`` (or, in the grey
  download, ``image_0/ image_1/`` with ``P0``, ``P1``), ``times.txt`` (seconds).

Baseline = (P_left[0,3] − P_right[0,3]) / fx; ``cx_right`` is set when the principal points differ.
No camera-to-vehicle extrinsics are read: the pipeline estimates them from the ground.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from ..errors import InputError, brief
from . import calibration as calib_io
from .folder import FolderSource, ImagePair, checked_stamps, matching_pairs, read_lines

# (left dir, right dir, projection keys in a calib/ file)
_STEREO_DIRS = (("image_2", "image_3", ("P2", "P3")), ("colored_0", "colored_1", ("P2", "P3")),
                ("image_0", "image_1", ("P0", "P1")))
_CALIB_DIRS = ("calib_cam_to_cam", "calib")


class KittiStereoFolder(FolderSource):
    """KITTI stereo 2012/2015 and object (one calibration file per scene)."""

    format = "kitti-stereo"
    calibration_hint = "calib_cam_to_cam/NNNNNN.txt or calib/NNNNNN.txt"

    @classmethod
    def _dirs(cls, path: Path):
        found = (dirs for dirs in _STEREO_DIRS if (path / dirs[0]).is_dir() and (path / dirs[1]).is_dir())
        left, right, keys = next(found, (None, None, None))
        calib = next((path / d for d in _CALIB_DIRS if (path / d).is_dir()), None)
        return left, right, keys, calib

    @classmethod
    def matches(cls, path: Path) -> bool:
        return cls._dirs(path)[0] is not None  # without a calibration folder: --calibration

    def _find_pairs(self) -> list[ImagePair]:
        left, right, keys, calib_dir = self._dirs(self.path)
        self._keys = keys if keys == ("P0", "P1") else None  # None: P_rect_02/03, else P2/P3

        def scene_file(name: str) -> Path | None:  # 000005_10.png -> 000005.txt
            return calib_dir / f"{name.split('.')[0].split('_')[0]}.txt" if calib_dir else None

        return matching_pairs(self.path / left, self.path / right, scene_file)

    def _read_calibration(self, path: Path):
        return calib_io.kitti_calibration(path, self._keys), None


class KittiRawFolder(FolderSource):
    """A KITTI raw drive (``..._sync`` or ``..._extract``)."""

    format = "kitti-raw"
    calibration_hint = "calib_cam_to_cam.txt in the drive folder or one or two folders up"

    @classmethod
    def matches(cls, path: Path) -> bool:
        return (path / "image_02" / "data").is_dir() and (path / "image_03" / "data").is_dir()

    def _find_pairs(self) -> list[ImagePair]:
        candidates = (self.path, self.path.parent, self.path.parent.parent)
        calib = next((d / "calib_cam_to_cam.txt" for d in candidates if (d / "calib_cam_to_cam.txt").is_file()), None)
        return matching_pairs(self.path / "image_02" / "data", self.path / "image_03" / "data", lambda n: calib)

    def _stamps_ns(self) -> list[int] | None:
        path = self.path / "image_02" / "timestamps.txt"
        if not path.is_file():
            return None
        # one line per left image: FolderSource keeps those of the images that have a pair
        return checked_stamps([_parse_kitti_time(line, path) for line in read_lines(path)], path) or None

    def _read_calibration(self, path: Path):
        return calib_io.kitti_calibration(path), None


def _parse_kitti_time(text: str, path: Path) -> int:
    """``2011-09-26 13:02:25.964389445`` (UTC) → nanoseconds since the epoch."""
    try:
        whole, _, fraction = text.partition(".")
        seconds = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=UTC).timestamp()
        return int(seconds) * 1_000_000_000 + int((fraction + "000000000")[:9])
    except ValueError:
        raise InputError(f"{path}: cannot parse timestamp {brief(text)}") from None


class KittiOdometryFolder(FolderSource):
    """A KITTI odometry sequence (``sequences/NN``): the colour cameras, else the grey ones."""

    format = "kitti-odometry"
    calibration_hint = "calib.txt"
    _CAMERAS = (("image_2", "image_3", ("P2", "P3")), ("image_0", "image_1", ("P0", "P1")))

    @classmethod
    def _cameras(cls, path: Path):
        return next(((left, right, keys) for left, right, keys in cls._CAMERAS
                     if (path / left).is_dir() and (path / right).is_dir()), None)

    @classmethod
    def matches(cls, path: Path) -> bool:
        return cls._cameras(path) is not None and (path / "calib.txt").is_file()

    def _find_pairs(self) -> list[ImagePair]:
        left, right, self._keys = self._cameras(self.path)
        calib = self.path / "calib.txt"
        return matching_pairs(self.path / left, self.path / right, lambda name: calib)

    def _stamps_ns(self) -> list[int] | None:
        path = self.path / "times.txt"
        if not path.is_file():
            return None
        try:
            stamps = [round(float(line) * 1e9) for line in read_lines(path)]
            if any(stamp < 0 for stamp in stamps):  # seconds since the sequence's start
                raise ValueError
        except (ValueError, OverflowError):  # OverflowError: inf
            raise InputError(f"{path}: need one finite time of 0 or more seconds per line") from None
        return checked_stamps(stamps, path)

    def _read_calibration(self, path: Path):
        return calib_io.kitti_calibration(path, self._keys), None
