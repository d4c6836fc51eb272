"""One typed configuration for the whole pipeline.

Every field is documented where it is declared; the defaults are the paper's values where the
paper gives one (degree 3, 25×25 control points, 0.5 m cells, 34 m × 22 m area ahead of the
vehicle). A :class:`Config` is loaded from TOML (one table per section) and overridden with
``section.field=value`` strings, as the CLI's ``--set`` does::

    cfg = load_config("my.toml", overrides=["terrain.control_points_x=15"])

Units: metres, radians, seconds; ``*_deg`` fields are degrees (human-facing limits only).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, brief


def _check(ok: bool, name: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"{name}: {message}")


MAX_CELLS_PER_AXIS = 2000
"""Upper bound on m0 and m1 (a 1 km square at 0.5 m): beyond it a grid is a typo, not a map."""
MAX_OFFSET_M = 10_000.0
"""Upper bound on the area's offsets and height limits from the vehicle, metres: likewise."""
MAX_NUMBER = 1e6
"""Upper bound on the magnitude of a float field (its unit m, px, s, degrees or none): beyond it a
value is a typo, and squares or products of it overflow mid-run."""
INT_RANGE = (-(2**31), 2**31 - 1)
"""The range of an integer field: a C int, as OpenCV's matcher takes them."""


@dataclass(slots=True)
class GridConfig:
    """The 2.5D grid over the area of interest (paper Sec. IV), vehicle frame.

    The area is ``x ∈ [x_min_m, x_min_m + length_m]`` (forward) by
    ``y ∈ [y_center_m − width_m/2, y_center_m + width_m/2]`` (left).
    """

    x_min_m: float = 2.0
    """Near edge of the area, metres ahead of the vehicle origin."""
    length_m: float = 34.0
    """Extent along x (forward), metres. Paper: 34 m."""
    width_m: float = 22.0
    """Extent along y (left), metres. Paper: 22 m."""
    y_center_m: float = 0.0
    """Lateral centre of the area, metres (positive = left)."""
    cell_size_m: float = 0.5
    """Cell edge, metres. Paper: 0.5 m ("sampling ratio 50 cm")."""
    z_min_m: float = -10.0
    """Points below this height (vehicle frame) are ignored as gross stereo errors."""
    z_max_m: float = 10.0
    """Points above this height are ignored (sky, overhanging structures)."""
    sigma_factor: float = 1.0
    """k in eq. 1, ``Z = max(min z, mean z − k·σ)``; the paper uses 1. It keeps cars and walls
    sharing cells with the road out of the surface (KITTI 000005: with 0 the lane's slope rises
    from 3.8° to 5.3°, and the parked cars' points labelled obstacle fall from 68 % to 44 %); the
    low bias it gives where stereo noise makes σ large is what ``stereo_noise_px`` takes out
    (docs/accuracy.md)."""
    stereo_noise_px: float = 0.5
    """Disparity noise of the stereo matcher (1σ, pixels). Where the pipeline knows the stereo
    rig, eq. 1's σ of a cell is reduced in quadrature by the height spread this noise alone gives
    there (``noise · Z·|z − c_z|/(f·B)``: 6 cm at 10 m, 12 cm at 20 m for the simulated rig), so
    that stereo noise does not pull the sample below the terrain while obstacles sharing a cell
    still do. 0 gives the paper's eq. 1 exactly. 0.5 is about SGBM's error on the simulated drives
    (std of errors under 3 px: 0.39–0.53; KITTI 000005: 0.85)."""
    fill_empty: bool = True
    """Empty cells take the mean height of their observed 8-neighbours (paper Sec. IV)."""

    def validate(self) -> None:
        for name in ("x_min_m", "y_center_m", "z_min_m", "z_max_m"):
            value = getattr(self, name)
            _check(abs(value) <= MAX_OFFSET_M, f"grid.{name}", f"must be within ±{MAX_OFFSET_M:g} m, got {value}")
        for name in ("length_m", "width_m", "cell_size_m"):
            value = getattr(self, name)
            _check(value > 0, f"grid.{name}", f"must be > 0, got {value}")
        for name in ("length_m", "width_m"):
            cells = getattr(self, name) / self.cell_size_m
            _check(
                cells <= MAX_CELLS_PER_AXIS,
                f"grid.{name}",
                f"gives {cells:.3g} cells of {self.cell_size_m} m; at most {MAX_CELLS_PER_AXIS} per axis",
            )
            _check(round(cells) >= 1, f"grid.{name}",  # first: an area under one cell is said to be so
                   f"must hold at least one cell of {self.cell_size_m} m, got {getattr(self, name)}")
            _check(
                abs(cells - round(cells)) < 1e-6,
                f"grid.{name}",
                f"must be a whole number of cells of {self.cell_size_m} m (grid.cell_size_m), got {getattr(self, name)}",
            )
        _check(self.z_min_m < self.z_max_m, "grid.z_min_m", "must be below grid.z_max_m")
        _check(self.stereo_noise_px >= 0, "grid.stereo_noise_px", f"must be >= 0, got {self.stereo_noise_px}")
        _check(0 <= self.sigma_factor <= 5, "grid.sigma_factor", f"must be in [0, 5], got {self.sigma_factor}")

    @property
    def shape(self) -> tuple[int, int]:
        """(m0, m1): number of cells along x and along y."""
        return (round(self.length_m / self.cell_size_m), round(self.width_m / self.cell_size_m))

    @property
    def y_min_m(self) -> float:
        return self.y_center_m - self.width_m / 2


MAX_CONTROL_POINTS = 4096
"""The most control points a terrain net may have in all (``control_points_x × control_points_y``)."""


