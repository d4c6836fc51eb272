import numpy as np
import pytest

from terrainmap.config import Config
from terrainmap.evaluation.baselines import METHODS, available_methods
from terrainmap.extrinsics import extrinsics_from_pose
from terrainmap.grid import cell_centers
from terrainmap.synthetic import cloud, rolling_terrain
from terrainmap.types import Label


@pytest.fixture(scope="module")
def scene():
    config = Config()
    points = cloud(60_000, seed=5)
    xs, ys = cell_centers(config.grid)
    return config, points, rolling_terrain(xs[:, None], ys[None, :])


@pytest.mark.parametrize("name", available_methods())
def test_every_available_method_gives_layers_and_labels(scene, name):
    config, points, truth = scene
    out = METHODS[name](points, config, extrinsics_from_pose(1.6))
    assert out.elevation.shape == config.grid.shape
    assert out.point_labels.shape == (len(points),) and out.point_labels.dtype == np.uint8
    assert set(np.unique(out.point_labels)) <= {int(v) for v in Label}
    if out.slope is not None:
        assert out.slope.shape == config.grid.shape


def test_terrainmap_beats_the_flat_and_single_fit_baselines_on_rolling_terrain(scene):
    config, points, truth = scene

    def rmse(name):
        e = METHODS[name](points, config, None).elevation
        return float(np.sqrt(np.nanmean((e - truth) ** 2)))

    assert rmse("terrainmap") < 0.06
    assert rmse("terrainmap") < rmse("ransac_plane") / 5


def test_optional_methods_are_listed_only_when_installed(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n: None if n in ("CSF", "pypatchworkpp") else real(n))
    assert available_methods() == ["terrainmap", "bspline_single", "ransac_plane", "lowest_point"]
