"""``terrainmap bench``: per-stage timings at the paper configuration (a benchmark, not a test).

Each stage is timed over repeated runs on the same input, the stages taking turns round by round;
we report the median, min and max in milliseconds, and :func:`goals` holds the medians to the
speed goals. The inputs are synthetic so the figures are comparable anywhere:

- ``grid``, ``surface``, ``labels``, ``obstacles``: a 300k-point cloud over rolling terrain
  with box obstacles (the size of a 640×480 stereo frame, its points in the order a camera
  delivers them: :func:`terrainmap.synthetic.cloud`), paper configuration (34 m × 22 m,
  0.5 m cells, 25×25 control points, degree 3), seen as from a stereo rig 1.8 m up with
  f·B = 150 px·m (so eq. 1 discounts its noise, as in the pipeline). ``surface`` is the whole
  iterative estimation with the slope and cell-label layers; ``grid`` includes each point's
  cell index, which ``labels`` reuses (as the pipeline does) to label every point.
- ``grid_labels_floor``: the passes over the points that ``grid`` and ``labels`` cannot do
  without, in plain numpy and nothing else (:func:`numpy_floor`): what those two stages would
  cost at the least without a compiled kernel.
- ``sgbm_alone``, ``frame_total``: one simulated 640×480 stereo pair (``terrainmap simulate``'s
  ``mounds`` scene, frame 0): OpenCV SGBM alone on the grey pair as given, and the whole per-frame
  pipeline (rectification check, sky mask, SGBM on the rows below the sky (164 of 480 rows there
  see only sky) of the pair padded for ``stereo.full_width``, points, terrain, labels, obstacles,
  cost), side by side in one run; ``frame_every_row``: the same with ``stereo.drop_sky`` off,
  so SGBM matches every row, as on a frame that shows no rows of only sky.
- ``upright``: the upright-surface cue on that frame (:mod:`terrainmap.upright`; in
  ``frame_total`` too).
- ``mcap_write``: writing that frame's result to a Foxglove MCAP (lz4), the default output.

With a log of one's own (:func:`first_frame`, ``terrainmap bench --log PATH``), :func:`all_stages`
times the same stages on its first stereo pair instead: the frame stages on its images, the core
stages on that pair's points as the pipeline makes them, seen from its rig.

Then :func:`process_rate` times ``terrainmap process`` as a whole, reading and writing included
(its two matching workers beside the main thread): frames/s over the log's first pairs, or over
a still simulated log (:func:`still_log`), held to the goal of at least 15.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .config import Config

if TYPE_CHECKING:
    from .types import FrameResult, StereoCamera, StereoFrame

Stage = Callable[[], object]


def _summary(times: list[float]) -> dict[str, float]:
    return {
        "median_ms": statistics.median(times),
        "min_ms": min(times),
        "max_ms": max(times),
        "runs": len(times),
    }


def core_stages(
    config: Config, n_points: int = 300_000, *, points: np.ndarray | None = None, camera: StereoCamera | None = None,
    labelled: FrameResult | None = None,
) -> dict[str, Stage]:
    """Stage name → zero-argument callable, for the terrain core on a synthetic cloud of
    ``n_points``, or on ``points`` ((N, 3), vehicle frame, m) seen by ``camera`` (a
    :class:`~terrainmap.types.StereoCamera`); ``labelled``, the pipeline's result for ``points``,
    gives the obstacles stage its labels and layers, the upright cue's included."""
    from .grid import cell_index, quantize
    from .obstacle_stage import make_tracker, run_obstacle_stage
    from .pipeline import map_points, map_surface
    from .segmentation import label_points
    from .synthetic import cloud
    from .types import StereoCamera

    if points is None:
        points = cloud(n_points, grid=config.grid)
        camera = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)  # the cloud's viewpoint
    result = labelled or map_points(points, config, camera=camera)
    grid = quantize(points, config.grid, camera=camera)  # the surface stage's input
    terrain, _, limits = map_surface(grid, config, camera)
    index = cell_index(points, config.grid)  # computed by the grid stage; the pipeline reuses it
    tracker = make_tracker(config)

    def labels_stage():
        label_points(points, terrain.elevation, terrain.dz_dx, terrain.dz_dy, config.grid, config.segmentation,
                     index=index, limits=limits)

    stamp = iter(range(0, 10**15, 100_000_000))

    def obstacles_stage():
        run_obstacle_stage(points, result.point_labels, result.grid, result.layers, next(stamp), tracker, config,
                           camera=camera, index=index)

    return {
        "grid": lambda: quantize(points, config.grid, camera=camera),
        "surface": lambda: map_surface(grid, config, camera),
        "labels": labels_stage,
        "grid_labels_floor": numpy_floor(points, config),
        "obstacles": obstacles_stage,
    }


