"""``terrainmap bench``: per-stage timings at the paper configuration (a benchmark, not a test).

Each stage is timed over repeated runs on the same input; we report the median, min and max in
milliseconds. The inputs are synthetic so the figures are comparable anywhere:

- ``grid``, ``surface``, ``labels``, ``obstacles``: a 300k-point cloud over rolling terrain
  with box obstacles (the size of a 640×480 stereo frame), paper configuration (34 m × 22 m,
  0.5 m cells, 25×25 control points, degree 3). ``surface`` is the whole iterative estimation
  with the slope and cell-label layers; ``labels`` labels every point.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np

from .config import Config

Stage = Callable[[], object]


def _time(fn: Stage, runs: int, warmup: int = 2) -> dict[str, float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return {
        "median_ms": statistics.median(times),
        "min_ms": min(times),
        "max_ms": max(times),
        "runs": runs,
    }


def core_stages(config: Config, n_points: int = 300_000) -> dict[str, Stage]:
    """Stage name → zero-argument callable, for the terrain core on a synthetic cloud."""
    from .grid import cell_index, quantize
    from .obstacle_stage import make_tracker, run_obstacle_stage
    from .pipeline import map_points
    from .segmentation import label_cells, label_points
    from .slope import layers as grid_layers
    from .synthetic import cloud
    from .terrain import estimate_terrain

    points = cloud(n_points, grid=config.grid)
    result = map_points(points, config)
    grid, terrain = result.grid, result.terrain
    tracker = make_tracker(config)

    def surface_stage():
        estimate = estimate_terrain(grid, config.terrain)
        layers = grid_layers(estimate.elevation, estimate.dz_dx, estimate.dz_dy)
        label_cells(grid, layers["elevation"], config.segmentation)

    def labels_stage():
        idx = cell_index(points, config.grid)
        label_points(points, terrain.elevation, terrain.dz_dx, terrain.dz_dy, config.grid, config.segmentation, index=idx)

    stamp = iter(range(0, 10**15, 100_000_000))

    def obstacles_stage():
        run_obstacle_stage(points, result.point_labels, grid, result.layers, next(stamp), tracker, config)

    return {
        "grid": lambda: quantize(points, config.grid),
        "surface": surface_stage,
        "labels": labels_stage,
        "obstacles": obstacles_stage,
    }


def environment() -> dict[str, str]:
    """The machine and library versions the figures were taken on."""
    import cv2
    import scipy

    from . import __version__

    return {
        "terrainmap": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "cpu": _cpu_name(),
        "cores": str(os.cpu_count()),
        "opencv_threads": str(cv2.getNumThreads()),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default"),
    }


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run(config: Config | None = None, *, runs: int = 30, stages: dict[str, Stage] | None = None) -> dict:
    """Time every stage; returns ``{stage: {median_ms, min_ms, max_ms, runs}}``."""
    config = config or Config()
    stages = stages if stages is not None else core_stages(config)
    return {name: _time(fn, runs) for name, fn in stages.items()}
