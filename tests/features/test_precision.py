"""Formal precision of the symmetric corner fit against Monte Carlo on a synthetic board."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half
from endomeasure.features.boards import parse_board_spec
from endomeasure.features.precision import symmetric_precision
from endomeasure.features.subpixel import local_quadratic, symmetric_corners
from endomeasure.features.synthetic import render_split_image

from .conftest import IMAGE_SIZE, SPLIT, pose_homographies

BOARD = parse_board_spec("chessboard:6x5:1.0")
NOISE_SIGMA = 3.0
"""Grey levels: about the simulator's shot + read noise on the white squares."""
DRAWS = 160
"""Monte Carlo draws: a corner's empirical sigma is then good to 1/sqrt(2 * 160) = 5.6 %
(one standard error), the pooled figure over 30 independent corners to about 1 %."""
POOLED_TOLERANCE = 0.06
"""Pooled empirical / formal sigma ratio: 1 within 5 standard errors plus the
linearisation (measured 1.03 / 1.00 for u / v with 300 draws)."""
CORNER_TOLERANCE = 0.25
"""Any single corner's ratio: 1 within 4.5 standard errors (measured 0.87-1.13)."""
CORR_TOLERANCE = 0.25
"""The u-v correlation per corner: a correlation estimated from 160 draws has a standard
error of about 0.08."""
RESIDUAL_VARIANCE_TOLERANCE = 0.1
"""Noise variance estimated from the fit's residuals at sigma 8 grey levels: the model
misfit of the renderer's 4x4 sampling adds about 2 grey levels^2 (measured on the
noise-free render), 3 % of 64."""


@pytest.fixture(scope="module")
def scene():
    homographies = pose_homographies(
        roll_deg=8.0, tilt_deg=(15.0, -10.0), distance_mm=12.0, board_centre_mm=(2.5, 2.0)
    )
    rendered = render_split_image(
        BOARD, homographies, IMAGE_SIZE, SPLIT, blur_sigma_px=0.8, exact_float=True
    )
    image = np.ascontiguousarray(rendered.image[:, :SPLIT])
    truth = rendered.true_pixels[Half.LEFT]
    steps, curvature = local_quadratic(truth.reshape(BOARD.rows, BOARD.cols, 2))
    return image, truth, steps, curvature


def test_formal_sigma_matches_monte_carlo(scene, rng):
    image, truth, steps, curvature = scene
    formal = symmetric_precision(image, truth, steps, curvature, noise=NOISE_SIGMA**2)
    errors = []
    for _ in range(DRAWS):
        noisy = image + rng.normal(0.0, NOISE_SIGMA, image.shape)
        result = symmetric_corners(noisy, None, truth, steps=steps, curvature=curvature)
        assert result.converged.all()
        errors.append(result.pixels - truth)
    errors = np.asarray(errors)
    errors -= errors.mean(axis=0)
    empirical = np.sqrt(np.mean(errors**2, axis=0))  # (n, 2)
    pooled = np.sqrt(np.mean(empirical**2, axis=0) / np.mean(formal.sigma**2, axis=0))
    np.testing.assert_allclose(pooled, 1.0, atol=POOLED_TOLERANCE)
    np.testing.assert_allclose(empirical / formal.sigma, 1.0, atol=CORNER_TOLERANCE)
    corr = [np.corrcoef(e[:, 0], e[:, 1])[0, 1] for e in errors.transpose(1, 0, 2)]
    np.testing.assert_allclose(corr, formal.corr_uv, atol=CORR_TOLERANCE)


def test_variance_map_and_scaling(scene):
    image, truth, steps, curvature = scene
    scalar = symmetric_precision(image, truth, steps, curvature, noise=4.0)
    mapped = symmetric_precision(image, truth, steps, curvature, noise=np.full(image.shape, 4.0))
    np.testing.assert_allclose(mapped.covariance, scalar.covariance, rtol=1e-12)
    np.testing.assert_allclose(mapped.noise_variance, 4.0, rtol=1e-12)
    # the covariance is linear in the pixel variance
    doubled = symmetric_precision(image, truth, steps, curvature, noise=8.0)
    np.testing.assert_allclose(doubled.covariance, 2 * scalar.covariance, rtol=1e-12)