def numpy_floor(points: np.ndarray, config: Config) -> Stage:
    """The least numpy work of grid + point labels on ``points`` ((N, 3), vehicle frame, m): each
    point's cell (two passes an axis), the count, Σz, Σz² and min z of each cell (eq. 1), one
    gather of the point's cell row (tangent plane and thresholds) and the two comparisons that
    label it. No checks, no trash bin for points outside the area (they are clipped into it), no
    per-cell work: a lower bound of what ``quantize`` and ``label_points`` can cost in numpy."""
    grid = config.grid
    m1, cells = grid.shape[1], grid.shape[0] * grid.shape[1]
    x, y, z = (np.ascontiguousarray(points[:, k], np.float32) for k in range(3))
    inv = np.float32(1.0 / grid.cell_size_m)
    table = np.zeros((cells + 1, 4), np.float32)
    lowest = np.empty(cells + 1)

    def passes() -> np.ndarray:
        index = ((x - np.float32(grid.x_min_m)) * inv).astype(np.intp)
        index *= m1
        index += ((y - np.float32(grid.y_min_m)) * inv).astype(np.intp)
        np.clip(index, 0, cells, out=index)
        z64 = z.astype(np.float64)
        for weights in (None, z64, z64 * z64):
            np.bincount(index, weights, cells + 1)
        lowest.fill(np.inf)
        np.minimum.at(lowest, index, z64)
        rows = table.take(index, axis=0)
        s = z - rows[:, 0] * x - rows[:, 1] * y
        return (s > rows[:, 2]).view(np.uint8) + (s < rows[:, 3]).view(np.uint8)

    return passes


def sim_frame(scene: str = "mounds", seed: int = 7, width: int = 640, height: int = 480):
    """A rendered stereo pair as a :class:`~terrainmap.types.StereoFrame` (calibration and true
    extrinsics attached, as a log from ``terrainmap simulate`` would give them)."""
    from .types import StereoFrame

    _, rig, rendered = _rendered(scene, seed, width, height)
    return StereoFrame(0, rendered.stamp_ns, rendered.left, rendered.right, rig.calibration(), rig.extrinsics())


def _rendered(scene: str, seed: int, width: int, height: int):
    """(scene, rig, first frame) of a short simulated drive over ``scene``."""
    from .sim import SimConfig
    from .sim.scenes import build_scene

    built = build_scene(scene, seed, length_m=10.0)
    renderer = SimConfig(scene=scene, frames=1, seed=seed, width=width, height=height).renderer(built)
    return built, renderer.rig, renderer.frame(0)


def still_log(path: Path, frames: int, scene: str = "mounds", seed: int = 7) -> Path:
    """A ROS 2 MCAP log with the topics ``terrainmap simulate`` writes (raw images, camera infos,
    tf, the truth's images and boxes) of ``frames`` copies of :func:`sim_frame`'s pair 0.1 s
    apart: a vehicle standing still, without the minute of rendering a drive takes. Its metadata
    is no full scene description: ``eval accuracy`` cannot read its truth."""
    from .sim.mcap_log import McapLog

    built, rig, rendered = _rendered(scene, seed, 640, 480)
    with McapLog(path, built, rig, {"scene": scene, "seed": seed, "still": True}) as log:
        for k in range(frames):
            log.write(dataclasses.replace(rendered, stamp_ns=rendered.stamp_ns + k * 10**8))
    return path


