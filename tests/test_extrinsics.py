"""Camera extrinsics: pose helpers and the robust ground-plane fit (synthetic and KITTI 000005)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import load_kitti

from terrainmap.config import ExtrinsicsConfig
from terrainmap.errors import CalibrationError, FrameError
from terrainmap.extrinsics import (
    describe_extrinsics,
    estimate_extrinsics,
    extrinsics_from_calibration,
    extrinsics_from_pose,
)
from terrainmap.stereo import StereoMatcher, to_vehicle


def _scene_cam(extrinsics, rng, ground=4000, clutter=1500):
    """Ground points (z = 0, 2–14 m ahead) plus boxes and noise, in the camera optical frame."""
    x = rng.uniform(2, 14, ground)
    y = rng.uniform(-5, 5, ground)
    points = [np.column_stack([x, y, rng.normal(0, 0.01, ground)])]
    points.append(
        np.column_stack(
            [rng.uniform(5, 7, clutter), rng.uniform(1, 3, clutter), rng.uniform(0, 1.5, clutter)]
        )
    )
    points.append(
        np.column_stack([rng.uniform(2, 14, 300), rng.uniform(-5, 5, 300), rng.uniform(-1, 1, 300)])
    )
    vehicle = np.vstack(points)
    R, t = extrinsics.rotation, extrinsics.translation
    return ((vehicle - t) @ R).astype(np.float32)  # p_cam = Rᵀ (p_vehicle − t)


def test_pose_round_trip_and_sign_conventions():
    extrinsics = extrinsics_from_pose(
        1.4, pitch_rad=math.radians(5), roll_rad=math.radians(-3), yaw_rad=math.radians(2)
    )
    described = describe_extrinsics(extrinsics)
    assert described == pytest.approx({"height_m": 1.4, "pitch_deg": 5.0, "roll_deg": -3.0, "yaw_deg": 2.0})
    pitched = extrinsics_from_pose(1.0, pitch_rad=math.radians(10))
    optical_axis_vehicle = pitched.rotation @ np.array([0.0, 0.0, 1.0])
    assert optical_axis_vehicle[2] < 0  # pitch > 0 looks down
    rolled = extrinsics_from_pose(1.0, roll_rad=math.radians(10))
    right_vehicle = rolled.rotation @ np.array([1.0, 0.0, 0.0])  # camera x = right
    assert right_vehicle[2] < 0  # roll > 0 lowers the right side


@pytest.mark.parametrize(
    ("height", "pitch_deg", "roll_deg"), [(1.6, 0.5, -1.9), (2.5, 12.0, 4.0), (0.8, -3.0, 0.0)]
)
def test_estimate_recovers_synthetic_pose(height, pitch_deg, roll_deg):
    truth = extrinsics_from_pose(height, math.radians(pitch_deg), math.radians(roll_deg))
    points_cam = _scene_cam(truth, np.random.default_rng(1))
    estimate = estimate_extrinsics(points_cam, ExtrinsicsConfig(), rng=0)
    assert estimate.source == "estimated"
    described = describe_extrinsics(estimate)
    assert described["height_m"] == pytest.approx(height, abs=0.01)
    assert described["pitch_deg"] == pytest.approx(pitch_deg, abs=0.2)
    assert described["roll_deg"] == pytest.approx(roll_deg, abs=0.2)
    assert described["yaw_deg"] == pytest.approx(0.0, abs=1e-9)
    ground = to_vehicle(points_cam[:4000], estimate)
    assert np.median(np.abs(ground[:, 2])) < 0.02  # the ground lands on z = 0
    assert np.median(ground[:, 0]) > 0  # and ahead of the vehicle


def test_estimate_is_deterministic_given_a_seed():
    points_cam = _scene_cam(extrinsics_from_pose(1.5, 0.05, 0.02), np.random.default_rng(2))
    a = estimate_extrinsics(points_cam, rng=7)
    b = estimate_extrinsics(points_cam, rng=7)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    np.testing.assert_array_equal(a.translation, b.translation)


def test_too_few_points_fail_with_no_ground():
    with pytest.raises(FrameError, match="only 10 points below the camera") as info:
        estimate_extrinsics(np.tile([0.0, 1.0, 5.0], (10, 1)))
    assert info.value.reason == "no_ground"


def test_implausible_ground_fails():
    rng = np.random.default_rng(3)
    wall = np.column_stack(
        [rng.uniform(-3, 3, 2000), rng.uniform(0.1, 3, 2000), np.full(2000, 6.0)]
    )  # facing us
    with pytest.raises(FrameError) as info:
        estimate_extrinsics(wall.astype(np.float32))
    assert info.value.reason == "no_ground" and "plausible" in str(info.value)


def test_scattered_points_fail_with_too_few_inliers():
    rng = np.random.default_rng(4)
    cloud = np.column_stack([rng.uniform(-5, 5, 3000), rng.uniform(0.1, 5, 3000), rng.uniform(1, 14, 3000)])
    with pytest.raises(FrameError, match="near points lie on the best plane") as info:
        estimate_extrinsics(cloud.astype(np.float32))
    assert info.value.reason == "no_ground"


@pytest.mark.parametrize("seed", range(8))
def test_ground_points_along_one_line_fail_instead_of_giving_a_pose(seed):
    """Ground seen along one line (a kerb, a single row of texture) 6 m ahead, with 3 mm of noise:
    every plane through the line fits it, so the fit must not pick one (it gave heights of 0.5 to
    5 m and pitches of -9 to 42° for a level camera 1.5 m up)."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(-4, 4, 3000)
    line = np.column_stack([6 + rng.normal(0, 0.003, t.size), t, rng.normal(0, 0.003, t.size)])
    extrinsics = extrinsics_from_pose(1.5)
    with pytest.raises(FrameError, match="along a line") as info:
        estimate_extrinsics(((line - extrinsics.translation) @ extrinsics.rotation).astype(np.float32), rng=seed)
    assert info.value.reason == "no_ground"


