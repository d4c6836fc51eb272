"""Accuracy of terrainmap and the baselines against the ground truth of a simulated log.

    from terrainmap.config import Config
    from terrainmap.evaluation.accuracy import evaluate

    report = evaluate("drive.mcap", Config(), methods=["terrainmap", "ransac_plane"], max_frames=20)
    report["methods"]["terrainmap"]["0-10"]["elevation_rmse_m"]

The log (written by ``terrainmap simulate``) is streamed: one stereo frame and its truth in memory
at a time. Each frame runs :func:`~terrainmap.pipeline.process_frame` once (terrainmap's own
layers, point labels and tracked obstacles) and every other method of
:mod:`.baselines` on the same ``points_vehicle`` with the same config. Metrics, per range band
(:data:`.scores.BANDS`, horizontal distance from the vehicle origin of the cell centre / point):

- ``elevation_rmse_m``, ``_mae_m``, ``_bias_m`` (method − truth), ``_p95_m`` (of |error|): the
  method's elevation at the cell centres (terrainmap's as ``process`` writes it: none in the cells
  without data) against the true terrain under them along base z
  (:mod:`.truth_grid`), over the cells where the method gives a finite value **and** the
  terrain is observed in this frame (the cell holds truth terrain pixels of the left camera).
- ``slope_error_median_deg``: ``|slope − true slope|`` over the same cells, the true slope being
  that of the cell-mean gradient of the truth in the vehicle frame; null for a method without slope
  (a baseline's finite differences give none only in a cell with no neighbour along an axis).
- ``coverage``: fraction of the observed terrain cells where the method gives a finite elevation.
- ``terrain_precision`` / ``_recall`` / ``_f1``: per point, "predicted TERRAIN" against "truth
  label at the point's pixel is terrain". Points on sky pixels and points the method leaves
  UNKNOWN are not scored; OBSTACLE **and BELOW** count as predicted not-terrain (a terrain point
  the surface passes above is a terrain point the method missed).
- ``obstacle_recall`` (terrainmap only): per frame, the truth obstacles whose top stands at least
  ``obstacle_min_height_m`` above the terrain at their centre, with at least ``min_visible_pixels``
  pixels that both cameras see (:func:`.truth_grid.truth_obstacles`), centre within
  ``obstacle_range_m`` and inside the grid area, that are matched by a *confirmed* positive
  terrainmap obstacle whose centre lies in the truth footprint dilated by ``obstacle_margin_m``
  (vehicle frame), one to one (:func:`match_tracks`: one track cannot find two obstacles);
  summed over frames. Bands by the truth centre's range.
- ``false_obstacles_per_frame`` (terrainmap only): confirmed positive obstacles matching no truth
  footprint (of any height), plus confirmed negative obstacles where the truth shows no
  depression (:func:`.truth_grid.depression_depth` below half of ``obstacles.min_depth_m``,
  ring radius = half the obstacle's width + margin), per evaluated frame. Bands by detection range.

``obstacles`` (extra key) holds, per truth obstacle, ``frames_to_confirmation`` (frames from
first being eligible to first being matched, None if never) and ``id_switches``: how often the
track credited with it changed between frames where it was eligible and matched
(:func:`match_tracks`: an obstacle seen as two tracked clusters does not switch while the
credited one keeps matching; the credit follows the obstacle from its first match in view, beyond
``obstacle_range_m`` too, so the track that brings it into range keeps it there);
``duplicate_frames``: the frames where it was eligible and matched, with more than one track's
centre in its footprint (one obstacle reported twice);
and ``false_on_steep_ground_per_frame``: the false positive obstacles within
``obstacle_range_m`` whose footprint covers true terrain steeper than ``cost.max_slope_deg``
(berms, walls: ground the vehicle cannot drive on, which the paper counts out of the
traversable terrain), per evaluated frame; ``blocked_by_cost``: the share of the eligible
obstacles (as for ``obstacle_recall``, summed over frames) whose footprint holds a cell of cost 1
in terrainmap's ``cost`` layer (a cell whose centre lies in it, or the cell under the centre of
a footprint too small to hold one): what a planner reading the cost alone is kept off.

``common_cells`` (extra key) repeats the elevation metrics over the cells that *every* selected
method covers, so methods with partial coverage are compared on the same cells.

Frames where the pipeline fails (FrameError) are counted by reason in ``failed_frames`` and
skipped for every method; a baseline failing on a frame says nothing there (NaN, no labels).
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..config import Config, check_config
from ..errors import ConfigError, FrameError, brief
from ..grid import cell_centers, cell_index
from ..pipeline import PipelineState, process_frame
from ..sim.truth import TruthFrame, open_truth, truth_at
from ..sources import open_source
from ..stereo import rig_camera
from ..types import FrameResult, Label
from . import baselines
from .scores import BANDS, METRICS, PROFILE_BINS, PROFILE_STEP_M, MethodScores
from .truth_grid import TERRAIN_PIXEL, GridTruth, depression_depth, grid_truth

logger = logging.getLogger(__name__)

__all__ = ["BANDS", "METRICS", "evaluate", "select_methods"]


def select_methods(methods: list[str] | None) -> list[str]:
    """The methods to run (default: every available one), checked.

    Raises
    ------
    ConfigError
        An unknown method, or one whose optional package is missing (the message lists the available ones).
    """
    available = baselines.available_methods()
    if methods is None:
        return available
    if isinstance(methods, str):
        raise ConfigError(f"methods (--methods): give a list of method names, got the string {methods!r}")
    for name in methods:
        if name not in baselines.METHODS:
            raise ConfigError(f"methods (--methods): unknown method {name!r}; available: {', '.join(available)}")
        if name not in available:
            raise ConfigError(f"methods (--methods): {name!r} needs an optional package that is not installed "
                              f"(pip install 'terrainmap[baselines]'); available: {', '.join(available)}")
    if not methods:
        raise ConfigError(f"methods (--methods): no method given; available: {', '.join(available)}")
    return list(dict.fromkeys(methods))


def _check_options(**options) -> None:
    """:class:`ConfigError` naming the first of :func:`evaluate`'s scoring options that is not a
    finite number ≥ 0 (a whole one for the pixel counts; ``min_terrain_pixels`` at least 1)."""
    for name, value in options.items():
        whole = name.endswith("_pixels")
        kinds = (int, np.integer) if whole else (int, float, np.integer, np.floating)
        least = 1 if name == "min_terrain_pixels" else 0
        if isinstance(value, bool) or not isinstance(value, kinds) or not (math.isfinite(value) and value >= least):
            what = "a whole number" if whole else "a finite number"
            raise ConfigError(f"{name}: must be {what} >= {least}, got {brief(value)}")


def match_tracks(hits: np.ndarray, distances: np.ndarray, previous: list[int | None], ids: list[int]) -> np.ndarray:
    """One-to-one matching of truth obstacles to tracks, as in the CLEAR MOT metrics.

    ``hits`` (T, D) bool: track d's centre lies in truth t's dilated footprint; ``distances`` (T, D),
    m: between their centres; ``previous`` (T,): the track id credited with each truth in its last
    matched frame (None if never); ``ids`` (D,): the tracks' ids. A truth whose credited track
    still hits it keeps that track (an obstacle seen as two tracked clusters does not switch while
    the credited one matches); the others are assigned by the Hungarian method, as many pairs
    as the hits allow and of those the nearest, each track and each truth used once (one cluster
    over a car and the rock beside it finds one of them, not both). Returns (T,) the matched
    track's index, -1 for none."""
    match = np.full(len(hits), -1)
    used = np.zeros(len(ids), bool)
    column = {track: d for d, track in enumerate(ids)}
    for t, track in enumerate(previous):
        d = column.get(track, -1)
        if d >= 0 and hits[t, d] and not used[d]:
            match[t], used[d] = d, True
    rows, cols = np.flatnonzero(match < 0), np.flatnonzero(~used)
    free, near = hits[np.ix_(rows, cols)], distances[np.ix_(rows, cols)]
    if free.any():  # a miss costs more than all the hits together: the most pairs first, then the nearest
        for r, c in zip(*linear_sum_assignment(np.where(free, near, 1.0 + near[free].sum())), strict=True):
            if free[r, c]:
                match[rows[r]] = cols[c]
    return match


