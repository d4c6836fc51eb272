"""Obstacle tracking: confirmation, false-positive pruning, stable ids, leaving the area, poses."""

from __future__ import annotations

import numpy as np
import pytest
from obstacle_scenes import GRID, Plane, box_points, labelled, terrain_points

from terrainmap.config import ConfigError, GridConfig, ObstacleConfig, TrackingConfig
from terrainmap.errors import InputError
from terrainmap.obstacles import extract_obstacles
from terrainmap.tracking import ObstacleTracker
from terrainmap.types import Obstacle, StereoCamera

DT_NS = 100_000_000  # 10 Hz


def detection(x: float, y: float, kind: str = "positive", height: float = 1.0, footprint=(1.0, 1.0)) -> Obstacle:
    return Obstacle(
        center_m=np.array([x, y, height / 2]),
        size_m=np.array([*footprint, height]),
        yaw_rad=0.0,
        height_m=height,
        point_count=50,
        range_m=float(np.hypot(x, y)),
        kind=kind,
    )


def pose(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def test_static_obstacle_is_confirmed_on_its_second_frame_and_keeps_its_id():
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=2))
    (first,) = tracker.update([detection(10, 1)], 0)
    assert first.track_id >= 1 and not first.confirmed
    for k in range(1, 6):
        (out,) = tracker.update([detection(10 + 0.02 * (-1) ** k, 1)], k * DT_NS)
        assert out.track_id == first.track_id and out.confirmed
    np.testing.assert_allclose(out.center_m[:2], [10, 1], atol=0.05)
    assert np.linalg.norm(out.velocity_mps) < 0.5 and out.velocity_mps[2] == 0


def test_single_frame_false_positive_in_the_points_is_never_confirmed():
    """A spurious cluster injected into the points of one frame never becomes an obstacle."""
    plane = Plane()
    ground = terrain_points(plane, spacing=0.25)
    box = box_points(plane, (12.0, 0.0), 1.0, 1.0, 1.0)
    ghost = box_points(plane, (25.0, -5.0), 0.8, 0.8, 1.5)
    tracker = ObstacleTracker(TrackingConfig(), area=GRID)
    ghost_ids = set()
    for k in range(8):
        parts = (ground, box, ghost) if k == 3 else (ground, box)
        points, labels = labelled(plane, *parts)
        tracked = tracker.update(extract_obstacles(points, labels, GRID, plane, ObstacleConfig()), k * DT_NS)
        ghosts = [o for o in tracked if o.center_m[0] > 20]
        assert not any(o.confirmed for o in ghosts)
        ghost_ids |= {o.track_id for o in ghosts}
        assert len(ghosts) == (1 if k == 3 else 0)
    assert len(ghost_ids) == 1
    assert [o.confirmed for o in tracked] == [True]


@pytest.mark.parametrize("height", [0.5, 1.0])
def test_obstacle_from_half_a_metre_is_confirmed_within_three_frames(height):
    plane = Plane(gx=0.05)
    ground = terrain_points(plane, spacing=0.25)
    tracker = ObstacleTracker(TrackingConfig(), area=GRID)
    confirmed_at = None
    for k in range(6):
        parts = (ground,) if k < 2 else (ground, box_points(plane, (18.0, 3.0), 0.6, 0.6, height))
        points, labels = labelled(plane, *parts)
        tracked = tracker.update(extract_obstacles(points, labels, GRID, plane, ObstacleConfig()), k * DT_NS)
        if confirmed_at is None and any(o.confirmed for o in tracked):
            confirmed_at = k
    assert confirmed_at is not None and confirmed_at - 2 + 1 <= 3  # first visible at frame 2


def test_moving_obstacles_keep_their_ids_and_get_their_velocity():
    tracker = ObstacleTracker(TrackingConfig())
    va, vb = np.array([3.0, 0.5]), np.array([-1.0, -2.0])
    a0, b0 = np.array([8.0, -3.0]), np.array([20.0, 4.0])
    ids = None
    rng = np.random.default_rng(0)
    for k in range(15):
        t = k * DT_NS * 1e-9
        dets = [
            detection(*(a0 + va * t + rng.normal(0, 0.05, 2))),
            detection(*(b0 + vb * t + rng.normal(0, 0.05, 2))),
        ]
        out = tracker.update(dets[::-1] if k % 2 else dets, k * DT_NS)  # order must not matter
        by_x = sorted(out, key=lambda o: o.center_m[1])
        current = [o.track_id for o in by_x]
        assert ids is None or current == ids
        ids = current
    a, b = by_x
    np.testing.assert_allclose(a.velocity_mps[:2], va, atol=0.4)
    np.testing.assert_allclose(b.velocity_mps[:2], vb, atol=0.4)
    assert a.confirmed and b.confirmed


