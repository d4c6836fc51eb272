"""Stereo front end: SGBM disparity, rectification and reprojection on real and synthetic pairs."""

from __future__ import annotations

import dataclasses
import re

import cv2
import numpy as np
import pytest
from conftest import load_kitti

from terrainmap import stereo
from terrainmap.config import StereoConfig
from terrainmap.errors import CalibrationError, ConfigError, InputError
from terrainmap.extrinsics import extrinsics_from_pose
from terrainmap.sim import SimConfig
from terrainmap.sim.scenes import build_scene
from terrainmap.stereo import StereoMatcher, _texture_energy, matching_pinhole, to_vehicle, trim_fattening
from terrainmap.types import StereoCalibration


@pytest.fixture(scope="module")
def kitti():
    """(left RGB, right RGB, GT disparity with NaN = unknown, calibration) of KITTI 000005_10."""
    return load_kitti()


@pytest.fixture(scope="module")
def kitti_result(kitti):
    left, right, gt, calib = kitti
    matcher = StereoMatcher(calib)
    return matcher, matcher.compute(left, right)


def test_kitti_disparity_matches_ground_truth(kitti, kitti_result):
    _, _, gt, _ = kitti
    _, result = kitti_result
    assert result.disparity.dtype == np.float32 and result.disparity.shape == gt.shape
    both = np.isfinite(gt) & np.isfinite(result.disparity)
    error = np.abs(result.disparity[both] - gt[both])
    assert both.sum() > 0.7 * np.isfinite(gt).sum()  # SGBM covers most of the GT pixels
    assert np.median(error) < 1.0
    assert np.mean(error > 3.0) < 0.15


def test_kitti_points_agree_with_ground_truth_points(kitti, kitti_result):
    _, _, gt, _ = kitti
    matcher, result = kitti_result
    points_sgbm, pixels_sgbm = matcher.reproject(result.disparity)
    points_gt, pixels_gt = matcher.reproject(gt)
    H, W = gt.shape
    gt_index = np.full(H * W, -1)
    gt_index[pixels_gt[:, 1] * W + pixels_gt[:, 0]] = np.arange(len(pixels_gt))
    match = gt_index[pixels_sgbm[:, 1] * W + pixels_sgbm[:, 0]]
    common = match >= 0
    assert common.sum() > 50000
    distance = np.linalg.norm(points_sgbm[common] - points_gt[match[common]], axis=1)
    relative = distance / points_gt[match[common], 2]
    assert np.median(relative) < 0.02  # depth error grows with range: compare relative to depth


