"""Write a simulated drive in terrainmap's generic folder layout, with ground truth beside it.

::

    OUT/
      left/000000.png ...        rectified left images (mono or RGB PNG)
      right/000000.png ...
      timestamps.txt             one integer stamp in nanoseconds per line
      calibration.yaml           width, height, fx, fy, cx, cy, baseline_m and extrinsics
                                 (left camera optical frame in base_link: translation_m, rotation 3×3)
      truth/scene.json           the simulation's description (as the MCAP metadata record)
      truth/terrain.npz          elevation (nx, ny) float32 [ix, iy], x_min_m, y_min_m, resolution_m
      truth/000000.npz ...       per frame: stamp_ns, rotation_world_base (3×3), position_world_base (3),
                                 depth (H×W float32 m, inf = sky), label, instance (H×W uint8),
                                 obstacle_id, obstacle_kind, obstacle_shape, obstacle_center_m,
                                 obstacle_size_m, obstacle_yaw_rad, obstacle_height_m, obstacle_velocity_mps

World frame ``odom``; :func:`terrainmap.sim.truth.open_truth` reads this layout and MCAP logs alike.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..errors import InputError
from .render import SimFrame
from .rig import CameraRig
from .scenes import Scene

FRAME_NAME = "{:06d}"


class FolderLog:
    """Context manager writing frames under the folder ``path`` (module docstring)."""

    def __init__(self, path: str | Path, scene: Scene, rig: CameraRig, description: dict):
        self.path = Path(path)
        if self.path.is_dir() and any(self.path.iterdir()) and not (self.path / "truth" / "scene.json").is_file():
            raise InputError(f"{self.path}: holds files that are not a simulated drive (no truth/scene.json); "
                             "give a new or empty folder")
        self.written: list[Path] = []  # every file written, for the summary's size
        for sub, pattern in (("left", "[0-9]*.png"), ("right", "[0-9]*.png"), ("truth", "[0-9]*.npz")):
            (self.path / sub).mkdir(parents=True, exist_ok=True)
            for stale in (self.path / sub).glob(pattern):  # frames of an earlier, longer run
                stale.unlink()
        fx, fy, cx, cy = rig.intrinsics
        extrinsics = rig.extrinsics()
        calibration = {
            "width": rig.width, "height": rig.height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "baseline_m": rig.baseline_m,
            "extrinsics": {"translation_m": extrinsics.translation.tolist(), "rotation": extrinsics.rotation.tolist()},
        }
        (self.path / "calibration.yaml").write_text(yaml.safe_dump(calibration, sort_keys=False))
        (self.path / "truth" / "scene.json").write_text(json.dumps(description, indent=1))
        terrain = scene.terrain
        np.savez_compressed(
            self.path / "truth" / "terrain.npz", elevation=terrain.z, x_min_m=terrain.x_min_m,
            y_min_m=terrain.y_min_m, resolution_m=terrain.resolution_m,
        )
        # Line-buffered: a run killed part way (SIGKILL) leaves the stamps of the frames it wrote.
        self._stamps = open(self.path / "timestamps.txt", "w", buffering=1)  # noqa: SIM115 - closed in close()
        self.written += [self.path / name for name in ("calibration.yaml", "truth/scene.json", "truth/terrain.npz",
                                                       "timestamps.txt")]

    def __enter__(self) -> FolderLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stamps.close()

    def discard(self) -> None:
        """Remove the folder (after a write failed: its frames and stamps would not agree). It was
        new, empty or a simulated drive being replaced (checked when it was opened)."""
        with contextlib.suppress(OSError):
            self._stamps.close()
        shutil.rmtree(self.path, ignore_errors=True)

    def write(self, frame: SimFrame) -> None:
        name = FRAME_NAME.format(frame.index)
        for side, image in (("left", frame.left), ("right", frame.right)):
            bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(self.path / side / f"{name}.png"), bgr):  # OpenCV says no more than that
                raise OSError(f"OpenCV cannot write {self.path / side / name}.png")
        self._stamps.write(f"{frame.stamp_ns}\n")
        boxes = frame.obstacles
        truth = self.path / "truth" / f"{name}.npz"
        self.written += [self.path / "left" / f"{name}.png", self.path / "right" / f"{name}.png", truth]
        np.savez_compressed(
            truth,
            stamp_ns=np.int64(frame.stamp_ns),
            rotation_world_base=frame.rotation_world_base,
            position_world_base=frame.position_world_base,
            depth=frame.depth, label=frame.label, instance=frame.instance,
            obstacle_id=np.array([b.id for b in boxes], np.int32),
            obstacle_kind=np.array([b.kind for b in boxes], str),
            obstacle_shape=np.array([b.shape for b in boxes], str),
            obstacle_center_m=np.array([b.center_m for b in boxes]).reshape(-1, 3),
            obstacle_size_m=np.array([b.size_m for b in boxes]).reshape(-1, 3),
            obstacle_yaw_rad=np.array([b.yaw_rad for b in boxes]),
            obstacle_height_m=np.array([b.height_m for b in boxes]),
            obstacle_velocity_mps=np.array([b.velocity_mps for b in boxes]).reshape(-1, 3),
        )