def test_track_leaving_the_area_is_dropped_at_once_and_its_id_not_reused():
    tracker = ObstacleTracker(TrackingConfig(max_misses=5), area=GRID)
    seen = set()
    x = 33.0
    for k in range(8):  # moving forward at 5 m/s across the far edge (36 m), unseen beyond it
        out = tracker.update([detection(x, 0)] if x < 36 else [], k * DT_NS)
        seen |= {o.track_id for o in out}
        x += 0.5
    # Predicted 0.5 m beyond the area → dropped without coasting through max_misses.
    assert out == [] and tracker.track_count == 0
    (new,) = tracker.update([detection(10, 0)], 8 * DT_NS)
    assert new.track_id not in seen


def test_track_leaving_the_area_across_its_left_edge_is_dropped():
    tracker = ObstacleTracker(TrackingConfig(max_misses=10), area=GRID)
    y = 8.0
    for k in range(10):  # moving left at 5 m/s across the left edge (+11 m), unseen beyond it
        out = tracker.update([detection(15.0, y)] if y < 11 else [], k * DT_NS)
        y += 0.5
    assert out == [] and tracker.track_count == 0  # 4 misses, well within max_misses


def test_a_tentative_track_is_dropped_at_its_first_miss():
    """Matched in fewer than ``confirm_hits`` frames, a track goes at its first miss (not after ``max_misses``)."""
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=3, max_misses=10))
    for k in range(2):
        (first,) = tracker.update([detection(10.0, 0)], k * DT_NS)
    assert not first.confirmed
    assert tracker.update([], 2 * DT_NS) == [] and tracker.track_count == 0
    (again,) = tracker.update([detection(10.0, 0)], 3 * DT_NS)
    assert again.track_id != first.track_id and not again.confirmed


def test_confirmed_track_coasts_through_misses_then_is_dropped():
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=2, max_misses=2, report_misses=2))
    for k in range(3):
        (out,) = tracker.update([detection(10 + 0.1 * k, 0)], k * DT_NS)
    track_id = out.track_id
    for k in range(3, 5):  # two misses: still reported, at the predicted position
        (coast,) = tracker.update([], k * DT_NS)
        assert coast.track_id == track_id and coast.confirmed
        assert coast.center_m[0] == pytest.approx(10 + 0.1 * k, abs=0.1)
    assert tracker.update([], 5 * DT_NS) == []  # third miss > max_misses
    assert tracker.track_count == 0


@pytest.mark.parametrize("gap", [3, 6])
def test_track_back_after_a_long_gap_keeps_its_id_and_is_confirmed_again(gap):
    """Back within ``reconfirm_misses`` (3) missed frames a track is an obstacle at once; after
    more (up to ``max_misses``, 10) it keeps its id but is confirmed only by ``confirm_hits``
    matches in a row again, like a new track."""
    tracker = ObstacleTracker(TrackingConfig())
    for k in range(2):
        (first,) = tracker.update([detection(10.0, 0)], k * DT_NS)
    assert first.confirmed
    for k in range(2, 2 + gap):
        assert tracker.update([], k * DT_NS) == []
    (back,) = tracker.update([detection(10.0, 0)], (2 + gap) * DT_NS)
    assert back.track_id == first.track_id and back.confirmed == (gap <= 3)
    (again,) = tracker.update([detection(10.0, 0)], (3 + gap) * DT_NS)
    assert again.track_id == first.track_id and again.confirmed