def test_reprojection_formula_and_pixels(kitti, kitti_result):
    _, _, gt, calib = kitti
    matcher, _ = kitti_result
    points, pixels = matcher.reproject(gt)
    assert points.dtype == np.float32 and points.shape[1] == 3
    assert pixels.dtype == np.int32 and pixels.shape == (len(points), 2)
    d = gt[pixels[:, 1], pixels[:, 0]]
    z = calib.fx * calib.baseline_m / d
    np.testing.assert_allclose(points[:, 2], z, rtol=1e-5)
    np.testing.assert_allclose(points[:, 0], (pixels[:, 0] - calib.cx) * z / calib.fx, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(points[:, 1], (pixels[:, 1] - calib.cy) * z / calib.fy, rtol=1e-4, atol=1e-5)
    config = matcher.config
    assert points[:, 2].min() >= config.min_range_m * (1 - 1e-5)
    assert points[:, 2].max() <= config.max_range_m * (1 + 1e-5)
    in_range = np.isfinite(gt) & (
        calib.fx * calib.baseline_m / np.where(np.isfinite(gt), gt, 1) <= config.max_range_m
    )
    assert abs(len(points) - in_range.sum()) <= 0.001 * len(points)


def _textured(height: int, width: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (height // 2, width // 2), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(noise, (width, height), interpolation=cv2.INTER_NEAREST), (3, 3), 0)


@pytest.mark.parametrize("doffs", [0.0, 8.0])
def test_fronto_parallel_plane_depth(doffs):
    H, W, shift = 240, 320, 20
    texture = _textured(H, W + shift)
    left, right = (
        texture[:, :-shift],
        texture[:, shift:],
    )  # a point at u in the left is at u - shift in the right
    calib = StereoCalibration(W, H, fx=400.0, fy=400.0, cx=160.0, cy=120.0, baseline_m=0.3, doffs=doffs)
    matcher = StereoMatcher(calib, StereoConfig(num_disparities=48))
    result = matcher.compute(left, right)
    assert np.nanmedian(result.disparity) == pytest.approx(shift, abs=0.1)
    points, _ = matcher.reproject(result.disparity)
    assert np.median(points[:, 2]) == pytest.approx(400.0 * 0.3 / (shift + doffs), rel=0.01)


@pytest.mark.parametrize("margin", [16, 32])
def test_full_width_matches_the_left_border_up_to_the_margin(margin):
    """OpenCV leaves the leftmost num_disparities columns without disparity; ``full_width`` fills
    them wherever the match lies at least ``left_margin_px`` inside the right image."""
    H, W, shift, n = 120, 320, 12, 64
    texture = _textured(H, W + shift, seed=3)
    left, right = texture[:, :-shift], texture[:, shift:]
    calib = StereoCalibration(W, H, fx=400.0, fy=400.0, cx=160.0, cy=60.0, baseline_m=0.3)
    plain = StereoMatcher(calib, StereoConfig(num_disparities=n, min_texture=0, full_width=False)).compute(left, right)
    full = StereoMatcher(
        calib, StereoConfig(num_disparities=n, min_texture=0, left_margin_px=margin)
    ).compute(left, right)
    assert np.isnan(plain.disparity[:, :n]).all()
    first = margin + shift  # the first column whose match lies `margin` inside the right image
    assert np.isnan(full.disparity[:, :first]).all()
    border = full.disparity[:, first:n]
    assert np.isfinite(border).mean() > 0.9
    assert np.nanmedian(np.abs(border - shift)) < 0.1
    # the rest of the image is matched as before
    np.testing.assert_allclose(np.nanmedian(full.disparity[:, n:]), np.nanmedian(plain.disparity[:, n:]), atol=0.05)


@pytest.mark.parametrize("margin", [0, 4, 9])
def test_the_rightmost_columns_are_dropped(margin):
    H, W, shift = 120, 320, 12
    texture = _textured(H, W + shift, seed=4)
    calib = StereoCalibration(W, H, fx=400.0, fy=400.0, cx=160.0, cy=60.0, baseline_m=0.3)
    config = StereoConfig(num_disparities=48, min_texture=0, right_margin_px=margin)
    disparity = StereoMatcher(calib, config).compute(texture[:, :-shift], texture[:, shift:]).disparity
    assert np.isnan(disparity[:, W - margin :]).all()
    assert np.isfinite(disparity[:, W - margin - 10 : W - margin]).mean() > 0.9


@pytest.mark.parametrize("columns", [0, 1, 2, 3])
def test_trim_fattening_drops_the_near_side_of_depth_edges(columns):
    """Background 4 px with a slope of 0.1 px per column, a near block of 10 px in columns 20–29:
    ``columns`` disparities of the block are dropped at each of its edges, nothing else; a block
    beside invalid pixels has no edge there."""
    background = 4.0 + 0.1 * np.arange(60, dtype=np.float32)
    disparity = np.tile(background, (3, 1))
    disparity[:, 20:30] = 10.0
    disparity[2, 40:45] = 9.0
    disparity[2, 45:50] = np.nan  # the second block's right side touches no disparity
    trimmed = disparity.copy()
    trim_fattening(trimmed, 1.0, columns)
    dropped = np.isnan(trimmed) & ~np.isnan(disparity)
    expected = np.zeros_like(dropped)
    expected[:, 20 : 20 + columns] = expected[:, 30 - columns : 30] = True
    expected[2, 40 : 40 + columns] = True
    np.testing.assert_array_equal(dropped, expected)
    np.testing.assert_array_equal(trimmed[~dropped], disparity[~dropped])


def test_the_matcher_trims_a_near_surface_at_its_depth_edge():
    """A textured block 20 px of disparity in front of a background at 8 px: with
    ``fattening_trim_px`` the block's last columns before the background lose their disparities,
    and the background keeps all of its own."""
    H, W, bg, fg = 120, 320, 8, 20
    back, front = _textured(H, W + bg, seed=5), _textured(H, W + fg, seed=6)
    left, right = back[:, :W].copy(), back[:, bg:].copy()
    left[40:80, 150:200] = front[40:80, 170:220]  # the block's columns 150–199 in the left image
    right[40:80, 130:180] = front[40:80, 170:220]
    calib = StereoCalibration(W, H, fx=400.0, fy=400.0, cx=160.0, cy=60.0, baseline_m=0.3)
    plain, trimmed = (
        StereoMatcher(calib, StereoConfig(num_disparities=48, min_texture=0, fattening_trim_px=n))
        .compute(left, right)
        .disparity[45:75]
        for n in (0, 2)
    )
    assert np.nanmedian(plain[:, 160:190]) == pytest.approx(fg, abs=0.1)
    assert (plain[:, 198] > 14).all()  # the block reaches (nearly) to its edge at column 199 ...
    assert not (trimmed[:, 198:] > 14).any()  # ... and is cut two columns short of it
    np.testing.assert_array_equal(trimmed[:, 202:], plain[:, 202:])


def test_cx_right_offset_is_applied():
    calib = StereoCalibration(64, 48, 100.0, 100.0, 32.0, 24.0, 0.5, cx_right=28.0, doffs=1.0)
    matcher = StereoMatcher(calib)
    assert matcher.pinhole.doffs == pytest.approx(1.0 + 28.0 - 32.0)
    points, _ = matcher.reproject(np.full((48, 64), 13.0, np.float32))
    np.testing.assert_allclose(points[:, 2], 100.0 * 0.5 / 10.0, rtol=1e-6)


def test_reprojection_takes_each_axis_its_own_focal_length():
    """``X = (u − cx)·Z/fx`` and ``Y = (v − cy)·Z/fy`` on a camera whose fx and fy differ."""
    calib = StereoCalibration(64, 48, fx=100.0, fy=80.0, cx=30.0, cy=20.0, baseline_m=0.5)
    points, pixels = StereoMatcher(calib).reproject(np.full((48, 64), 10.0, np.float32))
    assert len(points) == 64 * 48
    np.testing.assert_allclose(points[:, 2], 5.0, rtol=1e-6)
    np.testing.assert_allclose(points[:, 0], (pixels[:, 0] - 30.0) * 5.0 / 100.0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(points[:, 1], (pixels[:, 1] - 20.0) * 5.0 / 80.0, rtol=1e-5, atol=1e-6)


def test_the_min_range_holds_with_a_disparity_offset():
    """With Middlebury's ``doffs`` (20 px, f·B = 50 px·m), disparities nearer than ``min_range_m`` (1 m)
    give no points: 25 and 29 px (1.11 m, 1.02 m) are kept, 31, 35 and 45 px (0.98 m and nearer) are not."""
    calib = StereoCalibration(64, 48, fx=100.0, fy=100.0, cx=32.0, cy=24.0, baseline_m=0.5, doffs=20.0)
    matcher = StereoMatcher(calib, StereoConfig(min_range_m=1.0))
    disparity = np.full((48, 64), np.nan, np.float32)
    disparity[10, :5] = [25.0, 29.0, 31.0, 35.0, 45.0]
    points, pixels = matcher.reproject(disparity)
    assert pixels[:, 0].tolist() == [0, 1]
    np.testing.assert_allclose(points[:, 2], [50 / 45, 50 / 49], rtol=1e-6)


def test_rectification_recovers_disparity():
    """An unrectified pair rendered from a fronto-parallel plane with known R, T, K, D."""
    H, W, f, B, depth = 240, 320, 300.0, 0.2, 4.0  # true disparity f·B/Z = 15 px
    K = np.array([[f, 0, 160.0], [0, f, 120.0], [0, 0, 1]])
    D = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    angle = np.radians(2.0)
    R = cv2.Rodrigues(np.array([0.0, angle, angle / 2]))[0]  # right camera relative to left
    T = np.array([-B, 0.0, 0.0])
    texture = _textured(1200, 1600, seed=1)  # the plane Z = depth, 16 m × 12 m, 1 cm per texel

    def render(rotation, translation):
        u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        rays = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K, D).reshape(-1, 2)
        rays = np.column_stack([rays, np.ones(len(rays))]) @ rotation  # camera → left frame directions
        centre = -rotation.T @ translation
        s = (depth - centre[2]) / rays[:, 2]
        hit = centre[:2] + rays[:, :2] * s[:, None]
        map_x = (hit[:, 0] * 100 + 800).reshape(H, W).astype(np.float32)
        map_y = (hit[:, 1] * 100 + 600).reshape(H, W).astype(np.float32)
        return cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR)

    left, right = render(np.eye(3), np.zeros(3)), render(R, T)
    calib = StereoCalibration(
        W, H, f, f, 160.0, 120.0, B, rectified=False, K_left=K, K_right=K, dist_left=D, dist_right=D, R=R, T=T
    )
    matcher = StereoMatcher(calib, StereoConfig(num_disparities=48))
    assert matcher.pinhole.baseline_m == pytest.approx(B, rel=1e-6)
    assert matching_pinhole(calib) == matcher.pinhole  # what `info` shows (sources.calibration.summary)
    result = matcher.compute(left, right)
    points, _ = matcher.reproject(result.disparity)
    assert np.isfinite(result.disparity).mean() > 0.5
    centroid = np.median(points, axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][2]
    assert abs(normal @ centroid) == pytest.approx(depth, rel=0.02)
    assert np.median(np.abs((points - centroid) @ normal)) < 0.05  # 0.2 px of disparity at 4 m
    assert np.median(points[:, 2]) == pytest.approx(depth, rel=0.02)
    # Points are in the left camera's own frame, not the rectified one (turned by R1, 2.2° here):
    # the plane's exact disparity in the rectified image gives Z = depth at every pixel.
    R1 = cv2.stereoRectify(K, D, K, D, (W, H), R, T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)[0]
    p = matcher.pinhole
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - p.cx) / p.fx, (v - p.cy) / p.fy, np.ones((H, W))], -1)  # rectified frame, z = 1
    rectified_depth = depth / (rays @ R1)[..., 2]  # (R1ᵀ·ray)_z: the ray's z in the camera frame
    exact, _ = matcher.reproject((p.fx * p.baseline_m / rectified_depth - p.doffs).astype(np.float32))
    np.testing.assert_allclose(exact[:, 2], depth, rtol=1e-5)


