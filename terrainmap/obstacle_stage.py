"""Paper step 5 as one call: obstacle extraction, tracking and the traversability cost layer.

The pipeline calls :func:`run_obstacle_stage` once per frame after segmentation, with one
:class:`~terrainmap.tracking.ObstacleTracker` kept across the frames of a run (see
:func:`make_tracker`); ``terrainmap bench`` times this call as the stage ``obstacles``.
"""

from __future__ import annotations

import numpy as np

from .config import Config, CostConfig, check_section
from .cost import step_height, traversability_cost
from .grid import HeightGrid
from .obstacles import extract_obstacles
from .tracking import ObstacleTracker
from .types import Label, Obstacle, StereoCamera


def make_tracker(config: Config) -> ObstacleTracker:
    """A fresh tracker for one run (drops tracks that leave the grid area)."""
    return ObstacleTracker(config.tracking, area=config.grid)


def run_obstacle_stage(
    points_vehicle: np.ndarray,
    point_labels: np.ndarray,
    grid: HeightGrid,
    layers: dict[str, np.ndarray],
    stamp_ns: int,
    tracker: ObstacleTracker,
    config: Config,
    *,
    vehicle_pose: np.ndarray | None = None,
    camera: StereoCamera | None = None,
    index: np.ndarray | None = None,
) -> tuple[list[Obstacle], np.ndarray, list[Obstacle]]:
    """Obstacles of this frame (tracked), the cost layer and what else occupies it.

    Parameters
    ----------
    points_vehicle, point_labels : (N, 3) float, (N,) uint8
        Points (vehicle frame, m) and their :class:`~terrainmap.types.Label`.
    grid : HeightGrid
        The frame's grid (samples before equalization, observed/valid masks).
    layers : dict of (m0, m1) arrays
        ``elevation`` (m) and ``slope`` (rad) at the cell centres, ``label`` (cell labels).
        Cells labelled OBSTACLE are left out of the step term: what stands up that high is for
        the tracker to confirm, so a single-frame false positive leaves no trace in the cost
        unless the tracker takes it for a part of a confirmed obstacle.
    stamp_ns : int
        Frame stamp, nanoseconds.
    tracker : ObstacleTracker
        Per-run tracking state (:func:`make_tracker`).
    config : Config
    vehicle_pose : (4, 4) array, optional
        ``world_from_vehicle`` from odometry; tracks then live in the world frame.
    camera : StereoCamera, optional
        The stereo rig of the points: the tracker then knows how a detection's depth jitters.
    index : (N,) int array, optional
        The points' :func:`~terrainmap.grid.cell_index`, reused from the grid stage (taken as
        given, not checked).

    Returns
    -------
    obstacles : list of Obstacle
        Tracked obstacles, vehicle frame; those with ``confirmed`` true are the obstacles.
    cost : (m0, m1) float32
        Traversability cost in [0, 1], NaN where unknown (:mod:`terrainmap.cost`).
    occupied : list of Obstacle
        What else occupies the cost map (:attr:`~terrainmap.types.FrameResult.occupied`).
    """
    check_section(config.cost, CostConfig)  # (its occupied_misses is used before the cost is computed)
    elevation = layers["elevation"]
    steep = layers["slope"] >= np.radians(config.cost.max_slope_deg) if config.obstacles.drop_on_steep_ground else None
    detections = extract_obstacles(
        points_vehicle, point_labels, grid.config, None, config.obstacles, elevation=elevation,
        cell_counts=grid.count, steep=steep, index=index,
    )
    obstacles = tracker.update(detections, stamp_ns, vehicle_pose, camera)
    relief_cells = grid.observed & (layers["label"] != Label.OBSTACLE)
    step = step_height(grid.z, elevation, relief_cells)
    # Cells are occupied by the confirmed tracks, by the clusters taken for parts of them and by
    # those missed in the last cost.occupied_misses frames
    missed = min(config.cost.occupied_misses, config.tracking.reconfirm_misses)  # (CostConfig.occupied_misses)
    occupied = [*tracker.parts, *tracker.coasting(missed)]
    cost = traversability_cost(elevation, layers["slope"], grid.valid, grid.config, [*obstacles, *occupied],
                               config.cost, step=step)
    return obstacles, cost, occupied