@pytest.mark.parametrize("gap_s", [1.0, 60.0, 3600.0])
def test_a_static_obstacle_keeps_its_id_over_a_gap_in_the_log(gap_s):
    """Its centre drifting 0.1 m/s while seen (the view changes), then no frame for ``gap_s``: the
    velocity carries its prediction over 1 s at most (``max_extrapolation_s``), not 6 m in 60 s."""
    tracker = ObstacleTracker(TrackingConfig())
    for k in range(10):
        (out,) = tracker.update([detection(10.0 + 0.01 * k, 0)], k * DT_NS)
    assert out.confirmed and out.velocity_mps[0] == pytest.approx(0.1, abs=0.03)
    (back,) = tracker.update([detection(10.09, 0)], 9 * DT_NS + int(gap_s * 1e9))
    assert back.track_id == out.track_id and back.center_m[0] == pytest.approx(10.09, abs=0.05)


@pytest.mark.parametrize("interval_s, speed", [(0.1, 0.8), (1.0, 0.8), (2.0, 0.8), (5.0, 0.3)])
def test_a_log_slower_than_the_extrapolation_limit_is_tracked_as_without_it(interval_s, speed):
    """Frames 2 or 5 s apart (a 0.5 Hz log, ``--every 20``) are no gap: the limit changes nothing
    (with it, an obstacle walking 0.8 m/s 2 s apart got 1.6 m/s: twice the distance a second)."""
    for config in (TrackingConfig(), TrackingConfig(max_extrapolation_s=1e6)):
        tracker = ObstacleTracker(config)
        for k in range(12):
            (out,) = tracker.update([detection(10.0 + speed * interval_s * k, 0)], k * int(interval_s * 1e9))
        if config.max_extrapolation_s == 1.0:
            limited = out
    assert limited.track_id == out.track_id == 1 and limited.velocity_mps[0] == out.velocity_mps[0]
    assert out.velocity_mps[0] == pytest.approx(speed, rel=0.15)


def test_coasting_track_is_not_reported_by_default_but_keeps_its_id():
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=2, max_misses=2))
    for k in range(3):
        (out,) = tracker.update([detection(10.0, 0)], k * DT_NS)
    assert out.confirmed
    assert tracker.update([], 3 * DT_NS) == []  # missed: not an obstacle this frame
    assert tracker.track_count == 1
    (back,) = tracker.update([detection(10.0, 0)], 4 * DT_NS)
    assert back.track_id == out.track_id and back.confirmed


def test_world_frame_tracking_with_vehicle_pose():
    """A static obstacle seen from a vehicle driving at 5 m/s: standing still in the world frame."""
    with_pose = ObstacleTracker(TrackingConfig())
    without = ObstacleTracker(TrackingConfig())
    yaw = 0.3
    heading = np.array([np.cos(yaw), np.sin(yaw)])
    world_xy = np.array([25.0, 10.0])
    for k in range(10):
        vehicle_xy = heading * 5.0 * k * 0.1
        rel = world_xy - vehicle_xy
        local = np.array([rel @ heading, rel @ [-heading[1], heading[0]]])
        dets = [detection(*local)]
        (a,) = with_pose.update(dets, k * DT_NS, pose(*vehicle_xy, yaw))
        (b,) = without.update(dets, k * DT_NS)
    np.testing.assert_allclose(a.center_m[:2], local, atol=0.05)  # reported in the vehicle frame
    assert a.center_m[2] == pytest.approx(0.5)
    assert np.linalg.norm(a.velocity_mps) < 0.2  # over ground
    np.testing.assert_allclose(b.velocity_mps[:2], [-5.0, 0.0], atol=0.3)  # relative to the vehicle
    assert a.track_id == 1 and b.track_id == 1


def test_with_a_pose_a_moving_obstacle_is_reported_with_vehicle_frame_heading_and_velocity():
    """Tracks live in the world frame; what is reported goes back to the vehicle's axes: the box's
    heading as detected, and the velocity over ground turned into the vehicle frame."""
    import dataclasses

    tracker = ObstacleTracker(TrackingConfig())
    yaw = 0.3
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])  # vehicle → world
    velocity_world = np.array([1.0, 0.5])
    for k in range(10):
        t = k * 0.1
        vehicle_xy = rot[:, 0] * 5.0 * t
        local = rot.T @ (np.array([25.0, 10.0]) + velocity_world * t - vehicle_xy)
        det = dataclasses.replace(detection(*local), yaw_rad=0.2)  # the box's heading, vehicle frame
        (out,) = tracker.update([det], k * DT_NS, pose(*vehicle_xy, yaw))
    assert out.yaw_rad == pytest.approx(0.2, abs=1e-6)
    np.testing.assert_allclose(out.velocity_mps[:2], rot.T @ velocity_world, atol=0.15)


