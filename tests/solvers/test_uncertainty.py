"""The propagation core: UT against linear propagation and closed forms, the textbook
sigma-point sums, Monte Carlo, fallbacks, covariance builders, the measurement black box."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Status
from endomeasure.errors import BadInputError
from endomeasure.measure.kinds import length
from endomeasure.solvers.triangulate import triangulate
from endomeasure.solvers.uncertainty import (
    MeasurementFunction,
    input_covariance,
    linearised,
    monte_carlo,
    pixel_covariance,
    propagate,
    unscented,
)

LINEAR_TOL = 1e-12
"""UT and linear propagation of a linear f are the same sums (issue 8's acceptance)."""


def random_cov(rng, L):
    a = rng.normal(size=(L, L))
    return a @ a.T / L + 0.1 * np.eye(L)


def test_linear_f_ut_and_linear_agree_to_round_off(rng):
    cov, blocks = input_covariance(
        3, 0.3, rho_images=0.4, rho_points=0.2, param_cov=random_cov(rng, 5)
    )
    L = cov.shape[0]
    a = rng.normal(size=(4, L))  # 4 measurements, each its own linear map
    x0 = rng.normal(size=(4, L))

    def f(X):
        return np.einsum("mkl,ml->mk", X, a) + 3.0

    exact = np.einsum("ml,lk,mk->m", a, cov, a)
    for alpha in (0.1, 1.0):
        ut = unscented(f, x0, cov, alpha=alpha, blocks=blocks)
        np.testing.assert_allclose(ut.std**2, exact, rtol=LINEAR_TOL)
        np.testing.assert_allclose(ut.bias, 0.0, atol=1e-12 * np.sqrt(exact).max())
    lin = linearised(f, x0, cov, blocks=blocks)
    np.testing.assert_allclose(lin.std**2, exact, rtol=LINEAR_TOL)
    np.testing.assert_allclose(ut.std**2, lin.std**2, rtol=LINEAR_TOL)
    # the budget: each block's variance is a_B^T P_B a_B
    for name, sl in blocks.items():
        part = np.einsum("ml,lk,mk->m", a[:, sl], cov[sl, sl], a[:, sl])
        np.testing.assert_allclose(ut.parts[name][1] ** 2, part, rtol=1e-10)
        np.testing.assert_allclose(lin.parts[name][1] ** 2, part, rtol=1e-10)


def textbook_ut(f, x0, cov, alpha, beta, kappa):
    """Julier's scaled UT written out with its weights (independent of the closed form)."""
    L = x0.size
    lam = alpha**2 * (L + kappa) - L
    # the square root the UT documents: eigenvectors scaled by root eigenvalues
    w, V = np.linalg.eigh(cov)
    S = np.sqrt(L + lam) * V * np.sqrt(w)
    X = np.vstack([x0, x0 + S.T, x0 - S.T])
    y = f(X[None])[0]
    wm = np.full(2 * L + 1, 1.0 / (2 * (L + lam)))
    wc = wm.copy()
    wm[0] = lam / (L + lam)
    wc[0] = wm[0] + 1.0 - alpha**2 + beta
    mean = wm @ y
    return mean, np.sqrt(wc @ (y - mean) ** 2)


@pytest.mark.parametrize(
    ("alpha", "beta", "kappa"), [(0.1, 2.0, 0.0), (1.0, 2.0, 0.0), (0.5, 1.0, 1.0)]
)
def test_ut_equals_the_textbook_weighted_sums(rng, alpha, beta, kappa):
    L = 5
    cov = random_cov(rng, L)
    x0 = rng.normal(size=L)

    def f(X):
        return np.sin(X[..., 0]) * X[..., 1] + np.exp(0.3 * X[..., 2]) + X[..., 3] ** 3 * X[..., 4]

    mean, std = textbook_ut(f, x0, cov, alpha, beta, kappa)
    ut = unscented(f, x0, cov, alpha=alpha, beta=beta, kappa=kappa)
    assert ut.mean[0] == pytest.approx(mean, rel=1e-10, abs=1e-12)
    assert ut.std[0] == pytest.approx(std, rel=1e-10)
    assert ut.value[0] == pytest.approx(f(x0[None, None])[0, 0])


def test_ut_of_a_rank_one_quadratic_is_exact_in_the_small_alpha_limit(rng):
    # f = (w.x)^2 with x ~ N(x0, P): mean m0^2 + s2, variance 4 m0^2 s2 + 2 s2^2,
    # with m0 = w.x0 and s2 = w^T P w (Gaussian moments)
    L = 6
    cov = random_cov(rng, L)
    x0 = rng.normal(size=L)
    w = rng.normal(size=L)

    def f(X):
        return (X @ w) ** 2

    m0, s2 = w @ x0, w @ cov @ w
    for alpha in (1e-3, 0.1, 1.0):  # the mean (bias) is second-order exact for any alpha
        ut = unscented(f, x0, cov, alpha=alpha)
        assert ut.bias[0] == pytest.approx(s2, rel=1e-8)
    ut = unscented(f, x0, cov, alpha=1e-3)
    assert ut.std[0] ** 2 == pytest.approx(4 * m0**2 * s2 + 2 * s2**2, rel=1e-5)
    lin = linearised(f, x0, cov)
    assert lin.std[0] ** 2 == pytest.approx(4 * m0**2 * s2, rel=1e-6)
    assert lin.bias[0] == 0.0


def quadratic(rng, L, rank):
    """f(x) = g.x + x^T A x / 2 with a symmetric A of the given rank and mixed signs."""
    V = np.linalg.qr(rng.normal(size=(L, L)))[0][:, :rank]
    A = V @ np.diag(rng.uniform(0.5, 2.0, rank) * rng.choice([-1.0, 1.0], rank)) @ V.T
    g = rng.normal(size=L)

    def f(X):
        return X @ g + 0.5 * np.einsum("...i,ij,...j->...", X, A, X)

    return f, g, A


def gaussian_moments(g, A, x0, cov):
    """Mean and variance of the quadratic for x ~ N(x0, cov) (closed form)."""
    grad = g + A @ x0
    AP = A @ cov
    mean = g @ x0 + 0.5 * x0 @ A @ x0 + 0.5 * np.trace(AP)
    return mean, grad @ cov @ grad + 0.5 * np.trace(AP @ AP)


@pytest.mark.parametrize("alpha", [0.1, 1.0])
def test_cross_points_make_the_ut_exact_for_any_quadratic(rng, alpha):
    L = 6
    cov = random_cov(rng, L)
    x0 = rng.normal(size=L)
    f, g, A = quadratic(rng, L, rank=4)
    mean, var = gaussian_moments(g, A, x0, cov)
    ut = unscented(f, x0, cov, alpha=alpha, cross=True)
    assert ut.mean[0] == pytest.approx(mean, rel=1e-9)
    assert ut.std[0] ** 2 == pytest.approx(var, rel=1e-9)

    # the plain 2L+1 points see the curvature only through tr(AP)^2 (DEFAULT_BETA): for
    # f = |x|^2 / 2 with P = I (rank L, equal curvatures) they return L^2 / 2, not L / 2
    def sq(X):
        return 0.5 * np.sum(X * X, axis=-1)

    plain = unscented(sq, np.zeros(L), np.eye(L), alpha=1e-3, cross=None)
    assert plain.mean[0] == pytest.approx(L / 2, rel=1e-9)
    assert plain.std[0] ** 2 == pytest.approx(L**2 / 2, rel=1e-5)
    exact = unscented(sq, np.zeros(L), np.eye(L), alpha=alpha, cross=True)
    assert exact.std[0] ** 2 == pytest.approx(L / 2, rel=1e-9)


def test_cross_points_on_one_block(rng):
    # curvature only in the image block; the calibration block is linear: cross points
    # on the image block alone are exact, and the parts add up to the total
    cov, blocks = input_covariance(2, 0.7, rho_images=0.3, param_cov=random_cov(rng, 3))
    L = cov.shape[0]
    x0 = rng.normal(size=L)
    f_img, g_img, A_img = quadratic(rng, 8, rank=5)
    w = rng.normal(size=3)

    def f(X):
        return f_img(X[..., :8]) + X[..., 8:] @ w

    A = np.zeros((L, L))
    A[:8, :8] = A_img
    mean, var = gaussian_moments(np.concatenate([g_img, w]), A, x0, cov)
    ut = unscented(f, x0, cov, blocks=blocks, cross=("image",))
    assert ut.mean[0] == pytest.approx(mean, rel=1e-9)
    assert ut.std[0] ** 2 == pytest.approx(var, rel=1e-9)
    img, cal = ut.parts["image"][1][0], ut.parts["calibration"][1][0]
    assert img**2 + cal**2 == pytest.approx(var, rel=1e-9)
    assert cal**2 == pytest.approx(w @ cov[8:, 8:] @ w, rel=1e-9)


def test_the_measurement_black_box_asks_for_cross_points_from_three_points(raytrace_model):
    assert MeasurementFunction(raytrace_model, length, 2).cross_columns is None
    f = MeasurementFunction(raytrace_model, length, 3, with_params=True)
    assert f.cross_columns == slice(0, 12)


def test_monte_carlo_matches_the_gaussian_moments(rng):
    L = 4
    cov = random_cov(rng, L)
    x0 = rng.normal(size=L)
    w = rng.normal(size=L)
    m0, s2 = w @ x0, w @ cov @ w
    n = 50_000
    mc = monte_carlo(lambda X: (X @ w) ** 2, x0, cov, n_samples=n, seed=7)
    std = np.sqrt(4 * m0**2 * s2 + 2 * s2**2)
    assert abs(mc.mean[0] - (m0**2 + s2)) < 4 * std / np.sqrt(n)  # 4 standard errors
    assert mc.std[0] == pytest.approx(std, rel=4 * np.sqrt(2.0 / n) * 2)  # kurtosis allowance
    again = monte_carlo(lambda X: (X @ w) ** 2, x0, cov, n_samples=n, seed=7)
    assert again.std[0] == mc.std[0]  # seeded: reproducible


def test_invalid_sigma_points_fall_back_to_a_smaller_spread():
    cov = np.eye(2)
    x0 = np.zeros((2, 2))

    def f(X):
        y = X[..., 0] * 2.0 + X[..., 1]
        # measurement 0 is invalid beyond 0.1 sigma in x; measurement 1 everywhere valid
        bad = np.zeros(X.shape[:-1], dtype=bool)
        bad[0] = np.abs(X[0, :, 0]) > 0.1
        return np.where(bad, np.nan, y)

    ut = unscented(f, x0, cov)  # alpha 0.1 -> sigma points at 0.14 sigma
    assert list(ut.n_invalid) == [2, 0]
    assert ut.alpha[0] < 0.1 and ut.alpha[1] == 0.1
    np.testing.assert_allclose(ut.std, np.sqrt(5.0), rtol=1e-12)

    def never(X):
        return np.where(np.abs(X[..., 0]) > 0, np.nan, X[..., 1])

    ut = unscented(never, x0, cov)
    assert np.all(np.isnan(ut.std)) and np.all(ut.n_invalid == 2)


def test_pixel_covariance_structure():
    s, ri, rp = 0.2, 0.5, 0.3
    P = pixel_covariance(2, s, ri, rp)
    assert P.shape == (8, 8)
    # order u_L, v_L, u_R, v_R per point
    assert P[0, 0] == pytest.approx(s**2)
    assert P[0, 1] == 0.0  # u and v independent
    assert P[0, 2] == pytest.approx(ri * s**2)  # u_L, u_R of one point
    assert P[1, 3] == pytest.approx(ri * s**2)  # v_L, v_R
    assert P[0, 4] == pytest.approx(rp * s**2)  # u_L of points 1 and 2
    assert P[0, 6] == pytest.approx(rp * ri * s**2)  # u_L of 1, u_R of 2
    assert np.linalg.eigvalsh(pixel_covariance(3, 1.0, 1.0, 1.0)).min() > -1e-12
    assert np.linalg.eigvalsh(pixel_covariance(3, 1.0, -1.0, -0.5)).min() > -1e-12


def test_pixel_covariance_per_axis():
    su, sv, ri, rp = 0.02, 0.05, 0.4, 0.2
    P = pixel_covariance(2, (su, sv), ri, rp)
    assert np.diag(P) == pytest.approx(np.tile([su**2, sv**2], 4))
    assert P[0, 2] == pytest.approx(ri * su**2)  # u_L, u_R of one point
    assert P[1, 3] == pytest.approx(ri * sv**2)  # v_L, v_R
    assert P[1, 5] == pytest.approx(rp * sv**2)  # v_L of points 1 and 2
    assert P[0, 1] == 0.0 and P[0, 5] == 0.0  # u never correlates with v
    # a pair of equal values is the scalar form
    assert pixel_covariance(3, (0.1, 0.1), ri, rp) == pytest.approx(
        pixel_covariance(3, 0.1, ri, rp)
    )


def test_per_point_std_and_halves_correlation_are_the_plain_form_when_equal():
    # oracle: the Kronecker form of pixel_covariance, whose structure is tested above
    su, sv, ri = 0.02, 0.05, 0.4
    plain = pixel_covariance(3, (su, sv), ri)
    per_point, _ = input_covariance(
        3, None, pixel_std=np.tile([su, sv, su, sv], (3, 1)), pixel_rho=np.tile([ri, ri], (3, 1))
    )
    np.testing.assert_allclose(per_point, plain, rtol=1e-15)
    # batched, one row per measurement, with the parameters' block after the pixels'
    std = np.stack([np.tile([su, sv, su, sv], (3, 1)), np.tile([sv, su, sv, su], (3, 1))])
    cov, blocks = input_covariance(
        3, None, param_cov=np.eye(2), pixel_std=std, pixel_rho=np.array([[[ri, 0.0]], [[0.0, ri]]])
    )
    assert cov.shape == (2, 14, 14) and blocks["calibration"] == slice(12, 14)
    np.testing.assert_allclose(cov[0, :12, :12], pixel_covariance(3, (su, sv), 0.0) + np.kron(
        np.eye(3), [[0, 0, ri * su**2, 0], [0, 0, 0, 0], [ri * su**2, 0, 0, 0], [0, 0, 0, 0]]
    ), rtol=1e-15)  # fmt: skip
    assert cov[1, 1, 3] == pytest.approx(ri * su**2) and cov[1, 0, 2] == 0.0
    np.testing.assert_array_equal(cov[:, 12:, 12:], np.broadcast_to(np.eye(2), (2, 2, 2)))


def test_per_axis_sigma_scales_the_depth_error_with_u_only(raytrace_model):
    """The depth of a point comes from its disparity (u); v noise barely moves it, so the
    predicted depth std must follow sigma_u."""
    p = np.array([[0.5, -0.3, 20.0]])
    f = MeasurementFunction(raytrace_model, lambda x: x[..., 0, 2], 1)
    x0 = f.inputs(
        raytrace_model.project(p, "left").pixels, raytrace_model.project(p, "right").pixels
    )
    only_u = linearised(f, x0, pixel_covariance(1, (0.03, 0.0))).std[0]
    both = linearised(f, x0, pixel_covariance(1, (0.03, 0.3))).std[0]
    assert both == pytest.approx(only_u, rel=0.05)
    only_v = linearised(f, x0, pixel_covariance(1, (0.0, 0.03))).std[0]
    assert only_v < 0.1 * only_u


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((2, -1.0), "sigma"),
        ((2, (0.1, -0.1)), "sigma"),
        ((2, (0.1, 0.1, 0.1)), "sigma"),
        ((2, 0.1, 1.5), "rho_images"),
        ((3, 0.1, 0.0, -0.6), "rho_points"),
    ],
)
def test_bad_noise_descriptions_are_refused(args, message):
    with pytest.raises(BadInputError, match=message):
        pixel_covariance(*args)