def process_rate(config: Config, log=None, *, frames: int = 40, runs: int = 3, **open_kwargs) -> dict:
    """``terrainmap process``'s throughput, reading and writing included: the runner over the first
    ``frames`` stereo pairs of ``log`` (anything ``process`` reads; by default :func:`still_log`),
    written to a Foxglove MCAP (lz4) in a temporary folder, ``runs`` times. Returns
    ``{median_fps, min_fps, max_fps, runs, frames, failed}``: frames/s as the runner counts them
    (pairs read, failed ones too, over its wall time; ``process`` reads its first pair before),
    the pairs read in a run and the failed ones by reason (a failed pair skips the terrain fit, so
    a run with failures is faster than one without)."""
    import tempfile

    from . import runner
    from .errors import InputError
    from .sinks import open_mcap_sink
    from .sources import open_source

    if runs < 1 or frames < 1:
        raise InputError(f"process_rate: runs and frames must be at least 1, got {runs} and {frames}")
    rates = []
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as folder:
        log = log if log is not None else still_log(Path(folder) / "still.mcap", frames)
        for _ in range(runs):
            output = Path(folder) / "out.mcap"
            with open_source(log, **open_kwargs) as source:
                summary = runner.run(itertools.islice(source.frames(), frames), config,
                                     [open_mcap_sink(output, config=config)])
            output.unlink()
            rates.append(summary.fps)
    return {"median_fps": statistics.median(rates), "min_fps": min(rates), "max_fps": max(rates), "runs": runs,
            "frames": summary.frames_done + summary.frames_failed, "failed": dict(summary.failures)}


def first_frame(path, **open_kwargs) -> StereoFrame:
    """The first stereo pair of a log or folder (anything ``terrainmap process`` reads), as a
    :class:`~terrainmap.types.StereoFrame`; :class:`~terrainmap.errors.InputError` if it has none.
    ``open_kwargs``: topics, calibration and pairing tolerance, as for
    :func:`~terrainmap.sources.open_source`."""
    from .errors import InputError
    from .pipeline import check_stamp
    from .sources import open_source

    with open_source(path, **open_kwargs) as source:
        for frame in source.frames():
            check_stamp(frame)  # as process does: the benchmark's MCAP stage would refuse it, naming its own file
            return frame
    raise InputError(f"{path}: holds no stereo pair to time")


def all_stages(config: Config, frame: StereoFrame | None = None) -> dict[str, Stage]:
    """Every stage: the core on the synthetic cloud and the frame stages on the simulated pair, or,
    given ``frame`` (a :class:`~terrainmap.types.StereoFrame`), all of them on that pair.
    :class:`~terrainmap.errors.InputError` if the pipeline finds no terrain in ``frame``."""
    if frame is None:
        return {**core_stages(config), **frame_stages(config)}
    from .errors import FrameError, InputError
    from .pipeline import PipelineState, process_frame
    from .stereo import rig_camera

    try:
        result = process_frame(frame, config, PipelineState(config))
    except FrameError as exc:
        raise InputError(f"cannot time the first stereo pair: {exc}") from exc
    camera = rig_camera(result.pinhole, result.extrinsics)
    return {**core_stages(config, points=result.points_vehicle, camera=camera, labelled=result),
            **frame_stages(config, frame)}