def test_to_vehicle_applies_rotation_and_translation():
    extrinsics = extrinsics_from_pose(1.5, pitch_rad=0.1, roll_rad=-0.05)
    points_cam = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    expected = points_cam @ extrinsics.rotation.T + extrinsics.translation
    points_vehicle = to_vehicle(points_cam, extrinsics)
    assert points_vehicle.dtype == np.float32 and points_vehicle.shape == (100, 3)
    np.testing.assert_allclose(points_vehicle, expected, atol=1e-5)
    assert to_vehicle(np.empty((0, 3), np.float32), extrinsics).shape == (0, 3)


GOOD = StereoCalibration(64, 48, 100.0, 100.0, 32.0, 24.0, 0.5, source="calib.yaml")
_K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
UNRECTIFIED = {"rectified": False, "K_left": _K, "K_right": _K, "dist_left": np.zeros(5), "dist_right": np.zeros(5),
               "R": np.eye(3), "T": np.array([-0.5, 0, 0])}


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"baseline_m": 0.0}, "baseline_m must be > 0"),
        ({"baseline_m": -0.3}, r"baseline_m must be > 0, got -0.3 \(left and right swapped\?\)"),
        ({"fx": 0.0}, "fx must be > 0"),
        ({"fy": float("nan")}, "fy must be > 0"),
        ({"width": 100_000, "height": 100_000},  # refused before 37 GiB of per-pixel tables are allocated
         r"calib.yaml: image size must be at most 16384 px a side and 67108864 pixels \(a 67 MP camera\), got 100000×100000"),
        ({"width": 10_000, "height": 10_000}, "image size must be at most"),
        ({"rectified": False}, "rectified is false, so K_left"),
        ({**UNRECTIFIED, "R": np.arange(9.0).reshape(3, 3)}, "R must be a rotation matrix"),
        ({**UNRECTIFIED, "K_left": np.zeros((3, 3))}, "K_left must be a camera matrix"),
        ({**UNRECTIFIED, "dist_right": np.zeros(3)}, "dist_right must hold 4, 5, 8, 12 or 14 coefficients"),
        ({**UNRECTIFIED, "dist_left": np.array([1e300, 0, 0, 0, 0])}, "dist_left must hold finite coefficients below 1e6"),
        ({**UNRECTIFIED, "dist_left": np.full(5, np.nan)}, "dist_left must hold finite coefficients"),
        ({**UNRECTIFIED, "K_left": np.array([[100.0, 100, 32], [100, 100, 24], [0, 0, 1]])},  # singular
         r"K_left must be a camera matrix \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
        ({**UNRECTIFIED, "K_right": np.diag([1e-300, 1e-300, 1.0])}, "K_right: fx must be within 1..1e"),
        ({**UNRECTIFIED, "K_right": np.diag([1e300, 1e300, 1.0])}, "K_right must be a camera matrix"),
        ({**UNRECTIFIED, "T": np.array([-1e300, 0, 0])}, r"T \(the baseline\) must be 0.001..100 m long, got 1e\+300"),
        ({**UNRECTIFIED, "T": np.array([-1e-5, 0, 0])}, r"T \(the baseline\) must be 0.001..100 m long"),
        ({**UNRECTIFIED, "T": np.array([0, 0, -0.5])}, "the cameras are not side by side .*forward-looking stereo"),
    ],
)
def test_bad_calibration_is_rejected(changes, message):
    with pytest.raises(CalibrationError, match=message) as info:
        StereoMatcher(dataclasses.replace(GOOD, **changes))
    assert "calib.yaml" in str(info.value) and "\n" not in str(info.value)