@dataclass(slots=True)
class TerrainConfig:
    """Rational B-spline terrain estimation (paper Sec. V, Algorithm V-B.1)."""

    degree: int = 3
    """Spline degree d0 = d1 (paper: "order 3", i.e. cubic)."""
    control_points_x: int = 25
    """Final number of control points along x, n_max,0 + 1. Paper: 25. The net holds at most
    :data:`MAX_CONTROL_POINTS` (4096) in all."""
    control_points_y: int = 25
    """Final number of control points along y, n_max,1 + 1. Paper: 25."""
    start_control_points: int = 4
    """Control points per axis of the first, non-rational fit ("very few"); raised to degree + 1
    where lower and capped at the final net (so another degree or a small net needs no change here)."""
    control_point_growth: float = 1.5
    """Net growth per iteration: n ← max(n + 1, round(n · growth)) per axis, capped at the final
    net. 1.0 is the paper's pseudo-code (one control point more per iteration: 22 fits from 4 to
    25); the default 1.5 reaches 25 in 6 (4, 6, 9, 14, 21, 25) with the same accuracy (see the
    tests)."""
    weight_max: float = 100.0
    """Upper bound of the sample weight W of eq. 3 (W is infinite at Δz = 0 otherwise)."""
    threshold_factor: float = 2.0
    """th(ē) = threshold_factor · ē, ē the mean absolute fit error of valid samples (eq. 3)."""
    threshold_min_m: float = 0.02
    """Lower bound of th, so a near-perfect fit does not make every sample an outlier."""
    alpha_per_iteration: float = 0.5
    """Weighting speed: α = max(1, alpha_per_iteration · iteration), iteration counted from 1."""
    control_weight_min: float = 0.2
    """Lower bound of the control-point weights R (normalised to max 1) remapped from W."""
    equalize_tolerance_m: float = 0.05
    """Valid samples less than this above the surface are not equalized (stereo noise band);
    keeps the one-sided equalization from dragging the surface below the terrain."""
    equalize_tolerance_per_m: float = 0.002
    """Growth of that tolerance with range from the vehicle origin, metres per metre."""
    trust_below: bool = True
    """Samples more than the equalization band below the surface keep the maximum weight: every
    visible point lies on or above the terrain (see decision 5 in :mod:`terrainmap.terrain`)."""
    trust_below_px: float = 3.0
    """Where the stereo rig is known, such a sample must also lie deeper below the surface than a
    disparity error of this many pixels moves it (0: the band alone)."""
    slope_noise_iterations: int = 3
    """Where the stereo rig is known, the surfaces of the first this many iterations recompute
    eq. 1's samples with the stereo noise on the terrain's slope instead of level ground
    (decision 7 in :mod:`terrainmap.terrain`; 0: level ground throughout)."""
    epsilon_m: float = 0.005
    """Stop early when no valid sample moved more than this in the last equalization (0: never
    early, every net up to the final one is fitted)."""
    smoothness: float = 1e-3
    """Weight of the second-difference penalty on control points, relative to the mean data
    weight per control point; keeps fits well-posed where knot spans hold no sample."""
    filled_weight: float = 0.5
    """Relative weight of cells filled from neighbours (no points of their own)."""
    min_valid_cells: int = 16
    """Fewer observed cells (holding points) than this (and than (degree+1)²) → the frame fails with
    no terrain."""

    def validate(self, grid: GridConfig | None = None) -> None:
        _check(1 <= self.degree <= 5, "terrain.degree", f"must be 1..5, got {self.degree}")
        _check(self.start_control_points >= 1, "terrain.start_control_points", "must be >= 1")
        for name in ("control_points_x", "control_points_y"):
            value = getattr(self, name)
            _check(
                value >= self.degree + 1,
                f"terrain.{name}",
                f"must be at least degree + 1 = {self.degree + 1}, got {value}",
            )
        # The fit's normal equations and penalty grow with the square of the net's size: 64×64 takes
        # about 0.5 GB and 2 s a frame, the paper's 25×25 10 MB and 5 ms.
        _check(
            self.control_points_x * self.control_points_y <= MAX_CONTROL_POINTS,
            "terrain.control_points_x × control_points_y",
            f"must be at most {MAX_CONTROL_POINTS} (64×64), got {self.control_points_x}×{self.control_points_y}",
        )
        _check(
            1.0 <= self.control_point_growth <= 10,
            "terrain.control_point_growth",
            f"must be in [1, 10], got {self.control_point_growth}",
        )
        _check(1 < self.weight_max <= 1e6, "terrain.weight_max", f"must be in (1, 1e6], got {self.weight_max}")
        _check(self.threshold_factor > 0, "terrain.threshold_factor", "must be > 0")
        _check(self.threshold_min_m > 0, "terrain.threshold_min_m", "must be > 0")
        _check(self.alpha_per_iteration > 0, "terrain.alpha_per_iteration", "must be > 0")
        _check(1e-6 <= self.control_weight_min <= 1, "terrain.control_weight_min", "must be in [1e-6, 1]")
        _check(self.equalize_tolerance_m >= 0, "terrain.equalize_tolerance_m", "must be >= 0")
        _check(self.equalize_tolerance_per_m >= 0, "terrain.equalize_tolerance_per_m", "must be >= 0")
        _check(self.trust_below_px >= 0, "terrain.trust_below_px", "must be >= 0")
        _check(0 <= self.slope_noise_iterations <= 100, "terrain.slope_noise_iterations", "must be in 0..100")
        _check(self.epsilon_m >= 0, "terrain.epsilon_m", f"must be >= 0 (0: never stop early), got {self.epsilon_m}")
        _check(0 < self.smoothness <= 1e3, "terrain.smoothness", f"must be in (0, 1000], got {self.smoothness}")
        _check(0 <= self.filled_weight <= 1, "terrain.filled_weight", "must be in [0, 1]")
        _check(self.min_valid_cells >= 0, "terrain.min_valid_cells", "must be >= 0")
        if grid is not None:
            m0, m1 = grid.shape
            _check(self.min_valid_cells <= m0 * m1, "terrain.min_valid_cells",
                   f"({self.min_valid_cells}) exceeds the grid's {m0}×{m1} = {m0 * m1} cells")
            for name, n, m, axis in (
                ("control_points_x", self.control_points_x, m0, "x"),
                ("control_points_y", self.control_points_y, m1, "y"),
            ):
                _check(
                    n <= m,
                    f"terrain.{name}",
                    f"n_max = {n} exceeds the {m} grid cells along {axis} (grid.cell_size_m; paper: n_max <= min(m0, m1))",
                )


@dataclass(slots=True)
class SegmentationConfig:
    """Inlier/outlier labelling of points and cells against the terrain surface."""

    obstacle_height_m: float = 0.25
    """A point higher than this above the surface is an obstacle (outlier above)."""
    below_depth_m: float = 0.25
    """A point deeper than this below the surface is labelled below (hole, ditch, noise)."""
    threshold_per_m: float = 0.01
    """Both thresholds grow by this many metres per metre of range, as stereo height noise does
    (0.45 m at 20 m). Larger values trade recall of low obstacles near walls (KITTI's parked cars)
    for fewer false obstacles far away (simulated drives)."""
    disparity_tolerance_px: float = 1.0
    """Where the stereo camera is known, the obstacle threshold is at least the height above the
    surface that a disparity error of this many pixels produces at that cell (it grows with range
    on level ground and is largest on slopes that face the camera); 0 leaves it growing with range
    only. The below threshold has its own floor, ``below_tolerance_px``.
    See :mod:`terrainmap.segmentation`. On the simulated drives 1 (against 0, with
    ``below_tolerance_px`` 0 too) raises terrain F1 at 10–20 m (the canyon's from 0.825 to 0.991,
    `--seed 1`) and takes the false obstacles from 7.00 and 13.70 to 0.15 and 0.05 per frame summed
    (most of them on the canyon's walls and the climb's slope), with mean recall 0.862 against
    0.872 and 0.903 against 0.838; KITTI is labelled as before. The price is a higher bar for low
    obstacles on slopes facing the camera (docs/accuracy.md, settings table)."""
    below_tolerance_px: float = 2.0
    """The same floor under the below threshold, in pixels of disparity error: wider than
    ``disparity_tolerance_px`` because OpenCV's single-pass SGBM reads the disparity of ground
    about 0.2 px low (docs/accuracy.md), which drops stereo noise below the surface more than above
    it. 2 (against 1) removes most false negative obstacles on the simulated drives (slopes facing
    the camera, the ditch) and changes no obstacle recall; 0 leaves the below threshold growing
    with range only."""

    upright_ratio: float = 0.4
    """Where the stereo camera and disparities are known, points on upright surfaces (a disparity
    gradient down the image below this fraction of the terrain's; :mod:`terrainmap.upright`) are
    obstacles from ``upright_above_m`` above the surface, below the height threshold too. 0 turns
    the cue off. On the twelve simulated drives 0.4 (against 0) confirms two 0.5 m rocks within
    3 frames that are confirmed 10 frames late or never without it, the `--seed 1` ditch's one
    frame sooner (4 against 5), the `--seed 2` ditch's pedestrian two frames later (3 against 1),
    and raises obstacle recall from 0.838 and 0.875 to 0.862 and 0.903, for 0.00 and 0.05 more
    false obstacles per frame summed (docs/accuracy.md, settings table)."""
    upright_rows: int = 2
    """Half-window of the disparity gradient down the image, rows."""
    upright_min_height_m: float = 0.3
    """An upright point must belong to a vertical run of upright points at least this tall."""
    upright_min_ground_gradient: float = 0.1
    """The cue is used only where the terrain's disparity gradient down the image is at least this
    (px per row): on ground that slopes towards the camera, ground and upright faces look alike."""
    upright_above_m: float = 0.15
    """An upright point is an obstacle when it stands at least this high above the surface."""
    upright_min_range_m: float = 8.0
    """The cue is used for points at least this far (camera depth, metres): nearer, a pixel of
    disparity error moves a point little in height (0.1 m at 8 m for f·B = 150 px·m, 1.8 m up),
    and the height thresholds separate obstacles alone. 0: everywhere."""
    edge_margin_m: float = 0.1
    """Added to both thresholds of the cells at the edge of the observed area (an observed cell
    with an unobserved or outside neighbour, of its 8). The surface there is held by data on one
    side only, and at the sides of the field of view those data come from the image's sides, where
    SGBM errs most: on four smooth simulated drives the surface's RMSE is 8.3 cm in such cells
    against 5.9 cm three or more cells in, and low false obstacles gathered there. 0.1 took the
    false obstacles on the twelve simulated drives from 2.65 to 1.75 per frame summed when it came,
    with 68.4 % of KITTI 000005's parked cars' points labelled obstacle instead of 69.6 %; now,
    with the tolerances that grow towards the image's sides and the depth edges trimmed, it takes
    them from 0.30 to 0.20 for 0.005 less recall on `--seed 1` (docs/design.md)."""
    side_band: float = 0.2
    """Where the image is known, ``disparity_tolerance_px`` and ``below_tolerance_px`` grow towards
    the image's left and right sides over this fraction of its width on each side, reaching
    ``1 + side_gain`` times their value at the side. SGBM errs more there (fewer of its cost paths
    have run far, and its windows reach past the border): on three simulated drives 2 % of the
    ground's disparities in the middle fifth of the image are off by more than a pixel, 5 % at
    a fifth of the width from either side, 6–12 % over the next 80 px and 19–22 % in the outermost
    16 matched columns, and streaks of such errors stood up as low false obstacles there. 3 (against
    0) takes the false obstacles on the twelve simulated drives from 1.85 to 0.20 per frame summed,
    with recall unchanged and terrain F1 higher; KITTI 000005 is labelled as before (docs/design.md,
    docs/accuracy.md settings table)."""
    side_gain: float = 3.0
    """See ``side_band``; 0 keeps the tolerances the same across the image."""

    def validate(self) -> None:
        _check(self.obstacle_height_m > 0, "segmentation.obstacle_height_m", "must be > 0")
        _check(self.below_depth_m > 0, "segmentation.below_depth_m", "must be > 0")
        _check(self.threshold_per_m >= 0, "segmentation.threshold_per_m", "must be >= 0")
        _check(self.disparity_tolerance_px >= 0, "segmentation.disparity_tolerance_px", "must be >= 0")
        _check(self.below_tolerance_px >= 0, "segmentation.below_tolerance_px", "must be >= 0")
        _check(0 <= self.upright_ratio < 1, "segmentation.upright_ratio", "must be in [0, 1)")
        _check(1 <= self.upright_rows <= 20, "segmentation.upright_rows", "must be in 1..20")
        _check(self.upright_min_height_m > 0, "segmentation.upright_min_height_m", "must be > 0")
        _check(self.upright_min_ground_gradient > 0, "segmentation.upright_min_ground_gradient", "must be > 0")
        _check(self.upright_above_m >= 0, "segmentation.upright_above_m", "must be >= 0")
        value = self.upright_min_range_m
        _check(value == 0 or value >= 0.01, "segmentation.upright_min_range_m", f"must be 0 or >= 0.01 m, got {value}")
        _check(0 <= self.edge_margin_m <= 10, "segmentation.edge_margin_m", "must be in [0, 10]")
        _check(0 < self.side_band <= 0.5, "segmentation.side_band", "must be in (0, 0.5]")
        _check(0 <= self.side_gain <= 100, "segmentation.side_gain", "must be in [0, 100]")


