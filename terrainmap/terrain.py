"""Terrain estimation: Algorithm V-B.1 of the paper (iterative re-weighted rational B-spline
fitting with equalization).

Decisions where the paper's text is garbled or silent, each with the property it keeps:

1. **Schedule.** The first fit uses ``start_control_points`` per axis (at least degree + 1),
   R ≡ 1 and W ≡ 1 (a plain, unweighted, non-rational spline). Each iteration grows the net per axis to
   ``max(n + 1, round(n · control_point_growth))``, capped at the final net
   (``control_points_x/y``); growth 1.0 is the pseudo-code's ``δn ← δn + 1``. R is remapped onto
   the net of the next fit.
2. **Weights (eq. 3).** ``W = 1 + (|Δz|/th)^(−α)`` with Δz = P − S (sample minus surface),
   ``th = max(threshold_factor · ē, threshold_min_m)`` where ē is the mean |Δz| over valid cells,
   and ``α = max(1, alpha_per_iteration · k)`` at iteration k = 1, 2, … W is infinite at Δz = 0, so
   it is bounded by ``weight_max``. The fit uses ``W`` times a base weight: 1 for observed cells,
   ``filled_weight`` for cells filled from neighbours, 0 for INVALID cells (so Z = 0 never pulls).
3. **Control weights R.** The basis-weighted mean of the fit weights over each control point's
   support (:meth:`TensorFit.remap`), normalised to a maximum of 1 and bounded below by
   ``control_weight_min`` — unbounded R makes the rational basis ill-conditioned and the surface
   ring.
4. **Equalization.** The printed ``Z ← Z − Δz(1 + 1/W)`` would overshoot, contradicting the text
   ("adjustments are always smaller than Δz"). We use ``Z ← Z − f·Δz`` with
   ``f = 1/W_unbounded = r^α / (1 + r^α)``, ``r = |Δz|/th``: f ∈ (0, 1), growing with |Δz|
   ("the higher the distance, the higher the equalization"), so a sample never crosses the
   surface. Only valid samples more than ``max(th, noise band)`` above the surface move, where the
   noise band is ``equalize_tolerance_m + equalize_tolerance_per_m · range``: samples within the
   current threshold or the stereo noise are terrain, and moving them would drag the surface to
   the lower envelope of the noise. Valid samples below the surface never move. INVALID cells
   are set onto the surface (pulled both ways; they carry no weight).
   Each iteration equalizes the *original* samples against the current surface (the pseudo-code
   equalizes the previous P cumulatively): hills that an early, coarse surface could not follow
   would otherwise be shaved for good — on rolling terrain with plain noise this made the result
   3× worse than a single plain fit. ē and W come from the current P as in the pseudo-code, so
   lowered outliers stop inflating the threshold.
5. **Samples below the surface.** Eq. 3 weighs samples by |Δz| alone. But every visible point
   lies on or above the terrain ("the terrain ... must always be made of the lowest visible 3D
   points"), so a sample clearly below the surface (more than the band of 4.) is evidence that
   the surface is too high, not an outlier: with ``trust_below`` it keeps the maximum weight.
   Within the band, weights stay symmetric so the surface does not sink into the stereo noise.
   Where the grid knows the stereo rig, "clearly below" also means deeper than a disparity error
   of ``trust_below_px`` pixels moves a point there (:attr:`HeightGrid.height_per_px`): that
   grows with range, and a fixed band let far stereo noise hold the surface 10–20 cm under the
   terrain at 10–20 m. On KITTI 000005 trusting samples below keeps 69 % of the parked cars'
   points labelled obstacle (61 % without; measured before ``segmentation.edge_margin_m``), where
   the surface would otherwise climb the occluded kerb strips.
6. **Stop.** The pseudo-code's loop condition is garbled; the text says the loop ends when the
   final net is reached *or* no sample was equalized in the last step. We stop when no valid
   sample moved more than ``epsilon_m`` or when the net grows to the final one — as in the
   pseudo-code, where the loop ends as ``δn`` reaches ``n_max``, so no iteration fits the final
   net before the last fit (until 2026-11-26 one did: a 25×25 fit more per frame, 20 % of the
   estimation's time, for a median slope error 0.07–0.20° larger on the simulated drives); then
   one last fit on the final net with the last W, R (remapped onto it) and P gives the surface.
   A net that starts final (``start_control_points`` ≥ the final net) is fitted once plain, then
   last.
7. **Stereo noise on slopes.** Eq. 1 with the grid's noise discount (:mod:`terrainmap.grid`)
   needs the terrain's slope, which only the fit knows: a disparity error moves a point on ground
   that slopes towards the camera several times more in height than on level ground, so the
   level-ground discount leaves σ, and the sample's low bias, too large there. Where the grid
   knows the stereo rig, the surfaces of the first ``slope_noise_iterations`` iterations
   recompute the samples on their slope (:meth:`HeightGrid.on_slope`) before they are weighed
   and equalized; ``grid`` of the result is the last such grid. Early surfaces suffice: the
   slope of the terrain is settled long before its detail (on the simulated scenes, 3 refreshes
   do as well as one per iteration, and 1 nearly so). It took the 10–20 m elevation RMSE on the
   simulated 17° climb from 16 to 8 cm and the canyon's terrain F1 from 0.77 to 0.95
   (docs/accuracy.md).
8. **Well-posedness.** Each fit adds a small second-difference penalty on Q (see
   :class:`~terrainmap.bspline.TensorFit`), so knot spans without valid samples are bridged
   smoothly instead of making the normal equations singular.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .bspline import RationalSurface, TensorFit, clamped_knots
from .config import GridConfig, TerrainConfig, check_section
from .errors import FrameError, InputError
from .grid import HeightGrid, cell_centers


@dataclass
class TerrainEstimate:
    """Result of :func:`estimate_terrain`.

    ``surface``: the terrain S. ``elevation``, ``dz_dx``, ``dz_dy``: S and its analytic gradient
    at the cell centres, (m0, m1). ``samples``: the equalized sample heights P after the last
    iteration, (m0, m1) metres (``grid.z`` holds them before). ``weights``: the last sample
    weights W of eq. 3, (m0, m1). ``iterations``: fits before the final one. ``mean_error_m``:
    ē of the last iteration. ``converged``: stopped early because no sample moved more than ε.
    ``grid``: the grid whose samples the final fit used (decision 7; the input grid when it has
    no stereo rig).
    """

    surface: RationalSurface
    elevation: np.ndarray
    dz_dx: np.ndarray
    dz_dy: np.ndarray
    samples: np.ndarray
    weights: np.ndarray
    iterations: int
    mean_error_m: float
    converged: bool
    grid: HeightGrid


@lru_cache(maxsize=32)
def _fitter(grid: tuple, n0: int, n1: int, degree: int) -> TensorFit:
    """The :class:`TensorFit` of one control net on one grid geometry (cached per frame size)."""
    x_min, length, y_min, width, cell = grid
    config = GridConfig(x_min_m=x_min, length_m=length, y_center_m=y_min + width / 2, width_m=width, cell_size_m=cell)
    xs, ys = cell_centers(config)
    kx = clamped_knots(x_min, x_min + length, n0, degree)
    ky = clamped_knots(y_min, y_min + width, n1, degree)
    return TensorFit(xs, ys, kx, ky, degree)


def fitter_for(config: GridConfig, n0: int, n1: int, degree: int) -> TensorFit:
    key = (config.x_min_m, config.length_m, config.y_min_m, config.width_m, config.cell_size_m)
    return _fitter(key, n0, n1, degree)


def sample_weights(dz: np.ndarray, th: float, alpha: float, weight_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3 bounded by ``weight_max``, and the equalization fraction f = 1/W (unbounded W).

    Returns ``(W, f)`` shaped like ``dz``: W in [1, weight_max], decreasing in |Δz|; f in [0, 1),
    increasing in |Δz|. ``r^(−α)`` is computed as ``exp(−α·log r)`` with r clipped away from 0,
    so neither is ever inf or NaN."""
    log_r = np.log(np.maximum(np.abs(dz), 1e-12) / th)
    inv = np.exp(np.minimum(-alpha * log_r, 700.0))  # (|Δz|/th)^(−α)
    weights = 1.0 + np.minimum(inv, weight_max - 1.0)
    fraction = 1.0 / (1.0 + inv)
    return weights, fraction


