"""Tests of the simulator's rendering: determinism, geometry of the truth, stereo consistency, pose."""

from __future__ import annotations

import numpy as np
import pytest

from terrainmap.sim.render import Renderer
from terrainmap.sim.rig import CameraRig, vehicle_pose
from terrainmap.sim.scenes import SCENES, build_scene

SMALL = CameraRig(width=160, height=120, focal_px=125.0)


def _renderer(scene="mounds", seed=3, **kwargs) -> Renderer:
    return Renderer(build_scene(scene, seed, length_m=10.0), SMALL, seed=seed, **kwargs)


def _world_points(frame, rig: CameraRig) -> np.ndarray:
    """(H, W, 3) world points of the left depth image (NaN for sky)."""
    fx, fy, cx, cy = rig.intrinsics
    v, u = np.mgrid[0 : rig.height, 0 : rig.width]
    z = np.where(np.isfinite(frame.depth), frame.depth, np.nan).astype(np.float64)
    cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)
    base = cam @ rig.rotation_base_cam().T + rig.left_in_base()
    return base @ frame.rotation_world_base.T + frame.position_world_base


def test_same_seed_same_frame_other_seed_other_frame():
    a, b = _renderer(seed=3).frame(4), _renderer(seed=3).frame(4)
    for name in ("left", "right", "depth", "label", "instance"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = _renderer(seed=4).frame(4)
    assert not np.array_equal(a.left, c.left)
    assert not np.array_equal(a.depth, c.depth)


@pytest.mark.parametrize("scene", SCENES)
def test_every_scene_shows_sky_terrain_and_obstacles(scene):
    frame = _renderer(scene).frame(0)
    labels = set(np.unique(frame.label))
    assert labels == {1, 2} or labels == {0, 1, 2}
    assert (frame.label == 1).mean() > 0.3
    assert np.isinf(frame.depth[frame.label == 0]).all()
    assert np.isfinite(frame.depth[frame.label > 0]).all()
    visible = set(np.unique(frame.instance)) - {0}
    assert len(visible) >= 2
    assert visible <= {box.id for box in frame.obstacles}
    assert (frame.instance[frame.label != 2] == 0).all()


@pytest.mark.parametrize("scene", ["mounds", "canyon", "climb"])
def test_truth_depth_lands_on_the_terrain_or_an_obstacle(scene):
    renderer = _renderer(scene)
    frame = renderer.frame(5)
    points = _world_points(frame, SMALL)
    terrain = points[frame.label == 1]
    error = terrain[:, 2] - renderer.scene.terrain.height(terrain[:, 0], terrain[:, 1])
    assert np.percentile(np.abs(error), 99.9) < 0.002
    assert np.abs(error).max() < 0.01, np.abs(error).max()
    for box in frame.obstacles:
        mine = points[frame.instance == box.id]
        if not len(mine):
            continue
        local = box.to_local(mine) / (box.size_m / 2)
        # on the solid's surface: the box's largest normalised coordinate, or the ellipsoid's radius, is 1
        surface = np.abs(local).max(axis=1) if box.shape == "box" else np.linalg.norm(local, axis=1)
        assert np.allclose(surface, 1.0, atol=0.01), (box.kind, surface.min(), surface.max())


def test_ground_nearer_than_the_first_step_is_ground_not_sky():
    """A camera 0.15 m up, pitched 40° down, sees ground from 0.16 m (nearer than the marcher's
    first step, raycast.T_NEAR_M): the lower half of the image is terrain at the true depth."""
    rig = CameraRig(width=160, height=120, focal_px=125.0, camera_height_m=0.15, pitch_rad=np.radians(40))
    frame = Renderer(build_scene("flat", 1, length_m=10.0), rig, seed=1).frame(0)
    assert (frame.label[60:] == 1).all()
    world = _world_points(frame, rig)[60:]
    np.testing.assert_allclose(world[..., 2], build_scene("flat", 1, length_m=10.0).terrain.height(world[..., 0], world[..., 1]),
                               atol=2e-3)
    assert np.nanmin(frame.depth) < 0.17


def test_right_image_matches_the_left_through_the_true_disparity():
    renderer = _renderer("mounds", noise_dn=0.0, vignetting=0.0)
    frame = renderer.frame(2)
    fx = SMALL.focal_px
    v, u = np.nonzero((frame.label > 0) & np.isfinite(frame.depth))
    disparity = fx * SMALL.baseline_m / frame.depth[v, u]
    u_right = u - disparity
    inside = (u_right >= 0) & (u_right <= SMALL.width - 2)
    v, u, u_right = v[inside], u[inside], u_right[inside]
    u0 = np.floor(u_right).astype(int)
    w = u_right - u0
    right = frame.right.astype(float)
    sampled = (1 - w) * right[v, u0] + w * right[v, u0 + 1]
    diff = np.abs(sampled - frame.left[v, u].astype(float))
    assert np.median(diff) < 1.5, np.median(diff)
    assert np.percentile(diff, 80) < 4.0
    # the same comparison without the disparity shift is far worse: the test has teeth
    assert np.median(np.abs(right[v, u] - frame.left[v, u])) > 2 * np.median(diff)


def test_noise_is_gaussian_with_the_requested_sigma():
    """σ as asked, and the shape of a normal distribution: 38 % of the pixels within ±1 grey level
    (|noise| < 1.5 before rounding to whole levels) and a kurtosis of 3 (uniform noise of the same
    σ: 29 % and 1.8)."""
    clean = _renderer(noise_dn=0.0).frame(1).left.astype(float)
    noisy = _renderer(noise_dn=3.0).frame(1).left.astype(float)
    inner = (clean > 10) & (clean < 245)
    residual = noisy[inner] - clean[inner]
    sigma = np.std(residual)
    assert sigma == pytest.approx(3.0, rel=0.1)
    assert np.mean(np.abs(residual) <= 1) == pytest.approx(0.383, abs=0.03)
    assert np.mean((residual - residual.mean()) ** 4) / sigma**4 == pytest.approx(3.0, abs=0.4)


def test_texture_detail_keeps_finer_texture_on_distant_ground():
    """Twice the detail: more contrast between neighbouring pixels of terrain 10–20 m away."""

    def row_contrast(frame):
        ground = (frame.label == 1) & (frame.depth > 10) & (frame.depth < 20)
        both = ground[:, 1:] & ground[:, :-1]
        return np.mean(np.abs(np.diff(frame.left.astype(float), axis=1))[both])

    plain, sharp = (_renderer(noise_dn=0.0, texture_detail=k).frame(0) for k in (1.0, 2.0))
    assert row_contrast(sharp) > 1.3 * row_contrast(plain)
    np.testing.assert_array_equal(plain.depth, sharp.depth)  # the same scene, only its texture differs


def test_vehicle_pose_follows_the_terrain_slope():
    terrain = build_scene("climb", 0, length_m=40.0).terrain
    for x in (0.0, 20.0, 30.0):
        rotation, position = vehicle_pose(terrain, x, 0.0, 0.0)
        assert position[2] == pytest.approx(float(terrain.height(x, 0.0)), abs=0.05)
        slope = (terrain.height(x + 1.4, 0.0) - terrain.height(x - 1.4, 0.0)) / 2.8
        pitch_up = np.arctan2(rotation[2, 0], np.hypot(rotation[0, 0], rotation[1, 0]))
        assert pitch_up == pytest.approx(np.arctan(slope), abs=np.radians(1.5))
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    rotation, _ = vehicle_pose(terrain, 30.0, 0.0, 0.0)
    assert np.degrees(np.arcsin(rotation[2, 0])) > 8  # the climb really tilts the vehicle nose up


def test_moving_pedestrian_crosses_and_static_obstacles_stay():
    renderer = _renderer("mounds")
    first, later = renderer.frame(0), renderer.frame(10)
    walker = {b.id: b for b in first.obstacles if b.kind == "pedestrian"}
    assert walker
    for box in later.obstacles:
        before = next(b for b in first.obstacles if b.id == box.id)
        moved = np.linalg.norm(box.center_m[:2] - before.center_m[:2])
        expected = np.linalg.norm(box.velocity_mps[:2]) * 10 / renderer.fps
        assert moved == pytest.approx(expected, abs=1e-9)
    assert any(np.linalg.norm(b.velocity_mps) > 0.5 for b in walker.values())


@pytest.mark.parametrize("seed", [1, 2])
def test_no_obstacle_enters_the_vehicle_in_a_long_drive(seed):
    """A real log holds no obstacle inside the vehicle: over 200 frames (20 s) of every scene at
    the default speed, no obstacle's footprint (rectangle or ellipse) overlaps the wheel rectangle
    (walkers stop at the roadside or step off the track, the canyon's truck drives off ahead,
    ObstacleSpec.turns)."""
    from terrainmap.sim.rig import TRACK_M, WHEELBASE_M
    from terrainmap.sim.simulate import SimConfig

    s = np.linspace(-0.5, 0.5, 11)
    body = np.column_stack([np.repeat(s, s.size) * WHEELBASE_M, np.tile(s, s.size) * TRACK_M, np.zeros(s.size**2)])
    for name in SCENES:
        config = SimConfig(scene=name, seed=seed, frames=200)
        scene = build_scene(name, seed, length_m=config.length_m)
        for i in range(config.frames):
            time_s = i / config.fps
            rotation, position = vehicle_pose(scene.terrain, config.speed_mps * time_s, 0.0, 0.0)
            for spec in scene.obstacles:
                box = spec.at(scene.terrain, time_s)
                u, v = (box.to_local(body @ rotation.T + position)[:, :2] / (box.size_m[:2] / 2)).T
                inside = np.hypot(u, v) <= 1 if box.shape == "ellipsoid" else (np.abs(u) <= 1) & (np.abs(v) <= 1)
                assert not inside.any(), f"{name} frame {i}: {box.kind} {box.id} inside the vehicle"


def test_an_obstacle_turns_and_stops_where_its_spec_says():
    from terrainmap.sim.obstacles import ObstacleSpec

    spec = ObstacleSpec(1, "pedestrian", (26.0, 1.0), velocity_mps=(-1.0, 0.0),
                        turns=((2.0, (0.0, 1.0)), (3.5, (0.0, 0.0))))
    for time_s, xy, velocity, yaw in [(1.0, (25, 1), (-1, 0), np.pi), (2.0, (24, 1), (0, 1), np.pi / 2),
                                      (3.0, (24, 2), (0, 1), np.pi / 2), (9.0, (24, 2.5), (0, 0), np.pi / 2)]:
        at_xy, at_velocity, at_yaw = spec.motion(time_s)
        np.testing.assert_allclose(at_xy, xy, atol=1e-12)
        np.testing.assert_array_equal(at_velocity, velocity)
        assert at_yaw == pytest.approx(yaw)
    assert ObstacleSpec(2, "rock", (5.0, 1.0), yaw_rad=0.7).motion(4.0)[2] == 0.7  # static: its own yaw
    with pytest.raises(ValueError, match="in time order"):
        ObstacleSpec(3, "pedestrian", (0.0, 0.0), turns=((5.0, (0.0, 0.0)), (2.0, (0.0, 1.0))))


def test_truth_height_is_the_top_above_the_ground_at_the_centre():
    """An ellipsoid on a slope is centred on the lowest ground under it, so its top stands less
    than its nominal height above the ground at its centre: the truth height says how much."""
    from terrainmap.sim.heightfield import Heightfield
    from terrainmap.sim.obstacles import ObstacleSpec

    x = np.arange(100) * 0.1
    slope = Heightfield(np.repeat(0.3 * x[:, None], 100, axis=1).astype(np.float32), 0.0, 0.0, 0.1)  # 17°
    flat = Heightfield(np.zeros((100, 100), np.float32), 0.0, 0.0, 0.1)
    rock = ObstacleSpec(1, "rock", (5.0, 5.0), size_m=(0.7, 0.6, 0.5))
    car = ObstacleSpec(2, "car", (5.0, 5.0))
    assert rock.at(flat, 0.0).height_m == pytest.approx(0.5, abs=1e-6)
    on_slope = rock.at(slope, 0.0)
    top = on_slope.center_m[2] + on_slope.size_m[2] / 2
    assert on_slope.height_m == pytest.approx(top - slope.height(5.0, 5.0), abs=1e-6)
    assert on_slope.height_m == pytest.approx(0.5 - 0.3 * 0.35, abs=0.01)  # sunk by the slope over half its length
    assert car.at(slope, 0.0).height_m == pytest.approx(1.5, abs=1e-6)  # a box's top is placed that high


# --- geometry of the truth on hand-built scenes -------------------------------------------------------

def _plane(gx: float = 0.0, gy: float = 0.0):
    """Heightfield of the plane z = gx·x + gy·y over [0, 20] × [−10, 10] m at 0.1 m."""
    from terrainmap.sim.heightfield import Heightfield

    x, y = np.arange(200) * 0.1 + 0.05, np.arange(200) * 0.1 - 9.95
    return Heightfield((gx * x[:, None] + gy * y[None, :]).astype(np.float32), 0.0, -10.0, 0.1)


@pytest.mark.parametrize("shape", ["box", "ellipsoid"])
def test_a_ray_enters_a_solid_on_its_near_side(shape):
    """Rays from x = 0 along +x into a solid centred 10 m ahead, 2 m long: the hit is its entry at 9 m
    (the truth depth of the face the camera sees, not the back of the solid), the normal faces the camera."""
    from terrainmap.sim.obstacles import ObstacleBox

    solid = ObstacleBox(1, "rock", shape, np.array([10.0, 0.0, 0.5]), np.array([2.0, 1.0, 1.0]), 0.0, 1.0, np.zeros(3))
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.5, 0.0]], np.float32)  # the second one misses
    t, normal, _ = solid.intersect(np.array([0.0, 0.0, 0.5]), d)
    assert t[0] == pytest.approx(9.0, abs=1e-5) and np.isinf(t[1])
    np.testing.assert_allclose(normal[0], [-1.0, 0.0, 0.0], atol=1e-6)