@dataclass(slots=True)
class StereoConfig:
    """OpenCV StereoSGBM front end and reprojection (paper Sec. III, SGM after Hirschmüller).

    Defaults were chosen on KITTI 2015 pair 000005 (1242×375) and a 640×480 crop of it, on a
    2-core machine with OpenCV's default 2 threads (medians of 10 calls, machine shared, so ±20 %):

    ========== ===== ============== ============ =========== ===========
    mode       disp  ms 1242×375     ms 640×480   median |Δd| > 3 px
    ========== ===== ============== ============ =========== ===========
    sgbm       128   172            101          0.59 px     8.8 %
    hh         128   392            220          0.58 px     7.5 %
    hh4        128   198            115          0.58 px     6.8 %
    sgbm_3way  128   62             33           0.57 px     7.4 %
    sgbm_3way  96    52             30           0.58 px     8.0 %
    sgbm_3way  64    40             28           0.59 px     9.0 %
    ========== ===== ============== ============ =========== ===========

    ``sgbm_3way`` is the only mode OpenCV parallelises well (2 threads halve its time; the others
    barely gain) and it is as accurate as full 8-path ``hh`` here, hence the default. On one
    thread, as each of ``process``'s two matching workers runs on two cores, it is still the
    fastest: 86 ms against 110 for ``sgbm`` and 186 for ``hh4`` (48, 112 and 123 ms on two
    threads; a simulated 640×480 pair, medians of 5, 2026-11-27, a slow spell). D
    disparities reach down to a depth of f·B/D: 2.0 m on KITTI at the automatic D = 192 (its road
    is first visible at 5.8 m), 1.6 m on a 640×480 rig with f = 500 px and B = 0.3 m (D = 96).
    ``preFilterCap`` 63 and block 5 gave the fewest gross errors at equal coverage.
    """

    num_disparities: int = 0
    """Disparity search range in pixels (multiple of 16), from ``min_disparity``; 0 = 15 % of the
    image width, rounded up to 16 (96 at 640 px), which keeps the nearest usable depth the same
    for any resolution of the same lens (1.6 m at f = 500 px, B = 0.3 m)."""
    min_disparity: int = 0
    """Smallest disparity searched, pixels (before the principal-point / ``doffs`` offset)."""
    block_size: int = 5
    """SGBM matched block size (odd, 1..11)."""
    p1_per_pixel: int = 8
    """SGM smoothness penalty for ±1 px disparity changes: P1 = p1_per_pixel · block_size²."""
    p2_per_pixel: int = 32
    """SGM penalty for larger disparity changes: P2 = p2_per_pixel · block_size² (> P1)."""
    pre_filter_cap: int = 63
    """Truncation of the x-derivative prefilter (1..63)."""
    uniqueness_ratio: int = 10
    """Margin in percent by which the best cost must beat the second best (0 disables)."""
    speckle_window_size: int = 100
    """Largest connected blob of similar disparities treated as speckle noise (0 disables)."""
    speckle_range: int = 2
    """Disparity variation within a connected component, pixels (× 16 internally)."""
    disp12_max_diff: int = 1
    """Left-right consistency tolerance, pixels (negative disables the check)."""
    mode: str = "sgbm_3way"
    """One of ``sgbm``, ``hh``, ``sgbm_3way``, ``hh4`` (cv2.STEREO_SGBM_MODE_*); see the table."""
    min_range_m: float = 1.0
    """Points nearer than this (depth along the rectified left camera's axis: the camera's own
    for a rectified pair) are dropped."""
    max_range_m: float = 40.0
    """Points farther than this (depth along the rectified left camera's axis) are dropped."""
    min_texture: float = 2.75
    """Disparities are dropped where the left image's local texture (``texture_measure``, by
    default the standard deviation of the grey levels over ``texture_window`` pixels) is below
    this: untextured sky and glare match at random, and the band of sky that SGBM's smoothness
    drags above a horizon merges distant obstacles into one. 0 keeps everything. For the default
    measure: sensor noise of σ = 2 grey levels gives local deviations up to ~2.6; KITTI's asphalt
    2.5–5 (2.75 kept 71 % of KITTI 2015 pair 000005's ground-truth pixels, 2.5 kept 73 %, before
    ``full_width`` and the depth-edge trim; 75 % now, `terrainmap eval stereo`; on the
    simulated scenes it lifted obstacle recall within 20 m from 0.31–0.92 to 0.50–0.95 together
    with ``obstacles.min_cell_points`` 3)."""
    texture_window: int = 11
    """Side of the square window of ``min_texture``, pixels (odd)."""
    texture_measure: str = "variance"
    """What ``min_texture`` is compared with, in grey levels: ``variance`` — the standard deviation
    of the window; ``x_gradient`` — the rms over the window of the horizontal derivative
    ``(I(u+1) − I(u−1)) / 2``, which ignores horizontal edges (a horizon, a roof line) that
    matching along image rows cannot lock on to (sensor noise of σ alone gives σ/√2)."""
    texture_margin_px: int = 0
    """Also drop a pixel when the window centred up to this many pixels left, right, above or
    below it fails ``min_texture``: a stricter test near flat regions. 0 tests the pixel's own
    window only. The band of sky that SGBM smears beside silhouettes and above the horizon is
    ``drop_sky``'s; ``x_gradient`` with ``min_texture`` 2 and a margin of 5 (the former
    open-terrain preset) has less recall, less KITTI coverage and more false obstacles on the
    simulated drives (docs/accuracy.md, settings table)."""
    drop_sky: bool = True
    """Drop the disparities of pixels that see sky (:func:`terrainmap.stereo.sky_mask`): the flat
    region above the horizon that reaches the top of the image. SGBM carries a near object's
    disparity along the rows of flat sky beside its silhouette and above the horizon, where the
    ``texture_window`` reaches across the skyline and passes the texture test; those points float
    1–4 m above the ground at the object's range. On the simulated drives, before
    ``obstacles.tall_min_share``, it took the false obstacles within 20 m from 6.75 to 4.65 per
    frame summed over six scenes (docs/accuracy.md); on KITTI 2015 pair 000005 it
    changes nothing. Needs ``min_texture`` > 0."""
    sky_beyond_m: float = 20.0
    """``drop_sky`` looks for sky only where a ray would meet level ground under the camera no
    nearer than this, horizontal distance, metres (or never): it keeps flat ground and dark or
    saturated objects out of the sky. The sky just above a crest the vehicle climbs towards is
    seen along rays that meet level ground at crest distance × camera height / (camera height −
    crest height): 34 m for a crest 1 m up at 15 m. With 40 m (``max_range_m``, until
    2026-11-28) that sky kept the crest's disparity, and on the simulated hills ``--seed 5`` its
    points became 0.45 false obstacles per frame within 20 m (none at 20 or 25 m; on the other
    twenty-nine drives a few sky pixels of one: docs/accuracy.md)."""
    full_width: bool = True
    """Match the left image's left border too. OpenCV's SGBM gives no disparity in the leftmost
    ``min_disparity + num_disparities`` columns (15 % of the image by default), where a pixel's
    search range would reach past the right image's left edge, although distant ground and
    obstacles there are seen by both cameras. With this on, both images are padded on the left
    (edge pixels repeated) so that SGBM searches those columns, and a disparity is kept only where
    its match lies at least ``left_margin_px`` inside the right image. Costs 10–20 % more SGBM
    time at 640×480; on the simulated drives it gives an elevation to 6 % more of the observed cells
    within 20 m (0.986 against 0.927) at about the same RMSE (13.6 and 12.8 against 13.1 and 12.7
    cm) and raises obstacle recall (docs/accuracy.md, settings table)."""
    left_margin_px: int = 32
    """With ``full_width``: the nearest to the right image's left edge, pixels, that a match may
    lie. Nearer, SGBM's matches go wrong more often (on the simulated drives: 21 % gross errors
    within 8 px of the edge, 4 % at 24–32 px, 2 % beyond 96 px), most of them too small a
    disparity, which puts ground points below the ground."""
    right_margin_px: int = 4
    """Disparities of the image's rightmost this many columns are dropped. SGBM's matching
    windows run past the border there and its right-to-left cost path starts there: on the
    simulated drives 27–45 % of the ground's disparities in the last 4 columns are off by more
    than a pixel (6 % in the middle of the image); dropping them took the false obstacles from 3.40
    to 2.65 per frame summed over the twelve drives when it came; with the tolerances that now grow
    towards the image's sides it matters less (0.20 with it, 0.30 without: one fewer on each set
    of six; docs/design.md)."""
    fattening_trim_px: int = 2
    """Where two horizontally neighbouring disparities differ by more than ``fattening_jump_px``
    (a depth edge), the disparities of this many columns on the near side are dropped. SGBM's
    matching window and its smoothness carry a near surface's disparity a few pixels onto the
    background beside it (foreground fattening): on the simulated ditch, a car's side whose true
    edge lies at column 242 keeps its disparity (8 px, the background's 4) up to column 244–245,
    and those points float in the gap up to 1 m behind the car, where they became a false obstacle
    of their own in four frames. 2 (half SGBM's 5-pixel block) takes the false obstacles on the
    twelve simulated drives from 0.35 and 0.35 to 0.15 and 0.05 per frame summed, every drive at
    most 0.1 (docs/accuracy.md, settings table); on KITTI 000005 it changes the cars' and lane's
    labels by less than 0.1 %. 0 keeps every disparity."""
    fattening_jump_px: float = 1.0
    """The disparity difference between neighbouring columns, pixels, that ``fattening_trim_px``
    treats as a depth edge: more than a surface's disparity steps between neighbouring columns
    (up to 0.7 px along the simulated car's side, seen at a grazing 10°) and less than a car or a
    pole stands out from the ground behind it (4 px for a car at 18 m with ground 34 m away)."""
    vertical_passes: int = 1
    """1: SGBM as OpenCV runs it. 2: also match the pair upside down and average the two
    disparities. OpenCV's single-pass modes (``sgbm``, ``sgbm_3way``) aggregate costs only along
    paths that come from above, so on ground, whose disparity grows down the image, they read the
    disparity low (−0.23 px with the defaults on the simulated drives: ground points land below
    the ground, 6 cm at 10–20 m); the upside-down pass reads it high by as much, and the mean is
    unbiased. Doubles the SGBM time (``process`` at 19 instead of 28 frames/s here) for a 10–20 m
    elevation RMSE lower by 8–52 % on the simulated drives; on KITTI 000005 it keeps 70 % of the
    ground-truth pixels instead of 75 % and reads the lane 0.2 px higher than the single pass,
    further from the ground truth within 10 m (docs/accuracy.md)."""
    vertical_passes_min_range_m: float = 0.0
    """With ``vertical_passes`` = 2 and the camera pose known, a value above 0 has the upside-down pass
    match only the rows that see level ground at least this far (horizontally), down to 32 rows
    below them; nearer, the bias is small in metres (at 8 m, 0.25 px is 2.4 cm of height on level
    ground). 0: every row.
    On the simulated drives 8 kept the RMSE within 20 m at 11.1 and 10.3 cm (every row: 11.0 and
    10.2), the false obstacles at 0.20 and 0.15 per frame summed (0.25 and 0.10) and the recall at
    0.844 and 0.891 (0.847 and 0.891), for 1.8 instead of 2.1 × SGBM's time (docs/accuracy.md)."""
    vertical_passes_max_range_m: float = 0.0
    """With ``vertical_passes`` = 2, a value above 0 has the upside-down pass skip the rows above
    the first in which at least half the pixels lie nearer than this by their single-pass
    disparity (rows of sky and distant ground, which keep the single pass's values). That pass's
    paths run up the image, so the rows it skips do not feed those it matches. 0: every row.
    On the simulated drives 30, with ``vertical_passes_min_range_m`` 8, kept the RMSE within 20 m
    at 11.1 and 10.3 cm and the recall at 0.845 and 0.891, with 0.10 and 0.10 false obstacles per
    frame summed (without it 0.20 and 0.15), for 1.56–1.75 instead of 1.86–1.96 × SGBM's time on
    the simulated mounds frame (docs/accuracy.md, settings table)."""
    pass_tolerance_px: float = 2.0
    """With ``vertical_passes`` = 2: a pixel whose two disparities differ by more than this is
    dropped (one of them is a mismatch), as is a pixel only one pass matched."""

    def validate(self) -> None:
        _check(
            self.num_disparities >= 0 and self.num_disparities % 16 == 0,
            "stereo.num_disparities",
            f"must be 0 (auto) or a positive multiple of 16, got {self.num_disparities}",
        )
        _check(
            self.block_size % 2 == 1 and 1 <= self.block_size <= 11,
            "stereo.block_size",
            f"must be odd and in 1..11, got {self.block_size}",
        )
        _check(
            0 <= self.p1_per_pixel < self.p2_per_pixel,
            "stereo.p2_per_pixel",
            f"must exceed stereo.p1_per_pixel >= 0, got P1 {self.p1_per_pixel}, P2 {self.p2_per_pixel}",
        )
        _check(self.num_disparities <= 1024, "stereo.num_disparities", "must be at most 1024")
        _check(abs(self.min_disparity) <= 1024, "stereo.min_disparity", "must be in -1024..1024")
        _check(self.p2_per_pixel <= 10_000, "stereo.p2_per_pixel", "must be at most 10000")
        _check(self.disp12_max_diff <= 1024, "stereo.disp12_max_diff", "must be at most 1024 (< 0 disables)")
        _check(1 <= self.pre_filter_cap <= 63, "stereo.pre_filter_cap", "must be in 1..63")
        for name in ("uniqueness_ratio", "speckle_window_size", "speckle_range"):
            _check(0 <= getattr(self, name) <= 10_000, f"stereo.{name}", "must be in 0..10000")
        _check(
            self.mode in ("sgbm", "hh", "sgbm_3way", "hh4"),
            "stereo.mode",
            f"must be one of sgbm, hh, sgbm_3way, hh4, got {brief(self.mode)}",
        )
        _check(0.01 <= self.min_range_m < self.max_range_m, "stereo.min_range_m", "must be in [0.01 m, max_range_m)")
        _check(self.max_range_m <= MAX_OFFSET_M, "stereo.max_range_m", f"must be at most {MAX_OFFSET_M:g} m")
        _check(self.min_texture >= 0, "stereo.min_texture", "must be >= 0")
        _check(
            self.texture_window % 2 == 1 and 3 <= self.texture_window <= 101,
            "stereo.texture_window",
            "must be odd and in 3..101",
        )
        _check(
            self.texture_measure in ("variance", "x_gradient"),
            "stereo.texture_measure",
            f"must be variance or x_gradient, got {brief(self.texture_measure)}",
        )
        _check(0 <= self.texture_margin_px <= 100, "stereo.texture_margin_px", "must be in 0..100")
        _check(0 <= self.left_margin_px <= 1024, "stereo.left_margin_px", "must be in 0..1024")
        _check(0 <= self.right_margin_px <= 1024, "stereo.right_margin_px", "must be in 0..1024")
        _check(0 <= self.fattening_trim_px <= 100, "stereo.fattening_trim_px", "must be in 0..100")
        _check(self.fattening_jump_px > 0, "stereo.fattening_jump_px", "must be > 0")
        _check(self.vertical_passes in (1, 2), "stereo.vertical_passes", f"must be 1 or 2, got {self.vertical_passes}")
        _check(self.pass_tolerance_px > 0, "stereo.pass_tolerance_px", "must be > 0")
        _check(self.vertical_passes_min_range_m >= 0, "stereo.vertical_passes_min_range_m", "must be >= 0")
        _check(self.vertical_passes_max_range_m >= 0, "stereo.vertical_passes_max_range_m", "must be >= 0")
        _check(0 < self.sky_beyond_m <= MAX_OFFSET_M, "stereo.sky_beyond_m", f"must be in (0, {MAX_OFFSET_M:g}] m")
        low, high = self.vertical_passes_min_range_m, self.vertical_passes_max_range_m
        _check(not (low > 0 and high > 0 and low >= high), "stereo.vertical_passes_min_range_m",
               f"({low:g} m) must be below stereo.vertical_passes_max_range_m ({high:g} m) where both are set: "
               "no row would be matched twice")


