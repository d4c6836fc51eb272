"""The upright-surface cue: disparity gradients of planes, vertical runs, labelling a rock's face."""

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.config import GridConfig, SegmentationConfig
from terrainmap.errors import ConfigError
from terrainmap.stereo import RectifiedPinhole
from terrainmap.types import Extrinsics, Label
from terrainmap.upright import disparity_gradient, ground_gradient, label_upright, vertical_runs

PINHOLE = RectifiedPinhole(fx=500.0, fy=500.0, cx=320.0, cy=240.0, baseline_m=0.3, doffs=0.0, width=640, height=480)
OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes in the vehicle frame
CAMERA = Extrinsics(rotation=OPTICAL, translation=np.array([0.0, 0.0, 1.8]), source="test")
GRID = GridConfig()


def _surface(elevation, dz_dx=None):
    """A stand-in for a TerrainEstimate: the surface's height and gradient at the cell centres."""
    zero = np.zeros(np.shape(elevation))
    return SimpleNamespace(elevation=elevation, dz_dx=zero if dz_dx is None else dz_dx, dz_dy=zero)


def _ground_disparity(slope=0.0, start_m=10.0):
    """Exact disparity of the ground z = slope·(x − start_m) under the level camera, 1.8 m up:
    H×W float32, NaN where the rays miss it; and the depth."""
    v, _ = np.mgrid[0:480, 0:640].astype(float)
    down = (v - PINHOLE.cy) / PINHOLE.fy  # a ray (x, z) = Z·(1, −down) from (0, 1.8)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (1.8 + slope * start_m) / (down + slope)
    depth[~(depth > 0)] = np.nan
    return (PINHOLE.fx * PINHOLE.baseline_m / depth).astype(np.float32), depth


@pytest.mark.parametrize("slope", [0.0, 0.3])
def test_ground_gradient_is_the_disparity_gradient_of_the_tangent_plane(slope):
    """A plane's disparity grows by B·n_y / (n·(C − P₀)) per row: B/1.8 m on level ground, less on a
    slope rising 10 m ahead (its plane passes farther from the camera)."""
    disparity, _ = _ground_disparity(slope)
    shape = GRID.shape
    x = GRID.x_min_m + (np.arange(shape[0]) + 0.5) * GRID.cell_size_m
    elevation = np.broadcast_to(slope * (x[:, None] - 10.0), shape)
    expected = ground_gradient(_surface(elevation, np.full(shape, slope)), GRID, PINHOLE, CAMERA)
    np.testing.assert_allclose(expected, 0.3 / (1.8 + 10.0 * slope), rtol=1e-12)
    measured = disparity_gradient(disparity, 2)
    rows = np.nanmedian(measured[250:470], axis=1)
    np.testing.assert_allclose(rows, 0.3 / (1.8 + 10.0 * slope), rtol=1e-3)
    assert np.all(np.isnan(measured[:2]))  # the window leaves the image
    above = ground_gradient(_surface(np.full(shape, 2.0)), GRID, PINHOLE, CAMERA)
    assert np.isnan(above).all()  # a plane above the camera: no ground seen from above


def _runs_by_scanning(mask: np.ndarray) -> np.ndarray:
    """The length of the vertical run through each True pixel, column by column (0 elsewhere)."""
    out = np.zeros(mask.shape, int)
    for u in range(mask.shape[1]):
        v = 0
        while v < mask.shape[0]:
            end = v
            while end < mask.shape[0] and mask[end, u]:
                end += 1
            out[v:end, u] = end - v
            v = max(end, v + 1)
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 12), st.integers(1, 9), st.floats(0.0, 1.0), st.integers(0, 2**32 - 1))
def test_vertical_runs_match_a_scan_of_each_column(height, width, density, seed):
    mask = np.random.default_rng(seed).random((height, width)) < density
    at = np.flatnonzero(mask)
    np.testing.assert_array_equal(vertical_runs(at, mask.shape), _runs_by_scanning(mask).ravel()[at])


def _scene(bottom_m=0.0, top_m=0.5):
    """Level ground under the camera with an upright face from ``bottom_m`` to ``top_m`` above it,
    0.6 m wide, 18 m ahead (one disparity down its height). Returns the disparity, the points
    (vehicle frame), their pixels, which are on the face and which of those lie 2 rows or more
    inside it (the gradient's window stays on the face)."""
    disparity, _ = _ground_disparity()
    face_depth = 18.0
    top, bottom = (PINHOLE.cy + PINHOLE.fy * (1.8 - h) / face_depth for h in (top_m, bottom_m))
    rows = slice(int(np.ceil(top)), int(np.floor(bottom)) + 1)
    cols = slice(int(PINHOLE.cx - 0.3 * PINHOLE.fx / face_depth), int(PINHOLE.cx + 0.3 * PINHOLE.fx / face_depth))
    disparity[rows, cols] = PINHOLE.fx * PINHOLE.baseline_m / face_depth
    v, u = np.nonzero(disparity > PINHOLE.fx * PINHOLE.baseline_m / 40.0)  # nearer than 40 m
    z_cam = PINHOLE.fx * PINHOLE.baseline_m / disparity[v, u]
    points = np.column_stack([z_cam, -(u - PINHOLE.cx) * z_cam / PINHOLE.fx, 1.8 - (v - PINHOLE.cy) * z_cam / PINHOLE.fy])
    on_face = (v >= rows.start) & (v < rows.stop) & (u >= cols.start) & (u < cols.stop)
    inside = on_face & (v >= rows.start + 2) & (v < rows.stop - 2)
    return disparity, points.astype(np.float32), np.column_stack([u, v]).astype(np.int32), on_face, inside