def test_extrinsics_from_calibration_checks_the_rotation():
    pose = extrinsics_from_pose(1.2, 0.1)
    extrinsics = extrinsics_from_calibration(pose.rotation, pose.translation)
    assert extrinsics.source == "calibration"
    np.testing.assert_allclose(extrinsics.rotation, pose.rotation)
    with pytest.raises(CalibrationError, match="tf base_link: rotation is not a proper rotation"):
        extrinsics_from_calibration(2 * np.eye(3), np.zeros(3), name="tf base_link")
    with pytest.raises(CalibrationError, match="rotation must be 3×3"):
        extrinsics_from_calibration(np.eye(2), np.zeros(3))
    with pytest.raises(CalibrationError, match="tf: the camera must lie within 1000 m of the vehicle origin"):
        extrinsics_from_calibration(pose.rotation, [0, 0, 1e300], name="tf")  # a mount from a broken tf


@pytest.mark.parametrize(("pitch_deg", "roll_deg", "warned"), [(0, 0, False), (65, -40, False), (10, 180, False),
                                                              (-20, 0, False), (-45, 0, True)])
def test_a_camera_that_sees_no_ground_is_warned_about(caplog, pitch_deg, roll_deg, warned):
    """Pitched down steeply, rolled or upside down, a camera may be mounted; looking up it sees no ground."""
    pose = extrinsics_from_pose(1.5, math.radians(pitch_deg), math.radians(roll_deg))
    extrinsics_from_calibration(pose.rotation, pose.translation, name=f"calibration {pitch_deg} {roll_deg}")
    assert ("the camera looks 45° up" in caplog.text) == warned


def test_an_identity_rotation_is_warned_about_as_looking_up_once(caplog):
    """The likely slip of giving no optical-frame turn: the camera's z (forward) becomes the vehicle's up.
    Said once, though a library caller may build the extrinsics anew for every frame."""
    for _ in range(3):
        extrinsics_from_calibration(np.eye(3), [0, 0, 1.5], name="identity.yaml")
    assert caplog.text.count("identity.yaml: the camera looks 90° up, where it sees no ground") == 1
    assert "optical frame (x right, y down, z forward)" in caplog.text


@pytest.fixture(scope="module")
def kitti_points():
    """(GT-disparity points, SGBM points) of KITTI 000005 in the camera frame."""
    left, right, gt, calib = load_kitti()
    matcher = StereoMatcher(calib)
    points_gt, _ = matcher.reproject(gt)
    points_sgbm, _ = matcher.reproject(matcher.compute(left, right).disparity)
    return points_gt, points_sgbm


@pytest.mark.parametrize("which", [0, 1], ids=["gt_disparity", "sgbm"])
def test_kitti_camera_pose(kitti_points, which):
    """README: 1.62 m, |pitch| ≈ 0.5°, |roll| ≈ 1.9°; in our convention pitch < 0, roll > 0."""
    described = describe_extrinsics(estimate_extrinsics(kitti_points[which], rng=0))
    assert described["height_m"] == pytest.approx(1.62, abs=0.04)
    assert described["pitch_deg"] == pytest.approx(-0.5, abs=0.3)
    assert described["roll_deg"] == pytest.approx(1.9, abs=0.4)