@dataclass(slots=True)
class ExtrinsicsConfig:
    """Camera pose in the vehicle frame when the log and calibration give none: a robust
    ground-plane fit on near points (see :mod:`terrainmap.extrinsics`)."""

    near_range_m: float = 15.0
    """Only points nearer than this (camera depth) are used for the ground fit."""
    inlier_threshold_m: float = 0.05
    """RANSAC distance threshold to the plane, metres."""
    iterations: int = 200
    """RANSAC hypotheses."""
    min_inlier_fraction: float = 0.2
    """Fewer ground inliers than this fraction of the near points → the fit fails."""
    min_points: int = 200
    """Fewer near points below the camera than this → the fit fails."""
    max_tilt_deg: float = 45.0
    """A ground normal more than this from the camera's up axis (−y optical) is implausible."""
    sample_size: int = 2000
    """Near points (random subset) that score the RANSAC hypotheses (the refinement uses up to 10k)."""

    def validate(self) -> None:
        _check(self.near_range_m > 0, "extrinsics.near_range_m", "must be > 0")
        _check(self.inlier_threshold_m > 0, "extrinsics.inlier_threshold_m", "must be > 0")
        _check(1 <= self.iterations <= 100_000, "extrinsics.iterations", "must be in 1..100000")
        _check(0 < self.min_inlier_fraction < 1, "extrinsics.min_inlier_fraction", "must be in (0, 1)")
        _check(self.min_points >= 3, "extrinsics.min_points", "must be >= 3")
        _check(0 < self.max_tilt_deg < 90, "extrinsics.max_tilt_deg", "must be in (0, 90)")
        _check(self.sample_size >= 3, "extrinsics.sample_size", "must be >= 3")


