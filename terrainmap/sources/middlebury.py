"""Middlebury stereo scenes: ``im0.png`` (left), ``im1.png`` (right) and ``calib.txt``.

The path is either one scene folder or a folder of scene folders (e.g. MiddEval3's
``trainingQ/``); scenes are taken in name order, one pair each. ``calib.txt`` gives ``cam0``/``cam1``
(3×3), ``doffs`` (px, the x-difference of the principal points: Z = B·f / (d + doffs)),
``baseline`` (mm), ``width`` and ``height``.
"""

from __future__ import annotations

from pathlib import Path

from ..types import Extrinsics, StereoCalibration
from .calibration import middlebury_calibration
from .folder import FolderSource, ImagePair


def _is_scene(path: Path) -> bool:
    return all((path / name).is_file() for name in ("im0.png", "im1.png"))


def _scenes(path: Path) -> list[Path]:
    if _is_scene(path):
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.is_dir() and _is_scene(p))


class MiddleburyFolder(FolderSource):
    """One Middlebury scene, or a folder of them."""

    format = "middlebury"
    calibration_hint = "calib.txt next to im0.png"

    @classmethod
    def matches(cls, path: Path) -> bool:
        return bool(_scenes(path))

    def _find_pairs(self) -> list[ImagePair]:
        return [ImagePair(s / "im0.png", s / "im1.png", s / "calib.txt") for s in _scenes(self.path)]

    def _read_calibration(self, path: Path) -> tuple[StereoCalibration, Extrinsics | None]:
        return middlebury_calibration(path), None  # a calib.txt without cam0 is no KITTI file either
