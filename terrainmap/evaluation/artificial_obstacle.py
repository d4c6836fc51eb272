"""The artificial-obstacle evaluation of the paper (Sec. VI, Fig. 6).

Protocol: take a base scene the algorithm estimates perfectly (a flat plane), add a w × w box of
height h standing on it at ``position``, estimate the terrain again, and report the maximum
deviation ``max |S_with − S_without|`` over the area of interest, as a percentage of h.

The scene is "sampled like the grid": a regular point lattice of ``samples_per_cell²`` points
per cell over the whole area (z = base height), where points inside the box footprint take the
box top (base + h). Both clouds then go through the whole terrain pipeline (eq. 1 quantization,
Algorithm V-B.1). The deviation is measured on a lattice of ``cell/eval_per_cell`` spacing,
over the cells where the base scene has data (all of them for the flat scene; for a base taken
from a log, the unobserved parts of the area are extrapolation and are left out).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import numpy as np

from ..config import Config, GridConfig, TerrainConfig
from ..errors import FrameError, InputError
from ..grid import cell_index, quantize
from ..stereo import rig_camera
from ..terrain import estimate_terrain
from ..types import StereoCamera


@dataclass(frozen=True)
class Scenario:
    """One point of Fig. 6: a control net, an obstacle width and height (metres)."""

    control_points: int
    width_m: float
    height_m: float


@dataclass(frozen=True)
class Deviation:
    control_points: int
    width_m: float
    height_m: float
    max_deviation_m: float
    max_deviation_pct: float

    def to_dict(self) -> dict:
        return {
            "control_points": self.control_points,
            "width_m": self.width_m,
            "height_m": self.height_m,
            "max_deviation_m": self.max_deviation_m,
            "max_deviation_pct": self.max_deviation_pct,
        }


PAPER_GRID = GridConfig(x_min_m=0.0, length_m=22.0, width_m=22.0, y_center_m=0.0, cell_size_m=0.5)
"""The paper's Fig. 6 area: 22 m × 22 m, 0.5 m cells, the obstacle at (11.0, 0.0)."""
PAPER_NETS = (5, 25)
PAPER_WIDTHS_M = (0.8, 2.0, 4.0, 8.0, 12.0)
PAPER_HEIGHTS_M = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


def flat_base(grid: GridConfig, samples_per_cell: int = 4) -> np.ndarray:
    """A flat scene z = 0 sampled like the grid: (N, 3) points, vehicle frame, metres."""
    step = grid.cell_size_m / samples_per_cell
    m0, m1 = grid.shape
    xs = grid.x_min_m + (np.arange(m0 * samples_per_cell) + 0.5) * step
    ys = grid.y_min_m + (np.arange(m1 * samples_per_cell) + 0.5) * step
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def add_box(points: np.ndarray, center_xy: tuple[float, float], width_m: float, height_m: float) -> np.ndarray:
    """Copy of ``points`` where those inside the w × w footprint are raised by ``height_m``."""
    out = points.copy()
    inside = (np.abs(points[:, 0] - center_xy[0]) <= width_m / 2) & (np.abs(points[:, 1] - center_xy[1]) <= width_m / 2)
    out[inside, 2] += height_m
    return out