def test_positive_and_negative_obstacles_do_not_associate():
    tracker = ObstacleTracker(TrackingConfig())
    (pos,) = tracker.update([detection(10, 0, "positive")], 0)
    out = tracker.update([detection(10, 0, "negative")], DT_NS)
    assert [o.kind for o in out] == ["negative"] and out[0].track_id != pos.track_id


def test_far_detection_outside_the_gate_starts_a_new_track():
    tracker = ObstacleTracker(TrackingConfig(gate_m=1.0))
    (a,) = tracker.update([detection(10, 0)], 0)
    (b,) = tracker.update([detection(12, 0)], DT_NS)
    assert b.track_id != a.track_id and not b.confirmed



def test_track_missing_its_obstacle_does_not_take_a_neighbours_detection():
    """A frame without B's detection, but with A's and a fragment of A's: matching as many pairs
    as possible would give B A's detection (1.6 m, inside the gate) and A the fragment (0.7 m),
    and switch A's id; A keeps its obstacle and B coasts."""
    tracker = ObstacleTracker(TrackingConfig(gate_m=2.0))
    for k in range(2):
        a, b = tracker.update([detection(10, 0), detection(10, 1.6)], k * DT_NS)
    out = tracker.update([detection(10, 0), detection(10, -0.7)], 2 * DT_NS)
    ids = {o.track_id: o.center_m[1] for o in out}
    assert ids[a.track_id] == pytest.approx(0, abs=0.05)
    assert b.track_id not in ids

@pytest.mark.parametrize("radius", [1.5, 0.0])
def test_fragment_beside_a_confirmed_track_starts_no_track(radius):
    """A second cluster of an obstacle already tracked (1 m from it) starts no track of its own;
    one 3 m away does, and so does the fragment with the rule off."""
    tracker = ObstacleTracker(TrackingConfig(fragment_radius_m=radius))
    for k in range(2):
        (track,) = tracker.update([detection(10, 0)], k * DT_NS)
    out = tracker.update([detection(10, 0), detection(11, 0), detection(13, 0)], 2 * DT_NS)
    starts = sorted(o.center_m[0] for o in out if o.track_id != track.track_id)
    assert [o.center_m[0] for o in out if o.track_id == track.track_id] == pytest.approx([10])
    assert starts == pytest.approx([13] if radius else [11, 13])
    # the fragment is a part of the track: it occupies cells in the cost layer as the track does
    assert [(p.center_m[0], p.track_id, p.confirmed) for p in tracker.parts] == (
        [(11, track.track_id, True)] if radius else [])
    tracker.update([detection(10, 0)], 3 * DT_NS)
    assert tracker.parts == []  # a frame's parts only


def test_lower_cluster_in_a_confirmed_obstacles_shadow_starts_no_track():
    """A car 4.3 m long seen as two clusters as it comes into range: its far part, 3.6 m behind the
    tracked near part along the line of sight, lies in the near part's shadow (within the bearings
    of its footprint, up to ``fragment_radius_m`` beyond it) and starts no track. Detections in
    front of it, beside it, farther behind or taller (a person over a low rock) do."""
    def box(x, y, length, height):
        return detection(x, y, height=height, footprint=(length, 1.8))

    tracker = ObstacleTracker(TrackingConfig())
    for k in range(2):
        (car,) = tracker.update([box(17.0, 3.0, 4.3, 1.5)], k * DT_NS)
    others = {"far part": box(20.6, 3.2, 1.0, 1.0), "taller": box(20.8, 2.6, 0.5, 1.8),
              "in front": box(13.5, 2.6, 0.5, 1.0), "beyond": box(23.0, 3.4, 0.5, 1.0),
              "beside": box(17.0, 5.5, 0.5, 1.0)}  # fmt: skip
    out = tracker.update([box(17.0, 3.0, 4.3, 1.5), *others.values()], 2 * DT_NS)
    started = {tuple(o.center_m[:2].round(1)) for o in out if o.track_id != car.track_id}
    assert started == {tuple(d.center_m[:2].round(1)) for name, d in others.items() if name != "far part"}
    (part,) = tracker.parts
    assert part.track_id == car.track_id and part.center_m[:2] == pytest.approx(others["far part"].center_m[:2])
    off = ObstacleTracker(TrackingConfig(fragment_radius_m=0))
    for k in range(2):
        off.update([box(17.0, 3.0, 4.3, 1.5)], k * DT_NS)
    assert len(off.update([box(17.0, 3.0, 4.3, 1.5), *others.values()], 2 * DT_NS)) == 6


