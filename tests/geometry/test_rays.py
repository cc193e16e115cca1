"""Ray kernels against closed forms: Snell's law in its 2-D angle form, exact TIR threshold,
plane intersection and the common perpendicular."""

from __future__ import annotations

import numpy as np

from endomeasure.conventions import Status
from endomeasure.geometry.rays import common_perpendicular, intersect_plane, normalize, refract

SNELL_TOL = 1e-12  # float64 rounding of a handful of operations on unit vectors


def _frame(rng, n):
    """Random unit normals m and unit tangents t perpendicular to them."""
    m = normalize(rng.normal(size=(n, 3)))
    t = normalize(np.cross(m, rng.normal(size=(n, 3))))
    return m, t


def test_refract_matches_snell_angle_form(rng):
    n = 2000
    m, tangent = _frame(rng, n)
    n1, n2 = rng.uniform(1.0, 1.9, n), rng.uniform(1.0, 1.9, n)
    eta = n1 / n2
    # incidence angles below the critical angle where there is one
    crit = np.where(eta > 1, np.arcsin(np.minimum(1.0, 1.0 / eta)), np.pi / 2)
    theta1 = rng.uniform(0, 0.999, n) * crit
    d = -np.cos(theta1)[:, None] * m + np.sin(theta1)[:, None] * tangent  # towards the surface
    out = refract(d, m, eta)
    theta2 = np.arcsin(eta * np.sin(theta1))  # n1 sin(t1) = n2 sin(t2)
    expected = -np.cos(theta2)[:, None] * m + np.sin(theta2)[:, None] * tangent
    assert np.all(out.status == Status.OK)
    np.testing.assert_allclose(out.directions, expected, atol=SNELL_TOL, rtol=0)
    # the normal's orientation must not matter
    flipped = refract(d, -m, eta)
    np.testing.assert_allclose(flipped.directions, expected, atol=SNELL_TOL, rtol=0)


def test_total_internal_reflection_flagged_exactly_past_critical_angle(rng):
    n_glass = 1.5168
    critical = np.arcsin(1.0 / n_glass)
    m, tangent = _frame(rng, 4)
    below = critical * (1 - 1e-9)
    above = critical * (1 + 1e-9)
    for theta, expected in ((below, Status.OK), (above, Status.TOTAL_INTERNAL_REFLECTION)):
        d = -np.cos(theta) * m + np.sin(theta) * tangent
        out = refract(d, m, n_glass)  # glass -> air
        assert np.all(out.status == expected)
        assert np.all(np.isfinite(out.directions)) == (expected == Status.OK)


def test_intersect_plane_and_behind(rng):
    normal = normalize(np.array([0.1, -0.2, 1.0]))
    origins = rng.normal(size=(100, 3))
    directions = normalize(rng.normal(size=(100, 3)))
    hit = intersect_plane(origins, directions, normal, 5.0)
    ok = hit.status == Status.OK
    assert 10 < ok.sum() < 90
    np.testing.assert_allclose(hit.points[ok] @ normal, 5.0, atol=1e-12)
    assert np.all(hit.t[ok] > 0)
    assert np.all(np.isnan(hit.points[~ok]))
    assert np.all(hit.status[~ok] == Status.BEHIND)


def test_common_perpendicular_closed_form():
    # two skew lines: the x axis and a line parallel to y through (0, 0, 2)
    o1, d1 = np.array([5.0, 0, 0]), np.array([1.0, 0, 0])
    o2, d2 = np.array([0.0, -3, 2]), np.array([0.0, 1, 0])
    p = common_perpendicular(o1, d1, o2, d2)
    np.testing.assert_allclose(p.midpoint, [0, 0, 1], atol=1e-15)
    assert p.gap == 2.0 and p.s1 == -5.0 and p.s2 == 3.0
    par = common_perpendicular(o1, d1, o2, d1)
    assert par.status == Status.PARALLEL and np.isnan(par.gap)