class _Evaluation:
    """State of one run over a log (see :func:`evaluate`)."""

    def __init__(self, truth, config: Config, names: list[str], options: dict):
        self.truth, self.config, self.names, self.options = truth, config, names, options
        self.scores = {name: MethodScores() for name in names}
        self.seconds: dict[str, float] = defaultdict(float)
        self.method_failures: Counter = Counter()
        self.first_eligible: dict[str, int] = {}
        self.first_matched: dict[str, int] = {}
        self.last_track: dict[str, int] = {}
        self.id_switches: Counter = Counter()
        self.duplicate_frames: Counter = Counter()
        self.false_on_steep_ground = 0
        self.blocked = [0, 0]  # eligible obstacles whose footprint the cost layer blocks, of all eligible
        self.cell_xy = np.column_stack([a.ravel() for a in np.meshgrid(*cell_centers(config.grid), indexing="ij")])
        self.frames = 0

    def add_frame(self, result: FrameResult, truth_frame: TruthFrame) -> None:
        start = time.perf_counter()
        gt = grid_truth(self.truth, truth_frame, self.config.grid, min_pixels=self.options["min_terrain_pixels"])
        points = result.points_vehicle
        u, v = result.pixels[:, 0], result.pixels[:, 1]
        pixel_label = truth_frame.label[v, u]
        point_range = np.hypot(points[:, 0], points[:, 1])
        self.seconds["truth"] += time.perf_counter() - start
        outputs = {name: self._run(name, result) for name in self.names}
        common = gt.observed & np.logical_and.reduce([np.isfinite(o.elevation) for o in outputs.values()])
        for name, output in outputs.items():
            self.scores[name].add_cells(output.elevation, output.slope, gt.height_m, gt.slope_rad, gt.observed,
                                        gt.range_m)
            self.scores[name].add_common(output.elevation, gt.height_m, common, gt.range_m)
            if output.point_labels is not None:
                scored = (pixel_label != 0) & (output.point_labels != Label.UNKNOWN)
                self.scores[name].add_points(output.point_labels[scored] == Label.TERRAIN,
                                             pixel_label[scored] == TERRAIN_PIXEL, point_range[scored])
        if "terrainmap" in self.scores:
            self._score_obstacles(result, gt, truth_frame)
        self.frames += 1

    def _run(self, name: str, result: FrameResult) -> baselines.MethodOutput:
        if name == "terrainmap":
            return baselines.terrainmap_output(result)
        start = time.perf_counter()
        try:
            camera = rig_camera(result.pinhole, result.extrinsics)
            output = baselines.METHODS[name](result.points_vehicle, self.config, result.extrinsics, camera)
        except FrameError as exc:
            logger.info("%s failed on frame %d: %s", name, result.index, exc)
            self.method_failures[name] += 1
            output = baselines.MethodOutput(np.full(self.config.grid.shape, np.nan), None, None)
        self.seconds[name] += time.perf_counter() - start
        return output

    def _score_obstacles(self, result: FrameResult, gt: GridTruth, truth_frame: TruthFrame) -> None:
        opt, grid = self.options, self.config.grid
        confirmed = [o for o in result.obstacles if o.confirmed]
        tracks = [o for o in confirmed if o.kind == "positive"]
        positive = np.array([o.center_m[:2] for o in tracks]).reshape(-1, 2)
        x_max, y_min = grid.x_min_m + grid.length_m, grid.y_center_m - grid.width_m / 2
        in_view = [t for t in gt.obstacles if t.height_m >= opt["obstacle_min_height_m"]
                   and t.pixels >= opt["min_visible_pixels"]
                   and grid.x_min_m <= t.center_m[0] < x_max and y_min <= t.center_m[1] < y_min + grid.width_m]
        hits = np.array([t.contains_xy(positive, opt["obstacle_margin_m"]) for t in in_view], bool).reshape(
            len(in_view), len(tracks))  # (none in view: a frame with no obstacle within the grid)
        centers = np.array([t.center_m[:2] for t in in_view]).reshape(-1, 2)
        distances = np.linalg.norm(positive[None, :, :] - centers[:, None, :], axis=2)
        keys = [f"{t.id} {t.kind}" for t in in_view]
        assigned = match_tracks(hits, distances, [self.last_track.get(k) for k in keys], [o.track_id for o in tracks])
        eligible, matched = [], []
        for t, key, d, covering in zip(in_view, keys, assigned, hits.sum(axis=1), strict=True):
            is_eligible = t.range_m <= opt["obstacle_range_m"]
            if is_eligible:
                eligible.append(t)
                matched.append(d >= 0)
                self.first_eligible.setdefault(key, self.frames)
            if d >= 0:
                # The credit follows the obstacle from its first match in view, in range or not, so
                # that the track that has carried it since beyond the range keeps it within range.
                previous, track = self.last_track.get(key), tracks[d].track_id
                if is_eligible:
                    self.first_matched.setdefault(key, self.frames)
                    self.id_switches[key] += previous not in (None, track)
                    self.duplicate_frames[key] += int(covering > 1)
                self.last_track[key] = track
        matched = np.array(matched, bool)
        if "cost" in result.layers:  # (a result built without one: not scored)
            cost = result.layers["cost"].ravel()
            for t in eligible:  # the cells whose centres lie in its footprint, or the one under its centre
                inside = t.contains_xy(self.cell_xy, 0.0)
                cells = inside if inside.any() else np.argmin(np.hypot(*(self.cell_xy - t.center_m[:2]).T))
                self.blocked[0] += bool(np.any(cost[cells] >= 1))
            self.blocked[1] += len(eligible)
        false = [o for o in confirmed if self._is_false(o, gt, truth_frame)]
        false_range = [float(np.hypot(*o.center_m[:2])) for o in false]
        self.scores["terrainmap"].add_obstacles([t.range_m for t in eligible], matched, false_range)
        max_slope = np.radians(self.config.cost.max_slope_deg)
        near = [o for o, r in zip(false, false_range) if r <= opt["obstacle_range_m"]]
        self.false_on_steep_ground += sum(_steepest_under(o, gt, grid) > max_slope for o in near)

    def _is_false(self, obstacle, gt: GridTruth, truth_frame: TruthFrame) -> bool:
        margin = self.options["obstacle_margin_m"]
        if obstacle.kind == "positive":
            return not any(t.contains_xy(obstacle.center_m[:2], margin)[0] for t in gt.obstacles)
        radius = float(obstacle.size_m[1]) / 2 + margin
        depth = depression_depth(self.truth, truth_frame.pose_world_base(), obstacle.center_m[:2], radius)
        return depth < self.config.obstacles.min_depth_m / 2

    def report(self, log: Path, failed: Counter, wall_s: float) -> dict:
        confirmation = {k: (self.first_matched[k] - f if k in self.first_matched else None)
                        for k, f in sorted(self.first_eligible.items())}
        return {
            "log": str(log),
            "frames": self.frames,
            "failed_frames": dict(failed),
            "methods": {name: s.summary(self.frames) for name, s in self.scores.items()},
            "common_cells": {name: s.common_summary() for name, s in self.scores.items()},
            "method_failures": {name: self.method_failures[name] for name in self.names},
            "obstacles": {
                "margin_m": self.options["obstacle_margin_m"], "min_height_m": self.options["obstacle_min_height_m"],
                "range_m": self.options["obstacle_range_m"], "min_visible_pixels": self.options["min_visible_pixels"],
                "frames_to_confirmation": confirmation,
                "id_switches": {k: self.id_switches[k] for k in sorted(self.first_matched)},
                "duplicate_frames": {k: self.duplicate_frames[k] for k in sorted(self.first_matched)},
                "false_on_steep_ground_per_frame": self.false_on_steep_ground / self.frames
                if self.frames and "terrainmap" in self.scores else None,  # (only terrainmap has obstacles)
                "blocked_by_cost": self.blocked[0] / self.blocked[1] if self.blocked[1] else None,
            },
            "rmse_vs_range": {
                "range_edges_m": [k * PROFILE_STEP_M for k in range(PROFILE_BINS)] + [None],
                "methods": {name: s.rmse_profile() for name, s in self.scores.items()},
            },
            "seconds": {"wall": wall_s, **{k: round(v, 3) for k, v in self.seconds.items()}},
            "config": self.config.to_dict(),
        }