def test_parts_name_the_track_kept_when_theirs_is_merged_away():
    """Two confirmed tracks 1 m apart merge (one obstacle) after the fragment beside them was
    taken for a part of the one that goes: the part names the track that stays."""
    tracker = ObstacleTracker(TrackingConfig())
    tracker.update([detection(14, -2), detection(13, -2)], 0)
    out = tracker.update([detection(14, -2), detection(13, -2), detection(12, -2.5, height=0.5)], DT_NS)
    assert [p.track_id for p in tracker.parts] == [o.track_id for o in out]


def test_coasting_tracks_are_placed_in_the_last_frames_vehicle_frame():
    """A static obstacle (odometry frame) missed while the vehicle drives on is given for the cost
    at its place in the current vehicle frame, whatever the caller does with its pose array later;
    a frame logged twice keeps its parts, and an update that fails leaves none."""
    tracker = ObstacleTracker(TrackingConfig())
    for k in range(2):
        tracker.update([detection(10 - k, 0)], k * DT_NS, pose(float(k)))
    moving = pose(3.0)
    assert tracker.update([], 2 * DT_NS, moving) == []
    moving[0, 3] = 100.0  # the caller reuses its array
    (coasting,) = tracker.coasting(3)
    assert coasting.center_m[:2] == pytest.approx([7.0, 0.0], abs=0.05) and coasting.confirmed
    assert tracker.coasting(0) == []
    tracker.update([detection(7, 0), detection(8, 0)], 3 * DT_NS, pose(3.0))
    (part,) = tracker.parts
    tracker.update([detection(7, 0), detection(8, 0)], 3 * DT_NS, pose(3.0))  # logged twice
    assert tracker.parts == [part]
    with pytest.raises(InputError):
        tracker.update([detection(float("nan"), 0)], 4 * DT_NS, pose(3.0))
    assert tracker.parts == []


def test_stamp_going_back_resets_the_tracks(caplog):
    tracker = ObstacleTracker(TrackingConfig())
    tracker.update([detection(10, 0)], 5 * DT_NS)
    (out,) = tracker.update([detection(10, 0)], 6 * DT_NS)
    assert out.confirmed
    (after,) = tracker.update([detection(10, 0)], DT_NS)
    assert not after.confirmed and after.track_id != out.track_id
    tracker.update([detection(10, 0)], 9 * DT_NS, pose(100.0))
    tracker.update([detection(10, 0)], 8 * DT_NS, pose(100.0))  # back in time, with a pose
    assert tracker.in_world_frame
    warnings = [r for r in caplog.records if r.levelname == "WARNING" and "older than the previous" in r.getMessage()]
    assert len(warnings) == 1  # a log whose stamps keep going back is not one warning a frame


def test_switching_between_pose_and_no_pose_resets_the_tracks():
    tracker = ObstacleTracker(TrackingConfig())
    (a,) = tracker.update([detection(10, 0)], 0, pose(100.0))
    (b,) = tracker.update([detection(10, 0)], DT_NS)
    assert b.track_id != a.track_id and not b.confirmed


@pytest.mark.parametrize("bad", [np.eye(3), np.diag([2.0, 2.0, 2.0, 1.0]), np.diag([1.0, 1.0, -1.0, 1.0]),
                                 np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]])])
def test_a_pose_that_is_no_rigid_motion_raises_input_error(bad):
    """A scaled, mirrored or projective pose would move every track (a box 10 m ahead reported 40 m
    ahead under a scale of 2): refused, as the frame's extrinsics are."""
    with pytest.raises(InputError, match="vehicle_pose"):
        ObstacleTracker(TrackingConfig()).update([], 0, bad)


@pytest.mark.parametrize("x", [np.nan, np.inf, 1e300])
def test_a_detection_that_is_not_finite_is_refused_before_it_reaches_a_track(x):
    tracker = ObstacleTracker(TrackingConfig())
    with pytest.raises(InputError, match="finite centre"):
        tracker.update([detection(x, 0)], 0)
    assert tracker.track_count == 0
    assert len(tracker.update([detection(10, 0)], DT_NS)) == 1  # the tracker goes on


