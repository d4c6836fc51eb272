import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.config import GridConfig, TerrainConfig, load_config
from terrainmap.errors import ConfigError, FrameError
from terrainmap.grid import cell_centers, quantize
from terrainmap.slope import layers as slope_layers
from terrainmap.slope import slope_at
from terrainmap.synthetic import grid_samples
from terrainmap.terrain import equalize, estimate_terrain, fitter_for, sample_weights
from terrainmap.types import StereoCamera


def _rmse(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_accuracy_target_and_single_fit_is_many_times_worse(seed):
    """3 cm noise, 10 % outliers up to 2 m, 30 % empty cells: RMSE ≤ 3 cm; one plain fit ≫."""
    grid, truth = grid_samples(seed=seed)
    est = estimate_terrain(grid, TerrainConfig())
    xs, ys = cell_centers(grid.config)
    rmse = _rmse(est.surface.on_grid(xs, ys), truth)
    fit = fitter_for(grid.config, 25, 25, 3)
    R = np.ones((25, 25))
    single = _rmse(fit.evaluate(fit.fit(grid.z, grid.valid * 1.0, R, 1e-3), R), truth)
    assert rmse <= 0.03
    assert single >= 4 * rmse


def test_paper_schedule_gives_the_same_accuracy():
    """Growth 1.0 (one control point per iteration, the pseudo-code) vs the default 1.5."""
    grid, truth = grid_samples(seed=4)
    xs, ys = cell_centers(grid.config)
    fast = estimate_terrain(grid, TerrainConfig())
    paper = estimate_terrain(grid, TerrainConfig(control_point_growth=1.0))
    assert paper.iterations > fast.iterations
    assert abs(_rmse(fast.surface.on_grid(xs, ys), truth) - _rmse(paper.surface.on_grid(xs, ys), truth)) < 0.01


def test_clean_flat_scene_converges_early_and_exactly():
    cfg = GridConfig()
    xs, ys = cell_centers(cfg)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), 0.1 + 0.05 * X.ravel()])
    est = estimate_terrain(quantize(pts, cfg), TerrainConfig())
    assert est.converged and est.iterations < 4
    full = estimate_terrain(quantize(pts, cfg), TerrainConfig(epsilon_m=0.0))  # stops only at the final net
    assert not full.converged and full.iterations == 5  # 4, 6, 9, 14, 21 control points, then the final fit at 25
    np.testing.assert_allclose(est.surface.on_grid(xs, ys), 0.1 + 0.05 * X, atol=1e-3)
    slope, gx, gy = slope_at(est.surface, np.array([3.0, 20.0]), np.array([-5.0, 2.0]))  # any points
    np.testing.assert_allclose(slope, np.arctan(0.05), atol=1e-3)
    layers = slope_layers(est.elevation, est.dz_dx, est.dz_dy)  # and on the grid
    np.testing.assert_allclose(layers["slope"], np.arctan(0.05), atol=1e-3)


def test_noise_alone_leaves_little_bias():
    """The dead band keeps one-sided equalization from dragging the surface into the noise."""
    grid, truth = grid_samples(outlier_fraction=0.0, empty_fraction=0.0, noise_m=0.05, seed=3)
    est = estimate_terrain(grid, TerrainConfig())
    xs, ys = cell_centers(grid.config)
    # 1.6 cm here (noise σ = 5 cm); 2.6 cm without the dead band (equalize_tolerance_m = 0)
    assert abs(float(np.mean(est.surface.on_grid(xs, ys) - truth))) < 0.02