def equalize(P: np.ndarray, S: np.ndarray, fraction: np.ndarray, valid: np.ndarray, tolerance) -> np.ndarray:
    """The equalization filter: new sample heights (same shape as P).

    Valid samples more than ``tolerance`` above the surface move down by ``fraction · Δz``
    (``fraction`` < 1, so they never cross S); other valid samples stay; INVALID samples are set
    onto the surface.
    """
    dz = P - S
    step = np.where(valid & (dz > tolerance), fraction * dz, 0.0)
    return np.where(valid, P - step, S)


def check_grid(grid: HeightGrid, config: TerrainConfig) -> None:
    """Raise :class:`FrameError` when the grid cannot support the spline (too few samples), and
    :class:`InputError` when it is not a grid of its config's shape (a hand-built HeightGrid)."""
    shape = tuple(grid.config.shape)
    for name in ("z", "observed", "valid"):
        array = getattr(grid, name)
        if np.shape(array) != shape or (name != "z" and np.asarray(array).dtype != bool):
            raise InputError(f"HeightGrid.{name} must be a {shape[0]}×{shape[1]} {'float' if name == 'z' else 'bool'} array")
    if not np.isfinite(grid.z[grid.valid]).all():
        raise InputError("HeightGrid.z must be finite on its valid cells")
    if (grid.observed & ~grid.valid).any():
        raise InputError("HeightGrid.valid must include every observed cell")
    need = max(config.min_valid_cells, (config.degree + 1) ** 2)
    observed = grid.observed
    if observed.sum() < need:
        raise FrameError(
            "too_few_cells", f"only {int(observed.sum())} grid cells hold points; the spline needs at least {need}"
        )
    if np.count_nonzero(observed.any(1)) < 2 or np.count_nonzero(observed.any(0)) < 2:
        raise FrameError("too_few_cells", "the observed cells lie on a single grid row or column")


