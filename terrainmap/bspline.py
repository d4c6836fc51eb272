"""Rational B-spline tensor-product surfaces (paper Sec. V, eq. 2) and their weighted fit.

The surface over the vehicle-frame plane is the ratio of two sums (eq. 2, read as NURBS)::

    S(x, y) = Σ_ij R_ij N_i(x) N_j(y) Q_ij  /  Σ_ij R_ij N_i(x) N_j(y)

with clamped, uniform knot vectors over the area of interest, degree ``d`` on both axes,
control heights ``Q`` (n0×n1, metres) and control weights ``R`` (n0×n1, dimensionless, > 0).
With ``R`` fixed the surface is linear in ``Q``, so fitting it to weighted samples is a
weighted linear least-squares problem (:class:`TensorFit`). ``R ≡ 1`` gives the ordinary
(non-rational) B-spline surface, since the basis is a partition of unity.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg import lapack

from .errors import FrameError, InputError


def clamped_knots(lo: float, hi: float, n_ctrl: int, degree: int) -> np.ndarray:
    """Clamped uniform knot vector over ``[lo, hi]`` for ``n_ctrl`` control points.

    Returns ``n_ctrl + degree + 1`` knots: ``degree + 1`` copies of each end and
    ``n_ctrl - degree - 1`` uniformly spaced interior knots.
    """
    if n_ctrl < degree + 1:
        raise ValueError(f"{n_ctrl} control points cannot carry a degree-{degree} spline")
    inner = np.linspace(lo, hi, n_ctrl - degree + 1)
    return np.concatenate([np.full(degree, lo), inner, np.full(degree, hi)])


def basis_matrix(knots: np.ndarray, degree: int, t: np.ndarray, derivative: bool = False):
    """B-spline basis functions ``N_{i,degree}(t)`` (Cox–de Boor), vectorised over ``t``.

    Parameters
    ----------
    knots : (n_ctrl + degree + 1,) non-decreasing array
    t : (m,) parameters; values outside the knot range are clamped to it, and the right end
        belongs to the last span (so the basis is a partition of unity on the closed range).
    derivative : also return ``dN/dt``.

    Returns
    -------
    N : (m, n_ctrl) float64, and ``dN`` of the same shape when ``derivative`` is true.
    """
    t = np.clip(np.asarray(t, dtype=np.float64).ravel(), knots[0], knots[-1])[:, None]
    m = len(knots) - 1
    N = ((knots[:-1] <= t) & (t < knots[1:])).astype(np.float64)
    last = np.flatnonzero(knots[:-1] < knots[1:])[-1]
    N[t[:, 0] >= knots[-1], last] = 1.0
    prev = N
    for p in range(1, degree + 1):
        prev = N
        d1 = knots[p:m] - knots[: m - p]
        d2 = knots[p + 1 : m + 1] - knots[1 : m - p + 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(d1 > 0, (t - knots[: m - p]) / d1, 0.0)
            b = np.where(d2 > 0, (knots[p + 1 : m + 1] - t) / d2, 0.0)
        N = a * prev[:, : m - p] + b * prev[:, 1 : m - p + 1]
    if not derivative:
        return N
    if degree == 0:
        return N, np.zeros_like(N)
    d1 = knots[degree:m] - knots[: m - degree]
    d2 = knots[degree + 1 : m + 1] - knots[1 : m - degree + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        c1 = np.where(d1 > 0, degree / d1, 0.0)
        c2 = np.where(d2 > 0, degree / d2, 0.0)
    dN = c1 * prev[:, : m - degree] - c2 * prev[:, 1 : m - degree + 1]
    return N, dN


@dataclass(frozen=True)
class RationalSurface:
    """A rational B-spline tensor-product surface ``z = S(x, y)`` (eq. 2), vehicle frame, metres.

    ``control_points`` is Q (n0×n1, metres), ``control_weights`` is R (n0×n1, > 0),
    ``knots_x``/``knots_y`` the clamped knot vectors, ``degree`` the degree on both axes.
    Outside the knot range (the area of interest) the surface and its gradient are those at the
    nearest point of the range: the map says nothing there, so it extends its edge.
    """

    knots_x: np.ndarray
    knots_y: np.ndarray
    degree: int
    control_points: np.ndarray
    control_weights: np.ndarray

    def _parts(self, Bx, By, dBx=None, dBy=None):
        """Numerator/denominator (and derivatives) from per-point bases, shapes (m, n0)/(m, n1)."""
        R, RQ = self.control_weights, self.control_weights * self.control_points
        out = [np.einsum("mi,ij,mj->m", Bx, M, By) for M in (RQ, R)]
        if dBx is not None:
            out += [np.einsum("mi,ij,mj->m", dBx, M, By) for M in (RQ, R)]
            out += [np.einsum("mi,ij,mj->m", Bx, M, dBy) for M in (RQ, R)]
        return out

    def evaluate(self, x, y) -> np.ndarray:
        """Height S(x, y), metres, for broadcastable arrays ``x``, ``y`` (metres)."""
        x, y = xy_arrays("surface", x, y)
        Bx = basis_matrix(self.knots_x, self.degree, x)
        By = basis_matrix(self.knots_y, self.degree, y)
        num, den = self._parts(Bx, By)
        return (num / den).reshape(x.shape)

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Analytic ``(∂S/∂x, ∂S/∂y)`` (dimensionless) by the quotient rule."""
        x, y = xy_arrays("surface", x, y)
        Bx, dBx = basis_matrix(self.knots_x, self.degree, x, derivative=True)
        By, dBy = basis_matrix(self.knots_y, self.degree, y, derivative=True)
        num, den, num_x, den_x, num_y, den_y = self._parts(Bx, By, dBx, dBy)
        gx = (num_x * den - num * den_x) / den**2
        gy = (num_y * den - num * den_y) / den**2
        return gx.reshape(x.shape), gy.reshape(x.shape)

    def on_grid(self, xs, ys) -> np.ndarray:
        """Heights on the lattice ``xs × ys``: array (len(xs), len(ys)), ``[ix, iy]``."""
        Bx = basis_matrix(self.knots_x, self.degree, xs)
        By = basis_matrix(self.knots_y, self.degree, ys)
        R = self.control_weights
        return (Bx @ (R * self.control_points) @ By.T) / (Bx @ R @ By.T)

    def gradient_on_grid(self, xs, ys) -> tuple[np.ndarray, np.ndarray]:
        """Analytic gradient on the lattice ``xs × ys``: two arrays (len(xs), len(ys))."""
        Bx, dBx = basis_matrix(self.knots_x, self.degree, xs, derivative=True)
        By, dBy = basis_matrix(self.knots_y, self.degree, ys, derivative=True)
        return _on_lattice(Bx, dBx, By, dBy, self.control_points, self.control_weights)[1:]