@dataclass(slots=True)
class ObstacleConfig:
    """Obstacle extraction from above/below-terrain points (paper step 5)."""

    min_height_m: float = 0.3
    """Positive obstacles whose highest point is lower than this above the terrain are dropped."""
    min_depth_m: float = 0.3
    """Negative obstacles (ditches, holes) shallower than this below the terrain are dropped."""
    min_points: int = 12
    """Clusters with fewer points are dropped. Clusters of 10–12 points 14–19 m away, mismatches
    that a second frame repeats, were the false obstacles of the simulated `--seed 2` climb (10 until
    2026-11-26); the true obstacles there give 12 points or more (a 0.5 m rock at 20 m gives ~100)."""
    min_cells: int = 1
    """Clusters covering fewer grid cells are dropped."""
    min_cell_points: int = 3
    """A cell joins a cluster only when it holds at least this many points of that kind, so that
    stray mismatched points do not bridge separate obstacles into one cluster (a 0.5 m tall rock
    at 20 m puts ~100 points in its cells at 640×480, f = 500 px)."""
    negative: bool = True
    """Also extract negative obstacles from points labelled below the terrain."""
    split_min_length_m: float = 3.0
    """Clusters at least this long (along their major axis) are split where their points thin
    out: stereo smear joins a near obstacle to one behind it."""
    split_gap_fraction: float = 0.2
    """Where a cluster is split: a cell-sized stretch along its major axis is a gap when it holds
    at most this fraction of the points of the fuller stretches on both sides of it (of the
    lower of the two peaks). 0 never splits."""
    split_min_part: float = 0.08
    """A part of a split cluster is kept only if it holds at least this fraction of the
    cluster's points (smaller parts are smear and are dropped). A 0.5 m rock at 15 m that SGBM's
    smear joins to a 3 m pole 3 m in front of it holds 9–11 % of their cluster: with 0.1 it was
    dropped in two frames and confirmed a frame late (simulated ``--seed 1`` ditch); 0.05 keeps
    smear clumps beside the ``--seed 2`` mounds' car that take its rock's place."""
    tall_height_m: float = 0.7
    """Positive clusters standing at least this high above the terrain must hold at least
    ``tall_min_share`` of all the points in their cells. A tall object hides the ground behind
    it, so most points in its cells are its own; stereo mismatches standing up from ground
    that faces the camera are a few high points among the ground's."""
    tall_min_share: float = 0.3
    """See ``tall_height_m``; 0 turns the test off."""
    drop_on_steep_ground: bool = True
    """Drop positive clusters lower than ``tall_height_m`` with most of their points in cells
    whose terrain slope reaches ``cost.max_slope_deg``. The slope already costs 1 on most of the
    cells such a cluster would occupy (the rest are its clearance and its flatter cells); what
    goes is the relief of berms and walls standing just above a surface that lags their crests
    (on the 12 simulated drives 0.05 of 0.25 false obstacles per frame summed, and no true
    obstacle; 1.10 of 4.45 when it came). Taller clusters always stay: where the surface climbs a
    car or a truck, its cells are steep too (KITTI 000005)."""
    max_points: int = 20000
    """Where the clusters of one kind (above, below the terrain) hold more points than this in a
    frame, the largest are thinned to one common size until they fit: their shapes, heights and
    counts come from about one in k of their points (each standing for k), while smaller clusters
    (poles, rocks) keep every point and the cells are joined from all. The clusters' measuring
    then costs no more however dense the scene (a few passes over all the points remain). The
    simulated drives put at most 15,150 points above the terrain in a frame, so nothing is thinned
    there; KITTI 000005 puts 139,000. 0: no limit."""

    def validate(self) -> None:
        _check(self.min_height_m > 0, "obstacles.min_height_m", "must be > 0")
        _check(self.min_depth_m > 0, "obstacles.min_depth_m", "must be > 0")
        _check(self.min_points >= 1, "obstacles.min_points", "must be >= 1")
        _check(self.min_cells >= 1, "obstacles.min_cells", "must be >= 1")
        _check(self.min_cell_points >= 1, "obstacles.min_cell_points", "must be >= 1")
        _check(self.split_min_length_m > 0, "obstacles.split_min_length_m", "must be > 0")
        _check(0 <= self.split_gap_fraction < 1, "obstacles.split_gap_fraction", "must be in [0, 1)")
        _check(0 <= self.split_min_part <= 1, "obstacles.split_min_part", "must be in [0, 1]")
        _check(self.tall_height_m > 0, "obstacles.tall_height_m", "must be > 0")
        _check(0 <= self.tall_min_share <= 1, "obstacles.tall_min_share", "must be in [0, 1]")
        _check(self.max_points >= 0, "obstacles.max_points", "must be >= 0")