def frame_stages(config: Config, frame: StereoFrame | None = None) -> dict[str, Stage]:
    """``sgbm_alone``, ``frame_total``, ``frame_every_row``, ``upright`` and ``mcap_write`` on a
    simulated 640×480 pair, or on ``frame``."""
    import tempfile

    from .grid import cell_index
    from .pipeline import PipelineState, process_frame
    from .sinks import open_mcap_sink
    from .stereo import to_grey
    from .upright import label_upright

    frame = frame if frame is not None else sim_frame()
    state = PipelineState(config)
    # Each call is the next frame, 0.1 s on: with the stamp of the one before, the tracker would
    # take it for a frame logged twice and skip its update, as process never does.
    stamps = itertools.count(frame.stamp_ns, 10**8)
    for _ in range(3):  # by the third frame the obstacles are confirmed tracks, which the MCAP stage writes
        written = dataclasses.replace(frame, stamp_ns=next(stamps))
        result = process_frame(written, config, state)
    every_row = copy.deepcopy(config)  # a frame with no rows of only sky: SGBM matches them all
    every_row.stereo.drop_sky = False
    every_row_state = PipelineState(every_row)
    every_row_stamps = itertools.count(frame.stamp_ns, 10**8)
    grey = [to_grey(im) for im in (frame.left, frame.right)]
    # The file is removed with its folder at once: the open sink writes on into it, and nothing is
    # left behind however the benchmark ends.
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as folder:
        sink = open_mcap_sink(Path(folder) / "bench.mcap", config=config)
    index = cell_index(result.points_vehicle, config.grid)

    def upright_stage():
        label_upright(result.point_labels, result.points_vehicle, index, result.disparity, result.pixels,
                      result.terrain, config.grid, result.pinhole, result.extrinsics, config.segmentation)

    return {
        "sgbm_alone": lambda: state.matcher.sgbm.compute(*grey),
        "frame_total": lambda: process_frame(dataclasses.replace(frame, stamp_ns=next(stamps)), config, state),
        "frame_every_row": lambda: process_frame(dataclasses.replace(frame, stamp_ns=next(every_row_stamps)),
                                                 every_row, every_row_state),
        "upright": upright_stage,
        "mcap_write": lambda: sink.write(written, result),
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


def run(config: Config | None = None, *, runs: int = 30, stages: dict[str, Stage] | None = None, warmup: int = 2) -> dict:
    """Time every stage; returns ``{stage: {median_ms, min_ms, max_ms, runs}}``.

    The stages take turns, one call of each per round, so that a machine that slows down or
    speeds up during the run (a shared virtual machine drifts by ±25 %) weighs on all of them
    alike and ratios such as ``frame_total / sgbm_alone`` compare like with like.
    """
    config = config or Config()
    stages = stages if stages is not None else all_stages(config)
    times: dict[str, list[float]] = {name: [] for name in stages}
    for round_ in range(warmup + runs):
        for name, fn in stages.items():
            start = time.perf_counter()
            fn()
            if round_ >= warmup:
                times[name].append((time.perf_counter() - start) * 1e3)
    return {name: _summary(t) for name, t in times.items()}


def goals(results: dict) -> list[tuple[str, float, float]]:
    """The speed goals the medians are held to, ``(what, measured, at most)``, for the stages present."""
    med = {name: r["median_ms"] for name, r in results.items()}
    out = []
    if "surface" in med:
        out.append(("surface (estimation, slope, cell labels), ms", med["surface"], 5.0))
    if {"grid", "labels"} <= med.keys():
        floor = f" (numpy's floor for their passes: {med['grid_labels_floor']:.2f})" if "grid_labels_floor" in med else ""
        out.append((f"grid + labels, ms{floor}", med["grid"] + med["labels"], 5.0))
    if "obstacles" in med:
        out.append(("obstacles (extraction, tracking, cost), ms", med["obstacles"], 5.0))
    for frame in ("frame_total", "frame_every_row"):
        if {frame, "sgbm_alone"} <= med.keys():
            out.append((f"{frame} / sgbm_alone", med[frame] / med["sgbm_alone"], 1.6))
    return out
