import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrainmap.bspline import RationalSurface, TensorFit, basis_matrix, clamped_knots


@given(
    t=st.lists(st.floats(-5, 25, allow_nan=False), min_size=1, max_size=30),
    n=st.integers(4, 30),
    degree=st.integers(1, 4),
)
@settings(max_examples=60, deadline=None)
def test_basis_is_partition_of_unity_and_nonnegative(t, n, degree):
    n = max(n, degree + 1)
    N = basis_matrix(clamped_knots(-2.0, 20.0, n, degree), degree, np.array(t))
    assert N.shape == (len(t), n)
    assert np.all(N >= -1e-12)
    np.testing.assert_allclose(N.sum(1), 1.0, atol=1e-12)
    assert np.all(np.count_nonzero(N > 1e-14, axis=1) <= degree + 1)  # local support


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_basis_derivative_matches_finite_differences(degree):
    knots = clamped_knots(0.0, 10.0, 9, degree)
    t = np.linspace(0.05, 9.95, 97)
    t = t[np.min(np.abs(t[:, None] - knots[None]), 1) > 1e-3]  # away from knots (kinks at degree 1)
    _, dN = basis_matrix(knots, degree, t, derivative=True)
    h = 1e-6
    fd = (basis_matrix(knots, degree, t + h) - basis_matrix(knots, degree, t - h)) / (2 * h)
    np.testing.assert_allclose(dN, fd, atol=1e-5)


def _random_surface(rng, n0=8, n1=6, degree=3):
    return RationalSurface(
        clamped_knots(0.0, 20.0, n0, degree),
        clamped_knots(-5.0, 5.0, n1, degree),
        degree,
        rng.normal(0, 1, (n0, n1)),
        rng.uniform(0.2, 1.0, (n0, n1)),
    )