@dataclass(slots=True)
class TrackingConfig:
    """Kalman tracking of obstacles (prunes single-frame false positives)."""

    confirm_hits: int = 2
    """A track is confirmed after this many frames with a matching detection (1 = no pruning)."""
    max_misses: int = 10
    """A confirmed track is dropped after more than this many consecutive frames without a
    match (a tentative track is dropped at its first miss); until then it keeps its id for when
    its obstacle is seen again (a low mound can go undetected for ten frames)."""
    reconfirm_misses: int = 3
    """A confirmed track matched again after more than this many consecutive misses keeps its id
    but is an obstacle again only once it has been matched in ``confirm_hits`` frames in a row,
    like a new track: a false detection that happens to fall near a track kept that long is not
    reported at once. With 10 and 3 (against 3 and no such rule) the ``--seed 2`` mound keeps its
    id through ten missed frames and the false obstacles on the simulated drives went from 0.80
    and 2.55 to 0.80 and 2.35 per frame summed; reporting such a track at once gave 0.95 and 2.60."""
    report_misses: int = 0
    """A confirmed track is reported (and occupies the cost map) while it has missed at most
    this many consecutive frames; beyond that, up to ``max_misses``, it keeps its id for
    re-association and occupies the cost map through ``cost.occupied_misses`` missed frames.
    0 reports only tracks matched in the current frame."""
    gate_m: float = 2.0
    """Association gate: maximum distance between predicted track and detection, metres."""
    measurement_std_m: float = 0.2
    """Standard deviation of a detected obstacle centre (x and y), metres."""
    disparity_std_px: float = 0.3
    """Where the stereo rig is known, a detected centre is also uncertain along the line of sight
    by this much disparity, pixels: ``disparity_std_px · Z²/(f·B)`` metres at range Z (0.65 m at
    18 m for f·B = 150 px·m), so that depth jitter of a far obstacle does not read as motion.
    0: ``measurement_std_m`` in every direction."""
    acceleration_std_mps2: float = 1.0
    """Process noise of the constant-velocity model: white acceleration, m/s². With tracks in the
    odometry frame, where most obstacles stand still, 1 (was 2) confirmed more true obstacles
    and fewer false ones on the simulated drives."""
    max_extrapolation_s: float = 1.0
    """A track's velocity moves its predicted centre over at most this many seconds, or the
    interval between the two frames before if that is longer (a log at 0.5 Hz, ``--every``), of
    a gap in the log (a recording paused, frames dropped). Over such a gap a constant velocity
    says nothing: a static obstacle's velocity of noise, 0.1 m/s, would carry it 6 m in 60 s, out
    of the gate, and it would come back under a new id. Its uncertainty still grows with the
    whole gap."""
    initial_velocity_std_mps: float = 2.0
    """Standard deviation of the (zero) velocity a new track starts with, m/s. Larger values let
    the second detection set the velocity: at 20 m a pedestrian smeared 2 m in depth gave a new
    track 14 m/s, whose prediction then took the pedestrian's detection from its own track. With
    ``disparity_std_px``, 2 (5 before 2026-11-24) gave 2 id switches over the twelve simulated
    drives against 3 when it came (none now, with the later rules), and an obstacle moving at
    1 m/s is still followed through misses."""
    fragment_radius_m: float = 1.5
    """An unmatched detection this close (centre to centre, metres) to a confirmed track matched
    in the same frame is a fragment of that obstacle and starts no track of its own; so is one
    no taller than that track's detection in its shadow (behind it as the camera sees it, up to
    this far beyond its footprint). 0 = off."""
    duplicate_depth_sigmas: float = 3.0
    """Two tracks of one kind, one of them confirmed, are one obstacle when their centres lie
    within ``fragment_radius_m`` of each other across the line of sight and within that radius
    plus this many ``disparity_std_px`` depth errors along it, but no farther than ``gate_m``
    (an ellipse; a person at 18 m jitters 0.65 m in depth per 0.3 px; tracks farther apart than
    the gate never compete for a detection): the track with fewer hits is merged into the other,
    which keeps its id. Two tracks on one obstacle take its detection in turn, and each change
    is an id switch. On the simulated drives, 3 took the id switches from 3 and 1 to 2 and 1
    (docs/design.md). 0: the radius in every direction; ``fragment_radius_m`` 0 turns
    merging off too."""

    def validate(self) -> None:
        _check(self.confirm_hits >= 1, "tracking.confirm_hits", "must be >= 1")
        _check(self.max_misses >= 0, "tracking.max_misses", "must be >= 0")
        _check(self.reconfirm_misses >= 0, "tracking.reconfirm_misses", "must be >= 0")
        _check(
            0 <= self.report_misses <= self.max_misses,
            "tracking.report_misses",
            f"must be in 0..tracking.max_misses ({self.max_misses}), got {self.report_misses}",
        )
        for name in ("gate_m", "measurement_std_m", "acceleration_std_mps2", "max_extrapolation_s",
                     "initial_velocity_std_mps"):
            value = getattr(self, name)
            _check(value > 0, f"tracking.{name}", f"must be > 0, got {value}")
        _check(self.disparity_std_px >= 0, "tracking.disparity_std_px", f"must be >= 0, got {self.disparity_std_px}")
        _check(self.fragment_radius_m >= 0, "tracking.fragment_radius_m", f"must be >= 0, got {self.fragment_radius_m}")
        _check(self.duplicate_depth_sigmas >= 0, "tracking.duplicate_depth_sigmas", f"must be >= 0, got {self.duplicate_depth_sigmas}")