def _on_lattice(Bx, dBx, By, dBy, Q, R) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(S, ∂S/∂x, ∂S/∂y)`` on a lattice, each (m0, m1), by the quotient rule, from the bases
    ``Bx`` (m0, n0), ``By`` (m1, n1), their derivatives, control points Q and weights R (n0, n1)."""
    RQ = R * Q
    num_y, den_y = RQ @ By.T, R @ By.T  # (n0, m1)
    num, den = Bx @ num_y, Bx @ den_y
    gx = ((dBx @ num_y) * den - num * (dBx @ den_y)) / den**2
    gy = ((Bx @ RQ @ dBy.T) * den - num * (Bx @ R @ dBy.T)) / den**2
    return num / den, gx, gy


class TensorFit:
    """Weighted least-squares fit of Q for samples on a fixed lattice and a fixed control net.

    Minimises ``Σ_ab W_ab (S(x_a, y_b) − Z_ab)² + λ (‖Δ²_x Q‖² + ‖Δ²_y Q‖²)`` for given sample
    weights W (m0×m1, ≥ 0) and control weights R (n0×n1, > 0). The second-difference penalty
    (λ = ``smoothness`` × the mean diagonal of the data term; over the Greville abscissae, so
    planes cost nothing, see :func:`_penalty_band`) keeps the problem well-posed where whole knot
    spans hold no sample, without pulling the surface towards zero; its null space (bilinear
    surfaces) is fixed by the data.

    The normal matrix of the tensor-product basis is banded (bandwidth d·n1 + d with the
    control points ordered ``i·n1 + j``). It is assembled from (d+1)·(2d+1) small matrix products
    of the 1-D bases and solved by banded Cholesky — about a millisecond at 25×25 control points,
    with everything that depends only on the net precomputed here (build one per net size).
    """

    def __init__(self, xs: np.ndarray, ys: np.ndarray, knots_x: np.ndarray, knots_y: np.ndarray, degree: int):
        self.knots_x, self.knots_y, self.degree = knots_x, knots_y, degree
        self.xs, self.ys = xs, ys
        self._dB: tuple[np.ndarray, np.ndarray] | None = None  # derivative bases, built on first use
        self.Bx = basis_matrix(knots_x, degree, xs)  # (m0, n0)
        self.By = basis_matrix(knots_y, degree, ys)  # (m1, n1)
        n0, n1 = self.Bx.shape[1], self.By.shape[1]
        self.shape = (n0, n1)
        d = degree
        # Products of 1-D bases at column offsets p (x) and q (y): BBx[p][a, i] = Bx[a, i]·Bx[a, i+p].
        self.BBx = np.stack([_shifted_product(self.Bx, p) for p in range(d + 1)])  # (d+1, m0, n0)
        self.BBy = np.stack([_shifted_product(self.By, q) for q in range(-d, d + 1)])  # (2d+1, m1, n1)
        self.band = max(d, 2) * n1 + d
        self._dest, self._src, self._rows, self._cols = _band_layout(n0, n1, d, self.band)
        self._penalty = _penalty_band(greville(knots_x, d), greville(knots_y, d), self.band)

    def fit(self, Z: np.ndarray, W: np.ndarray, R: np.ndarray, smoothness: float) -> np.ndarray:
        """Control heights Q (n0×n1) for samples Z (m0×m1), weights W (m0×m1) and R (n0×n1).

        Raises :class:`FrameError` (reason ``fit_failed``) if the system cannot be solved.
        """
        D = self.Bx @ R @ self.By.T  # denominator of eq. 2 on the lattice, > 0
        Wd = W / (D * D)
        # T[p, q] = BBx_p^T · Wd · BBy_q: the data normal matrix for offset (p, q).
        U = np.matmul(self.BBx.transpose(0, 2, 1), Wd)  # (d+1, n0, m1)
        T = np.matmul(U[:, None], self.BBy[None])  # (d+1, 2d+1, n0, n1)
        r = R.ravel()
        ab = np.zeros((self.band + 1, r.size))
        ab.ravel()[self._dest] = T.ravel()[self._src] * r[self._rows] * r[self._cols]
        scale = ab[self.band].mean()
        if not np.isfinite(scale) or scale <= 0:
            raise FrameError("fit_failed", "no sample carries weight in the spline fit")
        ab += (smoothness * scale) * self._penalty
        ab[self.band] += 1e-9 * scale  # ridge: keeps Cholesky positive definite in degenerate cases
        rhs = R * (self.Bx.T @ (W * Z / D) @ self.By)
        _, q, info = lapack.dpbsv(ab, rhs.ravel(), lower=0, overwrite_ab=1, overwrite_b=1)
        if info != 0:
            raise FrameError("fit_failed", f"spline fit could not be solved (LAPACK dpbsv info {info})")
        return q.reshape(self.shape)

    def evaluate(self, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Surface heights on the fit lattice, (m0, m1)."""
        return (self.Bx @ (R * Q) @ self.By.T) / (self.Bx @ R @ self.By.T)

    def evaluate_with_gradient(self, Q: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(S, ∂S/∂x, ∂S/∂y)`` on the fit lattice, each (m0, m1), by the quotient rule."""
        if self._dB is None:
            self._dB = (basis_matrix(self.knots_x, self.degree, self.xs, derivative=True)[1],
                        basis_matrix(self.knots_y, self.degree, self.ys, derivative=True)[1])
        dBx, dBy = self._dB
        return _on_lattice(self.Bx, dBx, self.By, dBy, Q, R)

    def remap(self, W: np.ndarray) -> np.ndarray:
        """Down-sample lattice values W (m0×m1) to the control net: the basis-weighted mean of W
        over each control point's support, (n0, n1); 0 where W is 0 over the whole support (the
        caller bounds it: R in :mod:`terrainmap.terrain`), the overall mean of W where the support
        holds no lattice node (a net finer than the lattice)."""
        num = self.Bx.T @ W @ self.By
        den = self.Bx.sum(0)[:, None] * self.By.sum(0)[None, :]
        mean = W.mean() if W.size else 1.0
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 1e-12, num / den, mean)

    def surface(self, Q: np.ndarray, R: np.ndarray) -> RationalSurface:
        return RationalSurface(self.knots_x, self.knots_y, self.degree, Q, R)


def xy_arrays(what: str, x, y) -> tuple[np.ndarray, np.ndarray]:
    """``x``, ``y`` (m) as broadcast float64 arrays, or :class:`InputError` naming ``what`` and
    saying why they are not."""
    try:
        return np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: x and y must be broadcastable arrays of numbers ({exc})") from None


def _shifted_product(B: np.ndarray, offset: int) -> np.ndarray:
    """``out[a, i] = B[a, i] · B[a, i + offset]`` (0 where ``i + offset`` is out of range)."""
    out = np.zeros_like(B)
    n = B.shape[1]
    if offset >= 0:
        out[:, : n - offset] = B[:, : n - offset] * B[:, offset:]
    else:
        out[:, -offset:] = B[:, -offset:] * B[:, : n + offset]
    return out


@lru_cache(maxsize=64)
def _band_layout(n0: int, n1: int, d: int, band: int):
    """Index arrays that scatter T[p, q][i, j] into LAPACK upper banded storage.

    Entry M[r, c] with r = i·n1 + j, c = (i+p)·n1 + (j+q), c ≥ r, goes to ab[band + r − c, c].
    Returns (dest into ab.ravel(), src into T.ravel(), r, c).
    """
    n = n0 * n1
    i, j = np.meshgrid(np.arange(n0), np.arange(n1), indexing="ij")
    dest, src, rows, cols = [], [], [], []
    for p in range(d + 1):
        for qi, q in enumerate(range(-d, d + 1)):
            if p == 0 and q < 0:
                continue
            ok = (i + p < n0) & (j + q >= 0) & (j + q < n1)
            r = (i * n1 + j)[ok]
            c = ((i + p) * n1 + j + q)[ok]
            dest.append((band + r - c) * n + c)
            src.append(((p * (2 * d + 1) + qi) * n0 + i[ok]) * n1 + j[ok])
            rows.append(r)
            cols.append(c)
    return tuple(np.concatenate(a) for a in (dest, src, rows, cols))


@lru_cache(maxsize=64)
def _penalty_band(greville_x: tuple[float, ...], greville_y: tuple[float, ...], band: int) -> np.ndarray:
    """Second-difference penalty (Δ²_x ⊗ I + I ⊗ Δ²_y)ᵀ(…) in upper banded storage, over the
    control points' Greville abscissae (the mean of their d inner knots): divided differences,
    scaled by the median spacing, so that a linear function of x or y (a plane: control heights
    linear in the abscissae) costs nothing, also near the clamped ends, where the abscissae
    crowd together; where they are evenly spaced, the plain second difference of the heights."""

    def second_diff_gram(greville: tuple[float, ...]) -> np.ndarray:
        n = len(greville)
        if n < 3:
            return np.zeros((n, n))
        spacing = np.diff(greville)
        slopes = np.diff(np.eye(n), axis=0) / spacing[:, None]  # (n-1, n): first divided differences
        D = np.diff(slopes, axis=0) * np.median(spacing)
        return D.T @ D

    n0, n1 = len(greville_x), len(greville_y)
    P = np.kron(second_diff_gram(greville_x), np.eye(n1)) + np.kron(np.eye(n0), second_diff_gram(greville_y))
    n = n0 * n1
    ab = np.zeros((band + 1, n))
    for k in range(min(band, n - 1) + 1):
        ab[band - k, k:] = np.diagonal(P, k)
    ab.setflags(write=False)
    return ab


def greville(knots: np.ndarray, degree: int) -> tuple[float, ...]:
    """The Greville abscissae of the control points of ``knots`` (clamped), m: the mean of each
    one's ``degree`` inner knots; a spline whose control heights are a + b·ξ is a + b·x."""
    n = len(knots) - degree - 1
    return tuple(float(np.mean(knots[i + 1 : i + degree + 1])) for i in range(n))