def test_camera_matrices_as_calibration_files_write_them_are_accepted():
    rounded = _K + [[0, 0.5, 0], [1e-17, 0, 0], [0, 0, 0]]  # skew, and a zero written with rounding
    StereoMatcher(dataclasses.replace(GOOD, **{**UNRECTIFIED, "K_left": rounded, "K_right": _K * [[1.01], [1], [1]]}))


def test_bad_images_are_rejected():
    matcher = StereoMatcher(GOOD)
    image = np.zeros((48, 64), np.uint8)
    with pytest.raises(CalibrationError, match="images are 80×48 but the calibration is for 64×48"):
        matcher.compute(np.zeros((48, 80), np.uint8), np.zeros((48, 80), np.uint8))
    with pytest.raises(CalibrationError, match="left image is 64×48 but right image is 64×40"):
        matcher.compute(image, np.zeros((40, 64), np.uint8))
    with pytest.raises(InputError, match="uint8"):
        matcher.compute(image.astype(np.float32), image)
    with pytest.raises(InputError, match="disparity is"):
        matcher.reproject(np.zeros((10, 10), np.float32))


@pytest.mark.parametrize("width, changes", [(15, {}), (640, {"num_disparities": 640}), (640, {"min_disparity": -96})])
def test_a_disparity_range_the_images_cannot_hold_is_rejected(width, changes):
    """OpenCV crashes (or searches only disparities without depth) otherwise."""
    calibration = dataclasses.replace(GOOD, width=width, cx=width / 2)
    with pytest.raises(CalibrationError, match="cannot be matched over disparities"):
        StereoMatcher(calibration, StereoConfig(**changes))


def test_same_setup_recognises_equal_calibration():
    matcher = StereoMatcher(GOOD)
    assert matcher.same_setup(dataclasses.replace(GOOD), StereoConfig())
    assert not matcher.same_setup(dataclasses.replace(GOOD, fx=101.0), StereoConfig())
    assert not matcher.same_setup(GOOD, StereoConfig(num_disparities=64))