@dataclass(slots=True)
class CostConfig:
    """Traversability cost in [0, 1] from slope, step height and occupancy (see terrainmap.cost)."""

    max_slope_deg: float = 25.0
    """Slopes at or above this are untraversable (cost 1)."""
    max_step_m: float = 0.3
    """Steps (height differences within a cell's neighbourhood) at or above this cost 1."""
    clearance_m: float = 0.5
    """Cells within this distance of a confirmed obstacle's footprint are occupied (cost 1)."""
    occupied_misses: int = 3
    """A confirmed track keeps occupying the cost map, at its predicted position and with its
    last detected footprint, while it has missed at most this many consecutive frames (it is
    reported as an obstacle through ``tracking.report_misses`` of them only): the detections of
    a real obstacle flicker. On the twelve simulated drives (``eval accuracy``'s
    ``blocked_by_cost``), per frame, the footprints of 94.6 % of the true obstacles within 20 m
    (mean of the drives, 89.4–96.6 %) hold a cell of cost 1 with 3, 92.6 % (87.0–96.6 %) with 0,
    for 3 % more occupied cells lying more than 1 m from every true obstacle (2026-11-27). 0
    occupies with the reported tracks only. Counts as ``tracking.reconfirm_misses`` where larger:
    a track seen again after more misses is not confirmed at once, and would leave the cost on
    the frame it came back."""

    def validate(self) -> None:
        value = self.max_slope_deg
        _check(0.1 <= value < 90, "cost.max_slope_deg", f"must be in [0.1, 90), got {value}")
        _check(self.max_step_m >= 0.001, "cost.max_step_m", f"must be >= 0.001, got {self.max_step_m}")
        _check(self.clearance_m >= 0, "cost.clearance_m", f"must be >= 0, got {self.clearance_m}")
        _check(0 <= self.occupied_misses <= 1000, "cost.occupied_misses", f"must be in 0..1000, got {self.occupied_misses}")


@dataclass(slots=True)
class McapConfig:
    """What goes into the MCAP output besides the grid and obstacles (size only: every layer,
    label and obstacle is computed from every point)."""

    max_points: int = 0
    """Points written per frame to ``/terrainmap/points`` at most, every k-th point kept beyond
    that (k = ⌈points / max_points⌉); 0 writes every point. A 640×480 frame has about 150k points,
    13 bytes each (16 in the ROS 2 flavour): capping them at 30k makes the file of a long drive
    about 4 times smaller."""
    log_transforms: bool = True
    """Write the transforms the log's own tf holds too: the vehicle's pose in the odometry frame
    (``odom → base_link``) and a camera mount taken from tf, so that the output alone shows the
    drive. Off for playing the output beside its log in ROS, where tf2 warns of repeated data
    (TF_REPEATED_DATA) at every frame; transforms terrainmap made (an estimated or configured
    camera pose) are written either way."""

    def validate(self) -> None:
        _check(self.max_points >= 0, "mcap.max_points", "must be >= 0 (0: every point)")


@dataclass(slots=True)
class RerunConfig:
    """What goes into Rerun recordings (display only; does not change any result)."""

    max_points: int = 30000
    """Points logged per frame at most (uniformly subsampled beyond that)."""

    def validate(self) -> None:
        _check(self.max_points >= 1, "rerun.max_points", "must be >= 1")