@pytest.mark.parametrize("seed", [0, 1])
def test_stereo_noise_below_the_surface_does_not_hold_it_down(seed):
    """Level ground seen by a stereo rig (camera 1.8 m up, f·B = 150 px·m, 0.5 px disparity noise):
    the height noise grows with range. Trusting every sample below the fixed band sinks the surface
    at 10–20 m; with the band at least ``trust_below_px`` pixels of disparity error it does not."""
    grid, truth = grid_samples(outlier_fraction=0.0, empty_fraction=0.0, noise_m=1.0, seed=seed)
    xs, ys = cell_centers(grid.config)
    r = np.hypot(xs[:, None], ys[None, :])
    grid.height_per_px = 1.8 * r / 150
    grid.z = truth + (grid.z - truth) * 0.5 * grid.height_per_px
    far = (r > 10) & (r < 20)
    bias = {px: float(np.mean((estimate_terrain(grid, TerrainConfig(trust_below_px=px)).elevation - truth)[far]))
            for px in (0.0, 3.0)}
    assert bias[0.0] < -0.03
    assert abs(bias[3.0]) < 0.015


def test_samples_on_a_slope_facing_the_camera_follow_its_noise():
    """Ground rising 17° ahead of a stereo rig (1.8 m up, f·B = 150 px·m, 0.5 px noise): the
    level-ground noise discount of eq. 1 leaves the samples, and the surface, ~14 cm low at
    10–20 m; recomputing them on the slope of the early surfaces (decision 7) halves that."""
    rig = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)
    grid_config = GridConfig()
    rng = np.random.default_rng(0)
    x, y = rng.uniform(2, 27, 300_000), rng.uniform(-8, 8, 300_000)
    ray = np.column_stack([x, y, 0.3 * (x - 5)]) - rig.center_m
    points = rig.center_m + ray * (1 + ray[:, 0] * rng.normal(0, 0.5, x.size) / rig.focal_baseline)[:, None]
    grid = quantize(points, grid_config, camera=rig)
    xs, ys = cell_centers(grid_config)
    r = np.hypot(xs[:, None], ys[None, :])
    far = (r > 10) & (r < 20) & grid.observed
    truth = np.broadcast_to(0.3 * (xs[:, None] - 5), grid.shape)
    bias = {}
    for k in (0, 3):
        estimate = estimate_terrain(grid, TerrainConfig(slope_noise_iterations=k))
        bias[k] = float(np.mean((estimate.elevation - truth)[far]))
        assert (estimate.grid is grid) == (k == 0)
    assert bias[0] < -0.10
    assert bias[3] > bias[0] / 2


@given(
    dz=st.lists(st.floats(-5, 5, allow_nan=False), min_size=1, max_size=50),
    th=st.floats(0.01, 1.0),
    alpha=st.floats(1.0, 30.0),
)
@settings(max_examples=100, deadline=None)
def test_equalization_invariants(dz, th, alpha):
    dz = np.array(dz)
    S = np.zeros_like(dz)
    P = dz.copy()
    valid = np.ones(dz.shape, bool)
    valid[::3] = False
    W, f = sample_weights(dz, th, alpha, weight_max=100.0)
    assert np.all((W >= 1) & (W <= 100)) and np.all(np.isfinite(W))
    assert np.all((f >= 0) & (f < 1 + 1e-12))
    new = equalize(P, S, f, valid, tolerance=0.05)
    up = valid & (dz > 0)
    assert np.all(new[up] >= S[up] - 1e-12)  # never overshoots the surface
    assert np.all(new[up] <= P[up] + 1e-12)  # only moves down
    np.testing.assert_array_equal(new[valid & (dz <= 0.05)], P[valid & (dz <= 0.05)])  # below / in band: unmoved
    np.testing.assert_array_equal(new[~valid], S[~valid])  # INVALID: pulled onto S both ways
    # larger distance → larger fraction
    order = np.argsort(np.abs(dz))
    assert np.all(np.diff(f[order]) >= -1e-12)