@pytest.mark.parametrize("stamp", [None, "abc", 1.5, True])
def test_a_stamp_that_is_not_whole_nanoseconds_is_refused(stamp):
    with pytest.raises(InputError, match="stamp"):
        ObstacleTracker(TrackingConfig()).update([detection(10, 0)], stamp)


def test_many_detections_are_tracked_quickly():
    rng = np.random.default_rng(2)
    xy = rng.uniform([3, -10], [35, 10], (300, 2))
    # 300 obstacles packed closer than the fragment radius: neither fragments nor duplicates here
    tracker = ObstacleTracker(TrackingConfig(gate_m=0.3, fragment_radius_m=0), area=GridConfig())
    for k in range(3):
        out = tracker.update([detection(*p) for p in xy + rng.normal(0, 0.02, xy.shape)], k * DT_NS)
    assert len(out) == 300 and all(o.confirmed for o in out)
    assert len({o.track_id for o in out}) == 300


@pytest.mark.parametrize(
    "field",
    ["confirm_hits", "gate_m", "measurement_std_m", "acceleration_std_mps2", "initial_velocity_std_mps"],
)
def test_config_rejects_nonsense(field):
    with pytest.raises(ConfigError, match=f"tracking.{field}"):
        TrackingConfig(**{field: 0}).validate()
    with pytest.raises(ConfigError, match="tracking.fragment_radius_m"):
        TrackingConfig(fragment_radius_m=-1).validate()
    with pytest.raises(ConfigError, match="tracking.duplicate_depth_sigmas"):
        TrackingConfig(duplicate_depth_sigmas=float("nan")).validate()
    with pytest.raises(ConfigError, match="tracking.max_misses"):
        TrackingConfig(max_misses=-1).validate()
    with pytest.raises(ConfigError, match="tracking.report_misses"):
        TrackingConfig(max_misses=2, report_misses=3).validate()


def test_stereo_shift_grows_with_the_square_of_range_along_the_ray():
    camera = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)
    shift = camera.shift_per_px(np.array([[10.0, 0.0, 1.8], [20.0, 0.0, 1.8], [20.0, 5.0, 1.8]]))
    np.testing.assert_allclose(shift[0], [100 / 150, 0, 0])
    np.testing.assert_allclose(shift[1], [400 / 150, 0, 0])  # twice the range, four times the shift
    np.testing.assert_allclose(shift[2], np.array([20, 5, 0]) * 20 / 150)  # along the ray


def test_depth_jitter_of_a_far_obstacle_is_not_read_as_motion():
    """A static obstacle 18 m ahead whose detected centre jumps 0.6 m in range, then 1.2 m back (a
    quarter pixel of disparity is 0.6 m there): with the rig, the track's speed stays under
    0.6 m/s; without it, the first jump alone reads as 2 m/s (measured 0.41–0.50 against 2.0)."""
    camera = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)
    speeds = {}
    for rig in (camera, None):
        tracker = ObstacleTracker(TrackingConfig())
        speeds[rig is not None] = []
        for k, x in enumerate([18.0, 18.6, 17.4]):
            (out,) = tracker.update([detection(x, 1.0)], k * DT_NS, camera=rig)
            speeds[rig is not None].append(float(np.hypot(*out.velocity_mps[:2])))
    assert max(speeds[True]) < 0.6
    assert min(speeds[False][1:]) > 1.5


RIG = StereoCamera(np.array([0.0, 0.0, 1.8]), np.array([1.0, 0.0, 0.0]), 150.0)


@pytest.mark.parametrize(
    "second, camera, merged",
    [
        ((19.8, 0.0), RIG, True),  # 1.8 m behind, at 18 m: within 3 depth errors (0.65 m each)
        ((19.8, 0.0), None, False),  # without the rig, 1.8 m is beyond the 1.5 m radius
        ((18.0, 1.8), RIG, False),  # 1.8 m beside: depth error does not reach across the ray
    ],
)
def test_two_confirmed_tracks_on_one_obstacle_are_merged_into_the_older(second, camera, merged):
    """A person at 18 m whose cluster jumps in depth can leave two tracks on it, which then take
    its detection in turn (an id switch each time): they are one obstacle when they lie within
    the fragment radius (1.5 m) across the line of sight and within 3 disparity errors along it."""
    tracker = ObstacleTracker(TrackingConfig(), area=GridConfig())
    for k in range(2):
        (first,) = tracker.update([detection(18.0, 0.0)], k * DT_NS, camera=camera)
    for k in range(2, 4):  # a second, taller cluster 1.8 m away starts a track and confirms it
        out = tracker.update([detection(18.0, 0.0), detection(*second, height=1.2)], k * DT_NS, camera=camera)
    ids = [o.track_id for o in out]
    assert all(o.confirmed for o in out) and first.track_id in ids
    assert len(ids) == (1 if merged else 2)


