"""Depth profiles (issue 20) against closed forms: reference planes from exact points,
profiles of exact synthetic surfaces (the plane ``z = Z`` and a plane with a planted
step, built from the model's rays, never from the code under test), gaps, refusals; and
the dense search's profile of a rendered textured plane against that plane itself."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import make_raytrace_model
from tests.measure.dense_data import render_plane

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError
from endomeasure.measure.dense import DenseSettings, DenseStatus, DenseSurface, dense_surface
from endomeasure.measure.profile import (
    MIN_VALID_SAMPLES,
    area_profile_of,
    disc_pixels,
    path_pixels,
    plane_fit,
    plane_through_points,
    profile_of,
    slice_ends,
)

DEPTH_MM = 18.0
REGION = (240, 200, 300, 240)
SIGMA_MM = 0.01
"""1-sigma along the ray of the synthetic surfaces' points."""
EXACT_MM = 1e-9
UT_REL = 0.02
"""The UT of a linear-in-the-limit plane construction against its closed form: the
plane's tilt makes it nonlinear at the level of (sigma / extent)^2, far below this."""


@pytest.fixture(scope="module")
def model():
    return make_raytrace_model()


def _surface(model, depth_fn, status=None) -> DenseSurface:
    """A DenseSurface of REGION whose points are where each pixel's ray meets the surface
    ``z = depth_fn(x, y)`` (solved by fixed-point iteration, exact for planes)."""
    u0, v0, u1, v1 = REGION
    uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    rays = model.rays(np.stack([uu, vv], -1), Half.LEFT)
    z = np.full(uu.shape, DEPTH_MM)
    for _ in range(50):
        t = (z - rays.origins[..., 2]) / rays.directions[..., 2]
        p = rays.origins + t[..., None] * rays.directions
        z = depth_fn(p[..., 0], p[..., 1])
    st = np.zeros(uu.shape, np.uint8) if status is None else status
    ok = st == 0
    nan = np.full(uu.shape, np.nan)
    sigma = np.where(ok, SIGMA_MM, np.nan)
    return DenseSurface(REGION, np.where(ok, z, np.nan), sigma, np.where(ok[..., None], p, np.nan),
                        sigma, np.full((*uu.shape, 2), np.nan), nan, nan, np.zeros(uu.shape),
                        st, (None, None), 1, np.where(ok, 31, 0), np.zeros(uu.shape))  # fmt: skip


def test_three_point_plane_offset_sigma_is_the_closed_form(model):
    # three points on z = 18 with only z noise: the plane's height at their centroid is
    # the mean of three z's, variance sigma^2 / 3; the normal faces the probe
    pts = np.array([[-1.0, -1.0, DEPTH_MM], [1.5, -0.5, DEPTH_MM], [0.0, 1.2, DEPTH_MM]])
    cov = np.zeros((3, 3, 3))
    cov[:, 2, 2] = SIGMA_MM**2
    plane = plane_through_points(pts, cov)
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=EXACT_MM)
    assert np.sqrt(plane.cov[2, 2]) == pytest.approx(SIGMA_MM / np.sqrt(3), rel=UT_REL)


def test_collinear_reference_points_are_refused():
    pts = np.array([[0.0, 0.0, 18.0], [1.0, 1.0, 18.5], [2.0, 2.0, 19.0]])
    with pytest.raises(BadInputError, match="collinear"):
        plane_through_points(pts, np.zeros((3, 3, 3)))


def test_a_plane_against_itself_is_flat_and_a_planted_step_is_measured(model):
    step_mm, tilt = 0.2, 0.05  # a tilted plane; the right part 0.2 mm farther (a "pit")
    u_step = 270

    def depth_fn(x, y):
        return DEPTH_MM + tilt * x + 0.0 * y

    flat = _surface(model, depth_fn)
    ends = np.array([[245.0, 220.0], [295.0, 221.0]])
    areas = [disc_pixels(p, 4) for p in ends]
    from endomeasure.measure.profile import area_points

    plane = plane_fit([area_points(model, flat, a) for a in areas], window_px=9)
    prof = profile_of(model, flat, plane, path_pixels(*ends))
    assert np.nanmax(np.abs(prof.samples.height)) < 1e-6
    assert prof.coverage == 1.0 and prof.gaps == []
    # the position in mm runs along the path in the plane: the path's length at its end
    assert prof.samples.position_mm[-1] == pytest.approx(prof.length_mm, rel=1e-9)
    # the step: samples right of u_step lie step_mm behind the plane (along z; the
    # plane's normal is tilted by atan(tilt), so the height is -step cos(atan(tilt)))
    stepped = flat._replace(
        points=flat.points
        + np.where(
            (np.arange(REGION[0], REGION[2]) >= u_step)[None, :, None], [0.0, 0.0, step_mm], 0.0
        )  # fmt: skip
    )
    prof = profile_of(model, stepped, plane, path_pixels(*ends))
    expected = -step_mm / np.sqrt(1 + tilt**2)
    assert prof.deepest.height_mm == pytest.approx(expected, abs=1e-3 * step_mm)
    assert prof.deepest.pixel[0] >= u_step - 0.5
    # its sigma: the point's along its ray projected on the normal, with the plane's
    assert prof.deepest.sigma_mm >= SIGMA_MM * 0.9