def test_bad_input_is_reported_cleanly():
    sparse = np.array([[5.0 + i, 0.0, 0.0] for i in range(5)])
    with pytest.raises(FrameError) as err:
        estimate_terrain(quantize(sparse, GridConfig(fill_empty=False)), TerrainConfig())
    assert err.value.reason == "too_few_cells"
    with pytest.raises(ConfigError, match="terrain.control_points_x"):
        load_config(overrides=["terrain.control_points_x=70"])  # n_max > 68 cells along x
    with pytest.raises(ConfigError, match="terrain.degree"):
        load_config(overrides=["terrain.degree=0"])
    with pytest.raises(ConfigError, match="grid.cell_size_m"):
        load_config(overrides=["grid.cell_size_m=-0.5"])


def test_a_hand_built_grid_that_does_not_fit_is_an_input_error():
    import dataclasses

    from terrainmap.config import Config
    from terrainmap.errors import InputError
    from terrainmap.synthetic import cloud

    config = Config()
    grid = quantize(cloud(20_000, grid=config.grid), config.grid)
    for change, message in (
        ({"z": grid.z.T}, "HeightGrid.z must be a 68×44 float array"),
        ({"observed": grid.observed.astype(int)}, "HeightGrid.observed must be a 68×44 bool array"),
        ({"valid": np.zeros_like(grid.valid)}, "must include every observed cell"),
        ({"z": np.where(grid.valid, np.nan, 0.0)}, "must be finite on its valid cells"),
    ):
        with pytest.raises(InputError, match=message):
            estimate_terrain(dataclasses.replace(grid, **change), config.terrain)


def test_slope_layers_take_both_axes_each_in_its_place():
    """The slope of a plane that rises along x and y is atan(|∇z|) (not one axis, not their sum);
    ``dz_dx`` and ``dz_dy`` keep their axes."""
    out = slope_layers(np.zeros((2, 3)), np.full((2, 3), 0.1), np.full((2, 3), 0.3))
    np.testing.assert_allclose(out["slope"], np.arctan(np.hypot(0.1, 0.3)), rtol=1e-6)
    assert (out["dz_dx"] == np.float32(0.1)).all() and (out["dz_dy"] == np.float32(0.3)).all()


def test_eq3_weight_and_equalization_fraction_take_alpha_as_the_exponent():
    """W = 1 + (|Δz|/th)^(−α) and f = 1 / (1 + (|Δz|/th)^(−α)): with |Δz| = 2·th and α = 2,
    W = 1.25 and f = 0.8; W stops at ``weight_max``."""
    weights, fraction = sample_weights(np.array([0.2, -0.2, 1e-9]), th=0.1, alpha=2.0, weight_max=100.0)
    np.testing.assert_allclose(weights, [1.25, 1.25, 100.0])
    np.testing.assert_allclose(fraction[:2], [0.8, 0.8])


def test_alpha_grows_with_the_iteration(monkeypatch):
    """Eq. 3's exponent at iteration k = 1, 2, … is α = max(1, alpha_per_iteration · k)."""
    import terrainmap.terrain as terrain_module

    seen = []

    def spy(dz, th, alpha, weight_max):
        seen.append(alpha)
        return sample_weights(dz, th, alpha, weight_max)

    monkeypatch.setattr(terrain_module, "sample_weights", spy)
    grid, _ = grid_samples(seed=5)
    est = estimate_terrain(grid, TerrainConfig(alpha_per_iteration=0.5, epsilon_m=0.0))
    assert est.iterations == 5  # nets of 4, 6, 9, 14, 21 control points
    assert list(dict.fromkeys(seen)) == [1.0, 1.5, 2.0, 2.5]  # iterations 1 and 2 both at the floor of 1


def test_a_net_that_starts_final_is_fitted_once_and_not_converged():
    """``converged`` means stopped early; a net that starts at the final size never does."""
    grid, _ = grid_samples(seed=6)
    est = estimate_terrain(grid, TerrainConfig(start_control_points=25))
    assert est.iterations == 1 and not est.converged
    still = estimate_terrain(grid, TerrainConfig(start_control_points=25, epsilon_m=10.0))  # every sample moves < ε
    assert still.iterations == 1 and not still.converged
