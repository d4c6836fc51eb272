"""Kalman tracking of obstacles (paper step 5: "a Kalman filter is applied to prune false positives").

Each track is a constant-velocity Kalman filter on the obstacle's 2D centre, state
``(x, y, vx, vy)``. A detected centre is uncertain by ``measurement_std_m`` in every direction
and, where the stereo rig is known, by a disparity error of ``disparity_std_px`` along its line of
sight, which grows as the square of range: a far obstacle's centre jitters in depth, and a filter
that trusted it would read the jitter as motion. Tracks live in a *tracking frame*: the vehicle
frame when no pose is given, else the world/odometry frame of ``vehicle_pose`` (4×4
``world_from_vehicle``), so that static obstacles stand still while the vehicle moves. Obstacles
are reported back in the current vehicle frame either way.

Per frame (:meth:`ObstacleTracker.update`):

1. predict every track by ``dt`` (from the stamps) with white-acceleration process noise, its
   velocity moving it over at most ``max_extrapolation_s`` (or the frame interval before, if
   longer) of a longer gap;
2. associate detections to tracks of the same kind by the matching of least total distance
   between predicted and detected centres, a track or detection left unmatched costing
   ``gate_m / 2`` (:meth:`ObstacleTracker._associate`), so pairs farther than ``gate_m`` never match;
3. update matched tracks; start a tentative track for every unmatched detection but the
   fragments: one within ``fragment_radius_m`` of a confirmed track of its kind matched in this
   frame is another cluster of that obstacle (a low mound whose top flickers above the
   threshold, a person smeared in depth), and a track of its own would take the obstacle over
   whenever the first cluster is missed; such a fragment is one of the track's :attr:`parts`
   for this frame, which occupy cells in the cost map as the track does;
4. a track is *confirmed* once it has been matched in ``confirm_hits`` frames (counting the
   first); a tentative track is dropped at its first miss, a confirmed one after more than
   ``max_misses`` consecutive misses, and any track whose predicted centre leaves the grid area
   (when the tracker knows it) at once. A confirmed track matched again after more than
   ``reconfirm_misses`` misses keeps its id but counts as confirmed only once it has been
   matched ``confirm_hits`` times in a row again. Track ids count up from 1 and are never reused;
5. two tracks of a kind, one confirmed, that lie within ``fragment_radius_m`` across the line
   of sight and within ``duplicate_depth_sigmas`` depth errors more along it (at most
   ``gate_m``) follow one obstacle: the one with fewer hits is merged into the other
   (:meth:`ObstacleTracker._merge_duplicates`). Otherwise they would take its detection in
   turn, each change an id switch; a person at 18 m, whose centre jumps a metre or two in depth
   as it is seen whole or in part, left such pairs.

Reported: every track matched in this frame (tentative ones with ``confirmed=False``) and the
confirmed tracks that have missed at most ``report_misses`` frames (0 by default), at the
filter's position (corrected by this frame's detection where matched, predicted where coasting)
with their last detected shape. A confirmed track that coasts longer is not
reported but keeps its id if it is matched again within ``max_misses`` frames: on the simulated
scenes, reporting them through 3 missed frames gave 1.6–3.7× the false obstacles within 20 m in
every scene for up to 0.08 more obstacle recall. Only confirmed ones are obstacles for the
cost map (with their :attr:`parts`, and through ``cost.occupied_misses`` missed frames:
:meth:`ObstacleTracker.coasting`), so a candidate seen in a single frame never becomes one (for
``confirm_hits >= 2``) unless it is taken for part of a confirmed one. ``velocity_mps`` is
(vx, vy, 0): relative to the vehicle without a pose, over ground with one, in vehicle axes.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from .config import GridConfig, TrackingConfig, check_section
from .errors import ConfigError, InputError, is_whole
from .extrinsics import is_rotation
from .types import Obstacle, StereoCamera

logger = logging.getLogger(__name__)

_H = np.eye(2, 4)


class ObstacleTracker:
    """Tracks obstacles across frames; keep one per log (the pipeline's per-run state).

    Parameters
    ----------
    config : TrackingConfig
    area : GridConfig, optional
        The grid area (vehicle frame); tracks whose predicted centre leaves it are dropped.

    Raises
    ------
    ConfigError
        ``config`` or ``area`` does not validate.
    """

    def __init__(self, config: TrackingConfig, *, area: GridConfig | None = None):
        check_section(config, TrackingConfig)
        if area is not None:
            if not isinstance(area, GridConfig):
                raise ConfigError(f"ObstacleTracker: area must be the GridConfig, got {type(area).__name__}")
            check_section(area, GridConfig)
        self.config = config
        self.area = area
        self._next_id = 1
        self._stamp_ns: int | None = None
        self._backwards = 0  # stamps that went back: the first is warned about, the rest logged
        self.reset()

    def reset(self) -> None:
        """Forget every track (ids keep counting up)."""
        self._x = np.zeros((0, 4))  # state (x, y, vx, vy) in the tracking frame
        self._P = np.zeros((0, 4, 4))
        self._ids = np.zeros(0, dtype=np.int64)
        self._hits = np.zeros(0, dtype=np.int64)
        self._misses = np.zeros(0, dtype=np.int64)
        self._streak = np.zeros(0, dtype=np.int64)  # consecutive frames matched
        self._suspect = np.zeros(0, dtype=bool)  # back after a long gap, not yet confirmed again
        self._world: bool | None = None  # tracking in a world frame (poses given) or the vehicle's
        # per track: last detection, its centre z and its yaw in the tracking frame
        self._shape: list[tuple[Obstacle, float, float]] = []
        self._stamp_ns = None
        self._interval_s: float | None = None  # between the last two frames
        self._now = (np.eye(3), np.zeros(3), 0.0)  # the last frame's pose: rotation, translation, yaw
        self.parts: list[Obstacle] = []
        """The last frame's detections taken for parts of a confirmed track (fragments, step 3),
        vehicle frame, each with that track's id and ``confirmed``: no track of their own, but
        they occupy cells in the cost layer as the track does."""

    @property
    def _confirmed(self) -> np.ndarray:
        """Per track: matched in ``confirm_hits`` frames, and as many in a row since it came back
        after more than ``reconfirm_misses`` misses."""
        return (self._hits >= self.config.confirm_hits) & ~self._suspect

    @property
    def track_count(self) -> int:
        return len(self._ids)

    @property
    def in_world_frame(self) -> bool:
        """True when the last update came with a vehicle pose (tracks live in its world frame)."""
        return bool(self._world)

    def update(
        self,
        obstacles: list[Obstacle],
        stamp_ns: int,
        vehicle_pose: np.ndarray | None = None,
        camera: StereoCamera | None = None,
    ) -> list[Obstacle]:
        """Advance the tracks to ``stamp_ns`` with this frame's detections (vehicle frame).

        Parameters
        ----------
        obstacles : list of Obstacle
            Detections of this frame, vehicle frame (``extract_obstacles``).
        stamp_ns : int
            Frame stamp, nanoseconds. A stamp older than the previous one resets the tracker; the
            previous stamp again (a frame logged twice) changes no track.
        vehicle_pose : (4, 4) array, optional
            ``world_from_vehicle`` (odometry / tf); tracks then live in that world frame. Give
            one with every frame or with none: switching between the two resets the tracks.
        camera : StereoCamera, optional
            The stereo rig of the detections: their centres are then also uncertain along the
            line of sight, by ``disparity_std_px`` of disparity (:meth:`_measurement_noise`).

        Returns
        -------
        list of Obstacle
            Copies carrying ``track_id``, ``confirmed`` and ``velocity_mps``, vehicle frame.
        """
        previous, self.parts = self.parts, []  # (none after a frame that raises)
        rot, trans = (a.copy() for a in _pose(vehicle_pose))  # kept in _now: not the caller's array
        centers = _detection_centers(obstacles, stamp_ns)
        if self._world is not None and self._world != (vehicle_pose is not None):
            logger.warning("tracking: vehicle poses started or stopped; tracks reset")
            self.reset()
        yaw_v = float(np.arctan2(rot[1, 0], rot[0, 0]))
        if self._stamp_ns is not None and int(stamp_ns) == self._stamp_ns:
            # A frame logged twice (its stamp again) is no new evidence: the tracks stay as they are.
            self.parts, self._now = previous, (rot, trans, yaw_v)
            return self._report(rot, trans, yaw_v)
        dt = self._advance(int(stamp_ns))  # may reset the tracks, and with them _world
        self._world = vehicle_pose is not None
        self._predict(dt)
        self._drop(self._outside(rot, trans))

        centers_t = centers @ rot.T + trans  # tracking frame
        rows, cols = self._associate(centers_t[:, :2], [o.kind for o in obstacles])

        self._correct(rows, centers_t[cols, :2], self._measurement_noise(centers[cols], rot, camera))
        matched = np.zeros(len(self._ids), bool)
        matched[rows] = True
        self._mark_matched(rows)
        self._misses[~matched] += 1
        for r, c in zip(rows, cols, strict=True):
            self._shape[r] = (obstacles[c], centers_t[c, 2], obstacles[c].yaw_rad + yaw_v)
        new, parts = self._not_fragments(np.setdiff1d(np.arange(len(obstacles)), cols), centers_t, obstacles, rows)
        self._drop(
            (~matched) & ((self._hits < self.config.confirm_hits) | (self._misses > self.config.max_misses))
        )
        merged = self._merge_duplicates(rot, trans, camera)
        self.parts = [replace(p, track_id=merged.get(p.track_id, p.track_id)) for p in parts]
        self._spawn([obstacles[i] for i in new], centers_t[new], yaw_v)
        self._now = (rot, trans, yaw_v)
        return self._report(rot, trans, yaw_v)

    def _mark_matched(self, rows: np.ndarray) -> None:
        """Count a match for tracks ``rows``: one more hit, the run of consecutive matches, and
        whether the track is back after more than ``reconfirm_misses`` misses and not yet
        matched ``confirm_hits`` times in a row again."""
        self._hits[rows] += 1
        self._streak[rows] = np.where(self._misses[rows] == 0, self._streak[rows] + 1, 1)
        self._suspect[rows] |= self._misses[rows] > self.config.reconfirm_misses
        self._suspect[rows] &= self._streak[rows] < self.config.confirm_hits
        self._misses[rows] = 0

    def _advance(self, stamp_ns: int) -> float:
        """Seconds since the previous frame (0 for the first one); resets on a stamp going back."""
        if self._stamp_ns is not None and stamp_ns < self._stamp_ns:
            self._backwards += 1
            (logger.warning if self._backwards == 1 else logger.info)(
                "tracking: stamp %d is older than the previous %d; tracks reset%s", stamp_ns, self._stamp_ns,
                " (said once per tracker; again each time it happens at log level INFO, which terrainmap -v shows)"
                if self._backwards == 1 else "",
            )
            self.reset()
        dt = 0.0 if self._stamp_ns is None else (stamp_ns - self._stamp_ns) * 1e-9
        self._stamp_ns = stamp_ns
        return dt

    def _predict(self, dt: float) -> None:
        if dt <= 0:
            return
        # Over a gap much longer than the log's frame interval no velocity holds: it moves the
        # track for max_extrapolation_s, or the interval before the gap if longer, at most.
        moved = dt if self._interval_s is None else min(dt, max(self.config.max_extrapolation_s, self._interval_s))
        self._interval_s = dt
        if not len(self._ids):
            return
        F = np.eye(4)
        F[0, 2] = F[1, 3] = moved
        q = self.config.acceleration_std_mps2**2
        block = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        Q = np.zeros((4, 4))
        Q[np.ix_([0, 2], [0, 2])] = block
        Q[np.ix_([1, 3], [1, 3])] = block
        self._x = self._x @ F.T
        self._P = F @ self._P @ F.T + Q

    def _associate(self, centers_xy: np.ndarray, kinds: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """The matching of least total distance within the gate: (track rows, detection columns).

        Each track or detection left unmatched costs ``gate_m / 2``, so a pair (distance d < gate)
        is worth ``d − gate`` against leaving both unmatched: the Hungarian algorithm on those
        values, with 0 for pairs outside the gate, finds it. Matching as many pairs as possible
        instead lets a track whose own obstacle was missed in this frame take a neighbour's
        detection and push that neighbour's track onto a fragment: an id switch. Candidate pairs
        come from a k-d tree; a pair that is the only candidate of both its track and its
        detection is matched directly.
        """
        n, m = len(self._ids), len(centers_xy)
        none = np.zeros(0, np.intp)
        if not n or not m:
            return none, none
        pairs = cKDTree(self._x[:, :2]).sparse_distance_matrix(
            cKDTree(centers_xy), self.config.gate_m, output_type="ndarray"
        )
        track_kinds = np.array([s[0].kind for s in self._shape])
        pairs = pairs[track_kinds[pairs["i"]] == np.asarray(kinds)[pairs["j"]]]
        i, j, dist = pairs["i"].astype(np.intp), pairs["j"].astype(np.intp), pairs["v"]
        single = (np.bincount(i, minlength=n)[i] == 1) & (np.bincount(j, minlength=m)[j] == 1)
        rest = ~single
        if not rest.any():
            return i[single], j[single]
        rows, ri = np.unique(i[rest], return_inverse=True)
        cols, ci = np.unique(j[rest], return_inverse=True)
        cost = np.zeros((len(rows), len(cols)))  # against leaving the pair unmatched
        cost[ri, ci] = dist[rest] - self.config.gate_m  # < 0 within the gate
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] < 0
        return np.concatenate([i[single], rows[r[ok]]]), np.concatenate([j[single], cols[c[ok]]])

    def _not_fragments(
        self, new: np.ndarray, centers_t: np.ndarray, obstacles: list[Obstacle], rows: np.ndarray
    ) -> tuple[np.ndarray, list[Obstacle]]:
        """The unmatched detections ``new`` that are no fragment of a confirmed track of their
        kind matched in this frame: farther than ``fragment_radius_m`` from its centre and not
        in the shadow of its detection (:func:`_in_shadow`: behind it as the camera sees it, up to
        that radius beyond it, and no taller; what stands there is hidden by it, so a cluster
        there is its far side or its smear, as when a car comes into range as two clusters).
        And the fragments, as :attr:`parts` of the first such track."""
        radius = self.config.fragment_radius_m
        rows = rows[self._confirmed[rows]]
        if radius <= 0 or not len(new) or not len(rows):
            return new, []
        near = np.hypot(*(centers_t[new, None, :2] - self._x[None, rows, :2]).transpose(2, 0, 1)) <= radius
        near |= _in_shadow([obstacles[i] for i in new], [self._shape[r][0] for r in rows], radius)
        same = np.array([obstacles[i].kind for i in new])[:, None] == np.array([self._shape[r][0].kind for r in rows])
        part_of = near & same
        fragment = part_of.any(1)
        parts = [replace(obstacles[i], track_id=int(self._ids[rows[k]]), confirmed=True)
                 for i, k in zip(new[fragment], part_of[fragment].argmax(1), strict=True)]
        return new[~fragment], parts

    def _merge_duplicates(self, rot: np.ndarray, trans: np.ndarray, camera: StereoCamera | None) -> dict[int, int]:
        """Merge tracks that follow one obstacle (``TrackingConfig.duplicate_depth_sigmas``): the
        track with fewer hits (the younger on a tie) goes; the other keeps its id and, if only
        the one that goes was matched in this frame, takes over its state and detection.
        Returns the ids merged: gone → kept."""
        radius = self.config.fragment_radius_m
        merged: dict[int, int] = {}
        if radius <= 0 or len(self._ids) < 2:
            return merged
        xy = self._x[:, :2]
        # Per track, the ellipse r²·I + s·sᵀ, s the line-of-sight shift of k disparity errors.
        shift = np.zeros((len(xy), 2))
        if camera is not None:
            centers = self._centers_in_vehicle(np.arange(len(xy)), rot, trans)
            shift = _line_of_sight(centers, rot, camera, self.config.duplicate_depth_sigmas * self.config.disparity_std_px)
            # No longer than the gate: tracks farther apart never compete for one detection.
            longest = np.sqrt(max(self.config.gate_m**2 - radius**2, 0.0))
            shift *= np.minimum(1.0, longest / np.maximum(np.hypot(*shift.T), 1e-9))[:, None]
        reach = np.sqrt(radius**2 + (shift**2).sum(1))  # the ellipses' semi-major axes
        pairs = cKDTree(xy).query_pairs(reach.max(), output_type="ndarray")
        if not len(pairs):
            return merged
        i, j = pairs.T
        kinds = np.array([s[0].kind for s in self._shape])
        confirmed = self._confirmed
        d = xy[j] - xy[i]
        metric = radius**2 * np.eye(2) + (shift[i, :, None] * shift[i, None, :] + shift[j, :, None] * shift[j, None, :]) / 2
        inside = np.einsum("nk,nkl,nl->n", d, np.linalg.inv(metric), d) <= 1
        keep = inside & (kinds[i] == kinds[j]) & (confirmed[i] | confirmed[j])
        rank = np.lexsort((self._ids, -self._hits))  # best first: most hits, then oldest
        order = np.empty(len(rank), np.intp)
        order[rank] = np.arange(len(rank))
        gone = np.zeros(len(self._ids), bool)
        for a, b in sorted(zip(i[keep], j[keep], strict=True), key=lambda p: min(order[p[0]], order[p[1]])):
            winner, loser = (a, b) if order[a] < order[b] else (b, a)
            if gone[winner] or gone[loser]:
                continue
            # One obstacle: confirmed if either track was (a track back from a long gap merging
            # with the confirmed one that followed it meanwhile must not drop out of the cost).
            self._suspect[winner] &= ~confirmed[loser]
            if self._misses[loser] == 0 and self._misses[winner] > 0:  # the detection was the loser's
                self._x[winner], self._P[winner], self._shape[winner] = self._x[loser], self._P[loser], self._shape[loser]
                self._mark_matched(np.array([winner]))
            gone[loser] = True
            merged[int(self._ids[loser])] = int(self._ids[winner])
        self._drop(gone)  # (a track kept in one pair never goes in a later one: pairs come by their winner's rank)
        return merged

    def _measurement_noise(self, centers: np.ndarray, rot: np.ndarray, camera: StereoCamera | None) -> np.ndarray:
        """Covariance (n, 2, 2) of the detected centres (n, 3, vehicle frame) in the tracking frame:
        ``measurement_std_m``² in every direction, plus, with a camera, the variance of a
        ``disparity_std_px`` disparity error along each centre's line of sight (stereo depth error
        grows as Z², so a far obstacle's centre jitters in range far more than across it)."""
        noise = np.broadcast_to(self.config.measurement_std_m**2 * np.eye(2), (len(centers), 2, 2))
        if camera is None or self.config.disparity_std_px <= 0 or not len(centers):
            return noise
        shift = _line_of_sight(centers, rot, camera, self.config.disparity_std_px)
        return noise + shift[:, :, None] * shift[:, None, :]

    def _centers_in_vehicle(self, rows: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
        """Centres (k, 3) of tracks ``rows`` in the vehicle frame: rotᵀ·(p − t) per row."""
        z_t = np.array([self._shape[i][1] for i in rows]).reshape(-1)
        return (np.column_stack([self._x[rows, :2], z_t]) - trans) @ rot

    def _correct(self, rows: np.ndarray, z: np.ndarray, noise: np.ndarray) -> None:
        """Batched Kalman update of tracks ``rows`` with measured centres ``z`` (k, 2) of
        covariance ``noise`` (k, 2, 2)."""
        if not len(rows):
            return
        P = self._P[rows]
        S = P[:, :2, :2] + noise
        K = P[:, :, :2] @ np.linalg.inv(S)  # (k, 4, 2)
        innovation = z - self._x[rows, :2]
        self._x[rows] += (K @ innovation[:, :, None])[:, :, 0]
        # Joseph form, symmetrised: stays a covariance even when P is huge after a long gap
        # (the short form (I − KH)P cancels catastrophically there).
        A = np.eye(4) - K @ _H
        P = A @ P @ A.transpose(0, 2, 1) + K @ noise @ K.transpose(0, 2, 1)
        self._P[rows] = (P + P.transpose(0, 2, 1)) / 2

    def _spawn(self, obstacles: list[Obstacle], centers_t: np.ndarray, yaw_v: float) -> None:
        k = len(obstacles)
        if not k:
            return
        x = np.zeros((k, 4))
        x[:, :2] = centers_t[:, :2]
        P = np.diag([self.config.measurement_std_m**2] * 2 + [self.config.initial_velocity_std_mps**2] * 2)
        self._x = np.vstack([self._x, x])
        self._P = np.concatenate([self._P, np.broadcast_to(P, (k, 4, 4))])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + k)])
        self._next_id += k
        self._hits = np.concatenate([self._hits, np.ones(k, np.int64)])
        self._misses = np.concatenate([self._misses, np.zeros(k, np.int64)])
        self._streak = np.concatenate([self._streak, np.ones(k, np.int64)])
        self._suspect = np.concatenate([self._suspect, np.zeros(k, bool)])
        self._shape += [(o, c[2], o.yaw_rad + yaw_v) for o, c in zip(obstacles, centers_t, strict=True)]

    def _outside(self, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
        """Tracks whose predicted centre lies outside the grid area (vehicle frame)."""
        if self.area is None or not len(self._ids):
            return np.zeros(len(self._ids), bool)
        xy = (self._x[:, :2] - trans[:2]) @ rot[:2, :2]  # rotᵀ·(p − t), level-vehicle approximation
        a = self.area
        return (
            (xy[:, 0] < a.x_min_m)
            | (xy[:, 0] > a.x_min_m + a.length_m)
            | (xy[:, 1] < a.y_min_m)
            | (xy[:, 1] > a.y_min_m + a.width_m)
        )

    def _drop(self, mask: np.ndarray) -> None:
        if not mask.any():
            return
        keep = ~mask
        self._x, self._P, self._ids = self._x[keep], self._P[keep], self._ids[keep]
        self._hits, self._misses = self._hits[keep], self._misses[keep]
        self._streak, self._suspect = self._streak[keep], self._suspect[keep]
        self._shape = [s for s, k in zip(self._shape, keep, strict=True) if k]

    def coasting(self, misses: int) -> list[Obstacle]:
        """The confirmed tracks left out of the last frame's report that have missed at most
        ``misses`` frames in a row, at their predicted positions with their last detected
        shapes, vehicle frame: most likely still there, for the cost map."""
        rows = self._confirmed & (self._misses > self.config.report_misses) & (self._misses <= misses)
        return self._obstacles(np.flatnonzero(rows), *self._now)

    def _report(self, rot: np.ndarray, trans: np.ndarray, yaw_v: float) -> list[Obstacle]:
        shown = (self._misses == 0) | (self._confirmed & (self._misses <= self.config.report_misses))
        return self._obstacles(np.flatnonzero(shown), rot, trans, yaw_v)

    def _obstacles(self, shown: np.ndarray, rot: np.ndarray, trans: np.ndarray, yaw_v: float) -> list[Obstacle]:
        """Tracks ``shown`` as obstacles in the vehicle frame of pose (``rot``, ``trans``, ``yaw_v``)."""
        confirmed = self._confirmed
        centers = self._centers_in_vehicle(shown, rot, trans)
        velocities = np.column_stack([self._x[shown, 2:], np.zeros(len(shown))]) @ rot
        velocities[:, 2] = 0.0
        yaws = _wrap_half(np.array([self._shape[i][2] for i in shown]) - yaw_v).tolist()
        out = []
        for k, i in enumerate(shown.tolist()):
            last = self._shape[i][0]
            out.append(
                Obstacle(
                    center_m=centers[k],
                    size_m=last.size_m.copy(),  # the caller's to change (a safety margin): not the track's
                    yaw_rad=yaws[k],
                    height_m=last.height_m,
                    point_count=last.point_count,
                    range_m=last.range_m,
                    kind=last.kind,
                    track_id=int(self._ids[i]),
                    confirmed=bool(confirmed[i]),
                    velocity_mps=velocities[k],
                )
            )
        return out


_MAX_COORDINATE_M = 1e6
"""Detections and stamps are checked before they reach the filters: a NaN or astronomically far
centre would otherwise only fail in a later frame, deep in the association's k-d tree."""


def _detection_centers(obstacles, stamp_ns) -> np.ndarray:
    """The detections' centres, (n, 3) vehicle frame; :class:`InputError` unless ``stamp_ns`` is a
    whole number and every detection's centre, size and yaw are finite (centre within ±1e6 m)."""
    if not is_whole(stamp_ns):
        raise InputError(f"tracking: the stamp must be a whole number of nanoseconds, got {stamp_ns!r}")
    try:
        items = list(obstacles)
        values = np.array([[*o.center_m, *o.size_m, o.yaw_rad] for o in items], float).reshape(len(items), 7)
    except (TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"tracking: detections must be a list of Obstacle with 3-vector centre and size ({exc})") from exc
    if values.size and (not np.isfinite(values).all() or np.abs(values[:, :3]).max() > _MAX_COORDINATE_M):
        raise InputError("tracking: every detection needs a finite centre (within ±1e6 m), size and yaw")
    return values[:, :3]


def _pose(vehicle_pose: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(rotation 3×3, translation 3) of ``world_from_vehicle``; identity when None."""
    if vehicle_pose is None:
        return np.eye(3), np.zeros(3)
    T = np.asarray(vehicle_pose, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        what = f"shape {T.shape}" if T.shape != (4, 4) else "non-finite values"
        raise InputError(f"tracking: vehicle_pose must be a finite 4×4 matrix, got {what}")
    if not (is_rotation(T[:3, :3]) and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise InputError("tracking: vehicle_pose must be a rigid motion (a proper rotation, last row 0 0 0 1)")
    return T[:3, :3], T[:3, 3]


def _line_of_sight(centers: np.ndarray, rot: np.ndarray, camera: StereoCamera, disparity_px: float) -> np.ndarray:
    """How far ``disparity_px`` of disparity error moves each centre (n, 3, vehicle frame) along its
    line of sight: (n, 2) metres in the tracking frame."""
    return camera.shift_per_px(centers)[:, :2] @ rot[:2, :2].T * disparity_px


def _wrap_half(angle: np.ndarray) -> np.ndarray:
    """Footprint yaw folded into (−π/2, π/2] (a rectangle is symmetric under a half turn)."""
    return np.pi / 2 - np.mod(np.pi / 2 - angle, np.pi)


def _in_shadow(detections: list[Obstacle], boxes: list[Obstacle], depth_m: float) -> np.ndarray:
    """(n, k) bool: detection i lies in the shadow of box j as seen from the vehicle origin (the
    camera above it): within the bearings of box j's footprint corners, beyond its centre, no
    more than ``depth_m`` beyond its farthest corner and no taller. Vehicle frame, metres."""
    det = np.array([d.center_m[:2] for d in detections], float).reshape(-1, 2)
    centre = np.array([b.center_m[:2] for b in boxes], float).reshape(-1, 2)
    half = np.array([b.size_m[:2] / 2 for b in boxes], float).reshape(-1, 2)
    yaw = np.array([b.yaw_rad for b in boxes], float)
    signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], float)
    local = signs[None] * half[:, None]  # (k, 4, 2) corners in the box frame
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    corners = centre[:, None] + np.stack([local[..., 0] * cos - local[..., 1] * sin,
                                          local[..., 0] * sin + local[..., 1] * cos], axis=-1)  # fmt: skip
    bearing_c = np.arctan2(centre[:, 1], centre[:, 0])
    spread = _wrap_pi(np.arctan2(corners[..., 1], corners[..., 0]) - bearing_c[:, None])  # (k, 4)
    offset = _wrap_pi(np.arctan2(det[:, 1], det[:, 0])[:, None] - bearing_c[None])  # (n, k)
    within = (offset >= spread.min(1)[None]) & (offset <= spread.max(1)[None])
    rng = np.hypot(*det.T)[:, None]
    behind = (rng > np.hypot(*centre.T)[None]) & (rng <= np.hypot(*corners.transpose(2, 0, 1)).max(1)[None] + depth_m)
    lower = np.array([d.height_m for d in detections])[:, None] <= np.array([b.height_m for b in boxes])[None]
    return within & behind & lower


def _wrap_pi(angle: np.ndarray) -> np.ndarray:
    """Angles folded into [−π, π)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi
