"""Cubic B-spline interpolation shared by the corner refinement and the search."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.interpolation import noise_gain, spline_coefficients, spline_sample

POLY_TOL = 2e-5
"""A cubic B-spline interpolates cubic polynomials exactly; what is left is rounding of
the float32 coefficients: about 1e-7 relative to the values (up to ~90 here, so ~1e-5
at worst; 3.4e-6 measured) and the mirror boundary's transient, which decays as 0.268^d
and is far below that well inside the box."""


GAIN_TOLERANCE = 1e-5
"""The pixel weights of the interpolant are cut at ``CARDINAL_REACH`` = 10 px either side,
where they are below 2e-6; scipy's reference sees its mirror boundary 20 px away."""


def _poly(u, v):
    return 1e-4 * (u - 80) ** 3 - 2e-3 * (v - 60) ** 2 * (u - 70) / 10 + 0.5 * v + 3


def _poly_gradient(u, v):
    du = 3e-4 * (u - 80) ** 2 - 2e-3 * (v - 60) ** 2 / 10
    dv = -4e-3 * (v - 60) * (u - 70) / 10 + 0.5
    return du, dv


def test_cubic_polynomials_and_their_gradients_are_reproduced(rng):
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    points = np.stack([rng.uniform(40, 120, 200), rng.uniform(30, 90, 200)], axis=-1)
    coeffs, origin = spline_coefficients(_poly(u, v), points)
    values, gu, gv = spline_sample(coeffs, origin, points)
    np.testing.assert_allclose(values, _poly(points[:, 0], points[:, 1]), atol=POLY_TOL)
    du, dv = _poly_gradient(points[:, 0], points[:, 1])
    np.testing.assert_allclose(gu, du, atol=POLY_TOL)
    np.testing.assert_allclose(gv, dv, atol=POLY_TOL)


def test_the_box_stays_inside_the_given_columns(rng):
    """With ``cols`` the other half of a split image never enters the interpolant:
    changing it leaves every sample unchanged."""
    image = rng.normal(100.0, 20.0, (60, 120))
    points = np.stack([rng.uniform(5, 55, 50), rng.uniform(5, 55, 50)], axis=-1)
    coeffs, origin = spline_coefficients(image, points, cols=(0, 59))
    assert origin[0] >= 0 and origin[0] + coeffs.shape[1] <= 60
    other = image.copy()
    other[:, 60:] = 0.0
    again = spline_sample(*spline_coefficients(other, points, cols=(0, 59)), points)
    np.testing.assert_array_equal(spline_sample(coeffs, origin, points)[0], again[0])
    # on the pixel grid the interpolant passes through the pixels
    grid = np.array([[10.0, 20.0], [30.0, 40.0]])
    at_grid = spline_sample(*spline_coefficients(image, grid, cols=(0, 59)), grid)[0]
    np.testing.assert_allclose(at_grid, image[[20, 40], [10, 30]], rtol=1e-6)


def test_noise_gain_against_scipy():
    """The variance of interpolated unit white noise is the sum of the squared weights the
    pixels get in scipy's cubic spline interpolation (prefilter included)."""
    from scipy.ndimage import map_coordinates

    size = 41
    phases = np.array([0.0, 0.2, 0.5, 0.8])
    expected = []
    for t in phases:
        values = []
        for j in range(size):  # the interpolant of an impulse at j, sampled at 20 + t
            impulse = np.zeros(size)
            impulse[j] = 1.0
            values.append(map_coordinates(impulse, [[20.0 + t]], order=3, mode="mirror")[0])
        expected.append(np.sum(np.square(values)))
    np.testing.assert_allclose(noise_gain(phases), expected, atol=GAIN_TOLERANCE)
    assert noise_gain(np.array(0.0)) == pytest.approx(1.0, abs=GAIN_TOLERANCE)


@pytest.mark.parametrize("sigma_px", [0.0, 1.0])
def test_noise_transfer_of_a_prefilter_against_scipy(sigma_px):
    """After a prefilter ``k`` the interpolant of unit white noise has, per axis, the
    variance ``sum (w * k)^2`` and its derivative ``sum (w' * k)^2``: scipy's convolution,
    then scipy's cubic spline of each impulse (its value and derivative at 20 + t)."""
    from scipy.interpolate import make_interp_spline
    from scipy.ndimage import convolve1d

    from endomeasure.interpolation import gaussian_taps, noise_transfer

    size = 41
    taps = gaussian_taps(sigma_px)
    transfer = noise_transfer(taps)
    phases = (np.arange(64) + 0.5) / 64
    value_var, slope_var = [], []
    for t in phases:
        values, slopes = [], []
        for j in range(size):
            impulse = np.zeros(size)
            impulse[j] = 1.0
            spline = make_interp_spline(np.arange(size), convolve1d(impulse, taps, mode="constant"))
            values.append(spline(20.0 + t))
            slopes.append(spline.derivative()(20.0 + t))
        value_var.append(np.sum(np.square(values)))
        slope_var.append(np.sum(np.square(slopes)))
    np.testing.assert_allclose(transfer.gain(phases), value_var, rtol=1e-6)
    # along a unit direction in 2-D, averaged over directions and phases
    assert transfer.derivative == pytest.approx(np.mean(slope_var) * np.mean(value_var), rel=2e-3)


def test_the_correlated_share_of_a_sinusoid_is_the_prefilters_power_at_its_frequency():
    """For ``g = cos(omega u)`` the prefiltered noise keeps ``|K(omega)|^2`` of the white
    noise's variance of ``sum g n``: the taps' transform, summed directly."""
    from endomeasure.interpolation import gaussian_taps, noise_transfer

    taps = np.asarray(gaussian_taps(1.0))
    transfer = noise_transfer(tuple(taps))
    m = np.arange(taps.size) - taps.size // 2
    for omega in (0.3, 0.8, 1.5):
        g = np.tile(np.cos(omega * np.arange(400.0)), (60, 1))
        share = transfer.correlated_share(g, 31)[30, 100:300]
        expected = abs(np.sum(taps * np.exp(-1j * omega * m))) ** 2
        # a 31 px box holds a whole number of periods only by chance: a few percent
        np.testing.assert_allclose(np.median(share), expected, rtol=0.03)
    assert np.all(noise_transfer().correlated_share(g, 31) == 1.0)
