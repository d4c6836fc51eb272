"""Obstacle extraction from outlier points (paper step 5, first half).

Points labelled :attr:`Label.OBSTACLE` (above the terrain) and :attr:`Label.BELOW` (below it)
are clustered separately: each kind is counted per grid cell, cells holding at least
``min_cell_points`` such points are joined by 8-connectivity (:func:`scipy.ndimage.label`), and
every point takes the cluster of its cell. Clusters at least ``split_min_length_m`` long are then
cut where their points thin out along the major axis, and the thin stretches dropped: stereo
smear joins a near obstacle to one behind it (:func:`_split_at_gaps`). The points are sorted by
cluster once, and per-cluster statistics are reduced over each cluster's run of points at once
(:class:`Segments`), so thousands of tiny clusters cost no Python loop; only the clusters that
pass the filters become :class:`Obstacle` objects. Past ``max_points`` points of one kind, the
largest clusters are measured on about one in k of their points (:func:`_thinning`), which caps
that work on dense scenes (a street's house fronts) while small obstacles keep every point.

Per cluster (vehicle frame, metres):

* footprint: principal axes of the points' (x, y) covariance give ``yaw_rad`` (major axis,
  in (−π/2, π/2]), or, for a cluster with no clear major axis (a pedestrian, a pole, a rock),
  the axes of its least-area rectangle; the extents of the points along those axes (sparse tails
  trimmed, :func:`_robust_extent`) give length and width and the footprint centre (a point
  cluster's oriented bounding rectangle);
* ``height_m``: the largest point height above the terrain surface (positive) or depth below it
  (negative), the surface taken at each point by bilinear interpolation of its values at the cell
  centres (exact on planes between the outermost centres; in the grid's outer half cells, the
  nearest centre's value along that axis: :func:`terrain_at`);
* the box spans from the terrain at the footprint centre up to the highest point (positive) or
  from the deepest point up to the terrain (negative); ``center_m`` is its centre;
* ``range_m``: the distance from the vehicle origin to the nearest point of the cluster.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .config import GridConfig, ObstacleConfig
from .errors import InputError
from .grid import as_points, cell_centers, cell_index, check_shapes
from .segmentation import cells_holding
from .types import Label, Obstacle

_EIGHT = np.ones((3, 3), dtype=bool)


def extract_obstacles(
    points_vehicle: np.ndarray,
    point_labels: np.ndarray,
    grid_config: GridConfig,
    surface,
    config: ObstacleConfig,
    *,
    elevation: np.ndarray | None = None,
    cell_counts: np.ndarray | None = None,
    steep: np.ndarray | None = None,
    index: np.ndarray | None = None,
) -> list[Obstacle]:
    """Cluster above/below-terrain points into positive and negative obstacles.

    Parameters
    ----------
    points_vehicle : (N, 3) float array
        Points in the vehicle frame, metres. Points outside the grid area are ignored.
    point_labels : (N,) uint8 array
        :class:`Label` of each point.
    grid_config : GridConfig
        The grid the points are clustered on.
    surface : RationalSurface or None
        Terrain surface; only ``surface.on_grid(xs, ys)`` is used, and not at all (it may be
        None) when ``elevation`` is given.
    config : ObstacleConfig
        Minimum size, height and point count of an obstacle.
    elevation : (m0, m1) float array, optional
        The surface at the cell centres (the ``elevation`` layer), to avoid evaluating it again;
        finite in every cell.
    cell_counts : (m0, m1) int array, optional
        All points per cell, whatever their label (``HeightGrid.count``): with it, positive
        clusters at least ``config.tall_height_m`` tall must hold ``config.tall_min_share`` of
        the points in their cells.
    steep : (m0, m1) bool array, optional
        Cells whose terrain is too steep to drive (the cost's ``max_slope_deg``): positive
        clusters lower than ``config.tall_height_m`` with more than half their points in such
        cells are dropped (``ObstacleConfig.drop_on_steep_ground``).
    index : (N,) int array, optional
        :func:`~terrainmap.grid.cell_index` of the points, reused from the grid stage (taken as
        given, not checked).

    Returns
    -------
    list of Obstacle
        Positive obstacles, then negative ones, each sorted by range; ``track_id`` is -1.

    Raises
    ------
    InputError
        ``points_vehicle`` is not N×3, ``point_labels`` does not have one label per point, or a
        layer does not have the grid's shape or ``elevation`` is not finite.
    """
    points_vehicle = as_points(points_vehicle)
    point_labels = np.asarray(point_labels)
    if point_labels.shape != (len(points_vehicle),):
        raise InputError(
            f"obstacles: expected {len(points_vehicle)} point labels, got shape {point_labels.shape}"
        )
    if elevation is None:
        if surface is None:
            raise InputError("obstacles: give the terrain as elevation (or a surface)")
        elevation = surface.on_grid(*cell_centers(grid_config))
    check_shapes("obstacles", grid_config.shape, elevation=elevation, cell_counts=cell_counts, steep=steep)
    if not np.isfinite(elevation).all():  # a NaN would void the height of every cluster near it
        raise InputError("obstacles: elevation must be finite in every cell (the surface, as FrameResult.layers "
                         "holds it; written layers have NaN where no point is, and cannot serve)")
    check_shapes("obstacles", point_labels.shape, index=index)
    kinds = [(Label.OBSTACLE, "positive", config.min_height_m)]
    if config.negative:
        kinds.append((Label.BELOW, "negative", config.min_depth_m))
    result: list[Obstacle] = []
    terrain = _Bilinear(elevation, grid_config)
    # One pass over the labels finds the points of both kinds (OBSTACLE 2, BELOW 3); indices are
    # 10× faster than masks here.
    candidates = np.flatnonzero(point_labels >= Label.OBSTACLE)
    for label, kind, min_height in kinds:
        selected = candidates[point_labels[candidates] == label]
        idx = cell_index(points_vehicle[selected], grid_config) if index is None else index[selected]
        counts, on_steep = (cell_counts, steep) if kind == "positive" else (None, None)
        result += _clusters(
            points_vehicle, selected, idx, grid_config, terrain, config, kind, min_height,
            counts, on_steep,
        )
    return result


def terrain_at(x: np.ndarray, y: np.ndarray, elevation: np.ndarray, grid_config: GridConfig) -> np.ndarray:
    """Terrain height (m) under the points ``(x, y)`` ((N,) each, vehicle frame, m), bilinear
    between cell-centre values, (N,) float64.

    Exact where the terrain is a plane; points beyond the outermost cell centres take the
    nearest value along that axis; non-finite points get NaN. :class:`InputError` if ``elevation``
    is not (m0, m1) or x and y are not of one shape.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    check_shapes("terrain_at", grid_config.shape, elevation=elevation)
    check_shapes("terrain_at", x.shape, y=y)
    with np.errstate(invalid="ignore"):  # non-finite points: NaN, without numpy's warnings
        return _Bilinear(elevation, grid_config)(x, y)


class _Bilinear:
    """:func:`terrain_at` with its per-cell table built once (for several sets of points).

    Per dual cell (the rectangle between four neighbouring cell centres, or the half cell beyond
    the outermost ones, where the edge padding makes the surface flat along that axis) the
    bilinear interpolation is A + B·x + C·y + D·x·y: four takes and five operations a point."""

    def __init__(self, elevation: np.ndarray, grid_config: GridConfig):
        m0, m1 = np.shape(elevation)
        c = self.cell = grid_config.cell_size_m
        e = np.pad(np.asarray(elevation, np.float64), 1, mode="edge")
        f00, f10, f01, f11 = e[:-1, :-1], e[1:, :-1], e[:-1, 1:], e[1:, 1:]
        x0 = (grid_config.x_min_m + (np.arange(m0 + 1) - 0.5) * c)[:, None]  # the dual cells' corners
        y0 = (grid_config.y_min_m + (np.arange(m1 + 1) - 0.5) * c)[None, :]
        a, b, d = (f10 - f00) / c, (f01 - f00) / c, (f11 - f10 - f01 + f00) / (c * c)
        self.coefficients = [
            (f00 - a * x0 - b * y0 + d * x0 * y0).ravel(), (a - d * y0).ravel(), (b - d * x0).ravel(), d.ravel()
        ]
        self.shape = (m0, m1)
        self.offset = (0.5 - grid_config.x_min_m / c, 0.5 - grid_config.y_min_m / c)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        (m0, m1), (ox, oy) = self.shape, self.offset
        # Truncation sends everything below 1 to 0 (the first dual cell), as the clip would.
        jx = np.clip((x * (1 / self.cell) + ox).astype(np.intp), 0, m0)
        jy = np.clip((y * (1 / self.cell) + oy).astype(np.intp), 0, m1)
        jx *= m1 + 1
        jx += jy
        A, B, C, D = (k.take(jx) for k in self.coefficients)
        return A + x * (B + D * y) + C * y


def _clusters(
    points: np.ndarray,
    selected: np.ndarray,
    idx: np.ndarray,
    grid_config: GridConfig,
    terrain: _Bilinear,
    config: ObstacleConfig,
    kind: str,
    min_height: float,
    cell_counts: np.ndarray | None = None,
    steep: np.ndarray | None = None,
) -> list[Obstacle]:
    """Obstacles of one kind from the points ``points[selected]`` of that kind, in cells ``idx``
    (:func:`~terrainmap.grid.cell_index`), over ``terrain`` (see the module docstring); with
    ``cell_counts`` (all points per cell), tall clusters must hold ``config.tall_min_share`` of
    the points in their cells; with ``steep`` (bool per cell), low clusters must hold at most
    half their points in steep cells."""
    m0, m1 = grid_config.shape
    if not (idx < m0 * m1).any():
        return []
    cells, n = ndimage.label(cells_holding(idx, (m0, m1), config.min_cell_points), structure=_EIGHT)
    if n == 0:
        return []
    # Cluster of each point (-1: outside the area, or its cell has too few points); from here on
    # the points of clusters only, sorted by cluster, as contiguous float64 rows x, y, z.
    cid = np.append(cells.ravel(), 0)[idx] - 1
    keep = np.flatnonzero(cid >= 0)
    # Past max_points, a thinned cluster keeps the points whose position in the kind's points is a
    # multiple of its stride, each standing for stride (the cells were joined from all): point
    # counts below are the full cloud's.
    cid = cid[keep]
    stride = np.ones(n, np.int64)
    if config.max_points and cid.size > config.max_points:  # (the clusters' sizes sum to cid.size)
        stride = _thinning(np.bincount(cid, minlength=n), config.max_points)
        thin = keep % stride[cid] == 0
        keep, cid = keep[thin], cid[thin]
    order = _by_cluster(cid, n)
    keep, cid = keep[order], cid[order]
    idx = idx[keep]
    # take(): 5× faster than indexing rows with an array
    x, y, z = np.array(points.take(selected[keep], axis=0).T, np.float64)
    per_cell = np.ones(m0 * m1) if cell_counts is None else np.asarray(cell_counts, float).ravel()
    ncells, in_cells = (np.bincount(cells.ravel(), w, n + 1)[1:] for w in (None, per_cell))
    per = Segments(cid, n)
    split = None
    if config.split_gap_fraction > 0:
        split = _split_at_gaps(x, y, per, grid_config.cell_size_m, config, stride)
    if split is not None:  # the points in their new order, without the dropped ones
        order, cut, parts = split
        kept = order[cut >= 0]
        x, y, z, idx, cid = x[kept], y[kept], z[kept], idx[kept], cut[cut >= 0]
        n = int(parts.sum())
        per = Segments(cid, n)
        ncells, in_cells, stride = (np.repeat(a, parts) for a in (ncells, in_cells, stride))
        for part in np.flatnonzero(np.repeat(parts > 1, parts)):  # the parts of a cut cluster may share cells
            present = np.unique(idx[per.run(part)])
            ncells[part], in_cells[part] = present.size, per_cell[present].sum()
    height = z - terrain(x, y)
    if kind == "negative":
        height = -height

    npts = per.sum() * stride
    top = per.reduce(np.maximum, height)
    ok = (npts >= config.min_points) & (ncells >= config.min_cells) & (top >= min_height)
    if cell_counts is not None:  # tall objects hide the ground behind them (ObstacleConfig.tall_height_m)
        ok &= (top < config.tall_height_m) | (npts >= config.tall_min_share * in_cells)
    if steep is not None:  # low relief on ground the cost already forbids (drop_on_steep_ground)
        on_steep = per.sum(np.asarray(steep, float).ravel()[idx]) * stride
        ok &= (top >= config.tall_height_m) | (2 * on_steep <= npts)
    if not ok.any():
        return []
    # Keep only the surviving clusters' points from here on, renumbered 0..k-1 (still sorted).
    new_id = np.cumsum(ok) - 1
    sel = per.spread(ok)
    x, y, z, cid = x[sel], y[sel], z[sel], new_id[cid[sel]]
    k, npts, top = int(ok.sum()), npts[ok], top[ok]

    per = Segments(cid, k)
    yaw, u, v = _footprint_axes(x, y, per)
    (uc, u_half), (vc, v_half) = (_robust_extent(w, per, per.counts) for w in (u, v))
    # The length lies along the yaw: where the trimmed extents say otherwise (a nearly square
    # cluster), the same rectangle is described turned by 90° (yaw + π/2: u, v → v, −u; then
    # back into (−π/2, π/2] by half a turn, which flips both).
    turn = u_half < v_half
    flip = np.where(turn & (yaw > 0), -1.0, 1.0)
    uc, vc = np.where(turn, flip * vc, uc), np.where(turn, -flip * uc, vc)
    u_half, v_half = np.maximum(u_half, v_half), np.minimum(u_half, v_half)
    yaw = np.where(turn, yaw + np.pi / 2 - np.pi * (flip < 0), yaw)
    cos, sin = np.cos(yaw), np.sin(yaw)
    cx, cy = uc * cos - vc * sin, uc * sin + vc * cos
    ground = terrain(cx, cy)
    if kind == "positive":
        z_lo, z_hi = ground, np.maximum(per.reduce(np.maximum, z), ground)
    else:
        z_lo = np.minimum(per.reduce(np.minimum, z), ground)
        z_hi = ground
    rng = np.sqrt(per.reduce(np.minimum, x * x + y * y + z * z))

    order = np.argsort(rng, kind="stable")
    centers = np.column_stack([cx, cy, (z_lo + z_hi) / 2])[order]
    sizes = np.column_stack([2 * u_half, 2 * v_half, z_hi - z_lo])[order]
    scalars = zip(
        yaw[order].tolist(), top[order].tolist(), npts[order].tolist(), rng[order].tolist(), strict=True
    )
    return [
        Obstacle(center_m=c, size_m=sz, yaw_rad=y, height_m=h, point_count=n, range_m=r, kind=kind)
        for c, sz, (y, h, n, r) in zip(centers, sizes, scalars, strict=True)
    ]


def _by_cluster(cid: np.ndarray, n: int) -> np.ndarray:
    """The stable order that sorts points by cluster ``cid`` ((N,) in [0, n)): a radix sort, 6×
    faster than on int64, while the ids fit 16 bits."""
    return np.argsort(cid.astype(np.uint16) if n <= 1 << 16 else cid, kind="stable")


class Segments:
    """Per-cluster sums and extremes over points sorted by cluster: ``cid`` ((N,) ints in [0, n),
    non-decreasing). Each cluster's points are one contiguous run, reduced by ``ufunc.reduceat``:
    5–7× faster than :class:`~terrainmap.grid.PerBin`'s scatter, which pays for the sort over the
    twenty-odd reductions a cluster takes. Results are (n,) arrays; a cluster with no point has
    sum 0 and the reduction's identity."""

    def __init__(self, cid: np.ndarray, n: int):
        self.bounds = np.searchsorted(cid, np.arange(n + 1))  # cluster c: points bounds[c] .. bounds[c + 1] - 1
        self.counts = np.diff(self.bounds)
        self.present = np.flatnonzero(self.counts)
        self.starts = self.bounds[self.present]
        self.n = n

    def sum(self, weights: np.ndarray | None = None) -> np.ndarray:
        """Σ weights per cluster (the point count without weights), float64 (int64 for counts)."""
        if weights is None:
            return self.counts.copy()
        return self._scatter(np.add.reduceat(np.asarray(weights, np.float64), self.starts), 0.0)

    def reduce(self, ufunc: np.ufunc, values: np.ndarray) -> np.ndarray:
        """``np.minimum`` or ``np.maximum`` of float ``values`` ((N,) or (N, K)) per cluster, (n,)
        or (n, K) (±inf where empty)."""
        return self._scatter(ufunc.reduceat(values, self.starts), np.inf if ufunc is np.minimum else -np.inf)

    def spread(self, per_cluster: np.ndarray) -> np.ndarray:
        """Each point's value of ``per_cluster`` ((n,) → (N,)): ``per_cluster[cid]``."""
        return np.repeat(per_cluster, self.counts)

    def run(self, cluster: int) -> slice:
        """The points of ``cluster``, as a slice."""
        return slice(self.bounds[cluster], self.bounds[cluster + 1])

    def _scatter(self, values: np.ndarray, empty) -> np.ndarray:
        if self.present.size == self.n:
            return values
        out = np.full((self.n, *values.shape[1:]), empty, values.dtype)
        out[self.present] = values
        return out


def _split_at_gaps(
    x: np.ndarray, y: np.ndarray, per: Segments, bin_m: float, config: ObstacleConfig, stride: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Split clusters at least ``split_min_length_m`` long where their points thin out along the
    major axis, and drop the thin stretches.

    Stereo smears a near obstacle's points along the viewing ray towards one behind it (a person
    6 m in front of a car at 15–20 m), and cells of a few smeared points join both into one
    cluster whose centre lies on neither. Along the major axis, in bins of ``bin_m``, a bin is a
    gap when it holds at most ``split_gap_fraction`` of the lower of the two peaks around it (the
    fullest bins before and after it), a valley between two objects; each stretch between gaps
    that holds at least ``split_min_part`` of the cluster's points (and ``min_points``) becomes a
    cluster of its own when there are two or more, and the other points are dropped. A point of
    cluster c stands for ``stride[c]`` points (:func:`_thinning`).

    ``per``: the points' clusters (sorted). Returns None when no cluster was cut, else
    ``(order, cid, parts)``: the permutation of the points that puts each cut cluster's parts one
    after the other in its run (the dropped points first, every part's points in their order),
    the new cluster of each point in that order (−1: dropped; non-decreasing otherwise, the parts
    of cluster c numbered from ``(parts[:c]).sum()``), and the clusters each cluster became (n,).
    """
    npts = per.sum()
    _, u, _ = _principal_axes(x, y, per, np.maximum(npts, 1), minor=False)  # thinned: maybe none left
    parts = np.ones(per.n, np.intp)
    cuts = []  # (cluster, part of each of its points, −1: dropped)
    for c in np.flatnonzero(per.reduce(np.maximum, u) - per.reduce(np.minimum, u) >= config.split_min_length_m):
        members = per.run(c)
        along = u[members]
        bins = ((along - along.min()) / bin_m).astype(np.intp)
        counts = np.bincount(bins)
        peak = np.minimum(np.maximum.accumulate(counts), np.maximum.accumulate(counts[::-1])[::-1])
        dense = counts > config.split_gap_fraction * peak  # an end bin is its own peak: never a gap
        stretch = np.where(dense, np.cumsum(dense & np.diff(dense, prepend=False)) - 1, -1)  # per bin
        sizes = np.bincount(stretch[dense], counts[dense])  # points per stretch, counted by bin
        kept = np.flatnonzero(sizes >= max(config.min_points / stride[c], config.split_min_part * along.size))
        if len(kept) < 2:
            continue
        part = np.full(sizes.size + 1, -1)  # [-1]: the gaps' bins
        part[kept] = np.arange(len(kept))
        cuts.append((c, part[stretch][bins]))
        parts[c] = len(kept)
    if not cuts:
        return None
    first = np.cumsum(parts) - parts  # each cluster's first new id
    cid = np.repeat(first, npts)
    order = np.arange(cid.size)
    for c, part in cuts:
        run = per.run(c)
        local = np.argsort(part, kind="stable")
        order[run] = run.start + local
        cid[run] = np.where(part < 0, -1, first[c] + part)[local]
    return order, cid, parts


def _thinning(sizes: np.ndarray, budget: int) -> np.ndarray:
    """Per cluster, the stride k (about one point in k kept, standing for k) that brings clusters of
    ``sizes`` points ((n,) ints) within ``budget`` points together (0: no limit), (n,) int64: the
    largest are thinned to one common size, the others (small obstacles) keep every point."""
    stride = np.ones(sizes.size, np.int64)
    if not budget or sizes.sum() <= budget:
        return stride
    s = np.sort(sizes)
    whole = np.concatenate([[0], np.cumsum(s)[:-1]])  # points of the k smallest, k = 0 .. n-1
    share = (budget - whole) / np.arange(s.size, 0, -1)  # for each of the other n - k
    k = np.flatnonzero(share >= np.concatenate([[0], s[:-1]]))[-1]  # the most that fit whole
    size = max(share[k], 1.0)
    big = sizes > size
    stride[big] = np.ceil(sizes[big] / size)
    return stride


def _robust_extent(w: np.ndarray, per: Segments, npts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-cluster centre and half-size along one axis, of the interval [mean − 2σ, mean + 2σ]
    cut to the points' extent. Compact objects keep their full extent (2σ of a uniform spread
    exceeds half its length); the sparse tails that stereo depth error smears out behind and in
    front of an obstacle at range are cut off instead of stretching its box."""
    mean = per.sum(w) / npts
    sigma = np.sqrt(np.maximum(per.sum(w * w) / npts - mean * mean, 0.0))
    lo = np.maximum(per.reduce(np.minimum, w), mean - 2 * sigma)
    hi = np.minimum(per.reduce(np.maximum, w), mean + 2 * sigma)
    return (lo + hi) / 2, np.maximum(hi - lo, 0.0) / 2  # (a rounded mean can put lo a hair above hi)


def _principal_axes(x: np.ndarray, y: np.ndarray, per: Segments, npts: np.ndarray, minor: bool = True):
    """Per-cluster major-axis angle (k,) and every point's coordinates (u, v) along the axes
    (``per``: the points' clusters, ``npts`` the points per cluster; v is None unless ``minor``)."""
    yaw, _ = _covariance_yaw(x, y, per, npts)
    return (yaw, *_along(x, y, per, yaw, minor))


def _covariance_yaw(x: np.ndarray, y: np.ndarray, per: Segments, npts: np.ndarray):
    """Per-cluster major-axis angle of the points' (x, y) covariance, in (−π/2, π/2], and the
    ratio of its minor to its major variance (k,) each (0 for a line, 1 for a square or a disc)."""
    mx, my = per.sum(x) / npts, per.sum(y) / npts
    sxx = per.sum(x * x) - npts * mx * mx  # float64 sums of coordinates within ~50 m: cancellation
    syy = per.sum(y * y) - npts * my * my  # costs < 1e-10 m² against variances of 1e-4 m² and more
    sxy = per.sum(x * y) - npts * mx * my
    yaw = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    half_gap = np.hypot((sxx - syy) / 2, sxy)  # half the difference of the two variances (× npts)
    # No major axis (a single point, points stacked at one spot, a square or round cluster):
    # axis-aligned, not set by rounding (the cancellation above leaves ~1e-13 m² per point).
    yaw[half_gap <= 1e-9 * (sxx + syy) + 1e-12 * npts] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(sxx + syy > 1e-12 * npts, ((sxx + syy) / 2 - half_gap) / ((sxx + syy) / 2 + half_gap), 1.0)
    return yaw, ratio


def _along(x: np.ndarray, y: np.ndarray, per: Segments, yaw: np.ndarray, minor: bool = True):
    """Every point's coordinates (u, v) along its cluster's axes at ``yaw`` (v None unless ``minor``)."""
    cos, sin = per.spread(np.cos(yaw)), per.spread(np.sin(yaw))
    return x * cos + y * sin, (y * cos - x * sin) if minor else None


_BOX_ANGLES = np.radians(np.arange(0.0, 90.0, 3.0))
"""Candidate box orientations of clusters with no clear major axis (3° apart)."""
_BOX_POINTS = 200
"""About this many points of each such cluster choose its angle."""


def _footprint_axes(x: np.ndarray, y: np.ndarray, per: Segments):
    """:func:`_principal_axes` for the footprint rectangle: where the covariance has no clear
    major axis (the minor variance over half the major: a pedestrian, a pole, a rock, a square
    box), its axis is set by noise and a rectangle along it cuts off the corners, so the yaw is
    the one of the least-area rectangle among :data:`_BOX_ANGLES` (which of its sides is the length
    the caller decides from the extents)."""
    yaw, ratio = _covariance_yaw(x, y, per, per.counts)
    round_ = np.flatnonzero(ratio > 0.5)
    if round_.size:
        # About _BOX_POINTS points of each such cluster choose its angle (its extents are then
        # taken over all of them): 0.3 ms a frame on the benchmark's cloud, 1–2 ms over every point.
        stride = np.where(ratio > 0.5, -(-per.counts // _BOX_POINTS), 0)  # 0: not such a cluster
        step = per.spread(stride)
        rank = np.arange(len(x)) - per.spread(per.bounds[:-1])  # each point's place in its cluster
        inside = (step > 0) & (rank % np.maximum(step, 1) == 0)
        sub = Segments(per.spread(np.cumsum(stride > 0) - 1)[inside], round_.size)
        xs, ys = x[inside, None], y[inside, None]
        cos, sin = np.cos(_BOX_ANGLES), np.sin(_BOX_ANGLES)
        u, v = xs * cos + ys * sin, ys * cos - xs * sin  # (points, angles)
        length, width = (sub.reduce(np.maximum, w) - sub.reduce(np.minimum, w) for w in (u, v))
        yaw[round_] = _BOX_ANGLES[np.argmin(length * width, axis=1)]
    return (yaw, *_along(x, y, per, yaw))
