"""Stereo pairs from image folders: the shared :class:`FolderSource` and the generic layout.

Generic layout::

    my_run/
      left/   000000.png 000001.png ...   (IMAGE_SUFFIXES: png, jpg, pgm, ppm, bmp, tif, webp)
      right/  000000.png 000001.png ...   (the same file names)
      calibration.yaml                     (or .yml / .toml; format in terrainmap.sources.calibration)
      timestamps.txt                       (optional: one integer stamp in nanoseconds per left image, in natural name order)

Without timestamps, pair ``i`` is stamped ``i × 100 ms``.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from ..errors import STAMP_RANGE, CalibrationError, DamagedImageError, InputError, is_stamp
from ..types import Extrinsics, StereoCalibration, StereoFrame
from . import calibration as calib_io
from .base import DEFAULT_PERIOD_NS, PairRef, Source, extrinsics_entry, natural_key
from .images import read_image, stereo_pair

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff", ".webp")


@dataclass(frozen=True)
class ImagePair:
    """Left and right image files of one pair, and the calibration file that applies to it."""

    left: Path
    right: Path
    calibration: Path | None


def image_names(folder: Path) -> list[str]:
    """The image file names in ``folder`` in natural order (:func:`~.base.natural_key`; empty when
    it is not a directory). Hidden files are left out: ``._000005.png`` is the resource fork macOS
    writes beside an image on a USB or network drive, not an image."""
    if not folder.is_dir():
        return []
    return sorted((p.name for p in folder.iterdir()
                   if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and not p.is_dir()),
                  key=natural_key)


def checked_stamps(stamps: list[int], path: Path) -> list[int]:
    """``stamps`` (ns) read from the stamp file ``path``, or :class:`InputError` naming the file
    where one is no time that an MCAP or ROS stamp can hold."""
    bad = next((stamp for stamp in stamps if not is_stamp(stamp)), None)
    if bad is not None:
        raise InputError(f"{path}: stamp {bad} ns lies outside {STAMP_RANGE}")
    return stamps


def matching_pairs(left_dir: Path, right_dir: Path, calibration_for) -> list[ImagePair]:
    """Pairs of same-named images in two folders; ``calibration_for(name)`` gives each one's file."""
    right_names = set(image_names(right_dir))
    left_names = image_names(left_dir)
    pairs = [ImagePair(left_dir / n, right_dir / n, calibration_for(n)) for n in left_names if n in right_names]
    if len(pairs) < max(len(left_names), len(right_names)):
        alone = [left_dir / n for n in left_names if n not in right_names]
        alone += sorted((right_dir / n for n in right_names.difference(left_names)), key=lambda p: natural_key(p.name))
        more = f" and {len(alone) - 3} more" if len(alone) > 3 else ""
        logger.warning(
            "%s: %d left and %d right images, %d with the same name on both sides; left out for want of a "
            "partner: %s%s", left_dir.parent, len(left_names), len(right_names), len(pairs),
            ", ".join(map(str, alone[:3])), more,
        )
    return pairs


