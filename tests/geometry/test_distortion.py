"""Brown distortion with one coefficient set per point (a batch of lens models)."""

from __future__ import annotations

import numpy as np

from endomeasure.geometry.distortion import distort, max_monotonic_radius2, undistort

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