def test_a_merged_track_takes_over_the_detection_it_had_alone():
    """When only the younger duplicate was matched in a frame, the older one keeps its id and
    takes over the younger one's position and detection, so the obstacle stays reported."""
    tracker = ObstacleTracker(TrackingConfig(gate_m=2.5), area=GridConfig())
    for k in range(2):
        (first,) = tracker.update([detection(18.0, 0.0)], k * DT_NS, camera=RIG)
    # a second cluster 2.1 m behind (beyond the fragment radius) starts a track, then is the only one
    tracker.update([detection(18.0, 0.0), detection(20.1, 0.0)], 2 * DT_NS, camera=RIG)
    (out,) = tracker.update([detection(20.1, 0.0)], 3 * DT_NS, camera=RIG)
    assert out.track_id == first.track_id and out.confirmed  # merged on confirmation
    assert out.center_m[0] == pytest.approx(20.1, abs=0.1)
    assert tracker.track_count == 1


def test_a_merge_with_a_track_back_from_a_long_gap_keeps_the_obstacle_confirmed():
    """A track back after more than ``reconfirm_misses`` misses is not confirmed until seen again
    in a row; merged with the confirmed track that followed the obstacle meanwhile, the obstacle
    stays confirmed (and in the cost layer) under the older track's id."""
    tracker = ObstacleTracker(TrackingConfig())
    for k in range(10):
        (old,) = tracker.update([detection(10.0, 0.0, footprint=(0.5, 0.5))], k * DT_NS)
    for k in range(10, 15):  # the old track unseen; the obstacle seen 2.3 m on (beyond the gate)
        (new,) = tracker.update([detection(12.3, 0.0, footprint=(0.5, 0.5))], k * DT_NS)
        assert new.confirmed or k == 10
    out = tracker.update([detection(10.0, 0.0, footprint=(0.5, 0.5)), detection(10.6, 0.0, footprint=(0.5, 0.5))],
                         15 * DT_NS)
    assert [(o.track_id, o.confirmed) for o in out] == [(old.track_id, True)]


def test_a_frame_logged_twice_is_no_second_sighting():
    """A log that holds one frame twice (the same stamp again): a one-frame detection seen in both
    copies is still a single-frame false positive, and no track counts a miss."""
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=2, max_misses=1))
    for _ in range(2):
        (out,) = tracker.update([detection(20.0, -5.0)], DT_NS)
        assert not out.confirmed
    assert tracker.update([], 2 * DT_NS) == []  # unconfirmed and missed: dropped
    for k in range(3, 5):
        (out,) = tracker.update([detection(10.0, 0.0)], k * DT_NS)
    assert out.confirmed
    for _ in range(2):  # the same frame twice, without the obstacle: one miss (of max_misses 1), not two
        tracker.update([], 5 * DT_NS)
    (back,) = tracker.update([detection(10.0, 0.0)], 6 * DT_NS)
    assert back.track_id == out.track_id and back.confirmed


def test_a_caller_changing_a_reported_obstacle_changes_no_track():
    """An embedder that inflates the boxes it gets (a safety margin, in place) must not inflate the
    track's shape, which later frames report and the cost layer occupies."""
    tracker = ObstacleTracker(TrackingConfig(confirm_hits=2))
    for k in range(3):
        (out,) = tracker.update([detection(10, 1)], k * DT_NS)
        out.size_m *= 2
        out.center_m[:] = 0
    tracker.update([], 3 * DT_NS)  # no detection: the track coasts with its last shape
    (coasting,) = tracker.coasting(1)
    np.testing.assert_array_equal(coasting.size_m, [1.0, 1.0, 1.0])
    np.testing.assert_allclose(coasting.center_m[:2], [10, 1], atol=0.05)