def test_untextured_regions_give_no_disparity():
    """Sky-like noise only (σ = 2 grey levels) matches at random: the texture filter drops it."""
    rng = np.random.default_rng(0)
    h, w = 120, 200
    texture = rng.integers(0, 255, (h, w + 40)).astype(np.uint8)
    texture = cv2.GaussianBlur(texture, (3, 3), 0)
    left = texture[:, 20 : 20 + w].copy()
    right = texture[:, 28 : 28 + w].copy()  # 8 px disparity everywhere
    sky = (np.clip(rng.normal(128, 2, (h // 2, w)), 0, 255)).astype(np.uint8)
    left[: h // 2], right[: h // 2] = sky, np.clip(rng.normal(128, 2, (h // 2, w)), 0, 255).astype(np.uint8)
    calib = StereoCalibration(width=w, height=h, fx=100.0, fy=100.0, cx=w / 2, cy=h / 2, baseline_m=0.3)
    on = StereoMatcher(calib, StereoConfig(num_disparities=32)).compute(left, right).disparity
    off = StereoMatcher(calib, StereoConfig(num_disparities=32, min_texture=0)).compute(left, right).disparity
    inner = np.s_[h // 2 + 8 : h - 8, 48 : w - 8]
    assert np.nanmedian(on[inner]) == pytest.approx(8, abs=0.5)  # textured half kept
    assert np.isfinite(on[inner]).mean() > 0.9
    assert np.isfinite(on[8 : h // 2 - 8]).mean() < 0.05  # noise-only half dropped
    assert np.isfinite(off[8 : h // 2 - 8]).mean() > np.isfinite(on[8 : h // 2 - 8]).mean()


def _texture_kept(grey: np.ndarray, **fields) -> np.ndarray:
    """Which pixels of ``grey`` pass the texture filter under these StereoConfig fields."""
    config = StereoConfig(**fields)
    return _texture_energy(grey, config) >= config.min_texture**2


def test_x_gradient_ignores_horizontal_edges():
    """Horizontal stripes (a horizon, a roof line) vary only down the columns: SGBM, matching
    along rows, cannot lock on to them. The variance test keeps them, the x-gradient test drops
    them, and both keep texture that varies along the rows."""
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 2, (60, 80))
    stripes = np.where(np.arange(60)[:, None] // 4 % 2 == 0, 100.0, 160.0) + noise
    texture = cv2.GaussianBlur(rng.integers(0, 255, (60, 80)).astype(np.uint8), (3, 3), 0)
    for image, variance_keeps, gradient_keeps in ((stripes, 1.0, 0.0), (texture, 1.0, 1.0)):
        grey = np.clip(image, 0, 255).astype(np.uint8)
        inner = np.s_[8:-8, 8:-8]
        assert _texture_kept(grey)[inner].mean() == variance_keeps
        assert (
            _texture_kept(grey, texture_measure="x_gradient", min_texture=2.0)[inner].mean() == gradient_keeps
        )


def test_texture_margin_drops_the_band_beside_a_flat_region():
    """A window straddling flat sky and texture passes; with a margin, the sky pixels whose
    neighbouring window lies in the sky drop out, while texture farther in stays."""
    rng = np.random.default_rng(1)
    grey = np.clip(rng.normal(128, 2, (80, 80)), 0, 255).astype(np.uint8)  # sky: noise only
    grey[40:] = cv2.GaussianBlur(rng.integers(0, 255, (40, 80)).astype(np.uint8), (3, 3), 0)
    plain, margin = _texture_kept(grey), _texture_kept(grey, texture_margin_px=5)
    band = np.s_[36:40, 10:-10]  # sky rows whose 11×11 window reaches into the texture
    assert plain[band].all() and not margin[band].any()
    assert margin[52:-10, 10:-10].all() and not plain[:30].any()


def _sky_test_image(rng: np.random.Generator) -> np.ndarray:
    """120×200 grey image: noise-only sky (σ = 2) over textured ground from row 40, a flat patch
    closed in by texture in the sky's rows (a car's panel), and a flat dark strip down the left
    border below row 40 that touches the sky there."""
    grey = np.clip(rng.normal(128, 2, (120, 200)), 0, 255).astype(np.uint8)
    grey[40:] = cv2.GaussianBlur(rng.integers(0, 255, (80, 200)).astype(np.uint8), (3, 3), 0)
    grey[10:40, 120:180] = cv2.GaussianBlur(rng.integers(0, 255, (30, 60)).astype(np.uint8), (3, 3), 0)
    grey[18:32, 135:165] = np.clip(rng.normal(60, 2, (14, 30)), 0, 255).astype(np.uint8)  # the panel
    grey[40:, :12] = np.clip(rng.normal(20, 2, (80, 12)), 0, 255).astype(np.uint8)  # the dark strip
    return grey


def test_sky_is_the_flat_region_above_the_horizon_that_reaches_the_top():
    """The sky mask takes the flat region that reaches the top row, up to the skyline (its
    5×5 flatness test misses the last two rows, which the growth restores), and nothing that
    the texture closes in or that lies below the horizon, though flat and touching the sky."""
    from terrainmap.stereo import RectifiedPinhole, sky_mask

    grey = _sky_test_image(np.random.default_rng(3))
    pinhole = RectifiedPinhole(100.0, 100.0, 100.0, 40.0, 0.3, 0.0, 200, 120)  # horizon at row 40
    level = extrinsics_from_pose(1.5)
    sky = sky_mask(grey, pinhole, level, StereoConfig())
    assert sky[:40, :120].all() and sky[:10, 120:].all()  # the sky, down to the skyline
    assert not sky[40:, 12:].any()  # textured ground
    assert not sky[18:32, 135:165].any()  # the flat panel closed in by texture
    assert not sky[44:, :12].any()  # flat and touching the sky, but below the horizon
    assert sky[:40, 180:].all()  # sky to the right of the textured block reaches the top too
    assert not sky_mask(grey, pinhole, level, StereoConfig(min_texture=0)).any()
    down = extrinsics_from_pose(1.5, np.radians(40.0))  # pitched 40° down
    assert not sky_mask(grey, pinhole, down, StereoConfig()).any()  # a camera looking at the ground sees no sky


def test_sky_mask_takes_the_sky_disparities_of_a_rendered_frame_and_nothing_else():
    """On a simulated hills frame SGBM gives ~3200 sky pixels a near object's disparity (the band
    above the horizon, fringes beside silhouettes; they float 1–4 m above the ground): the sky
    mask takes every one of them (measured 3249 → 0) and not one terrain or obstacle pixel."""
    from terrainmap.stereo import sky_mask

    renderer = SimConfig(scene="hills", frames=1, seed=1).renderer(build_scene("hills", 1, length_m=10.0))
    frame, rig = renderer.frame(0), renderer.rig
    result = StereoMatcher(rig.calibration()).compute(frame.left, frame.right)
    sky = sky_mask(frame.left, result.pinhole, rig.extrinsics(), StereoConfig())
    matched = np.isfinite(result.disparity) & (result.disparity > 3)  # nearer than 50 m
    on_sky = matched & (frame.label == 0)
    assert on_sky.sum() > 1000
    assert (on_sky & ~sky).sum() < 0.02 * on_sky.sum()
    assert sky[frame.label == 0].mean() > 0.99
    assert not sky[frame.label != 0].any()


def test_the_sky_just_above_a_crest_ahead_is_sky_too():
    """Driving towards a crest (the simulated hills, ``--seed 5``, frame 13), the sky just above
    it is seen along rays that meet level ground 20–40 m away, and SGBM gives 1790 of its pixels
    the crest's disparity (measured; they became false obstacles): looking for sky down to rays
    that meet level ground at 20 m (``stereo.sky_beyond_m``) takes all but 10 of them, and not
    one terrain or obstacle pixel; at 40 m half of them stay."""
    from terrainmap.stereo import sky_mask

    config = SimConfig(scene="hills", frames=14, seed=5)
    renderer = config.renderer(build_scene("hills", 5, length_m=config.length_m))
    frame, rig = renderer.frame(13), renderer.rig
    result = StereoMatcher(rig.calibration()).compute(frame.left, frame.right)
    on_sky = np.isfinite(result.disparity) & (result.disparity > 3) & (frame.label == 0)
    sky, at_40 = (sky_mask(frame.left, result.pinhole, rig.extrinsics(), StereoConfig(sky_beyond_m=b))
                  for b in (20.0, 40.0))
    assert on_sky.sum() > 1000
    assert (on_sky & ~sky).sum() < 0.02 * on_sky.sum() and (on_sky & ~at_40).sum() > 0.3 * on_sky.sum()
    assert not sky[frame.label != 0].any()


def test_the_pipeline_drops_the_points_of_the_sky_unless_told_not_to():
    """``match_frame`` applies the sky mask once the camera pose is known (``stereo.drop_sky``)."""
    from terrainmap.config import Config
    from terrainmap.pipeline import PipelineState, match_frame
    from terrainmap.types import StereoFrame

    renderer = SimConfig(scene="hills", frames=1, seed=1).renderer(build_scene("hills", 1, length_m=10.0))
    rendered, rig = renderer.frame(0), renderer.rig
    frame = StereoFrame(0, rendered.stamp_ns, rendered.left, rendered.right, rig.calibration(), rig.extrinsics())
    on_sky = {}
    for drop in (True, False):
        config = Config()
        config.stereo.drop_sky = drop
        matched = match_frame(frame, config, PipelineState(config))
        on_sky[drop] = int((rendered.label[matched.pixels[:, 1], matched.pixels[:, 0]] == 0).sum())
    assert on_sky[False] > 1000 and on_sky[True] < 0.02 * on_sky[False]


def test_rows_that_see_only_sky_are_not_matched():
    """With the camera's extrinsics, ``compute`` finds the sky first and hands SGBM only the rows
    below the last row of nothing but sky, less a margin for the windows (the simulated hills
    frame shows 138 rows of 480 of nothing but sky). The disparities elsewhere are those of matching the whole frame and
    then dropping the sky, up to SGBM's sensitivity to where its image starts (its parallel
    stripes move)."""
    renderer = SimConfig(scene="hills", frames=1, seed=1).renderer(build_scene("hills", 1, length_m=10.0))
    frame, rig = renderer.frame(0), renderer.rig
    matcher, extrinsics = StereoMatcher(rig.calibration()), rig.extrinsics()
    whole = matcher.compute(frame.left, frame.right)
    matcher.drop_sky(whole, extrinsics)

    heights = []
    sgbm = matcher.sgbm

    class Recorder:
        def compute(self, left, right):
            heights.append(left.shape[0])
            return sgbm.compute(left, right)

    matcher.sgbm = Recorder()
    cropped = matcher.compute(frame.left, frame.right, extrinsics).disparity
    sky_rows = int(np.argmin(matcher.sky(whole.grey, extrinsics).all(axis=1)))
    assert sky_rows > 0.25 * frame.left.shape[0]
    assert heights == [frame.left.shape[0] - sky_rows + StereoConfig().texture_window]
    assert np.isnan(cropped[:sky_rows]).all()
    a, b = whole.disparity, cropped
    assert (np.isfinite(a) == np.isfinite(b)).mean() > 0.98
    both = np.isfinite(a) & np.isfinite(b)
    assert (np.abs(a[both] - b[both]) <= 1).mean() > 0.99


def test_single_pass_sgbm_reads_ground_low_and_two_pass_or_upside_down_averaging_does_not():
    """OpenCV's single-pass modes aggregate along paths from the rows above only, so on ground,
    whose disparity grows down the image, they read low; the two-pass modes, with paths from
    below too, do not (docs/accuracy.md), and neither does ``stereo.vertical_passes = 2``,
    which averages with a match of the pair turned upside down (it reads high by as much).
    Measured on the first frame of the simulated flat drive, ground pixels 2–35 m away:
    sgbm_3way −0.23 px (upside down +0.3 px), averaged +0.03 px, sgbm −0.6 px, hh4 −0.03 to +0.07 px."""
    renderer = SimConfig(scene="flat", frames=1, seed=1).renderer(build_scene("flat", 1, length_m=10.0))
    frame, calibration = renderer.frame(0), renderer.rig.calibration()
    truth = calibration.fx * calibration.baseline_m / frame.depth  # depth along the optical axis
    ground = (frame.label == 1) & (frame.depth < 35)
    bias, kept_share = {}, {}
    for name, fields in {
        "sgbm_3way": {},
        "hh4": {"mode": "hh4"},
        "two_passes": {"vertical_passes": 2},
    }.items():
        matcher = StereoMatcher(calibration, StereoConfig(**fields))
        disparity = matcher.compute(frame.left, frame.right).disparity
        kept = ground & np.isfinite(disparity)
        bias[name] = float(np.median(disparity[kept] - truth[kept]))
        kept_share[name] = kept.sum() / ground.sum()
    assert -0.35 < bias["sgbm_3way"] < -0.15
    assert abs(bias["hh4"]) < 0.1
    assert abs(bias["two_passes"]) < 0.1
    assert kept_share["two_passes"] > 0.95 * kept_share["sgbm_3way"]  # only disagreements drop
    strict = StereoMatcher(calibration, StereoConfig(vertical_passes=2, pass_tolerance_px=0.05))
    kept_strict = ground & np.isfinite(strict.compute(frame.left, frame.right).disparity)
    assert kept_strict.sum() < 0.5 * ground.sum() * kept_share["two_passes"]  # the passes rarely agree that well


def test_a_second_pass_on_the_far_rows_only_unbiases_far_ground_and_leaves_the_near_rows():
    """With the camera pose known, ``vertical_passes = 2`` matches upside down only the rows that
    see ground beyond ``vertical_passes_min_range_m``: there the ground reads unbiased, as with the
    whole second pass; nearer rows keep the single pass's values exactly."""
    renderer = SimConfig(scene="flat", frames=1, seed=1).renderer(build_scene("flat", 1, length_m=10.0))
    frame, calibration, extrinsics = renderer.frame(0), renderer.rig.calibration(), renderer.rig.extrinsics()
    truth = calibration.fx * calibration.baseline_m / frame.depth
    single = StereoMatcher(calibration, StereoConfig()).compute(frame.left, frame.right, extrinsics).disparity
    far_only = StereoMatcher(calibration, StereoConfig(vertical_passes=2, vertical_passes_min_range_m=8.0))
    disparity = far_only.compute(frame.left, frame.right, extrinsics).disparity
    ground = (frame.label == 1) & (frame.depth > 10) & (frame.depth < 35)
    kept = ground & np.isfinite(disparity)
    assert abs(np.median(disparity[kept] - truth[kept])) < 0.1
    near_rows = (frame.depth < 7.5).all(axis=1)  # every pixel nearer than 7.5 m: below the rows seeing 8 m
    assert near_rows.sum() > 100
    np.testing.assert_array_equal(disparity[near_rows], single[near_rows])
    with pytest.raises(ConfigError, match="stereo.vertical_passes_min_range_m"):
        StereoConfig(vertical_passes_min_range_m=-1).validate()


def test_a_second_pass_on_the_rows_of_near_ground_only_unbiases_them_and_leaves_the_rows_above():
    """``vertical_passes_max_range_m`` has the upside-down pass skip the rows above the first in
    which half the pixels lie nearer than it: on the hills, those rows keep the single pass's values
    exactly, and the ground below reads unbiased as with the whole second pass."""
    renderer = SimConfig(scene="hills", frames=1, seed=1).renderer(build_scene("hills", 1, length_m=10.0))
    frame, calibration = renderer.frame(0), renderer.rig.calibration()
    truth = calibration.fx * calibration.baseline_m / frame.depth
    single = StereoMatcher(calibration, StereoConfig()).compute(frame.left, frame.right).disparity
    band = StereoMatcher(calibration, StereoConfig(vertical_passes=2, vertical_passes_max_range_m=20.0))
    disparity = band.compute(frame.left, frame.right).disparity
    near = calibration.fx * calibration.baseline_m / 20.0
    first = int(np.argmax(np.count_nonzero(single >= near, axis=1) >= 0.5 * calibration.width))
    assert 150 < first < 300  # rows of sky and of ground beyond 20 m above it
    np.testing.assert_array_equal(disparity[:first], single[:first])
    ground = (frame.label == 1) & (frame.depth < 20)
    ground[:first] = False
    kept = ground & np.isfinite(disparity)
    assert kept.sum() > 0.95 * (ground & np.isfinite(single)).sum()  # only disagreements drop
    assert abs(np.median(disparity[kept] - truth[kept])) < 0.1
    both = kept & np.isfinite(single)
    assert np.median(single[both] - truth[both]) < -0.15  # what the second pass takes away
    with pytest.raises(ConfigError, match="stereo.vertical_passes_max_range_m"):
        StereoConfig(vertical_passes_max_range_m=float("nan")).validate()


def test_rig_camera_places_columns_in_the_rectified_image():
    from terrainmap.stereo import RectifiedPinhole, rig_camera

    turn = cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0]  # R1: the rectified camera turned 0.05 rad about its y
    pinhole = RectifiedPinhole(500.0, 500.0, 320.0, 240.0, 0.3, 0.0, 640, 480, tuple(turn.ravel()))
    extrinsics = extrinsics_from_pose(1.8, pitch_rad=0.1)
    camera = rig_camera(pinhole, extrinsics)
    assert (camera.fx_px, camera.cx_px, camera.width_px, camera.focal_baseline) == (500.0, 320.0, 640, 150.0)
    # A point on the rectified camera's optical axis (p_rect = R1·p_cam) appears at column cx.
    axis_cam = turn.T @ np.array([0.0, 0.0, 1.0])
    point = extrinsics.translation + np.asarray(extrinsics.rotation) @ (10.0 * axis_cam)
    assert camera.column(*point) == pytest.approx(320.0)
    # Unturned, the same point would appear 500·tan(0.05) ≈ 25 px off centre.
    assert abs(rig_camera(dataclasses.replace(pinhole, rectifying_rotation=None), extrinsics).column(*point) - 320.0) > 20


def test_the_pipeline_knows_the_image_columns_of_its_camera():
    from terrainmap.bench import sim_frame
    from terrainmap.config import Config
    from terrainmap.pipeline import PipelineState, match_frame

    config = Config()
    frame = sim_frame()
    camera = match_frame(frame, config, PipelineState(config)).camera
    assert camera.has_image and (camera.width_px, camera.cx_px) == (640, frame.calibration.cx)


@pytest.mark.parametrize("change, message", [
    ({"fx": "500"}, "fx must be a number, got '500'"),
    ({"width": 64.0}, "width must be an integer, got 64.0"),
    ({"cx": None}, "cx must be a number, got None"),
    ({"baseline_m": True}, "baseline_m must be a number, got True"),
])
def test_a_calibration_built_in_code_with_a_value_of_the_wrong_kind_names_the_field(change, message):
    calib = StereoCalibration(64, 48, fx=100.0, fy=100.0, cx=32.0, cy=24.0, baseline_m=0.5, source="rig.yaml")
    with pytest.raises(CalibrationError, match=f"rig.yaml: {re.escape(message)}"):
        StereoMatcher(dataclasses.replace(calib, **change))


def test_an_image_with_one_channel_axis_is_told_to_drop_it():
    calib = StereoCalibration(64, 48, fx=100.0, fy=100.0, cx=32.0, cy=24.0, baseline_m=0.5)
    image = np.zeros((48, 64, 1), np.uint8)
    with pytest.raises(InputError, match=r"left image has 1 channels, expected 3 or an H×W mono image \(give a mono"):
        StereoMatcher(calib).rectify(image, image)


@pytest.mark.parametrize("passes", [1, 2])
def test_matching_from_a_row_at_or_past_the_last_matches_nothing(passes):
    """``match(first_row=)`` at or past the image's last row (a frame all sky) gives an all-NaN
    disparity, not OpenCV's assertion on an empty image."""
    calibration = StereoCalibration(width=160, height=120, fx=120.0, fy=120.0, cx=80.0, cy=60.0, baseline_m=0.3)
    matcher = StereoMatcher(calibration, StereoConfig(vertical_passes=passes, vertical_passes_max_range_m=30))
    image = np.random.default_rng(0).integers(0, 255, (120, 160), dtype=np.uint8)
    for first_row in (119, 120, 500):
        disparity = matcher.match(image, image, first_row)
        assert disparity.shape == (120, 160) and np.isnan(disparity[:119]).all()


def test_threads_matching_at_once_each_use_an_sgbm_of_their_own_and_get_the_sequential_disparities():
    """OpenCV's SGBM keeps a work buffer between calls; the runner's worker threads share one
    matcher, so a call made while another thread matches with ``matcher.sgbm`` uses a copy of its
    settings (that copy made again when they change), and gets the same disparities."""
    from concurrent.futures import ThreadPoolExecutor

    renderer = SimConfig(scene="mounds", frames=4, seed=1, width=320, height=240, focal_px=250.0).renderer(
        build_scene("mounds", 1, length_m=20.0)
    )
    frames = [renderer.frame(i) for i in range(4)]
    matcher = StereoMatcher(renderer.rig.calibration())
    alone = [matcher.compute(f.left, f.right).disparity for f in frames]
    assert matcher._spares == []
    with ThreadPoolExecutor(2) as pool:
        together = list(pool.map(lambda f: matcher.compute(f.left, f.right).disparity, frames * 6))
    for got, want in zip(together, alone * 6, strict=True):
        np.testing.assert_array_equal(got, want)
    assert len(matcher._spares) <= 1

    with matcher._matching:  # another thread matching with matcher.sgbm: this call uses a copy
        np.testing.assert_array_equal(matcher.compute(frames[0].left, frames[0].right).disparity, alone[0])
        (spare,) = matcher._spares
        assert spare is not matcher.sgbm
        matcher.sgbm.setUniquenessRatio(60)  # a caller's tuning reaches the copies too
        tuned = matcher.compute(frames[0].left, frames[0].right).disparity
        assert matcher._spares[0].getUniquenessRatio() == 60
    np.testing.assert_array_equal(tuned, matcher.compute(frames[0].left, frames[0].right).disparity)
    assert np.isfinite(tuned).sum() < np.isfinite(alone[0]).sum()

    def written(sgbm) -> str:  # every setting OpenCV saves, not only those the copy reads
        storage = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
        sgbm.write(storage)
        return storage.releaseAndGetString()

    odd = cv2.StereoSGBM.create(3, 32, 7, 100, 900, 2, 31, 5, 50, 3, cv2.STEREO_SGBM_MODE_HH4)  # none a default
    assert written(stereo._copy_of(odd)) == written(odd)


@pytest.mark.parametrize(("change", "warned"), [
    ({}, None),
    ({"baseline_m": 53.27}, "a baseline of 53.27 m is unusually wide for a stereo rig; is it in metres (not cm)?"),
    ({"fx": 3.6, "fy": 3.6}, "a focal length of 3.6 px gives the 640 px wide images a field of view of 179°"),
    ({"cx": 5000.0}, "the principal point (5000, 240) lies outside the 640×480 images"),
    ({"cy": -3.0}, "the principal point (320, -3) lies outside the 640×480 images"),
])
def test_a_calibration_likely_in_the_wrong_unit_or_for_other_images_is_warned_about(caplog, change, warned):
    """Within the checked ranges, so used, but said once: the run would only end in "no ground"."""
    calibration = StereoCalibration(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0, baseline_m=0.3,
                                    source=f"calib {change}")
    calibration = dataclasses.replace(calibration, **change)
    with caplog.at_level("WARNING", logger="terrainmap.stereo"):
        for _ in range(3):
            stereo.check_calibration(calibration)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == (warned is not None)  # once, not once a frame
    assert warned is None or said[0].startswith(f"calib {change}: {warned}")


def test_a_raw_pair_with_t_given_the_other_way_round_says_how_opencv_gives_it():
    eye = np.eye(3).tolist()
    calibration = StereoCalibration(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, baseline_m=0.3,
                                    rectified=False, K_left=[[50, 0, 32], [0, 50, 24], [0, 0, 1]],
                                    K_right=[[50, 0, 32], [0, 50, 24], [0, 0, 1]], R=eye, T=[0.3, 0.0, 0.0],
                                    source="calib.yaml")
    with pytest.raises(CalibrationError, match=re.escape("swap the images, or give T as OpenCV's stereoCalibrate "
                                                         "does (the left camera's origin in the right camera's "
                                                         "frame: [-B, 0, 0] for a baseline of B m)")):
        stereo.check_calibration(calibration)
    stereo.check_calibration(dataclasses.replace(calibration, T=[-0.3, 0.0, 0.0]))


def test_a_camera_matrix_with_skew_is_warned_about_as_opencv_ignores_it(caplog):
    K = [[50, 0, 32], [0, 50, 24], [0, 0, 1]]
    skewed = [[50, 7.5, 32], [0, 50, 24], [0, 0, 1]]
    calibration = StereoCalibration(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, baseline_m=0.3,
                                    rectified=False, K_left=skewed, K_right=K, R=np.eye(3).tolist(),
                                    T=[-0.3, 0.0, 0.0], source="skewed.yaml")
    with caplog.at_level("WARNING", logger="terrainmap.stereo"):
        stereo.check_calibration(calibration)
        stereo.check_calibration(dataclasses.replace(calibration, K_left=K))
    assert [r.getMessage() for r in caplog.records] == [
        "skewed.yaml: K_left has a skew of 7.5 px (K[0][1]), which OpenCV's rectification ignores: the images are "
        "rectified as if it were 0"]