def test_an_obstacles_length_lies_along_its_yaw():
    """A car (4.3 m long, 1.8 m wide) at yaw 90° is long along world y: a ray along +x meets its side
    0.9 m before its centre, its corners span 1.8 m in x and 4.3 m in y."""
    from terrainmap.sim.obstacles import ObstacleBox

    car = ObstacleBox(1, "car", "box", np.array([10.0, 0.0, 0.75]), np.array([4.3, 1.8, 1.5]), np.pi / 2, 1.5, np.zeros(3))
    corners = car.corners_world()
    np.testing.assert_allclose(np.ptp(corners, axis=0), [1.8, 4.3, 1.5], atol=1e-6)
    t, _, _ = car.intersect(np.array([0.0, 0.0, 0.75]), np.array([[1.0, 0.0, 0.0]], np.float32))
    assert t[0] == pytest.approx(9.1, abs=1e-5)
    np.testing.assert_allclose(car.to_local(np.array([[10.0, 2.0, 0.75]])), [[2.0, 0.0, 0.0]], atol=1e-12)


def test_a_box_on_a_slope_reaches_below_its_lowest_ground():
    """A box's bottom is 5 cm below the lowest terrain under its footprint (so no gap shows under it on a
    slope), its top its height above the ground at its centre."""
    from terrainmap.sim.obstacles import ObstacleSpec

    slope = _plane(gx=0.3)
    car = ObstacleSpec(1, "car", (10.0, 0.0)).at(slope, 0.0)
    bottom, top = car.center_m[2] - car.size_m[2] / 2, car.center_m[2] + car.size_m[2] / 2
    assert bottom == pytest.approx(0.3 * (10.0 - 4.3 / 2) - 0.05, abs=1e-4)
    assert top == pytest.approx(0.3 * 10.0 + 1.5, abs=1e-4)