def estimate_terrain(grid: HeightGrid, config: TerrainConfig) -> TerrainEstimate:
    """Fit the terrain surface to the grid samples (Algorithm V-B.1; decisions in the module doc).

    Parameters
    ----------
    grid : HeightGrid
        Samples P from :func:`terrainmap.grid.quantize`.
    config : TerrainConfig
        Degree, control nets, weighting and equalization parameters.

    Raises
    ------
    ConfigError
        ``config`` does not validate against the grid.
    FrameError
        ``too_few_cells`` if fewer cells are observed than the net needs; ``fit_failed`` if a fit
        cannot be solved.
    """
    if not isinstance(grid, HeightGrid):
        raise InputError(f"estimate_terrain: grid must be a HeightGrid (terrainmap.grid.quantize), got {type(grid).__name__}")
    check_section(config, TerrainConfig, grid.config)
    check_grid(grid, config)
    gcfg = grid.config
    xs, ys = cell_centers(gcfg)
    tolerance = config.equalize_tolerance_m + config.equalize_tolerance_per_m * np.hypot(xs[:, None], ys[None, :])
    valid = grid.valid
    base = np.where(grid.observed, 1.0, np.where(valid, config.filled_weight, 0.0))
    P = grid.z.astype(np.float64)
    final = (config.control_points_x, config.control_points_y)
    start = max(config.start_control_points, config.degree + 1)
    n = (min(start, final[0]), min(start, final[1]))
    fit = fitter_for(gcfg, *n, config.degree)
    W = np.ones_like(P)
    R = np.ones(n)
    iteration, converged, error = 0, False, 0.0
    while True:
        iteration += 1
        Q = fit.fit(P, base * W, R, config.smoothness)
        if iteration <= config.slope_noise_iterations and grid.camera is not None:  # decision 7
            S, gx, gy = fit.evaluate_with_gradient(Q, R)
            grid = grid.on_slope(gx, gy)
        else:
            S = fit.evaluate(Q, R)
        dz = P - S
        error = float(np.abs(dz[valid]).mean())
        th = max(config.threshold_factor * error, config.threshold_min_m)
        alpha = max(1.0, config.alpha_per_iteration * iteration)
        band = np.maximum(tolerance, th)
        W, _ = sample_weights(dz, th, alpha, config.weight_max)
        if config.trust_below:
            below_noise = 0.0 if grid.height_per_px is None else config.trust_below_px * grid.height_per_px
            W = np.where(dz < -np.maximum(band, below_noise), config.weight_max, W)
        _, f = sample_weights(grid.z - S, th, alpha, config.weight_max)
        P_next = equalize(grid.z, S, f, valid, band)
        moved = float(np.max(np.abs(P_next - P)[valid]))
        P = P_next
        if n == final or moved < config.epsilon_m:
            converged = n != final
            break
        n = tuple(min(max(k + 1, round(k * config.control_point_growth)), top) for k, top in zip(n, final))
        if n == final:  # the pseudo-code's loop ends as δn reaches n_max: the final fit is the only one on it
            break
        fit = fitter_for(gcfg, *n, config.degree)
        R = _control_weights(fit, base * W, config.control_weight_min)
    fit = fitter_for(gcfg, *final, config.degree)
    if R.shape != final:  # R of the last iteration's net, remapped onto the final one
        R = _control_weights(fit, base * W, config.control_weight_min)
    Q = fit.fit(P, base * W, R, config.smoothness)
    if not np.all(np.isfinite(Q)):
        raise FrameError("fit_failed", "the terrain fit produced non-finite control points")
    elevation, gx, gy = fit.evaluate_with_gradient(Q, R)
    return TerrainEstimate(fit.surface(Q, R), elevation, gx, gy, P, W, iteration, error, converged, grid)


def _control_weights(fit: TensorFit, weights: np.ndarray, floor: float) -> np.ndarray:
    """R from the sample weights: remapped to the net, normalised to max 1, bounded below."""
    R = fit.remap(weights)
    top = R.max()
    return np.clip(R / top, floor, 1.0) if top > 0 else np.ones_like(R)