def _steepest_under(obstacle, gt: GridTruth, grid) -> float:
    """The largest true terrain slope (rad) over the cells under an obstacle's footprint."""
    c, s = np.cos(obstacle.yaw_rad), np.sin(obstacle.yaw_rad)
    steps = np.linspace(-0.5, 0.5, 5)
    u, v = (a.ravel() for a in np.meshgrid(steps * obstacle.size_m[0], steps * obstacle.size_m[1]))
    x, y = obstacle.center_m[0] + u * c - v * s, obstacle.center_m[1] + u * s + v * c
    cells = cell_index(np.column_stack([x, y, np.zeros_like(x)]), grid)
    cells = cells[cells < gt.slope_rad.size]
    return float(gt.slope_rad.ravel()[cells].max()) if cells.size else 0.0


def evaluate(
    log_path: str | Path,
    config: Config,
    *,
    methods: list[str] | None = None,
    max_frames: int | None = None,
    obstacle_margin_m: float = 0.5,
    obstacle_min_height_m: float = 0.5,
    obstacle_range_m: float = 20.0,
    min_visible_pixels: int = 20,
    min_terrain_pixels: int = 1,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Score terrainmap and the baselines on a simulated log (definitions in the module docstring).

    Parameters
    ----------
    log_path : path
        A log written by ``terrainmap simulate`` (MCAP or folder), with its truth.
    config : Config
        Pipeline configuration, used by every method.
    methods : list of str, optional
        Names from :data:`.baselines.METHODS` (default: all available).
    max_frames : int, optional
        Evaluate at most this many frames.
    obstacle_margin_m, obstacle_min_height_m, obstacle_range_m, min_visible_pixels
        Obstacle matching and eligibility (module docstring).
    min_terrain_pixels : int
        Truth terrain pixels a cell needs to count as observed.
    progress : callable, optional
        Called with the number of frames done after each frame.

    Returns
    -------
    dict
        ``{"methods": {name: {band: {metric: value or None}}}, "log", "frames", "failed_frames",
        "common_cells", "method_failures", "obstacles", "rmse_vs_range", "seconds", "config"}``.

    Raises
    ------
    InputError
        The log has no ground truth (names the missing topics or files) or cannot be read.
    ConfigError
        Bad config, method names or scoring options (NaN or negative margins, say).
    """
    start = time.perf_counter()
    check_config("eval accuracy", config)
    names = select_methods(methods)
    _check_options(obstacle_margin_m=obstacle_margin_m, obstacle_min_height_m=obstacle_min_height_m,
                   obstacle_range_m=obstacle_range_m, min_visible_pixels=min_visible_pixels,
                   min_terrain_pixels=min_terrain_pixels)
    log_path = Path(log_path)
    options = {"obstacle_margin_m": obstacle_margin_m, "obstacle_min_height_m": obstacle_min_height_m,
               "obstacle_range_m": obstacle_range_m, "min_visible_pixels": min_visible_pixels,
               "min_terrain_pixels": min_terrain_pixels}
    failed: Counter = Counter()
    with open_truth(log_path) as truth, open_source(log_path) as source:
        run = _Evaluation(truth, config, names, options)
        state = PipelineState(config)
        truth_frames = truth.frames()
        for done, frame in enumerate(source.frames(max_frames=max_frames), 1):
            truth_frame = truth_at(truth_frames, frame.stamp_ns, log_path, frame.left.shape[:2])
            t0 = time.perf_counter()
            try:
                result = process_frame(frame, config, state)
            except FrameError as exc:
                failed[exc.reason] += 1
                logger.info("frame %d failed: %s", frame.index, exc)
                continue
            finally:
                run.seconds["pipeline"] += time.perf_counter() - t0
            run.add_frame(result, truth_frame)
            if progress is not None:
                progress(done)
    return run.report(log_path, failed, time.perf_counter() - start)