def _label(scene, config=None):
    from terrainmap.grid import cell_index

    disparity, points, pixels, _, _ = scene
    labels = np.full(len(points), Label.TERRAIN, np.uint8)
    out = label_upright(labels, points, cell_index(points, GRID), disparity, pixels, _surface(np.zeros(GRID.shape)),
                        GRID, PINHOLE, CAMERA, config or SegmentationConfig())
    assert (labels == Label.TERRAIN).all()  # the input is left alone
    return out == Label.OBSTACLE


def test_a_face_standing_up_is_labelled_obstacle_from_upright_above_m():
    scene = _scene(0.0, 0.5)
    _, points, _, on_face, inside = scene
    obstacle = _label(scene)
    face_above = inside & (points[:, 2] >= 0.15)
    assert face_above.sum() > 100 and obstacle[face_above].all()
    assert not obstacle[~on_face].any()  # the ground
    assert not obstacle[points[:, 2] < 0.15].any()  # the foot of the face: not far enough above the surface
    assert not _label(scene, SegmentationConfig(upright_above_m=0.6)).any()  # a face lower than that


def test_an_upright_stretch_lower_than_upright_min_height_m_is_not_taken():
    """0.2 m of upright face (7 rows at 18 m, as a streak of one disparity in SGBM's output) standing
    0.25 m up: its points stand above upright_above_m but its run is too short."""
    scene = _scene(0.25, 0.45)
    _, points, _, _, inside = scene
    assert inside.sum() > 30 and not _label(scene).any()
    assert _label(scene, SegmentationConfig(upright_min_height_m=0.15))[inside].all()


def test_the_cue_leaves_points_nearer_than_upright_min_range_m_to_the_height_cue():
    scene = _scene(0.0, 0.5)  # the face stands 18 m ahead
    assert _label(scene, SegmentationConfig(upright_min_range_m=17.0)).any()
    assert not _label(scene, SegmentationConfig(upright_min_range_m=19.0)).any()
    assert _label(scene, SegmentationConfig(upright_min_range_m=0.0)).any()  # 0: everywhere


def test_the_cue_is_off_on_ground_that_faces_the_camera_too_steeply():
    """Where the terrain's disparity gradient is under upright_min_ground_gradient (here set above
    level ground's), ground and faces look alike through stereo noise: nothing is taken."""
    config = SegmentationConfig(upright_min_ground_gradient=0.3 / 1.8 + 0.01)
    assert not _label(_scene(), config).any()


@pytest.mark.parametrize("field, value", [("upright_ratio", 1.0), ("upright_ratio", -0.1), ("upright_rows", 0),
                                          ("upright_min_height_m", 0.0), ("upright_min_ground_gradient", 0.0),
                                          ("upright_above_m", -1.0), ("upright_min_range_m", -1.0)])
def test_nonsense_upright_settings_are_named(field, value):
    with pytest.raises(ConfigError, match=f"segmentation.{field}"):
        SegmentationConfig(**{field: value}).validate()


def test_the_pipeline_takes_upright_points_as_obstacles_and_times_the_stage():
    """On a simulated frame: with the cue, the labels are those without it plus upright obstacle points."""
    from terrainmap.bench import sim_frame
    from terrainmap.config import Config
    from terrainmap.pipeline import PipelineState, process_frame

    frame = sim_frame(width=320, height=240)
    on, off = Config(), Config()
    off.segmentation.upright_ratio = 0.0
    with_cue, without = (process_frame(frame, c, PipelineState(c)) for c in (on, off))
    assert "upright" in with_cue.timings_ms and "upright" not in without.timings_ms
    changed = with_cue.point_labels != without.point_labels
    assert changed.any()
    assert (without.point_labels[changed] == Label.TERRAIN).all() and (with_cue.point_labels[changed] == Label.OBSTACLE).all()
    from terrainmap.grid import cell_index

    cells = np.bincount(cell_index(with_cue.points_vehicle[changed], on.grid), minlength=on.grid.shape[0] * on.grid.shape[1] + 1)
    held = cells[:-1].reshape(on.grid.shape) >= on.obstacles.min_cell_points  # the cells those points hold
    assert held.any() and (with_cue.layers["label"][held] == Label.OBSTACLE).all()
    others = ~held
    np.testing.assert_array_equal(with_cue.layers["label"][others], without.layers["label"][others])
