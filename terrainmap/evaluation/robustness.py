"""Robustness of the terrain estimator on synthetic grid samples with known truth.

The setting of the core accuracy target: one sample per cell of ``rolling_terrain`` with
Gaussian noise, gross outliers above the ground and empty cells
(:func:`terrainmap.synthetic.grid_samples`). Reports the surface RMSE against the truth for the
iterative estimator (Algorithm V-B.1) and for a single unweighted fit of the same net.
"""

from __future__ import annotations

import numpy as np

from ..config import Config, check_config
from ..grid import cell_centers
from ..synthetic import grid_samples
from ..terrain import estimate_terrain, fitter_for


def run(config: Config, *, seeds=range(5), noise_m=0.03, outlier_fraction=0.1, outlier_max_m=2.0,
        empty_fraction=0.3) -> dict[str, float]:
    """Mean over ``seeds`` of the RMSE (m) of ``iterative`` and ``single`` fits, and their ratio
    (:class:`ConfigError` for a bad config)."""
    check_config("robustness", config)
    xs, ys = cell_centers(config.grid)
    t = config.terrain
    fit = fitter_for(config.grid, t.control_points_x, t.control_points_y, t.degree)
    R = np.ones(fit.shape)
    iterative, single = [], []
    for seed in seeds:
        grid, truth = grid_samples(config.grid, noise_m=noise_m, outlier_fraction=outlier_fraction,
                                   outlier_max_m=outlier_max_m, empty_fraction=empty_fraction, seed=seed)
        surface = estimate_terrain(grid, t).surface.on_grid(xs, ys)
        plain = fit.evaluate(fit.fit(grid.z, grid.valid * 1.0, R, t.smoothness), R)
        iterative.append(np.sqrt(np.mean((surface - truth) ** 2)))
        single.append(np.sqrt(np.mean((plain - truth) ** 2)))
    return {
        "iterative_rmse_m": float(np.mean(iterative)),
        "single_fit_rmse_m": float(np.mean(single)),
        "ratio": float(np.mean(single) / np.mean(iterative)),
    }