@pytest.mark.parametrize("gx, gy", [(0.2, 0.0), (0.0, 0.2), (-0.1, 0.15)])
def test_the_vehicle_stands_on_a_plane_with_its_z_axis_along_the_normal(gx, gy):
    rotation, position = vehicle_pose(_plane(gx, gy), 10.0, 1.0, 0.0)
    np.testing.assert_allclose(rotation[:, 2], np.array([-gx, -gy, 1.0]) / np.sqrt(1 + gx * gx + gy * gy), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0)  # right-handed: y to the left of x
    assert rotation[1, 1] > 0.9 and rotation[0, 0] > 0.9  # heading +x
    assert position[2] == pytest.approx(10.0 * gx + 1.0 * gy, abs=1e-5)


TINY = CameraRig(width=64, height=48, focal_px=50.0)


def test_each_frame_and_camera_has_its_own_noise_and_frames_render_in_any_order():
    """Noise comes from (seed, frame, camera): left and right, frame 1 and frame 2 get different noise,
    and frame 2 is the same whether frame 1 was rendered before it or not."""
    scene = build_scene("flat", 2, length_m=10.0)
    clean = Renderer(scene, TINY, seed=2, noise_dn=0.0)
    noisy = Renderer(scene, TINY, seed=2, noise_dn=4.0)
    noise = {}
    for i in (1, 2):
        a, b = clean.frame(i), noisy.frame(i)
        noise[i] = [b.left.astype(int) - a.left, b.right.astype(int) - a.right]
    assert all(np.std(n) > 2 for pair in noise.values() for n in pair)
    assert np.corrcoef(noise[1][0].ravel(), noise[1][1].ravel())[0, 1] < 0.5  # left ≠ right
    assert np.corrcoef(noise[1][0].ravel(), noise[2][0].ravel())[0, 1] < 0.5  # frame 1 ≠ frame 2
    np.testing.assert_array_equal(Renderer(scene, TINY, seed=2, noise_dn=4.0).frame(2).left, noisy.frame(2).left)