def test_unknown_method_is_refused():
    with pytest.raises(BadInputError, match="unknown propagation method"):
        propagate(lambda X: X[..., 0], np.zeros(1), np.eye(1), "taylor")


def test_measurement_function_is_triangulate_then_formula(raytrace_model, rng):
    model = raytrace_model
    pts = np.array([[[1.0, 0.5, 20.0], [3.0, 0.0, 21.0]], [[-1.0, 1.0, 15.0], [0.5, 2.0, 16.0]]])
    ql = model.project(pts, "left").pixels
    qr = model.project(pts, "right").pixels
    f = MeasurementFunction(model, length, 2, with_params=True)
    x0 = f.inputs(ql, qr)
    assert x0.shape == (2, 8 + int(model.free_mask.sum()))
    X = x0[:, None] + rng.normal(0.0, 0.05, (2, 5, x0.shape[1])) * (np.arange(x0.shape[1]) < 8)
    X[:, 0] = x0  # a repeated row: deduplicated, same answer
    values = f(X)
    pl = X[..., :8].reshape(2, 5, 2, 4)
    tri = triangulate(model, pl[..., :2], pl[..., 2:])
    assert np.all(tri.status == Status.OK)
    np.testing.assert_allclose(values, length(tri.points), rtol=1e-12)
    np.testing.assert_allclose(
        values[:, 0], np.linalg.norm(pts[:, 1] - pts[:, 0], axis=-1), atol=1e-7
    )
    # a parameter column that makes an invalid model gives NaN, not an exception
    bad = x0.copy()
    bad[0, 8 + list(np.flatnonzero(model.free_mask)).index(model.index("fx"))] = -1.0
    assert np.isnan(f(bad[:, None])[0, 0]) and np.isfinite(f(bad[:, None])[1, 0])
