"""Brown distortion with one coefficient set per point (a batch of lens models)."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.geometry.distortion import (
    distort,
    distort_coeff_jacobian,
    distort_jacobian,
    max_monotonic_radius2,
    undistort,
)

INVERSE_TOL = 1e-12
"""Newton's residual tolerance passed to undistort (normalised units); the inverse then
agrees with the scalar-coefficient call to rounding and with the forward map to it."""


def test_undistort_with_a_coefficient_set_per_point_inverts_each_points_own_map(rng):
    n = 200
    x = rng.uniform(-0.6, 0.6, n)
    y = rng.uniform(-0.45, 0.45, n)
    coeffs = [
        rng.uniform(-0.15, -0.05, n),  # k1
        rng.uniform(0.0, 0.03, n),  # k2
        rng.uniform(-1e-3, 1e-3, n),  # p1
        rng.uniform(-1e-3, 1e-3, n),  # p2
        np.zeros(n),  # k3
    ]
    xd, yd = distort(x, y, coeffs)
    batched = undistort(xd, yd, coeffs, np.full(n, INVERSE_TOL))
    assert batched.converged.all()
    np.testing.assert_allclose(batched.x, x, atol=1e-11)
    np.testing.assert_allclose(batched.y, y, atol=1e-11)
    for i in range(0, n, 37):
        own = undistort(xd[i], yd[i], [c[i] for c in coeffs], INVERSE_TOL)
        assert own.x == batched.x[i] and own.y == batched.y[i]


@pytest.mark.parametrize("size", [5, 8, 10])
def test_compiled_undistort_matches_the_array_path_step_for_step(rng, size):
    """One coefficient set takes the compiled per-point loop; the same set given per point
    takes numpy's: the same Newton steps, so the same answers and the same refusals
    (points beyond the fold-back radius included)."""
    full = (-0.3, 0.1, 1e-3, -2e-3, -0.02, 0.1, 0.02, 1e-3, 2e-3, -1e-3)[:size]
    x, y = rng.uniform(-1.2, 1.2, 2000), rng.uniform(-0.9, 0.9, 2000)
    xd, yd = distort(x, y, full)
    xd[:3] = np.nan
    compiled = undistort(xd, yd, full, INVERSE_TOL)
    per_point = undistort(xd, yd, [np.full(x.size, c) for c in full], INVERSE_TOL)
    np.testing.assert_array_equal(compiled.converged, per_point.converged)
    assert 0.9 < compiled.converged.mean() < 1.0  # some points lie beyond the fold-back
    np.testing.assert_allclose(compiled.x, per_point.x, rtol=0, atol=1e-11)
    np.testing.assert_allclose(compiled.y, per_point.y, rtol=0, atol=1e-11)


def test_fold_back_radius_per_coefficient_set():
    """Closed form for k2 = k3 = 0: 1 + 3 k1 s = 0 at s = -1 / (3 k1); no fold for k1 >= 0."""
    k1 = np.array([-0.2, -0.1, 0.05, -0.2])
    zero = np.zeros(4)
    r2 = max_monotonic_radius2(k1, zero, zero)
    np.testing.assert_allclose(r2, [1 / 0.6, 1 / 0.3, np.inf, 1 / 0.6])
    assert max_monotonic_radius2(-0.1, 0.0, 0.0) == r2[1]
    # beyond the fold, the per-point inverse is refused like the scalar one
    xd = np.array([0.5, 2.0])
    und = undistort(xd, np.zeros(2), [np.full(2, -0.2), *np.zeros((4, 2))], 1e-12)
    np.testing.assert_array_equal(und.converged, [True, False])


RATIONAL = (0.3, 0.05, 2e-4, -3e-4, 0.002, 0.5, 0.08, 0.003)
"""A strong rational lens (OpenCV order k1 k2 p1 p2 k3 k4 k5 k6), monotonic to r^2 > 4."""
IMAGE_SIDE = (-4e-4, 2.5e-4)  # p1_image, p2_image
FD_STEP = 1e-7
FD_TOL = 1e-7  # central differences at this step: truncation ~1e-14, rounding ~1e-9


def test_rational_distortion_matches_opencv(rng):
    import cv2

    x, y = rng.uniform(-1.5, 1.5, 300), rng.uniform(-1.2, 1.2, 300)
    points = np.stack([x, y, np.ones_like(x)], axis=-1)
    q, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), np.eye(3), np.array(RATIONAL))
    np.testing.assert_allclose(np.stack(distort(x, y, RATIONAL), -1), q[:, 0], atol=1e-14, rtol=0)
    und = undistort(q[:, 0, 0], q[:, 0, 1], RATIONAL, INVERSE_TOL)
    assert und.converged.all()
    np.testing.assert_allclose(und.x, x, atol=1e-11)
    np.testing.assert_allclose(und.y, y, atol=1e-11)


def test_zero_extension_coefficients_change_nothing(rng):
    """The 8 and 10 coefficient forms with their extra terms 0 are the 5-term form, bit for bit."""
    x, y = rng.uniform(-1, 1, 200), rng.uniform(-0.8, 0.8, 200)
    five = (-0.12, 0.02, 2e-4, -1e-4, -0.003)
    for longer in ((*five, 0.0, 0.0, 0.0), (*five, 0.0, 0.0, 0.0, 0.0, 0.0)):
        for f in (distort, distort_jacobian):
            for a, b in zip(f(x, y, five), f(x, y, longer), strict=True):
                np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(
            distort_coeff_jacobian(x, y, longer)[..., :5], distort_coeff_jacobian(x, y)
        )


def test_jacobians_of_every_form_match_central_differences(rng):
    x, y = rng.uniform(-1.5, 1.5, 100), rng.uniform(-1.2, 1.2, 100)
    for coeffs in (RATIONAL[:5], RATIONAL, (*RATIONAL, *IMAGE_SIDE), (*RATIONAL, 0.0, 0.0)):
        jac = np.stack(distort_jacobian(x, y, coeffs), axis=-1).reshape(-1, 2, 2)

        def at(dx, dy, c=coeffs):
            return np.stack(distort(x + dx, y + dy, c), axis=-1)

        numeric_x = (at(FD_STEP, 0.0) - at(-FD_STEP, 0.0)) / (2 * FD_STEP)
        numeric_y = (at(0.0, FD_STEP) - at(0.0, -FD_STEP)) / (2 * FD_STEP)
        np.testing.assert_allclose(jac[:, :, 0], numeric_x, atol=FD_TOL, rtol=0)
        np.testing.assert_allclose(jac[:, :, 1], numeric_y, atol=FD_TOL, rtol=0)
        by_coeff = distort_coeff_jacobian(x, y, coeffs)
        assert by_coeff.shape == (100, 2, len(coeffs))
        for i in range(len(coeffs)):
            plus, minus = list(coeffs), list(coeffs)
            plus[i] += FD_STEP
            minus[i] -= FD_STEP
            numeric = (at(0.0, 0.0, plus) - at(0.0, 0.0, minus)) / (2 * FD_STEP)
            np.testing.assert_allclose(by_coeff[:, :, i], numeric, atol=FD_TOL, rtol=0)


def test_image_side_decentering_inverts_a_pixel_to_ray_map_to_second_order(rng):
    """A lens defined from pixel to ray, ``u = g(x_d) + T_p(x_d)`` (Brown's decentering
    on the distorted point, ``g`` the inverse of a radial map ``h``): ``distort`` with the
    radial ``h`` and image-side ``-p`` recovers ``x_d`` with an error of order ``p^2``
    (halving ``p`` quarters it), the ray-side ``p1 p2`` only to order ``p``."""
    radial = (0.3, 0.05, 0.0, 0.0, 0.002, 0.5, 0.08, 0.003)
    xd, yd = rng.uniform(-1.0, 1.0, 400), rng.uniform(-0.8, 0.8, 400)
    gx = undistort(xd, yd, radial, 1e-15)  # g(x_d): the radial map's preimage
    assert gx.converged.all()

    def errors(p):
        p1, p2 = p
        r2, xy2 = xd * xd + yd * yd, 2.0 * xd * yd
        u = gx.x + p1 * xy2 + p2 * (r2 + 2.0 * xd * xd)
        v = gx.y + p1 * (r2 + 2.0 * yd * yd) + p2 * xy2
        image_side = np.stack(distort(u, v, (*radial, -p1, -p2)), -1)
        ray_side = np.stack(distort(u, v, (radial[0], radial[1], -p1, -p2, *radial[4:])), -1)
        truth = np.stack([xd, yd], -1)
        return (np.abs(image_side - truth).max(), np.abs(ray_side - truth).max())

    (img, ray), (img_half, ray_half) = errors((2e-3, -1.5e-3)), errors((1e-3, -0.75e-3))
    assert 3.5 < img / img_half < 4.5  # second order
    assert 1.5 < ray / ray_half < 2.5  # first order
    assert img < 0.05 * ray


def test_fold_back_radius_of_a_rational_factor_against_a_dense_scan(rng):
    """The first r^2 where ``r R(r^2)`` stops growing or ``R`` has a pole, by scanning."""
    s = np.linspace(0.0, 12.0, 1_200_001)
    checked = 0
    for _ in range(40):
        k = rng.uniform(-0.3, 0.3, 6) * np.array([1.0, 0.3, 0.05, 1.0, 0.3, 0.05])
        num = 1 + s * (k[0] + s * (k[1] + s * k[2]))
        den = 1 + s * (k[3] + s * (k[4] + s * k[5]))
        g = np.sqrt(s) * num / den
        bad = (np.diff(g) <= 0) | (den[1:] <= 0)
        expected = s[np.argmax(bad)] if bad.any() else np.inf
        got = max_monotonic_radius2(*k[:3], *k[3:])
        if np.isfinite(expected) and expected < 11.9:
            assert abs(got - expected) < 2e-5 * max(1.0, expected)
            checked += 1
        else:
            assert got > 11.9
    assert checked > 10
    np.testing.assert_array_equal(  # one answer per coefficient set
        max_monotonic_radius2(np.array([-0.2, -0.2]), 0.0, 0.0, np.array([0.0, 0.1]), 0.0, 0.0),
        [max_monotonic_radius2(-0.2, 0.0, 0.0), max_monotonic_radius2(-0.2, 0, 0, 0.1, 0, 0)],
    )
