"""Measurement kinds against closed forms, their vectorisation and their refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from endomeasure.errors import BadInputError
from endomeasure.measure.kinds import (
    KINDS,
    area,
    depth,
    evaluate,
    length,
    measure,
    point_line,
    polyline,
)

EXACT = 1e-12
"""Closed forms on small integers: only round-off separates the results (mm)."""


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_length_and_polyline_closed_forms():
    p = np.array([[0.0, 0.0, 10.0], [3.0, 4.0, 10.0], [3.0, 4.0, 22.0]])
    assert length(p[:2]) == pytest.approx(5.0, abs=EXACT)
    assert polyline(p) == pytest.approx(5.0 + 12.0, abs=EXACT)
    assert polyline(p[:2]) == pytest.approx(length(p[:2]), abs=EXACT)


def test_point_line_closed_form():
    # the line x = 0, z = 20 along y; the point 3 mm off in x and 4 mm off in z
    p = np.array([[0.0, -1.0, 20.0], [0.0, 5.0, 20.0], [3.0, 100.0, 24.0]])
    assert point_line(p) == pytest.approx(5.0, abs=EXACT)
    # a third point on the line measures zero (a legitimate answer, not an error)
    on_line = np.array([[0.0, -1.0, 20.0], [0.0, 5.0, 20.0], [0.0, 7.5, 20.0]])
    assert measure("point-line", on_line) == pytest.approx(0.0, abs=EXACT)


def test_depth_sign_points_towards_the_probe():
    # plane z = 20 seen from the origin; a bump towards the probe (z = 18) is +2 mm,
    # a pit behind the surface (z = 23) is -3 mm, whatever the order of the plane points
    plane = np.array([[0.0, 0.0, 20.0], [1.0, 0.0, 20.0], [0.0, 1.0, 20.0]])
    for order in ([0, 1, 2], [0, 2, 1], [2, 1, 0]):
        bump = np.vstack([plane[order], [0.3, 0.3, 18.0]])
        pit = np.vstack([plane[order], [5.0, -4.0, 23.0]])
        assert depth(bump) == pytest.approx(2.0, abs=EXACT)
        assert depth(pit) == pytest.approx(-3.0, abs=EXACT)
    # a different viewpoint on the far side flips the sign
    bump = np.vstack([plane, [0.3, 0.3, 18.0]])
    assert depth(bump, towards=np.array([0.0, 0.0, 40.0])) == pytest.approx(-2.0, abs=EXACT)


def test_depth_of_a_tilted_plane(rng):
    # plane through three points with normal n at distance 15 from the origin
    n = np.array([0.2, -0.3, 1.0])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    base = 15.0 * n
    plane = base + np.array([0 * u, 2 * u, 3 * v + u])
    for h in (-1.5, 0.0, 0.7):
        point = base + 0.4 * u - 0.9 * v - h * n  # -h along n: towards the origin for h > 0
        assert depth(np.vstack([plane, point])) == pytest.approx(h, abs=1e-12)


def test_area_of_polygons():
    square = np.array([[0.0, 0, 30], [2, 0, 30], [2, 2, 30], [0, 2, 30]])
    assert area(square) == pytest.approx(4.0, abs=EXACT)
    triangle = np.array([[0.0, 0, 10], [3, 0, 10], [0, 4, 10]])
    assert area(triangle) == pytest.approx(6.0, abs=EXACT)
    # a non-convex L-shape of area 3 (unit squares), fanned from a reflex-free vertex
    ell = np.array([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]])
    assert area(ell) == pytest.approx(3.0, abs=EXACT)
    # the same L fanned from its reflex vertex (signed triangles cancel correctly)
    assert area(np.roll(ell, -3, axis=0)) == pytest.approx(3.0, abs=EXACT)


@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_kinds_are_invariant_under_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-5, 5, (6, 3)) + [0, 0, 30]
    R = random_rotation(rng)
    t = rng.uniform(-3, 3, 3)
    q = p @ R.T + t
    for fn, n in ((length, 2), (point_line, 3), (area, 6), (polyline, 6)):
        assert fn(q[:n]) == pytest.approx(fn(p[:n]), rel=1e-9, abs=1e-9)
    # depth keeps its magnitude; its sign depends on the viewpoint, so move that too
    assert depth(q[:4], towards=t) == pytest.approx(depth(p[:4]), rel=1e-9, abs=1e-9)


def test_kinds_vectorise_over_leading_dimensions(rng):
    p = rng.uniform(-5, 5, (4, 3, 5, 3)) + [0, 0, 30]
    for kind, n in (("length", 2), ("point-line", 3), ("depth", 4), ("area", 5), ("polyline", 5)):
        values = evaluate(kind, p[..., :n, :])
        assert values.shape == (4, 3)
        assert values[2, 1] == pytest.approx(KINDS[kind].function(p[2, 1, :n]), abs=EXACT)


@pytest.mark.parametrize(
    ("kind", "points", "message"),
    [
        ("length", [[0, 0, 10]], "exactly 2 points, got 1"),
        ("length", [[0, 0, 10]] * 3, "exactly 2 points, got 3"),
        ("depth", [[0, 0, 10], [1, 0, 10], [0, 1, 10]], "exactly 4 points"),
        ("area", [[0, 0, 10], [1, 0, 10]], "at least 3 points"),
        ("polyline", [[0, 0, 10]], "at least 2 points"),
        ("length", [[1, 2, 10], [1, 2, 10]], "points 1 and 2 coincide"),
        ("polyline", [[0, 0, 10], [1, 0, 10], [1, 0, 10]], "points 2 and 3 coincide"),
        ("point-line", [[0, 0, 10], [0, 0, 10], [1, 1, 10]], "define no line"),
        ("depth", [[0, 0, 10], [1, 1, 10], [2, 2, 10], [0, 1, 9]], "collinear"),
        ("depth", [[0, 0, 10], [0, 1, 20], [0, 2, 5], [1, 0, 10]], "edge-on"),
        ("area", [[0, 0, 10], [1, 0, 10], [2, 0, 10]], "collinear"),
        ("length", [[0, 0, 10], [np.nan, 0, 10]], "could not be triangulated"),
        ("volume", [[0, 0, 10]], "unknown measurement kind"),
    ],
)
def test_bad_input_is_refused_with_one_clear_line(kind, points, message):
    with pytest.raises(BadInputError, match=message) as info:
        measure(kind, np.array(points, dtype=float))
    assert "\n" not in str(info.value)


def test_measure_returns_a_float_for_valid_points():
    value = measure("area", np.array([[0.0, 0, 30], [2, 0, 30], [2, 2, 30], [0, 2, 30]]))
    assert isinstance(value, float)
    assert value == pytest.approx(4.0, abs=EXACT)