def _surface_on_lattice(points: np.ndarray, grid: GridConfig, terrain: TerrainConfig, per_cell: int,
                        camera: StereoCamera | None = None):
    """The estimated surface on a lattice of ``per_cell`` steps per cell, and a mask of the lattice
    nodes that lie in (or on the edge of) a cell of the grid that holds points (``camera``: the
    stereo rig of the points, for eq. 1's noise discount as the pipeline applies it)."""
    height_grid = quantize(points, grid, camera=camera)
    est = estimate_terrain(height_grid, terrain)
    step = grid.cell_size_m / per_cell
    xs = grid.x_min_m + np.arange(grid.shape[0] * per_cell + 1) * step
    ys = grid.y_min_m + np.arange(grid.shape[1] * per_cell + 1) * step
    ix = np.minimum(np.arange(len(xs)) // per_cell, grid.shape[0] - 1)
    iy = np.minimum(np.arange(len(ys)) // per_cell, grid.shape[1] - 1)
    return est.surface.on_grid(xs, ys), height_grid.observed[np.ix_(ix, iy)]


def run(
    scenarios: Iterable[Scenario],
    *,
    grid: GridConfig = PAPER_GRID,
    terrain: TerrainConfig | None = None,
    position_xy: tuple[float, float] = (11.0, 0.0),
    base_points: np.ndarray | None = None,
    camera: StereoCamera | None = None,
    samples_per_cell: int = 4,
    eval_per_cell: int = 5,
    progress: Callable[[Deviation], None] | None = None,
) -> list[Deviation]:
    """Run the protocol for each scenario; returns one :class:`Deviation` per scenario.

    ``terrain`` supplies every setting but the control net (default: the paper's); ``base_points``
    (N×3, vehicle frame) replaces the flat base scene, e.g. points from a real frame, seen by
    ``camera`` (:func:`points_from_log` gives both).
    """
    terrain = terrain or TerrainConfig()
    grid.validate()
    base = flat_base(grid, samples_per_cell) if base_points is None else np.asarray(base_points, float)
    reference: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    results = []
    for sc in scenarios:
        cfg = replace(terrain, control_points_x=sc.control_points, control_points_y=sc.control_points)
        cfg.validate(grid)
        if sc.control_points not in reference:
            reference[sc.control_points] = _surface_on_lattice(base, grid, cfg, eval_per_cell, camera)
        scene = add_box(base, position_xy, sc.width_m, sc.height_m)
        _check_box_is_seen(base, scene, grid, position_xy, sc, grid.cell_size_m / samples_per_cell)
        with_box, _ = _surface_on_lattice(scene, grid, cfg, eval_per_cell, camera)
        surface, observed = reference[sc.control_points]
        dev = float(np.max(np.abs(with_box - surface)[observed]))
        pct = 100.0 * dev / sc.height_m if sc.height_m > 0 else math.nan
        result = Deviation(sc.control_points, sc.width_m, sc.height_m, dev, pct)
        results.append(result)
        if progress:
            progress(result)
    return results


def _check_box_is_seen(base: np.ndarray, scene: np.ndarray, grid: GridConfig, position_xy, sc: Scenario,
                       spacing_m: float) -> None:
    """Raise :class:`InputError` when no raised point of the box reaches the grid (a box outside
    the area, or so tall that its top lies above ``grid.z_max_m``): it would score a silent 0 %."""
    raised = scene[scene[:, 2] != base[:, 2]]
    if not (cell_index(raised, grid) < grid.shape[0] * grid.shape[1]).any():
        x, y = position_xy
        raise InputError(
            f"a {sc.width_m:g} m wide, {sc.height_m:g} m tall box at ({x:g}, {y:g}) leaves no point in the grid: "
            f"its footprint must overlap the area (x {grid.x_min_m:g}..{grid.x_min_m + grid.length_m:g} m, "
            f"y {grid.y_min_m:g}..{grid.y_min_m + grid.width_m:g} m, where the base scene has points), be wide enough "
            f"to hold one of its points (the flat scene's lie {spacing_m:g} m apart) and its top must stay "
            f"below grid.z_max_m = {grid.z_max_m:g} m"
        )


def points_from_log(path, config: Config, frame_index: int = 0, **open_kwargs) -> tuple[np.ndarray, StereoCamera]:
    """The vehicle-frame stereo points (N×3, m) of one frame of a log or folder and the rig that
    saw them, as the pipeline sees them (``open_kwargs``: topics, calibration and pairing
    tolerance, as for :func:`~terrainmap.sources.open_source`).

    Raises :class:`InputError` if the log has fewer frames or the frame yields no terrain (naming
    the log and the pair), and the pipeline's errors otherwise.
    """
    from ..pipeline import PipelineState, process_frame
    from ..sources import open_source

    with open_source(path, **open_kwargs) as source:
        for frame in source.frames(max_frames=frame_index + 1):
            if frame.index == frame_index:
                try:
                    result = process_frame(frame, config, PipelineState(config))
                except FrameError as exc:
                    raise InputError(f"{path}: stereo pair {frame_index}: {exc}") from exc
                return result.points_vehicle.astype(float), rig_camera(result.pinhole, result.extrinsics)
    raise InputError(f"{path}: has no stereo pair number {frame_index}")


def grid_of_scenarios(nets: Iterable[int], widths_m: Iterable[float], heights_m: Iterable[float]) -> list[Scenario]:
    return [Scenario(n, w, h) for n in nets for w in widths_m for h in heights_m]


def plot(results: list[Deviation], path: str) -> None:
    """Draw the results like the paper's Fig. 6: one panel per control net, one curve per width."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nets = sorted({r.control_points for r in results})
    widths = sorted({r.width_m for r in results})
    fig, axes = plt.subplots(len(nets), 1, figsize=(7, 3.2 * len(nets)), sharex=True, squeeze=False)
    for ax, net in zip(axes[:, 0], nets):
        for w in widths:
            pts = sorted((r.height_m, r.max_deviation_pct) for r in results if r.control_points == net and r.width_m == w)
            if pts:
                ax.plot(*zip(*pts), marker="o", label=f"width {w:g} m")
        ax.set_title(f"{net}×{net} control points")
        ax.set_ylabel("max deviation [% of height]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("obstacle height [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
