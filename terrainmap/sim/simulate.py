"""Run a simulation: build the scene, render every frame, write the log.

    from terrainmap.sim import SimConfig, simulate
    summary = simulate("drive.mcap", SimConfig(scene="mounds", frames=20, seed=7))
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from ..config import check_kinds
from ..errors import ConfigError, InputError, counted
from ..stereo import PLAUSIBLE
from .folder_log import FolderLog
from .mcap_log import McapLog
from .render import Renderer
from .rig import LEFT_FRAME, VEHICLE_FRAME, WORLD_FRAME, CameraRig
from .scenes import MAX_SCENE_CELLS, SCENES, Scene, build_scene, grid_size

logger = logging.getLogger(__name__)


@dataclass
class SimConfig:
    """Everything a simulated log depends on (the CLI's options, same names)."""

    scene: str = "mounds"
    """One of :data:`terrainmap.sim.scenes.SCENES`."""
    frames: int = 50
    seed: int = 0
    format: str = "mcap"
    """``mcap`` (ROS 2 log) or ``folder`` (generic image folder with truth/)."""
    width: int = 640
    height: int = 480
    focal_px: float = 500.0
    baseline_m: float = 0.3
    camera_height_m: float = 1.8
    """Left camera above the vehicle origin (on the ground), metres."""
    pitch_deg: float = 6.0
    """Camera pitch, degrees down from the vehicle's x axis."""
    noise: float = 2.0
    """Gaussian pixel noise, σ in grey levels."""
    vignetting: float = 0.15
    """Brightness loss at the image corners (0: none)."""
    texture_detail: float = 1.0
    """How much fine surface texture survives with range: an octave of the texture fades out
    below 4 / ``texture_detail`` pixel footprints and is gone below half that
    (:mod:`~terrainmap.sim.shading`). 2 keeps about what a pixel's box filter keeps, with no
    other loss of sharpness (lens blur, motion, compression); 1, the default, blurs distant
    ground more, as those do (docs/accuracy.md: what 2 changes)."""
    speed_mps: float = 4.0
    fps: float = 10.0
    color: bool = False
    """rgb8 images instead of mono8."""
    compressed: bool = False
    """MCAP only: PNG ``sensor_msgs/CompressedImage`` camera topics instead of raw images."""
    terrain_resolution_m: float = 0.2

    def validate(self) -> None:
        """:class:`ConfigError` naming the field (``SimConfig.frames: ...``) of a value out of range."""
        def check(ok: bool, field: str, message: str) -> None:
            if not ok:
                raise ConfigError(f"SimConfig.{field}: {message}")

        check_kinds("SimConfig", self)  # built in code: a str or a bool where a number belongs

        check(self.scene in SCENES, "scene", f"unknown scene {self.scene!r}; choose one of {', '.join(SCENES)}")
        check(self.format in ("mcap", "folder"), "format", f"must be mcap or folder, got {self.format!r}")
        check(not (self.compressed and self.format == "folder"), "compressed",
              "applies to an MCAP log only (a folder's images are PNG files)")
        check(1 <= self.frames <= 100_000, "frames", f"must be in 1..100000, got {self.frames}")
        check(0 <= self.seed < 2**32, "seed", f"must be in 0..2^32-1, got {self.seed}")
        # process's stereo matcher searches at least 16 px of disparity, so at 16 px it has no column
        # to match; 32 px leaves it 16 (whether they see terrain depends on the rig: the tests use 64×48).
        for name, low in (("width", 32), ("height", 16)):
            value = getattr(self, name)
            check(low <= value <= 4096, name, f"must be {low}..4096 pixels, got {value}")
        for name in ("focal_px", "baseline_m", "camera_height_m", "fps", "terrain_resolution_m"):
            value = getattr(self, name)
            check(math.isfinite(value) and value > 0, name, f"must be > 0, got {value}")
        for name, field in (("focal_px", "fx"), ("baseline_m", "baseline_m")):  # as process will check the log's
            low, high, unit = PLAUSIBLE[field]
            value = getattr(self, name)
            check(low <= value <= high, name, f"must be within {low:g}..{high:g} {unit}, got {value:g}")
        check(self.camera_height_m <= 100, "camera_height_m", f"must be at most 100 m, got {self.camera_height_m:g}")
        check(-30 <= self.pitch_deg <= 45, "pitch_deg", f"must be within [-30, 45] degrees, got {self.pitch_deg}")
        check(0 <= self.noise <= 50, "noise", f"must be within [0, 50] grey levels, got {self.noise}")
        check(0 <= self.vignetting < 1, "vignetting", f"must be within [0, 1), got {self.vignetting}")
        check(0.25 <= self.texture_detail <= 8, "texture_detail", f"must be within [0.25, 8], got {self.texture_detail}")
        check(0 <= self.speed_mps <= 40, "speed_mps", f"must be within [0, 40] m/s, got {self.speed_mps}")
        cells = math.prod(grid_size(self.length_m, self.terrain_resolution_m))
        if math.prod(grid_size(self.length_m)) > MAX_SCENE_CELLS:  # too long at the default resolution
            check(False, "frames", f"a drive of {self.length_m:.4g} m ((frames − 1) × speed / fps) needs a terrain of "
                  f"{cells:.3g} cells, more than the {MAX_SCENE_CELLS:.3g} the simulator holds: give fewer frames, "
                  "a lower speed or a higher frame rate")
        check(cells <= MAX_SCENE_CELLS, "terrain_resolution_m", f"{self.terrain_resolution_m:g} m gives a terrain of "
              f"{cells:.3g} cells, more than the {MAX_SCENE_CELLS:.3g} the simulator holds: choose a coarser one")

    def rig(self) -> CameraRig:
        return CameraRig(
            width=self.width, height=self.height, focal_px=self.focal_px, baseline_m=self.baseline_m,
            camera_height_m=self.camera_height_m, pitch_rad=math.radians(self.pitch_deg),
        )

    def renderer(self, scene: Scene) -> Renderer:
        """The renderer of ``scene`` with this rig, motion and sensor settings."""
        return Renderer(
            scene, self.rig(), speed_mps=self.speed_mps, fps=self.fps, noise_dn=self.noise,
            vignetting=self.vignetting, texture_detail=self.texture_detail, mono=not self.color, seed=self.seed,
        )

    @property
    def length_m(self) -> float:
        """Distance driven over the log."""
        return self.speed_mps * (self.frames - 1) / self.fps


def describe(config: SimConfig, scene) -> dict:
    """JSON-able description written into every log (MCAP metadata / truth/scene.json)."""
    from .. import __version__

    terrain = scene.terrain
    return {
        "generator": f"terrainmap {__version__} terrainmap.sim",
        "config": asdict(config),
        "frames": {"world": WORLD_FRAME, "vehicle": VEHICLE_FRAME, "camera": LEFT_FRAME},
        "terrain": {
            "x_min_m": terrain.x_min_m, "y_min_m": terrain.y_min_m,
            "resolution_m": terrain.resolution_m, "shape": list(terrain.shape),
        },
        "obstacles": [
            {"id": s.id, "kind": s.kind, "shape": s.shape, "xy_m": list(s.xy_m), "size_m": s.size_m,
             "yaw_rad": s.yaw_rad, "velocity_mps": list(s.velocity_mps),
             "turns": [[t, list(v)] for t, v in s.turns]}
            for s in scene.obstacles
        ],
    }


def simulate(out: str | Path, config: SimConfig, progress: Callable[[int], None] | None = None) -> dict:
    """Render ``config.frames`` frames and write them to ``out``.

    ``progress(i)`` is called after each frame. Returns a summary: ``path``, ``frames``,
    ``seconds`` (wall time), ``bytes`` written. Raises ConfigError for a bad config.
    """
    if not isinstance(config, SimConfig):
        raise ConfigError(f"simulate: expected a SimConfig, got {type(config).__name__}")
    config.validate()
    start = time.perf_counter()
    scene = build_scene(config.scene, config.seed, length_m=config.length_m, resolution_m=config.terrain_resolution_m)
    renderer = config.renderer(scene)
    rig = renderer.rig
    description = describe(config, scene)
    out = Path(out)
    log = None
    try:
        if config.format == "mcap":
            log = McapLog(out, scene, rig, description, compressed=config.compressed)
        else:
            log = FolderLog(out, scene, rig, description)
        with log:
            for index in range(config.frames):
                log.write(renderer.frame(index))
                if progress is not None:
                    progress(index)
    except OSError as exc:  # disk full, device gone: the error says where
        removed = ""
        if log is not None:  # a log that cannot be ended is no log; the same command renders it again
            log.discard()
            removed = "; the part written is removed"
        raise InputError(f"{out}: cannot write the simulated log ({exc.strerror or exc}){removed}") from exc
    seconds = time.perf_counter() - start
    size = out.stat().st_size if out.is_file() else sum(p.stat().st_size for p in log.written)
    logger.info("wrote %s of %s to %s in %.1f s", counted(config.frames, "frame"), config.scene, out, seconds)
    return {"path": str(out), "frames": config.frames, "seconds": seconds, "bytes": size}