@dataclass(slots=True)
class Config:
    """The effective configuration of a run: one section per pipeline stage."""

    grid: GridConfig = field(default_factory=GridConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    extrinsics: ExtrinsicsConfig = field(default_factory=ExtrinsicsConfig)
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    cost: CostConfig = field(default_factory=CostConfig)
    mcap: McapConfig = field(default_factory=McapConfig)
    rerun: RerunConfig = field(default_factory=RerunConfig)

    def validate(self) -> Config:
        """Check every section; raise :class:`ConfigError` naming the first bad field."""
        for section in fields(self):  # grid first: the terrain's ranges are checked against it
            value = getattr(self, section.name)
            if type(value) is not section.default_factory:
                raise ConfigError(f"{section.name}: must be a {section.default_factory.__name__}, "
                                  f"got {type(value).__name__}")
            check_section(value, section.default_factory, self.grid)
        cells = self.grid.shape[0] * self.grid.shape[1]
        _check(self.obstacles.min_cells <= cells, "obstacles.min_cells",
               f"({self.obstacles.min_cells}) exceeds the grid's {cells} cells: no obstacle could be found")
        return self

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    def to_toml(self) -> str:
        """The config as TOML text that :func:`load_config` reads back."""
        lines: list[str] = []
        for section, values in self.to_dict().items():
            lines.append(f"[{section}]")
            lines.extend(f"{key} = {_toml_value(value)}" for key, value in values.items())
            lines.append("")
        return "\n".join(lines)


_SECTION_NAMES = {f.default_factory: f.name for f in fields(Config)}
"""Section class → its name in a config (``GridConfig`` → ``grid``), for messages."""

_KINDS = {"bool": ((bool,), "true or false"), "int": ((int,), "an integer"), "float": ((int, float), "a number"),
          "str": ((str,), "a string")}
"""Declared field type → (accepted Python types, how a message names it)."""


def check_section(section: Any, kind: type, grid: GridConfig | None = None) -> None:
    """What :meth:`Config.validate` checks of one section, for a section used on its own (the
    stage functions take one): that it is the section the stage takes (of class ``kind``, e.g.
    :class:`GridConfig`), kinds and finite numbers, its own ranges (the terrain's against
    ``grid``), then :data:`MAX_NUMBER` and :data:`INT_RANGE`, so that a field with a range of its
    own names it. :class:`ConfigError` naming the first bad field. A section equal to the last one
    of its kind that passed (values and their types, and ``grid``) is not checked again: the
    stages check theirs every frame."""
    if not isinstance(section, TerrainConfig):
        grid = None  # only the terrain's ranges depend on it: so the stages' checks find what validate() passed
    if type(section) is not kind:
        raise ConfigError(f"expected config.{_SECTION_NAMES[kind]} (a {kind.__name__}), got {type(section).__name__}")
    if _passed_before(section, grid):
        return
    name = _SECTION_NAMES[type(section)]
    check_kinds(name, section)
    try:
        section.validate(grid) if isinstance(section, TerrainConfig) else section.validate()
    except ConfigError as exc:
        raise _with_value(exc, name, section) from None
    for f in fields(section):
        value, kind = getattr(section, f.name), str(f.type)
        if kind == "float" and abs(value) > MAX_NUMBER:
            raise ConfigError(f"{name}.{f.name}: must be at most {MAX_NUMBER:g} in magnitude, got {brief(value)}")
        if kind == "int" and not INT_RANGE[0] <= value <= INT_RANGE[1]:
            raise ConfigError(f"{name}.{f.name}: must be within {INT_RANGE[0]}..{INT_RANGE[1]}, got {brief(value)}")
    _PASSED[type(section)] = (dataclasses.replace(section), grid and dataclasses.replace(grid))


def _with_value(error: ConfigError, name: str, section: Any) -> ConfigError:
    """``error`` of one field of ``section`` (config section ``name``) with ", got VALUE" added
    where its message is of that field alone (it names no other field of the section) and says
    no number equal to the value."""
    field, _, message = str(error).partition(": ")
    section_name, _, key = field.partition(".")
    if section_name != name or key not in section.__dataclass_fields__:
        return error
    words, value = set(re.findall(r"\w+", message)), getattr(section, key)
    if "got" in words or words & (set(section.__dataclass_fields__) - {key}):
        return error
    said = {float(n) for n in re.findall(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", message)}
    if isinstance(value, int | float) and value in said:
        return error
    return ConfigError(f"{field}: {message}, got {brief(value)}")


_PASSED: dict[type, tuple] = {}
"""Section class → copies of the last section of that class that :func:`check_section` passed,
and of its grid."""


def _passed_before(section: Any, grid: GridConfig | None) -> bool:
    passed = _PASSED.get(type(section))
    return passed is not None and same_values(passed, (section, grid))


def check_config(what: str, config: Config) -> None:
    """:class:`ConfigError` naming ``what`` (an output, an evaluation) unless ``config`` is a valid
    :class:`Config`."""
    if not isinstance(config, Config):
        raise ConfigError(f"{what}: config must be a Config, got {type(config).__name__}")
    config.validate()


def same_values(a: Any, b: Any) -> bool:
    """Whether ``a`` and ``b`` (configs, sections, or tuples of them) hold equal values of the same
    types: ``True``, ``1`` and ``1+0j`` equal ``1.0`` to Python but are no float setting, and a
    field holding an array cannot be compared: neither is the same as what was checked."""
    try:
        if a != b:
            return False
    except (TypeError, ValueError):  # a field holding an array
        return False
    return _kinds(a) == _kinds(b)


def _kinds(value: Any) -> Any:
    """The types of ``value``'s fields, nested as a config's sections and tuples are (for
    :func:`same_values`; a section's fields are numbers, flags and texts)."""
    if isinstance(value, tuple):
        return tuple(map(_kinds, value))
    if isinstance(value, Config):
        return tuple(_kinds(getattr(value, f.name)) for f in fields(value))
    if hasattr(value, "__dataclass_fields__"):
        return type(value), *(type(getattr(value, f.name)) for f in fields(value))
    return type(value)


def check_kinds(name: str, section: Any) -> None:
    """Every field of ``section`` holds a value of its declared kind (an int where a float is
    declared is fine), and every number is finite: what TOML and ``--set`` ensure for a loaded
    config, checked here for one built in code (so the sections' own checks are of ranges only).
    A numpy scalar (``np.float32(0.5)``) is replaced by the Python number it holds."""
    for f in fields(section):
        value, kind = getattr(section, f.name), str(f.type)
        if isinstance(value, np.generic):
            value = value.item()
            setattr(section, f.name, value)
        types, what = _KINDS[kind]
        if not isinstance(value, types) or (kind != "bool" and isinstance(value, bool)):
            raise ConfigError(f"{name}.{f.name}: must be {what}, got {brief(value)}")
        if kind == "float" and not math.isfinite(value):
            raise ConfigError(f"{name}.{f.name}: must be finite, got {brief(value)}")


def _toml_value(value: Any) -> str:
    if isinstance(value, np.generic):  # a numpy scalar set in code: the Python value it holds
        value = value.item()
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


_DECIMAL = re.compile(r"[+-]?((0|[1-9](_?\d)*)(\.(\d(_?\d)*)?)?|\.\d(_?\d)*)([eE][+-]?\d(_?\d)*)?", re.ASCII)
"""A number as ``--set`` takes it: as TOML writes numbers (``100_000``, no leading zero, so not
``0_5``, which Python's float() reads as 5; ASCII digits only), and ``.5`` or ``5.`` too."""


def _coerce(section: str, name: str, current: Any, value: Any, text: bool) -> Any:
    """Convert ``value`` to the type of ``current``: from a ``--set`` string when ``text``, else a
    TOML value, which must already have the field's kind (a quoted "0.5" is no number)."""
    key, given = f"{section}.{name}", value
    try:
        if not text and isinstance(value, str) != isinstance(current, str):
            raise ValueError
        if text and type(current) in (int, float):
            if not _DECIMAL.fullmatch(value.strip()):
                raise ValueError
            value = value.replace("_", "")
        if isinstance(current, bool):
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                    raise ValueError
                return value.lower() in ("true", "1", "yes", "on")
            if not isinstance(value, bool):
                raise ValueError
            return value
        if isinstance(value, bool):  # TOML true/false is no number (bool is an int in Python)
            raise ValueError
        if isinstance(current, int):
            whole = isinstance(value, str) and value.strip().lstrip("+-").isdigit()  # exact, however long
            number = float(value) if isinstance(value, str) and not whole else value  # "3.0" as TOML's 3.0
            if isinstance(number, float) and not number.is_integer():
                raise ValueError
            return int(number)
        if isinstance(current, float):
            result = float(value)
            if not math.isfinite(result):
                raise ValueError
            return result
        if isinstance(current, (tuple, list)):
            items = value.split(",") if text else list(value)
            return type(current)(_coerce(section, name, current[0], v, text) for v in items)
        if text and len(value) > 1 and value[0] == value[-1] and value[0] in "\"'":  # TOML's quoting, as in a file
            value = value[1:-1]
        return str(value)
    except (TypeError, ValueError, OverflowError):
        kind = _KINDS[type(current).__name__][1]
        raise ConfigError(f"{key}: cannot use {brief(given)}, expected {kind}") from None


def apply_values(config: Config, values: dict[str, Any], source: str = "config", *, text: bool = False) -> Config:
    """Apply ``{section: {field: value}}`` onto ``config`` in place (unknown keys are errors);
    ``text``: the values are ``--set`` strings, else typed TOML values."""
    sections = {f.name: getattr(config, f.name) for f in fields(config)}
    for section, table in values.items():
        if section not in sections:
            what = f"section [{section}]" if isinstance(table, dict) else f"top-level key {section!r}"
            raise ConfigError(f"{source}: unknown {what} (known sections: {', '.join(sections)})")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: [{section}] must be a table")
        target = sections[section]
        names = {f.name for f in fields(target)}
        for name, value in table.items():
            if name not in names:
                near = difflib.get_close_matches(str(name), sorted(names), n=1)
                hint = f" (did you mean {section}.{near[0]}?)" if near else f" (fields: {', '.join(sorted(names))})"
                raise ConfigError(f"{source}: unknown field {section}.{name}{hint}")
            try:
                setattr(target, name, _coerce(section, name, getattr(target, name), value, text))
            except ConfigError as exc:  # a --set names the value already; a file is named here
                raise ConfigError(str(exc) if text else f"{source}: {exc}") from None
    return config


def parse_override(text: str) -> dict[str, dict[str, str]]:
    """``"terrain.degree=2"`` → ``{"terrain": {"degree": "2"}}``."""
    key, sep, value = text.partition("=")
    section, dot, name = (part.strip() for part in key.partition("."))
    if not sep or not dot or not section or not name:
        raise ConfigError(f"--set {text!r}: expected section.field=value, e.g. terrain.degree=3")
    return {section: {name: value.strip()}}


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] | None = ()) -> Config:
    """Defaults, then the TOML file at ``path`` (if any), then ``overrides`` (``--set`` strings
    such as ``"terrain.degree=3"``); validated."""
    texts = () if isinstance(overrides, str) else tuple(overrides or ())  # a generator can be read once only
    if isinstance(overrides, str) or not all(isinstance(text, str) for text in texts):
        raise ConfigError(f"overrides must be a list of 'section.field=value' strings, got {overrides!r}")
    config, data = Config(), {}
    if path is not None:
        if not isinstance(path, str | os.PathLike):
            raise ConfigError(f"config file: expected a path, got {brief(path)}")
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # (a Windows editor's byte order mark)
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read config file ({exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        except RecursionError:
            raise ConfigError(f"{path}: not valid TOML (values nested too deep)") from None
        apply_values(config, data, source=str(path))
    set_keys = set()
    for text in texts:
        values = parse_override(text)
        apply_values(config, values, source=f"--set {text}", text=True)
        set_keys |= {f"{section}.{name}" for section, table in values.items() for name in table}
    try:
        return config.validate()
    except ConfigError as exc:  # a value the file gave (and no --set replaced) is named with the file
        file_keys = {f"{section}.{name}" for section, table in data.items() for name in table}
        section, *fields = re.findall(r"\w+", str(exc).partition(":")[0]) or [""]  # "terrain.a × b": a and b
        named = {f"{section}.{field}" for field in fields}
        if named & file_keys and not named & set_keys:
            raise ConfigError(f"{path}: {exc}") from None
        raise
