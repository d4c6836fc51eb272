"""The pure per-frame core: points → grid → terrain → layers → labels.

:func:`map_points` runs the terrain part (paper steps 2–4 and the segmentation) on a point cloud
already in the vehicle frame; :func:`process_frame` runs the whole pipeline on a stereo frame.
Neither does I/O or printing; per-stage wall times are returned as data
(``timings_ms``), so the runner can report them.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from typing import NamedTuple

import numpy as np

from .config import Config, same_values
from .errors import STAMP_RANGE, CalibrationError, ConfigError, InputError, is_stamp, is_whole
from .extrinsics import estimate_extrinsics, extrinsics_from_calibration
from .grid import HeightGrid, cell_index, quantize
from .obstacle_stage import make_tracker, run_obstacle_stage
from .segmentation import cells_holding, label_cells, label_points, thresholds, widen_at_edges
from .slope import layers as grid_layers
from .stereo import StereoMatcher, StereoResult, rig_camera, to_vehicle
from .terrain import TerrainEstimate, estimate_terrain
from .tracking import ObstacleTracker
from .types import Extrinsics, FrameResult, Label, StereoCamera, StereoFrame
from .upright import label_upright


class Stopwatch:
    """Collects wall times of named stages, in milliseconds (``with watch("grid"): ...``)."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.ms[stage] = self.ms.get(stage, 0.0) + (time.perf_counter() - start) * 1e3


@dataclass
class TerrainMap:
    """Output of :func:`map_points`.

    ``layers``: float32 ``elevation`` (m), ``slope`` (rad), ``dz_dx``, ``dz_dy``; uint8 ``label``;
    bool ``valid`` — all (m0, m1), indexed [ix, iy]. ``point_labels``: (N,) uint8 Label. ``index``:
    (N,) the points' flat cell index (:func:`~terrainmap.grid.cell_index`).
    """

    grid: HeightGrid
    terrain: TerrainEstimate
    layers: dict[str, np.ndarray]
    point_labels: np.ndarray
    index: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def stats(self) -> dict[str, float]:
        return {
            "iterations": float(self.terrain.iterations),
            "mean_error_m": self.terrain.mean_error_m,
            "observed_cells": float(self.grid.observed.sum()),
            "valid_cells": float(self.grid.valid.sum()),
        }


def map_points(
    points_vehicle: np.ndarray, config: Config, watch: Stopwatch | None = None, camera: StereoCamera | None = None
) -> TerrainMap:
    """Terrain map of one point cloud.

    Parameters
    ----------
    points_vehicle : (N, 3) float array
        Points in the vehicle frame, metres; non-finite points and points outside the area are
        ignored (labelled UNKNOWN).
    config : Config
        Uses the ``grid``, ``terrain`` and ``segmentation`` sections.
    camera : StereoCamera, optional
        The stereo rig the points came from: eq. 1 then discounts its height noise
        (``grid.stereo_noise_px``) and segmentation thresholds can follow it.

    Raises
    ------
    ConfigError
        ``config`` does not validate (:meth:`Config.validate`).
    InputError
        ``points_vehicle`` is not an (N, 3) array of numbers.
    FrameError
        No terrain can be found (no points in the area, too few cells, fit failure).
    """
    _whole_config("map_points", config)  # a section would pass its own validate() and fail later
    if camera is not None and not isinstance(camera, StereoCamera):
        raise InputError(f"map_points: camera must be a StereoCamera or None, got {type(camera).__name__}")
    return _map_points(points_vehicle, config.validate(), watch or Stopwatch(), camera)


def _map_points(points_vehicle: np.ndarray, config: Config, watch: Stopwatch, camera: StereoCamera | None) -> TerrainMap:
    """:func:`map_points` for a config already validated (a run checks the whole config once, not
    every frame; the stage functions check the section they take only when it changed)."""
    with watch("grid"):
        idx = cell_index(points_vehicle, config.grid)
        grid = quantize(points_vehicle, config.grid, index=idx, camera=camera)
    with watch("surface"):
        terrain, layers, limits = map_surface(grid, config, camera)
    with watch("labels"):
        labels = label_points(
            points_vehicle, terrain.elevation, terrain.dz_dx, terrain.dz_dy, config.grid, config.segmentation,
            index=idx, limits=limits,
        )
    return TerrainMap(terrain.grid, terrain, layers, labels, idx, watch.ms)