def test_gaps_are_reported_never_bridged(model):
    status = np.zeros((REGION[3] - REGION[1], REGION[2] - REGION[0]), np.uint8)
    status[:, 260 - REGION[0] : 266 - REGION[0]] = DenseStatus.UNTEXTURED
    surface = _surface(model, lambda x, y: DEPTH_MM + 0 * x, status)
    ends = np.array([[245.0, 220.0], [295.0, 220.0]])
    plane = plane_fit([area_points_of(model, surface, p) for p in ends], window_px=9)
    prof = profile_of(model, surface, plane, path_pixels(*ends))
    assert len(prof.gaps) == 1
    a, b = prof.gaps[0]
    assert prof.samples.pixels[a, 0] == pytest.approx(260, abs=0.5)
    assert prof.samples.pixels[b, 0] == pytest.approx(265, abs=0.5)
    assert np.all(np.isnan(prof.samples.height[a : b + 1]))
    assert np.all(np.isfinite(prof.samples.height[:a]))
    assert prof.coverage == pytest.approx(1 - (b - a + 1) / prof.samples.height.size)


def area_points_of(model, surface, centre):
    from endomeasure.measure.profile import area_points

    return area_points(model, surface, disc_pixels(centre, 4))


def test_a_profile_without_depth_is_refused(model):
    status = np.full((REGION[3] - REGION[1], REGION[2] - REGION[0]), DenseStatus.NOT_SEEN,
                     np.uint8)  # fmt: skip
    surface = _surface(model, lambda x, y: DEPTH_MM + 0 * x)
    blind = surface._replace(status=status)
    plane = plane_fit([area_points_of(model, surface, p) for p in ((245, 220), (295, 220))], 9)
    with pytest.raises(BadInputError, match=f"fewer than {MIN_VALID_SAMPLES}"):
        profile_of(model, blind, plane, path_pixels((245, 220), (295, 220)))
    with pytest.raises(BadInputError, match="too few for a plane"):
        plane_fit([area_points_of(model, blind, p) for p in ((245, 220), (295, 220))], 9)


def test_area_profile_slices_and_the_extreme_slice(model):
    # a bump of 0.1 mm towards the probe centred on y = y0: the slices cross it at
    # different heights; the one nearest its top holds the extreme
    rays = model.rays(np.array([[270.0, 228.0]]), Half.LEFT)
    t = (DEPTH_MM - rays.origins[0, 2]) / rays.directions[0, 2]
    x0, y0 = (rays.origins[0] + t * rays.directions[0])[:2]

    def depth_fn(x, y):
        return DEPTH_MM - 0.1 * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * 0.3**2))

    surface = _surface(model, depth_fn)
    line1 = np.array([[245.0, 204.0], [245.0, 236.0]])
    line2 = np.array([[295.0, 204.0], [295.0, 236.0]])
    ends = slice_ends(line1, line2, 5)
    np.testing.assert_allclose(ends[:, 0, 1], [204, 212, 220, 228, 236])
    from endomeasure.measure.profile import area_points, line_pixels

    plane = plane_fit([area_points(model, surface, line_pixels(*line1)),
                       area_points(model, surface, line_pixels(*line2))], 9)  # fmt: skip
    area = area_profile_of(model, surface, plane, ends)
    assert area.extreme_slice == 3
    assert area.extreme.height_mm == pytest.approx(0.1, abs=0.01)
    assert len(area.slices) == 5


def test_the_dense_profile_of_a_rendered_plane_is_zero_within_its_sigma(model):
    from endomeasure.measure.profile import area_points

    image = render_plane(model, DEPTH_MM, np.random.default_rng(11))
    surface = dense_surface(model, image, (250, 200, 310, 232), DenseSettings(window_px=15))
    ends = np.array([[256.0, 216.0], [304.0, 216.0]])
    plane = plane_fit([area_points(model, surface, disc_pixels(p, 7)) for p in ends], 15)
    prof = profile_of(model, surface, plane, path_pixels(*ends))
    h, s = prof.samples.height, prof.samples.sigma
    ok = np.isfinite(h)
    assert ok.sum() >= 0.9 * h.size
    assert np.mean(np.abs(h[ok]) <= 2 * s[ok]) >= 0.9
    for e in (prof.deepest, prof.highest):
        assert abs(e.height_mm) <= 3 * e.sigma_mm