def test_residual_noise_estimate(scene, rng):
    image, truth, steps, curvature = scene
    sigma = 8.0
    noisy = image + rng.normal(0.0, sigma, image.shape)
    estimated = symmetric_precision(noisy, truth, steps, curvature)
    assert abs(np.median(estimated.noise_variance) / sigma**2 - 1) < RESIDUAL_VARIANCE_TOLERANCE


BINOMIAL = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]) / 16.0
"""A 3 x 3 smoothing of white noise: the correlation of bilinear demosaicing's kind."""


def _binomial_autocorrelation() -> np.ndarray:
    from scipy.signal import convolve2d

    auto = convolve2d(BINOMIAL, BINOMIAL[::-1, ::-1])
    return auto / auto[2, 2]


def _correlated_noise(rng, shape, sigma):
    """Noise of per-pixel standard deviation ``sigma`` correlated by :data:`BINOMIAL`."""
    from scipy.ndimage import convolve

    return convolve(rng.normal(0.0, sigma / np.sqrt(np.sum(BINOMIAL**2)), shape), BINOMIAL)


def test_noise_autocorrelation_of_white_and_smoothed_noise(scene, rng):
    from endomeasure.features.precision import noise_autocorrelation

    image = scene[0]
    white = noise_autocorrelation(image + rng.normal(0.0, 3.0, image.shape))
    np.testing.assert_allclose(white, np.pad([[1.0]], 2), atol=0.02)
    smoothed = noise_autocorrelation(image + _correlated_noise(rng, image.shape, 3.0))
    np.testing.assert_allclose(smoothed, _binomial_autocorrelation(), atol=0.02)


CORRELATED_DRAWS = 120
"""The pooled empirical sigma over 30 corners is then good to about 1.3 %."""


def test_formal_sigma_under_correlated_noise_matches_monte_carlo(scene, rng):
    """Noise smoothed over 3 x 3 pixels: the sandwich with its autocorrelation matches
    the scatter; assuming independent pixels understates it by half."""
    image, truth, steps, curvature = scene
    rho = _binomial_autocorrelation()
    formal = symmetric_precision(image, truth, steps, curvature, noise=NOISE_SIGMA**2,
                                 correlated=rho)  # fmt: skip
    white = symmetric_precision(image, truth, steps, curvature, noise=NOISE_SIGMA**2)
    errors = []
    for _ in range(CORRELATED_DRAWS):
        noisy = image + _correlated_noise(rng, image.shape, NOISE_SIGMA)
        result = symmetric_corners(noisy, None, truth, steps=steps, curvature=curvature)
        assert result.converged.all()
        errors.append(result.pixels - truth)
    errors = np.asarray(errors)
    errors -= errors.mean(axis=0)
    empirical = np.sqrt(np.mean(errors**2, axis=(0, 1)))  # (2,) pooled over corners
    pooled = np.sqrt(np.mean(formal.sigma**2, axis=0))
    np.testing.assert_allclose(empirical / pooled, 1.0, atol=POOLED_TOLERANCE)
    assert np.all(empirical / np.sqrt(np.mean(white.sigma**2, axis=0)) > 1.5)


def test_residual_noise_estimate_under_correlated_noise(scene, rng):
    """With the noise estimated from the image, the variance and autocorrelation come out
    right, so the formal sigma is the sandwich's above."""
    from endomeasure.features.precision import noise_autocorrelation

    image, truth, steps, curvature = scene
    sigma = 8.0  # as in the residual test: the render's misfit stays a few per cent
    noisy = image + _correlated_noise(rng, image.shape, sigma)
    estimated = symmetric_precision(noisy, truth, steps, curvature)
    assert abs(np.median(estimated.noise_variance) / sigma**2 - 1) < RESIDUAL_VARIANCE_TOLERANCE
    np.testing.assert_allclose(noise_autocorrelation(noisy), _binomial_autocorrelation(),
                               atol=0.03)  # fmt: skip
    exact = symmetric_precision(noisy, truth, steps, curvature, noise=sigma**2,
                                correlated=_binomial_autocorrelation())  # fmt: skip
    ratio = np.sqrt(np.mean(estimated.sigma**2, axis=0) / np.mean(exact.sigma**2, axis=0))
    np.testing.assert_allclose(ratio, 1.0, atol=RESIDUAL_VARIANCE_TOLERANCE)