def test_rational_gradient_matches_finite_differences():
    s = _random_surface(np.random.default_rng(3))
    x = np.linspace(0.3, 19.7, 40)
    y = np.linspace(-4.7, 4.7, 40)
    gx, gy = s.gradient(x, y)
    h = 1e-6
    np.testing.assert_allclose(gx, (s.evaluate(x + h, y) - s.evaluate(x - h, y)) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(gy, (s.evaluate(x, y + h) - s.evaluate(x, y - h)) / (2 * h), atol=1e-6)
    X, Y = np.meshgrid(x, y, indexing="ij")
    ggx, ggy = s.gradient_on_grid(x, y)
    np.testing.assert_allclose(ggx, s.gradient(X, Y)[0], atol=1e-12)
    np.testing.assert_allclose(ggy, s.gradient(X, Y)[1], atol=1e-12)
    np.testing.assert_allclose(s.on_grid(x, y), s.evaluate(X, Y), atol=1e-12)


def test_unit_weights_equal_the_non_rational_surface():
    rng = np.random.default_rng(4)
    s = _random_surface(rng)
    flat = RationalSurface(s.knots_x, s.knots_y, s.degree, s.control_points, np.ones_like(s.control_weights))
    x, y = rng.uniform(0, 20, 200), rng.uniform(-5, 5, 200)
    Bx = basis_matrix(s.knots_x, 3, x)
    By = basis_matrix(s.knots_y, 3, y)
    plain = np.einsum("mi,ij,mj->m", Bx, s.control_points, By)
    np.testing.assert_allclose(flat.evaluate(x, y), plain, atol=1e-12)


def _fit(n0=10, n1=8, degree=3):
    xs = np.linspace(0.25, 19.75, 40)
    ys = np.linspace(-4.75, 4.75, 20)
    fit = TensorFit(xs, ys, clamped_knots(0, 20, n0, degree), clamped_knots(-5, 5, n1, degree), degree)
    return fit, *np.meshgrid(xs, ys, indexing="ij")


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_fit_reproduces_polynomials_of_degree_at_most_d(degree):
    fit, X, Y = _fit(degree=degree)
    Z = 0.3 + 0.05 * X - 0.1 * Y + 0.01 * X * Y
    if degree >= 2:
        Z = Z + 0.002 * X**2 - 0.01 * Y**2 * (degree >= 2)
    if degree >= 3:
        Z = Z + 1e-4 * X**3 + 0.001 * X * Y**2
    W = np.ones_like(Z)
    R = np.ones(fit.shape)
    np.testing.assert_allclose(fit.evaluate(fit.fit(Z, W, R, smoothness=1e-6), R), Z, atol=1e-5)
    # With unequal control weights the rational basis still reproduces constants exactly.
    R = np.random.default_rng(0).uniform(0.2, 1, fit.shape)
    np.testing.assert_allclose(fit.evaluate(fit.fit(np.full_like(Z, 1.7), W, R, 1e-6), R), 1.7, atol=1e-6)


def test_fit_solves_the_weighted_rational_least_squares_problem():
    """The banded solver equals a dense solve of the same normal equations."""
    rng = np.random.default_rng(5)
    fit, X, Y = _fit()
    Z = np.sin(X / 3) + rng.normal(0, 0.05, X.shape)
    W = rng.uniform(0, 3, X.shape)
    R = rng.uniform(0.2, 1, fit.shape)
    lam = 1e-3
    Q = fit.fit(Z, W, R, lam)
    D = fit.Bx @ R @ fit.By.T
    A = (np.einsum("ai,bj,ij->abij", fit.Bx, fit.By, R) / D[..., None, None]).reshape(Z.size, -1)
    M = A.T @ (W.ravel()[:, None] * A)
    scale = np.diag(M).mean()
    n0, n1 = fit.shape

    def divided(knots, n):  # second divided differences over the Greville abscissae, × the median spacing
        xi = np.array([knots[i + 1 : i + 4].mean() for i in range(n)])  # degree 3
        h = np.diff(xi)
        D = np.zeros((n - 2, n))
        for r in range(n - 2):
            D[r, r : r + 3] = 1 / h[r], -1 / h[r] - 1 / h[r + 1], 1 / h[r + 1]
        return D * np.median(h)

    D0, D1 = divided(fit.knots_x, n0), divided(fit.knots_y, n1)
    P = np.kron(D0.T @ D0, np.eye(n1)) + np.kron(np.eye(n0), D1.T @ D1)
    dense = np.linalg.solve(M + lam * scale * P + 1e-9 * scale * np.eye(n0 * n1), A.T @ (W * Z).ravel())
    np.testing.assert_allclose(Q.ravel(), dense, atol=1e-8)


@pytest.mark.parametrize("smoothness", [1e-3, 1.0])
def test_the_smoothness_penalty_leaves_a_plane_alone_up_to_the_edges(smoothness):
    """A steep plane sampled without noise is fitted exactly, slope included, in the outermost
    cells too: the penalty is taken over the Greville abscissae, which crowd together at the
    clamped ends (by index, a plane's control heights have second differences there)."""
    fit, X, Y = _fit()
    Z = 0.1 * X + 0.577 * Y
    R = np.ones(fit.shape)
    S, gx, gy = fit.evaluate_with_gradient(fit.fit(Z, np.ones_like(Z), R, smoothness), R)
    np.testing.assert_allclose(S, Z, atol=1e-7)
    np.testing.assert_allclose(gx, 0.1, atol=1e-7)
    np.testing.assert_allclose(gy, 0.577, atol=1e-7)


def test_fit_is_well_posed_when_knot_spans_hold_no_sample():
    fit, X, Y = _fit(n0=20, n1=10)
    Z = 0.1 * X
    W = np.ones_like(Z)
    W[10:30, :] = 0.0  # half the area, many whole knot spans, carries no weight
    Q = fit.fit(Z, W, np.ones(fit.shape), smoothness=1e-3)
    S = fit.evaluate(Q, np.ones(fit.shape))
    assert np.all(np.isfinite(Q))
    np.testing.assert_allclose(S, Z, atol=1e-3)  # a plane is in the penalty's null space