def read_lines(path: Path) -> list[str]:
    """Non-empty lines of a text file, or InputError naming it."""
    try:
        return [line.strip() for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None


class FolderSource(Source):
    """Base of the folder layouts: a list of :class:`ImagePair` with stamps and calibration files.

    Subclasses implement :meth:`_find_pairs`, and may override :meth:`_stamps_ns` (None: index ×
    100 ms) and :meth:`_read_calibration` (default: :func:`calibration.load_calibration_file`).
    """

    format = "folder"
    calibration_hint = "a calibration file"

    def __init__(self, path: str | Path, *, calibration: str | Path | None = None):
        super().__init__(path)
        self._override = calib_io.load_calibration_file(calibration) if calibration else None
        self.pairs = self._find_pairs()
        if not self.pairs:
            raise InputError(f"{self.path}: {self.format} layout but no left/right image pairs in it (image files: "
                             f"{', '.join(IMAGE_SUFFIXES)})")
        stamps = self._stamps_ns()
        if stamps is not None:
            stamps = self._stamps_of_pairs(stamps)
        if stamps is not None and len(stamps) < len(self.pairs):
            raise InputError(f"{self.path}: {len(stamps)} timestamps for {len(self.pairs)} image pairs")
        if stamps is not None and len(stamps) > len(self.pairs):
            logger.warning(
                "%s: %d timestamps for %d image pairs; the first %d are used",
                self.path, len(stamps), len(self.pairs), len(self.pairs),
            )
        self.stamps_ns = stamps or [i * DEFAULT_PERIOD_NS for i in range(len(self.pairs))]
        backwards = sum(b <= a for a, b in zip(self.stamps_ns, self.stamps_ns[1 : len(self.pairs)], strict=False))
        if backwards:  # outputs stamped so would overlay or reorder frames in a viewer
            logger.warning("%s: %d of %d pair stamps are not later than the one before (repeated or out of order)",
                           self.path, backwards, len(self.pairs))
        self._calibration: tuple[Path, tuple[StereoCalibration, Extrinsics | None]] | None = None  # the last file read

    def _stamps_of_pairs(self, stamps: list[int]) -> list[int]:
        """The pairs' stamps from a stamp file of one line per left image in name order: where a
        left image has no right one, its line is skipped, so that the later pairs keep theirs. A
        file with as many lines as there are pairs, or fewer than left images, is taken in order."""
        names = image_names(self.pairs[0].left.parent)
        if len(names) == len(self.pairs) or len(stamps) < len(names):
            return stamps
        by_name = dict(zip(names, stamps, strict=False))
        return [by_name[pair.left.name] for pair in self.pairs]

    @abstractmethod
    def _find_pairs(self) -> list[ImagePair]:
        """The layout's image pairs, in time order."""

    def _stamps_ns(self) -> list[int] | None:
        return None

    def _read_calibration(self, path: Path) -> tuple[StereoCalibration, Extrinsics | None]:
        return calib_io.load_calibration_file(path)

    def calibration_for(self, pair: ImagePair) -> tuple[StereoCalibration, Extrinsics | None]:
        """The pair's calibration and extrinsics: ``calibration=`` override, else its own file."""
        if self._override is not None:
            return self._override
        if pair.calibration is None or not pair.calibration.is_file():
            where = pair.calibration or self.path
            raise CalibrationError(f"{where}: no calibration found (need {self.calibration_hint}, or pass --calibration)")
        if self._calibration is None or self._calibration[0] != pair.calibration:  # pairs of one file come in a row
            self._calibration = pair.calibration, self._read_calibration(pair.calibration)
        return self._calibration[1]

    def _load(self, index: int) -> StereoFrame | None:
        pair = self.pairs[index]
        try:
            images = read_image(pair.left), read_image(pair.right)
        except DamagedImageError as exc:  # one file cut short or corrupt: that pair is lost, the run goes on
            self._skip_damaged(f"{self.path}: stereo pair {index}", exc)
            return None
        left, right = stereo_pair(*images, str(pair.left), str(pair.right))
        calib, extrinsics = self.calibration_for(pair)
        return StereoFrame(
            index=index,
            stamp_ns=self.stamps_ns[index],
            left=left,
            right=right,
            calibration=calib_io.fit_to_image(calib, left.shape, str(pair.left)),
            extrinsics=extrinsics,
            source=f"{pair.left} + {pair.right}",
        )

    def _pairs(self) -> Iterator[PairRef]:
        for index, stamp_ns in enumerate(self.stamps_ns[: len(self.pairs)]):
            yield PairRef(index, stamp_ns, partial(self._load, index))

    def describe(self) -> dict:
        first = self.pairs[0]
        calib, extrinsics = self.calibration_for(first)
        for pair in self.pairs:  # the first pair whose left image decodes (frames() skips the others)
            try:
                shape = read_image(pair.left).shape
            except DamagedImageError:
                continue
            calib, extrinsics = self.calibration_for(pair)  # scenes of a folder have their own
            calib = calib_io.fit_to_image(calib, shape, str(pair.left))
            break
        return {
            "format": self.format,
            "path": str(self.path),
            "frames": len(self.pairs),
            "duration_s": (self.stamps_ns[len(self.pairs) - 1] - self.stamps_ns[0]) / 1e9,
            "left": str(first.left.parent),
            "right": str(first.right.parent),
            "first_pair": [first.left.name, first.right.name],
            "calibration": calib_io.summary(calib),
            "extrinsics": extrinsics_entry(extrinsics),
        }


class GenericFolder(FolderSource):
    """``left/`` + ``right/`` + ``calibration.yaml`` (see the module docstring)."""

    format = "folder"
    calibration_hint = "calibration.yaml, .yml or .toml"

    @classmethod
    def matches(cls, path: Path) -> bool:
        return (path / "left").is_dir() and (path / "right").is_dir()

    def _calibration_file(self) -> Path | None:
        found = [p for p in (self.path / f"calibration{s}" for s in (".yaml", ".yml", ".toml")) if p.is_file()]
        if len(found) > 1 and self._override is None:  # which one is current is not for us to guess
            raise CalibrationError(f"{self.path}: {' and '.join(p.name for p in found)} are both there; keep one, "
                                   "or name the one to use with --calibration")
        return found[0] if found else None

    def _find_pairs(self) -> list[ImagePair]:
        calib = self._calibration_file()
        return matching_pairs(self.path / "left", self.path / "right", lambda name: calib)

    def _stamps_ns(self) -> list[int] | None:
        path = self.path / "timestamps.txt"
        if not path.is_file():
            return None
        try:
            return checked_stamps([int(line) for line in read_lines(path)], path)
        except ValueError:
            raise InputError(f"{path}: need one integer stamp in nanoseconds per line") from None