def map_surface(
    grid: HeightGrid, config: Config, camera: StereoCamera | None = None
) -> tuple[TerrainEstimate, dict[str, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The surface stage of :func:`map_points`: the terrain fit, its layers (elevation, slope,
    ..., per-cell ``label`` and ``valid``, (m0, m1) each) and the per-cell (above, below)
    labelling thresholds. The cells are labelled against ``terrain.grid``, whose samples the fit
    recomputed on the terrain's slope (terrain.py, decision 7)."""
    terrain = estimate_terrain(grid, config.terrain)
    gradient = (terrain.dz_dx, terrain.dz_dy)
    layers = grid_layers(terrain.elevation, *gradient)
    limits = thresholds(config.grid, config.segmentation, camera, terrain.elevation, *gradient)
    limits = widen_at_edges(limits, terrain.grid.observed, config.segmentation.edge_margin_m)
    layers["label"] = label_cells(terrain.grid, layers["elevation"], config.segmentation, limits=limits)
    layers["valid"] = terrain.grid.valid
    return terrain, layers, limits


@dataclass
class PipelineState:
    """What one run carries from frame to frame (everything else is per frame).

    ``matcher``: the stereo matcher, rebuilt only when the calibration or config changes.
    ``extrinsics``: camera pose estimated from the data on the first frame where the ground fit
    succeeds, then kept (the camera is rigidly mounted); unused when frames carry extrinsics.
    ``tracker``: obstacle tracks, of the frames ``tracked_matcher`` matched. A new calibration
    (another camera, or the next scene of a folder of unrelated scenes, each with its calibration
    file) starts the estimated pose and the tracks afresh, and so do new stereo settings (a new
    matcher), whether in a new config or changed in place; another config with other tracking or
    grid settings replaces the tracker with a new one, its tracks starting afresh (one changed in
    place is followed by the tracker): give each config a state of its own.
    """

    config: Config
    matcher: StereoMatcher | None = None
    extrinsics: Extrinsics | None = None
    tracker: ObstacleTracker | None = None
    tracked_matcher: StereoMatcher | None = None
    checked: tuple = (None, None)
    """A copy of the config's fields and the frame extrinsics validated last: a run checks them
    once, not every frame, and again when the config is changed (in place too)."""

    def __post_init__(self) -> None:
        _whole_config("PipelineState", self.config)
        self.check(self.config)  # a config built in code: ConfigError here, not a numpy error mid-run
        if self.tracker is None:
            self.tracker = make_tracker(self.config)

    def check(self, config: Config, frame: StereoFrame | None = None) -> None:
        """Validate ``config`` (ConfigError) and the ``frame``'s extrinsics (CalibrationError for a
        pose that is no rigid motion, naming where the frame and the extrinsics come from), each
        only when it is not the one checked last."""
        checked, extrinsics = self.checked[0], frame.extrinsics if frame is not None else None
        if not same_values(config, checked):  # (a value of another type, True for 1.0, is checked too)
            config.validate()
            checked = replace(config, **{f.name: replace(getattr(config, f.name)) for f in fields(config)})
        if extrinsics is not None and extrinsics is not self.checked[1]:
            name = f"{frame.source or 'frame'} (pair {frame.index}): extrinsics ({extrinsics.source})"
            try:  # the stages use them as they are: the shapes, not only the numbers (reshaped) below
                shapes = np.shape(extrinsics.rotation), np.shape(extrinsics.translation)
            except ValueError:  # ragged
                shapes = None
            if shapes != ((3, 3), (3,)):
                got = f"{shapes[0]} and {shapes[1]}" if shapes else "ragged arrays"
                raise CalibrationError(f"{name}: rotation must be 3×3 and translation 3 numbers, got {got}")
            extrinsics_from_calibration(extrinsics.rotation, extrinsics.translation, name=name)
        self.checked = (checked, extrinsics)


@dataclass
class Matched:
    """The first half of a frame (:func:`match_frame`): stereo and the points in the vehicle frame,
    and the ``matcher`` (``state.matcher`` then) that matched it."""

    stereo: StereoResult
    points_vehicle: np.ndarray
    pixels: np.ndarray
    extrinsics: Extrinsics
    timings_ms: dict[str, float]
    matcher: StereoMatcher | None = None

    @property
    def camera(self) -> StereoCamera:
        """The rig's noise geometry and image columns in the vehicle frame: the rectified pinhole
        and the rectified left camera's pose (:func:`~terrainmap.stereo.rig_camera`)."""
        return rig_camera(self.stereo.pinhole, self.extrinsics)


def check_arguments(frame: StereoFrame, config: Config, state: PipelineState) -> None:
    """:class:`ConfigError` or :class:`InputError` naming the argument of :func:`process_frame`
    that is not of its type (a library caller's slip, said here rather than as an AttributeError)."""
    _whole_config("process_frame", config)
    for name, value, kind in (("frame", frame, StereoFrame), ("state", state, PipelineState)):
        if not isinstance(value, kind):
            raise InputError(f"process_frame: {name} must be a {kind.__name__}, got {type(value).__name__}")
    if not is_whole(frame.index):  # the outputs number frames by it
        raise InputError(f"process_frame: frame.index must be a whole number, got {frame.index!r}")
    if frame.extrinsics is not None and not isinstance(frame.extrinsics, Extrinsics):
        raise InputError(f"process_frame: frame.extrinsics must be an Extrinsics or None, got "
                         f"{type(frame.extrinsics).__name__}")
    ids = {"frame.frame_id": frame.frame_id, "frame.odometry_frame_id": frame.odometry_frame_id}
    if frame.extrinsics is not None:
        ids.update({"frame.extrinsics.camera_frame_id": frame.extrinsics.camera_frame_id,
                    "frame.extrinsics.vehicle_frame_id": frame.extrinsics.vehicle_frame_id})
    for name, value in ids.items():  # the outputs name frames by them (tf, headers)
        if not isinstance(value, str) or not value:
            raise InputError(f"process_frame: {name} must be a frame name (a non-empty str), got {value!r}")


def _whole_config(what: str, config) -> None:
    """:class:`ConfigError` naming ``what`` unless ``config`` is a :class:`Config` (not a section)."""
    if not isinstance(config, Config):
        raise ConfigError(f"{what}: config must be the whole Config, got {type(config).__name__}")


def check_stamp(frame: StereoFrame) -> None:
    """:class:`InputError` naming the frame's source when its stamp is no time an MCAP or ROS
    stamp (unsigned 64-bit) can hold, before an output refuses it mid-write (the tracker would take it)."""
    if not is_whole(frame.stamp_ns):
        raise InputError(f"{frame.source or 'input'}: frame {frame.index} has stamp {frame.stamp_ns!r}; "
                         "a stamp is a whole number of nanoseconds")
    if not is_stamp(frame.stamp_ns):
        raise InputError(f"{frame.source or 'input'}: frame {frame.index} has stamp {frame.stamp_ns} ns, "
                         f"outside {STAMP_RANGE}")


class Prepared(NamedTuple):
    """What :func:`prepare_match` chose for a frame: its ``matcher``, the ``extrinsics`` to use
    (None: to be estimated from this frame) and the ``watch`` timing the frame so far."""

    matcher: StereoMatcher
    extrinsics: Extrinsics | None
    watch: Stopwatch


def prepare_match(frame: StereoFrame, config: Config, state: PipelineState) -> Prepared:
    """The part of :func:`match_frame` that reads and updates ``state`` before matching: checks
    (``state.checked``), the matcher (rebuilt for another calibration or stereo config) and the
    extrinsics. Called in frame order, it lets the matching itself run in several threads at once
    (the runner); a frame prepared without extrinsics must be matched (its pose estimated into
    ``state``) before the next frame is prepared, or that one would estimate a pose of its own."""
    check_arguments(frame, config, state)
    check_stamp(frame)
    watch = Stopwatch()
    with watch("stereo"):
        if state.matcher is None or not state.matcher.same_setup(frame.calibration, config.stereo):
            if state.matcher is not None:  # another camera or scene (a folder of KITTI or Middlebury
                state.extrinsics = None  # scenes): the pose estimated before does not hold for it
            state.matcher = StereoMatcher(frame.calibration, config.stereo)
        state.check(config, frame)
    return Prepared(state.matcher, frame.extrinsics or state.extrinsics, watch)


def match_frame(frame: StereoFrame, config: Config, state: PipelineState, prepared: Prepared | None = None) -> Matched:
    """SGM disparity → 3D points in the vehicle frame (uses and updates ``state.matcher``,
    ``state.extrinsics`` and ``state.checked`` only, so it can run ahead of :func:`finish_frame`).
    ``prepared``: what :func:`prepare_match` gave for this frame, called apart (the runner); the
    matching then updates ``state`` only where the frame had no extrinsics (with the pose
    estimated from it)."""
    matcher, extrinsics, watch = prepared or prepare_match(frame, config, state)
    with watch("stereo"):
        stereo = matcher.compute(frame.left, frame.right, extrinsics)  # drops the sky if it can
    with watch("points"):
        if extrinsics is None:  # the sky's horizon needs the extrinsics: estimated first, here
            points_cam, _ = matcher.reproject(stereo.disparity)
            estimated = estimate_extrinsics(points_cam, config.extrinsics)
            extrinsics = state.extrinsics = replace(estimated, camera_frame_id=frame.frame_id)
            matcher.drop_sky(stereo, extrinsics)
        points_cam, pixels = matcher.reproject(stereo.disparity)
        points = to_vehicle(points_cam, extrinsics)
    return Matched(stereo, points, pixels, extrinsics, watch.ms, matcher)


def finish_frame(frame: StereoFrame, matched: Matched, config: Config, state: PipelineState) -> FrameResult:
    """Points → grid → terrain → slope, labels → obstacles (``state.tracker``) and cost."""
    watch = Stopwatch()
    watch.ms.update(matched.timings_ms)
    if matched.matcher is not state.tracked_matcher:  # another camera or scene: its obstacles are
        state.tracker.reset()  # not these (here, as match_frame may run a frame ahead)
        state.tracked_matcher = matched.matcher
    if (state.tracker.config, state.tracker.area) != (config.tracking, config.grid):  # another config's tracking
        state.tracker = make_tracker(config)
    points, camera = matched.points_vehicle, matched.camera
    terrain = _map_points(points, config, watch, camera)  # config checked by match_frame
    if config.segmentation.upright_ratio > 0:
        with watch("upright"):
            labels = label_upright(
                terrain.point_labels, points, terrain.index, matched.stereo.disparity, matched.pixels, terrain.terrain,
                config.grid, matched.stereo.pinhole, matched.extrinsics, config.segmentation,
            )
            made = terrain.index[labels != terrain.point_labels]  # their cells hold obstacles too
            terrain.layers["label"][cells_holding(made, config.grid.shape, config.obstacles.min_cell_points)] = (
                Label.OBSTACLE
            )
            terrain.point_labels = labels
    with watch("obstacles"):
        obstacles, cost, occupied = run_obstacle_stage(
            points, terrain.point_labels, terrain.grid, terrain.layers, frame.stamp_ns, state.tracker, config,
            vehicle_pose=frame.vehicle_pose, camera=camera, index=terrain.index,
        )
    return FrameResult(
        index=frame.index,
        stamp_ns=frame.stamp_ns,
        extrinsics=matched.extrinsics,
        points_vehicle=points,
        pixels=matched.pixels,
        point_labels=terrain.point_labels,
        grid=terrain.grid,
        terrain=terrain.terrain,
        layers={**terrain.layers, "cost": cost},
        disparity=matched.stereo.disparity,
        image=matched.stereo.image,
        pinhole=matched.stereo.pinhole,
        obstacles=obstacles,
        occupied=occupied,
        stats={**terrain.stats, "points": float(len(points)), "detections": float(len(obstacles)),  # tracked or not
               "obstacles": float(sum(o.confirmed for o in obstacles))},
        timings_ms=watch.ms,
    )


def process_frame(frame: StereoFrame, config: Config, state: PipelineState) -> FrameResult:
    """The whole pipeline on one stereo pair: SGM disparity → 3D points (vehicle frame) → grid →
    terrain surface → slope, labels → obstacles (tracked) and traversability cost.

    Parameters
    ----------
    frame : StereoFrame
        Left and right images (H×W or H×W×3 RGB, uint8, of one size), their calibration, the
        stamp (ns) and, where known, the camera's extrinsics (else estimated on the first frame and
        kept in ``state``) and the vehicle's pose in the odometry frame (tracks then live there).
    config : Config
        The settings (``load_config()`` for the paper's defaults).
    state : PipelineState
        What the run carries from frame to frame (matcher, estimated camera pose, tracks): one per
        run, ``PipelineState(config)``, given every frame in stamp order.

    Returns
    -------
    FrameResult
        Points (N×3 float32, vehicle frame, m) with their pixels and labels, the grid's layers
        (``elevation`` m, ``slope`` rad, ``label``, ``valid``, ``cost`` in [0, 1], indexed
        ``[ix, iy]``), the tracked obstacles (vehicle frame; tentative tracks too: those with
        ``confirmed`` true are the obstacles the outputs show), the disparity and per-stage
        timings (ms); see :class:`~terrainmap.types.FrameResult`. ``image`` is the frame's own
        left array where it came rectified: copy it to keep it past a buffer the camera reuses.

    Raises
    ------
    FrameError
        This frame yields no terrain (no ground for the extrinsics, no points in the area, too few
        cells, fit failure); the runner counts it and goes on.
    CalibrationError, InputError
        The frame cannot be used at all (bad calibration, image sizes); the run stops.
    ConfigError
        ``config`` does not validate (it is checked whenever it changed since the last frame).
    """
    return finish_frame(frame, match_frame(frame, config, state), config, state)
