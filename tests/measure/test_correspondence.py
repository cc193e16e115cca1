"""Correspondence search (measure/correspondence.py, measure/epipolar.py).

Ground truth is independent of the search: the test renders its own images by tracing
every pixel's ray (``model.rays``) to an analytic surface with an analytic texture, and
the true match of a left pixel is ``model.project`` of the point its ray hits. The
texture is a sum of sinusoids with wavelengths of several pixels, so sampling it at the
pixel centres is free of aliasing and both halves see exactly the same signal.

Planted failures: a band without texture, a band of stripes repeating along the
epipolar direction, and points whose surface point the other half does not see.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.errors import BadInputError
from endomeasure.measure.correspondence import (
    MatchSettings,
    MatchStatus,
    estimate_noise,
    find_match,
    find_matches,
)
from endomeasure.measure.epipolar import SPACING_PX, epipolar_curve

MATCH_RMS_TOL_PX = 0.2
"""Acceptance of issue 9: matched pixels within 0.2 px RMS of the true match."""
MATCH_MAX_TOL_PX = 0.6
"""No single accepted match further than this from the truth (3x the RMS goal; the
worst seen on these renders is about 0.35 px, on a plane tilted by 39 degrees)."""
DEPTH_TOL_MM = 0.05
"""z of the matched point against the surface: 0.2 px of disparity at 11 mm is ~0.03 mm."""
RAY_GAP_TOL_MM = 0.01
"""The model is exact, so the rays of a good match nearly meet (0.2 px ~ 0.01 mm here)."""
CURVE_TOL_PX = 0.02
"""A projected ray point lies on the sampled curve within the chord error of 0.4 px
steps of a gently curved line."""
NOISE_DN = 1.0
"""Gaussian noise added to the renders before rounding to 8 bits, grey levels."""
NOISE_ESTIMATE_TOL = 0.05
"""Relative error of the robust noise estimate on pure noise over 200x200 pixels."""
PLANE_DEPTH_MM = 11.0
PLANE_NORMAL = (0.2, 0.1, -1.0)
"""A plane about 12 degrees off facing the probe (it tilts the local map between halves)."""
FLAT_BAND_MM = (-3.0, -1.4)
STRIPE_BAND_MM = (1.4, 3.0)
"""Bands (in the plane's y, mm) of the planted failures: no texture; vertical stripes."""
STRIPE_PERIOD_MM = 0.4
"""About 9 px at 11 mm: several periods along a curve of 20-40 px."""


# ----- the test renderer -------------------------------------------------------------------


def sinusoid_texture(rng: np.random.Generator, n: int = 40, wavelengths_mm=(0.2, 1.0)):
    """Albedo in [0.2, 0.8]: a sum of ``n`` plane waves of random direction and phase."""
    angle = rng.uniform(0.0, np.pi, n)
    wavelength = np.exp(rng.uniform(*np.log(wavelengths_mm), n))
    k = (2.0 * np.pi / wavelength)[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    amp = rng.uniform(0.5, 1.0, n)
    amp = amp / np.sqrt(np.sum(amp**2) / 2.0)  # unit RMS

    def texture(xy: np.ndarray) -> np.ndarray:
        return 0.5 + 0.12 * np.sum(amp * np.sin(xy @ k.T + phase), axis=-1)

    return texture


def planted_texture(base):
    """``base`` with a flat band and a band of stripes along x (smooth 0.2 mm edges)."""

    def band_weight(y, band):
        lo, hi = band
        inside = np.minimum(y - lo, hi - y)
        return np.clip(inside / 0.2 + 0.5, 0.0, 1.0)  # 1 inside the band, 0 outside

    def texture(xy: np.ndarray) -> np.ndarray:
        out = base(xy)
        w_flat = band_weight(xy[..., 1], FLAT_BAND_MM)
        out = out + w_flat * (0.5 - out)
        w_stripe = band_weight(xy[..., 1], STRIPE_BAND_MM)
        stripes = 0.5 + 0.25 * np.sin(2.0 * np.pi * xy[..., 0] / STRIPE_PERIOD_MM)
        return out + w_stripe * (stripes - out)

    return texture


class Plane:
    """A textured plane through ``centre`` with normal ``normal``; texture coordinates are
    the in-plane axes (x roughly along the camera's x, y along its y), mm."""

    def __init__(self, centre, normal, texture):
        self.centre = np.asarray(centre, dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
        self.normal = n / np.linalg.norm(n)
        e1 = -np.cross([0.0, 1.0, 0.0], self.normal)  # ~ +x for a plane facing the probe
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(self.e1, self.normal)  # ~ +y
        self.texture = texture

    def hit(self, o, d):
        t = ((self.centre - o) @ self.normal) / (d @ self.normal)
        p = o + t[..., None] * d
        rel = p - self.centre
        return p, np.stack([rel @ self.e1, rel @ self.e2], axis=-1), t > 0


class Cylinder:
    """A textured convex cylinder, axis parallel to y, front surface at z = ``z_front``;
    texture coordinates are arc length and height, mm."""

    def __init__(self, z_front, radius, texture):
        self.z_front, self.radius, self.texture = z_front, radius, texture

    def hit(self, o, d):
        r = self.radius
        ox, oz = o[..., 0], o[..., 2] - (self.z_front + r)
        a = d[..., 0] ** 2 + d[..., 2] ** 2
        b = 2.0 * (ox * d[..., 0] + oz * d[..., 2])
        c = ox**2 + oz**2 - r * r
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore"):
            t = (-b - np.sqrt(disc)) / (2.0 * a)
        p = o + t[..., None] * d
        arc = r * np.arctan2(p[..., 0], self.z_front + r - p[..., 2])
        return p, np.stack([arc, p[..., 1]], axis=-1), (disc > 0) & (t > 0)


def render(model, surface, rng, noise_dn: float = NOISE_DN, vignetting=None) -> np.ndarray:
    """8-bit image of ``surface`` through ``model``: each pixel centre's ray, both halves;
    ``vignetting(pixels, half)`` multiplies the brightness in the image plane."""
    width, height = model.config.image_size
    split = model.config.split
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    pixels = np.stack([u, v], axis=-1)
    albedo = np.full((height, width), 0.1)
    for half, cols in ((Half.LEFT, slice(0, split)), (Half.RIGHT, slice(split, width))):
        rays = model.rays(pixels[:, cols], half)
        _, xy, ok = surface.hit(rays.origins, rays.directions)
        ok &= rays.status == Status.OK
        albedo[:, cols] = np.where(ok, surface.texture(np.nan_to_num(xy)), 0.1)
        if vignetting is not None:
            albedo[:, cols] *= vignetting(pixels[:, cols], half)
    image = 255.0 * albedo + rng.normal(0.0, noise_dn, albedo.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def true_matches(model, surface, pixels):
    """Surface points of left pixels, their texture coordinates and right-half pixels."""
    rays = model.rays(pixels, Half.LEFT)
    points, xy, ok = surface.hit(rays.origins, rays.directions)
    projection = model.project(points, Half.RIGHT)
    return points, xy, projection.pixels, projection.status


def grid(model, step=4, margin=10):
    """Left-half pixel grid with room for a patch."""
    v, u = np.mgrid[margin : model.config.image_size[1] - margin : step,
                    margin : model.config.split - margin : step]  # fmt: skip
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)


# ----- scenes (rendered once per module) -----------------------------------------------------


_RENDERS: dict = {}
"""Renders cached for the module (each takes about a second)."""


@pytest.fixture(params=["pinhole", "raytrace"])
def plane_scene(request, model_factory):
    """(name, model, surface, image): a tilted plane with the planted bands."""
    name = request.param
    if name not in _RENDERS:
        model = model_factory[name]()
        rng = np.random.default_rng(11)
        texture = planted_texture(sinusoid_texture(rng))
        surface = Plane([0.0, 0.0, PLANE_DEPTH_MM], PLANE_NORMAL, texture)
        _RENDERS[name] = (name, model, surface, render(model, surface, rng))
    return _RENDERS[name]


@pytest.fixture
def cylinder_scene(model_factory):
    """(model, surface, image): a convex cylinder of 6 mm radius through the raytrace model."""
    if "cylinder" not in _RENDERS:
        model = model_factory["raytrace"]()
        rng = np.random.default_rng(12)
        surface = Cylinder(PLANE_DEPTH_MM, 6.0, sinusoid_texture(rng))
        _RENDERS["cylinder"] = (model, surface, render(model, surface, rng))
    return _RENDERS["cylinder"]


def _select(rng, candidates, count):
    assert candidates.shape[0] >= count, f"only {candidates.shape[0]} candidate points"
    return candidates[rng.choice(candidates.shape[0], count, replace=False)]


def _has_room(model, truth, room=20.0):
    """True matches with room for a patch (plus a margin) inside the right half."""
    width, height = model.config.image_size
    u, v = truth[:, 0], truth[:, 1]
    return (u > model.config.split + room) & (u < width - room) & (v > room) & (v < height - room)


def _off_bands(xy, clear=0.8):
    """Texture coordinates (mm) at least ``clear`` from a planted band, so that a patch
    and its search stay on the random texture."""
    off = np.ones(xy.shape[0], bool)
    for lo, hi in (FLAT_BAND_MM, STRIPE_BAND_MM):
        off &= (xy[:, 1] < lo - clear) | (xy[:, 1] > hi + clear)
    return off


def _textured_points(model, surface, rng, count=30):
    """Left pixels on the random texture whose true match is well inside the right half."""
    q = grid(model, step=3, margin=20)
    _, xy, truth, status = true_matches(model, surface, q)
    keep = (status == Status.OK) & _off_bands(xy) & _has_room(model, truth)
    return _select(rng, q[keep], count)


def _band_points(model, surface, rng, band, count=20):
    """Left pixels whose whole patch lies inside a planted band, true match inside."""
    q = grid(model, step=3)
    _, xy, truth, status = true_matches(model, surface, q)
    inner = (band[0] + 0.55, band[1] - 0.55)  # ~ half a 15 px patch at 11 mm, plus the edge
    keep = (status == Status.OK) & _has_room(model, truth)
    keep &= (xy[:, 1] > inner[0]) & (xy[:, 1] < inner[1])
    return _select(rng, q[keep], count)


def _errors(matches, truth):
    accepted = np.array([m.ok for m in matches])
    err = np.array([m.match - t for m, t in zip(matches, truth, strict=True) if m.ok])
    return accepted, err


# ----- epipolar curves ----------------------------------------------------------------------


def test_curve_samples_are_dense_and_on_the_projected_ray(any_model, rng):
    checked = 0
    for pixel in grid(any_model, step=40)[::3]:
        curve = epipolar_curve(any_model, pixel, Half.LEFT, (8.0, 60.0))
        inside = curve.pixels[curve.inside]
        if inside.shape[0] < 2:
            continue
        steps = np.linalg.norm(np.diff(curve.pixels, axis=0), axis=-1)
        assert np.nanmax(steps) <= SPACING_PX
        # independent: a ray point at a random depth projects onto the sampled polyline
        ray = any_model.rays(pixel, Half.LEFT)
        z = rng.uniform(8.0, 60.0)
        point = ray.origins + (z - ray.origins[2]) / ray.directions[2] * ray.directions
        q = any_model.project(point, Half.RIGHT)
        if q.status != Status.OK:
            continue
        a, b = curve.pixels[:-1], curve.pixels[1:]
        ab = b - a
        s = np.clip(np.sum((q.pixels - a) * ab, -1) / np.sum(ab * ab, -1), 0, 1)
        distance = np.nanmin(np.linalg.norm(a + s[:, None] * ab - q.pixels, axis=-1))
        assert distance < CURVE_TOL_PX
        checked += 1
    assert checked > 5


def test_curve_runs_far_to_near_uniform_in_inverse_depth(raytrace_model):
    curve = epipolar_curve(raytrace_model, np.array([290.0, 240.0]), "left", (8.0, 60.0))
    assert curve.depths_mm[0] == pytest.approx(60.0)
    assert curve.depths_mm[-1] == pytest.approx(8.0)
    step = (1 / 8 - 1 / 60) / (curve.depths_mm.size - 1)
    np.testing.assert_allclose(np.diff(1.0 / curve.depths_mm), step)
    np.testing.assert_allclose(curve.points[:, 2], curve.depths_mm)


def test_curve_of_a_pixel_outside_its_half_is_empty(pinhole_model):
    curve = epipolar_curve(pinhole_model, np.array([400.0, 240.0]), "left")
    assert curve.pixels.shape == (0, 2)
    assert curve.ray_status == Status.OUTSIDE_HALF


def test_curve_rejects_a_bad_depth_range(pinhole_model):
    with pytest.raises(ValueError, match="depth range"):
        epipolar_curve(pinhole_model, np.array([100.0, 240.0]), "left", (20.0, 10.0))


# ----- accuracy on textured surfaces -----------------------------------------------------------


def test_matches_on_a_textured_plane(plane_scene, rng):
    name, model, surface, image = plane_scene
    pixels = _textured_points(model, surface, rng)
    points, _, truth, _ = true_matches(model, surface, pixels)
    matches = find_matches(model, image, pixels, "left")
    accepted, err = _errors(matches, truth)
    assert accepted.all(), [m.message for m in matches if not m.ok]
    assert np.sqrt(np.mean(np.sum(err**2, -1))) < MATCH_RMS_TOL_PX
    assert np.linalg.norm(err, axis=-1).max() < MATCH_MAX_TOL_PX
    depth = np.array([m.depth_mm for m in matches])
    np.testing.assert_allclose(depth, points[:, 2], atol=DEPTH_TOL_MM)
    np.testing.assert_allclose(np.array([m.point for m in matches]), points, atol=3 * DEPTH_TOL_MM)
    assert max(m.ray_gap_mm for m in matches) < RAY_GAP_TOL_MM
    for m in matches:  # the diagnostics of a good match
        assert m.score > 0.9 and m.second_ratio < 0.9 and m.back_px < 1.0
        assert m.curve.shape[0] > 10 and m.message == ""


def test_matches_on_a_curved_surface(cylinder_scene, rng):
    model, surface, image = cylinder_scene
    q = grid(model, step=3, margin=20)
    _, _, truth, status = true_matches(model, surface, q)
    pixels = _select(rng, q[(status == Status.OK) & _has_room(model, truth)], 30)
    _, _, truth, _ = true_matches(model, surface, pixels)
    matches = find_matches(model, image, pixels, "left")
    accepted, err = _errors(matches, truth)
    assert accepted.all(), [m.message for m in matches if not m.ok]
    assert np.sqrt(np.mean(np.sum(err**2, -1))) < MATCH_RMS_TOL_PX
    assert np.linalg.norm(err, axis=-1).max() < MATCH_MAX_TOL_PX


VIGNETTING_SLOPE = 0.004
"""Log-brightness slope per px across each half, opposite in the two (each darker towards
its outer edge): about what the random designs' vignetting gives."""


def _dark_marks(base, centres_mm, sigma_mm=0.08):
    """``base`` with dark Gaussian spots at ``centres_mm`` (texture coordinates), some
    two pixels wide: smooth enough for the renderer's point samples."""

    def texture(xy):
        out = base(xy)
        for c in centres_mm:
            r2 = np.sum((xy - c) ** 2, axis=-1)
            out = out * (1.0 - 0.9 * np.exp(-0.5 * r2 / sigma_mm**2))
        return out

    return texture


def test_vignetting_that_differs_between_the_halves_does_not_move_the_match(raytrace_model):
    """Dark marks on texture: each half darkened towards its own edge moves a match that
    ignores the gain field across its patch; measured apart, the match stays on the truth."""
    from endomeasure.measure import correspondence

    model = raytrace_model
    rng = np.random.default_rng(21)
    marks = rng.uniform(-1.5, 1.5, (40, 2))
    surface = Plane(
        [0.0, 0.0, PLANE_DEPTH_MM],
        (0.0, 0.0, -1.0),
        _dark_marks(sinusoid_texture(rng, wavelengths_mm=(0.4, 2.0)), marks),
    )
    split, width = model.config.split, model.config.image_size[0]

    def vignetting(pixels, half):
        centre = split / 2 if half is Half.LEFT else (split + width) / 2
        sign = -1.0 if half is Half.LEFT else 1.0
        # at half the brightness, so that the brighter end stays below 8-bit saturation
        return 0.5 * np.exp(-sign * VIGNETTING_SLOPE * (pixels[..., 0] - centre))

    plain = render(model, surface, rng, noise_dn=0.0)
    shaded = render(model, surface, rng, noise_dn=0.0, vignetting=vignetting)
    rays = model.rays(grid(model, step=1, margin=0), Half.LEFT)
    points, xy, ok = surface.hit(rays.origins, rays.directions)
    at_mark = grid(model, step=1, margin=0)[np.argmin(
        np.linalg.norm(xy[:, None] - marks[None], axis=-1), axis=0)]  # fmt: skip
    _, _, truth, status = true_matches(model, surface, at_mark)
    use = (status == Status.OK) & _has_room(model, truth)
    pixels, truth = at_mark[use], truth[use]
    assert pixels.shape[0] >= 20

    def errors(image):
        accepted, err = _errors(find_matches(model, image, pixels, "left"), truth)
        out = np.full(truth.shape, np.nan)
        out[accepted] = err
        return out

    plain_err, shaded_err = errors(plain), errors(shaded)
    original = correspondence._relative_gain  # the test can fail: without the measured
    correspondence._relative_gain = lambda *args: np.zeros(2)  # field the matches move
    try:
        ignored_err = errors(shaded)
    finally:
        correspondence._relative_gain = original
    both = np.all(np.isfinite(np.hstack([plain_err, shaded_err, ignored_err])), axis=1)
    assert both.sum() >= 20
    bias = {k: e[both].mean(axis=0) for k, e in
            (("plain", plain_err), ("shaded", shaded_err), ("ignored", ignored_err))}  # fmt: skip
    rms = {k: float(np.sqrt(np.mean(e[both] ** 2))) for k, e in
           (("plain", plain_err), ("shaded", shaded_err), ("ignored", ignored_err))}  # fmt: skip
    assert np.abs(bias["shaded"] - bias["plain"]).max() < 0.005
    assert rms["shaded"] < 1.5 * rms["plain"] + 0.005, rms
    assert rms["ignored"] > 2 * rms["shaded"], rms


def test_search_from_the_right_half_finds_the_left_point(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixels = _textured_points(model, surface, rng, count=8)
    _, _, truth, _ = true_matches(model, surface, pixels)
    back = find_matches(model, image, truth, "right")
    assert all(m.ok for m in back), [m.message for m in back if not m.ok]
    err = np.array([m.match for m in back]) - pixels
    assert np.sqrt(np.mean(np.sum(err**2, -1))) < MATCH_RMS_TOL_PX
    assert all(m.half is Half.RIGHT for m in back)
    np.testing.assert_array_equal(back[0].left, back[0].match)


def test_warped_patches_beat_plain_ncc_through_the_prism(plane_scene, rng):
    """The choice of the default warp: through the biprism the halves' local scale and
    shear differ, and plain square patches match worse (and are refused more often)."""
    name, model, surface, image = plane_scene
    if name != "raytrace":
        pytest.skip("the pinhole design's halves have nearly the same local scale")
    pixels = _textured_points(model, surface, rng, count=25)
    _, _, truth, _ = true_matches(model, surface, pixels)
    rms = {}
    for warp in ("plane", "none"):
        accepted, err = _errors(
            find_matches(model, image, pixels, "left", MatchSettings(warp=warp)), truth
        )
        rms[warp] = (np.sqrt(np.mean(np.sum(err**2, -1))), accepted.mean())
    assert rms["plane"][0] < 0.5 * rms["none"][0]
    assert rms["plane"][1] >= rms["none"][1]


def test_without_the_back_search_the_match_is_the_same(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixel = _textured_points(model, surface, rng, count=1)[0]
    checked = find_match(model, image, pixel, "left")
    unchecked = find_match(model, image, pixel, "left", MatchSettings(check_back=False))
    assert checked.ok and unchecked.ok
    np.testing.assert_array_equal(unchecked.match, checked.match)
    assert np.isnan(unchecked.back_px) and checked.back_px < 1.0


def test_image_type_does_not_change_the_match(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixel = _textured_points(model, surface, rng, count=1)[0]
    grey = find_match(model, image, pixel, "left")
    deep = find_match(model, image.astype(np.uint16) * 257 + 3, pixel, "left")
    colour = find_match(model, np.repeat(image[..., None], 3, axis=2), pixel, "left")
    assert grey.ok and deep.ok and colour.ok
    np.testing.assert_allclose(deep.match, grey.match, atol=1e-6)
    np.testing.assert_allclose(colour.match, grey.match, atol=1e-9)


# ----- planted failures -----------------------------------------------------------------------


def test_untextured_points_are_refused(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixels = _band_points(model, surface, rng, FLAT_BAND_MM)
    matches = find_matches(model, image, pixels, "left")
    assert [m.status for m in matches] == [MatchStatus.UNTEXTURED] * len(matches)
    assert all(np.isnan(m.match).all() and "texture" in m.message for m in matches)
    assert not any("inf" in m.message or "nan" in m.message for m in matches)


def test_repeated_texture_is_refused_as_ambiguous(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixels = _band_points(model, surface, rng, STRIPE_BAND_MM)
    matches = find_matches(model, image, pixels, "left")
    assert [m.status for m in matches] == [MatchStatus.AMBIGUOUS] * len(matches), [
        m.message for m in matches if m.status is not MatchStatus.AMBIGUOUS
    ]
    assert all(m.second_ratio > 0.9 and np.isnan(m.match).all() for m in matches)


def test_points_seen_in_one_half_only_are_refused(plane_scene, rng):
    """Left pixels whose surface point falls outside the right half, although part of
    their epipolar curve (at other depths) has room for the patch there."""
    _, model, surface, image = plane_scene
    q = grid(model, step=2)
    _, xy, _, status = true_matches(model, surface, q)
    q = q[(status == Status.OUTSIDE_HALF) & _off_bands(xy)]
    # where each candidate's ray lands in the right half over the depth range (vectorised)
    rays = model.rays(q, Half.LEFT)
    z = np.geomspace(8.0, 60.0, 40)[:, None, None]
    t = (z - rays.origins[None, :, 2:3]) / rays.directions[None, :, 2:3]
    landing = model.project(rays.origins[None] + t * rays.directions[None], Half.RIGHT).pixels
    room = _has_room(model, landing.reshape(-1, 2), room=12.0).reshape(z.shape[0], -1)
    candidates = q[np.count_nonzero(room, axis=0) >= 2]
    pixels = _select(rng, np.array(candidates), 20)
    matches = find_matches(model, image, pixels, "left")
    assert [m.status for m in matches] == [MatchStatus.OUTSIDE] * len(matches), [
        m.message for m in matches if m.status is not MatchStatus.OUTSIDE
    ]


def test_a_point_too_close_to_its_half_edge_is_refused(plane_scene):
    _, model, _, image = plane_scene
    m = find_match(model, image, [model.config.split - 3.0, 240.0], "left")
    assert m.status is MatchStatus.OUTSIDE and "patch" in m.message


def test_a_point_outside_the_depth_range_is_refused(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixel = _textured_points(model, surface, rng, count=1)[0]
    settings = MatchSettings(depth_range_mm=(20.0, 60.0))  # the plane is at ~11 mm
    m = find_match(model, image, pixel, "left", settings)
    assert m.status is MatchStatus.OUTSIDE or m.status is MatchStatus.LOW_SCORE
    assert not m.ok and np.isnan(m.match).all()


# ----- inputs, noise, output --------------------------------------------------------------


def test_bad_inputs_are_domain_errors(pinhole_model):
    image = np.zeros((480, 640), np.uint8)
    with pytest.raises(BadInputError, match="expects 640x480"):
        find_match(pinhole_model, np.zeros((100, 100), np.uint8), [100, 100], "left")
    with pytest.raises(BadInputError, match="not in the left half"):
        find_match(pinhole_model, image, [400, 100], "left")
    with pytest.raises(BadInputError, match="patch size"):
        MatchSettings(patch=14)
    with pytest.raises(BadInputError, match="warp"):
        MatchSettings(warp="perspective")
    with pytest.raises(BadInputError, match="depth range"):
        MatchSettings(depth_range_mm=(0.0, 10.0))
    with pytest.raises(BadInputError, match="two coordinates"):
        find_match(pinhole_model, image, [100, 100, 1], "left")
    with pytest.raises(BadInputError, match="NaN"):
        find_matches(pinhole_model, image, [[np.nan, 100]], "left")


def test_noise_estimate_of_pure_noise(rng):
    sigma = 2.5
    noise = rng.normal(100.0, sigma, (200, 200))
    ramp = np.add.outer(np.arange(200.0), 0.5 * np.arange(200.0))  # cancelled by the operator
    assert estimate_noise(noise + ramp) == pytest.approx(sigma, rel=NOISE_ESTIMATE_TOL)


def test_match_to_dict_is_json_ready(plane_scene, rng):
    _, model, surface, image = plane_scene
    pixel = _textured_points(model, surface, rng, count=1)[0]
    good = find_match(model, image, pixel, "left").to_dict(curve=True)
    refused = find_match(model, image, [model.config.split - 3.0, 240.0], "left").to_dict()
    text = json.dumps([good, refused], allow_nan=False)
    back = json.loads(text)
    assert back[0]["status"] == "ok" and len(back[0]["curve"]) > 10
    assert back[1]["status"] == "outside" and back[1]["match"] == [None, None]


# ----- the simulator's scene images (an independent renderer) ---------------------------------

SAMPLES = Path(__file__).parents[2] / "sample_sessions"
MARKS_RMS_TOL_PX = MATCH_RMS_TOL_PX
"""Issue 9's acceptance on the simulator's ``scene`` images (found: about 0.05 px)."""


@pytest.mark.skipif(not (SAMPLES / "simulation.json").exists(), reason="no committed samples")
def test_marks_on_the_simulator_scene_images():
    """The committed ``scene`` set (supersampled, defocused, vignetted, noisy renders of a
    textured metal cylinder): every mark's left image is matched, within 0.2 px RMS of
    the truth model's projection of the mark into the right half."""
    import cv2

    from endomeasure.models import model_from_dict

    model = model_from_dict(json.loads((SAMPLES / "simulation.json").read_text())["truth_model"])
    errors = []
    for path in sorted((SAMPLES / "scene").glob("scene_*.json")):
        truth = json.loads(path.read_text())
        image = cv2.imread(str(path.with_name(truth["image"])), cv2.IMREAD_UNCHANGED)
        marks = np.asarray(truth["marks"]["points_mm"])
        left = model.project(marks, "left").pixels
        right = model.project(marks, "right").pixels
        matches = find_matches(model, image, left, "left")
        assert all(m.ok for m in matches), [m.message for m in matches if not m.ok]
        errors += [m.match - r for m, r in zip(matches, right, strict=True)]
    errors = np.array(errors)
    assert errors.shape[0] >= 20
    assert np.sqrt(np.mean(np.sum(errors**2, -1))) < MARKS_RMS_TOL_PX


# ----- sub-pixel sampling and the back-search confirmation (private helpers) ----------------

SHIFT_TOL_PX = 0.01
"""Refinement of a noise-free, pure sub-pixel shift of a smooth texture (spline samples:
0.005 px, the 4.5 px wavelength is not reproduced exactly); with bilinear samples the
phase-dependent blur leaves 0.04-0.07 px on this texture."""


def _texture(u, v):
    """Smooth analytic texture (wavelengths 4.5-13 px), grey levels around 128."""
    return (
        128 + 30 * np.sin(2 * np.pi * (u / 7.3 + v / 11.1))
        + 25 * np.cos(2 * np.pi * (0.8 * u - v) / 4.5)
        + 20 * np.sin(2 * np.pi * (u / 13.0 - v / 5.9) + 1.0)
    )  # fmt: skip


@pytest.mark.parametrize("shift", [(0.5, 0.25), (0.3, -0.4), (-0.15, 0.45)])
def test_refinement_recovers_a_sub_pixel_shift(shift):
    from endomeasure.measure.correspondence import _refine, _sample_spline

    v, u = np.mgrid[0:100, 0:200].astype(np.float64)
    grey = np.where(u < 100, _texture(u, v), _texture(u - 100 - shift[0], v - shift[1]))
    offsets = np.stack(np.meshgrid(np.arange(-7.0, 8), np.arange(-7.0, 8)), -1).reshape(-1, 2)
    pixel = np.array([50.37, 48.81])  # not on the grid: the template is interpolated too
    template = _sample_spline(grey, pixel + offsets, (0, 99))[0]
    truth = pixel + np.array([100.0, 0.0]) + shift
    start = truth + np.array([0.4, -0.3])
    q, _ = _refine(grey, start, offsets.copy(), offsets, template, (100, 199), 100)
    assert np.linalg.norm(q - truth) < SHIFT_TOL_PX


def test_back_search_confirms_only_with_a_credible_score():
    from endomeasure.measure.correspondence import MatchSettings, _mutual, _Search
    from endomeasure.measure.epipolar import EpipolarCurve

    m = 50
    pixels = np.stack([np.linspace(10, 60, m), np.full(m, 20.0)], -1)  # 1.02 px apart
    curve = EpipolarCurve(pixels, np.linspace(60, 8, m), np.zeros((m, 3)),
                          np.zeros(m, np.uint8), np.zeros(3), np.array([0, 0, 1.0]), 0)  # fmt: skip
    settings = MatchSettings()
    query = pixels[10]
    flat = np.full(m, 0.15)  # what a point the other half does not see meets
    flat[30] = 0.17  # best, 20 px away; the query scores 0.88 of it
    confirmed, distance = _mutual(_Search(curve, np.ones(m, bool), None, flat, 30), query,
                                  settings, 1.1)  # fmt: skip
    assert not confirmed and distance == pytest.approx(np.linalg.norm(pixels[30] - query))
    repeated = np.full(m, 0.3)
    repeated[[10, 30]] = 0.93, 0.95  # repeated texture: the query scores 0.98 of the best
    confirmed, _ = _mutual(_Search(curve, np.ones(m, bool), None, repeated, 30), query,
                           settings, 1.1)  # fmt: skip
    assert confirmed
    near = flat.copy()
    near[10] = 0.2  # the back search's own peak at the query, but not a credible score
    assert not _mutual(_Search(curve, np.ones(m, bool), None, near, 10), query, settings, 1.1)[0]
    near[10] = 0.75  # credible once corrected for noise (0.75 x 1.1 >= 0.8)
    assert _mutual(_Search(curve, np.ones(m, bool), None, near, 10), query, settings, 1.1)[0]


# ----- the predicted precision --------------------------------------------------------------


SPLINE_VARIANCE_TOL = 1e-5
"""The tabulated spline weights against scipy's spline interpolation of unit impulses
(the table's linear interpolation is exact to about 1e-7; the weights beyond 10 pixels
are below 2e-6)."""
CORRELATION_TOL = 0.01
"""Relative error of the mean correlation row sum, which leaves out weights beyond 4
pixels (below 0.005; their share of the sums is some 0.3 %)."""
WEAK_NOISE_DN = 12.0
"""Noise that makes the test plane's texture weak: predicted precisions 0.1-0.3 px, the
regime of the simulator's metal at its sensor noise, where the first-order precision
(the relative shift of two noisy patches alone) is about 2x optimistic."""
Z_RMS_RANGE = (0.75, 1.3)
"""RMS of the along-curve error in units of ``precision_px`` over some 60 matches: an
honest 1-sigma gives 1 within the sampling spread of such a count (about +-0.1) and the
model approximations (+-0.15)."""


def _impulse_weights(positions, size):
    """Spline weights of every pixel of a ``size`` x ``size`` image at ``positions``
    (n, 2), by scipy's cubic spline interpolation of unit impulses: (n, size * size)."""
    from scipy import ndimage

    out = np.empty((positions.shape[0], size * size))
    for k in range(size * size):
        impulse = np.zeros((size, size))
        impulse.flat[k] = 1.0
        out[:, k] = ndimage.map_coordinates(impulse, [positions[:, 1], positions[:, 0]],
                                            order=3, mode="mirror")  # fmt: skip
    return out


def test_interpolated_noise_variance_and_correlation_match_scipy(rng):
    from endomeasure.measure.correspondence import (
        _interpolated_noise_correlation,
        _spline_noise_variance,
    )

    size = 36
    points = rng.uniform(14, 22, (40, 2))
    weights = _impulse_weights(points, size)
    variance, gradient = _spline_noise_variance(points)
    np.testing.assert_allclose(variance, np.sum(weights**2, axis=1), atol=SPLINE_VARIANCE_TOL)
    h = 1e-4
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = h
        above = np.sum(_impulse_weights(points + step, size) ** 2, axis=1)
        below = np.sum(_impulse_weights(points - step, size) ** 2, axis=1)
        numeric = (above - below) / (2 * h)
        np.testing.assert_allclose(gradient[:, axis], numeric, atol=1e-4)
    offsets = np.stack(np.meshgrid(np.arange(-4.0, 5), np.arange(-4.0, 5)), -1).reshape(-1, 2)
    for warp in (np.eye(2), [[0.5, 0.1], [-0.05, 0.6]], [[1.8, 0.3], [0.2, 1.4]]):
        positions = 18.3 + offsets @ np.asarray(warp).T
        w = _impulse_weights(positions, size)
        correlation = w @ w.T  # of unit white pixel noise at the samples
        expected = np.mean(correlation.sum(axis=1))
        got = _interpolated_noise_correlation(positions)
        assert got == pytest.approx(expected, rel=CORRELATION_TOL)


def test_precision_is_an_honest_sigma_on_weak_texture(plane_scene):
    """Against the simulator's truth: on weak texture the along-curve errors of the
    accepted matches are ``precision_px`` in size, not twice it."""
    name, model, surface, _ = plane_scene
    if name != "raytrace":
        pytest.skip("one model suffices")
    rng = np.random.default_rng(5)
    pixels = _textured_points(model, surface, rng, count=30)
    _, _, truth, _ = true_matches(model, surface, pixels)
    z, precision = [], []
    for _ in range(2):
        image = render(model, surface, rng, noise_dn=WEAK_NOISE_DN)
        for m, t in zip(find_matches(model, image, pixels, "left"), truth, strict=True):
            if m.ok:
                k = int(np.argmin(np.linalg.norm(m.curve - m.match, axis=1)))
                tangent = m.curve[min(k + 2, len(m.curve) - 1)] - m.curve[max(k - 2, 0)]
                along = (m.match - t) @ tangent / np.linalg.norm(tangent)
                z.append(along / m.precision_px)
                precision.append(m.precision_px)
    assert len(z) >= 40
    assert 0.08 < np.median(precision) < 0.4  # the weak regime this test is about
    rms = np.sqrt(np.mean(np.square(z)))
    assert Z_RMS_RANGE[0] < rms < Z_RMS_RANGE[1], rms


def test_the_misfit_is_what_the_residual_holds_beyond_its_noise(rng):
    # oracle: residuals built from spline-interpolated white noise of known sigma (the
    # variance the function subtracts, checked against scipy above) plus a deterministic
    # difference of known RMS
    from endomeasure.measure.correspondence import _measured_misfit, _spline_noise_variance

    n, gain, s_ref, s_t = 20_000, 0.8, 2.0, 3.0
    ref = rng.uniform(10, 20, (n, 2))
    target = rng.uniform(10, 20, (n, 2))
    std = np.sqrt(gain**2 * s_ref**2 * _spline_noise_variance(ref)[0]
                  + s_t**2 * _spline_noise_variance(target)[0])  # fmt: skip
    noise = rng.normal(0.0, 1.0, n) * std
    assert _measured_misfit(noise, gain, s_ref, s_t, ref, target, 4) < 0.1 * s_t
    difference = 1.5 * np.sqrt(2.0) * np.sin(np.linspace(0, 40 * np.pi, n))  # RMS 1.5
    got = _measured_misfit(noise + difference, gain, s_ref, s_t, ref, target, 4)
    assert got == pytest.approx(1.5, rel=0.05)
    # a noise-free, perfectly fitted patch has no misfit
    assert _measured_misfit(np.zeros(n), gain, s_ref, s_t, ref, target, 4) == 0.0


def test_the_noise_level_function_recovers_a_photon_counting_sensors_noise():
    """Poisson shot noise plus Gaussian read noise on a smooth, textured scene: the fitted
    read and shot terms against the sensor's (closed form: ``sigma^2 = r^2 + g * I``)."""
    from endomeasure.measure.correspondence import noise_level

    rng = np.random.default_rng(3)
    gain_dn_per_e, read_e = 255.0 / 6000.0, 12.0
    yy, xx = np.mgrid[0:480, 0:320]
    signal_dn = 10.0 + 200.0 * np.exp(-((xx - 160) ** 2 + (yy - 240) ** 2) / (2 * 110.0**2))
    signal_dn *= 1.0 + 0.2 * np.sin(xx / 3.0) * np.cos(yy / 4.0)
    electrons = rng.poisson(signal_dn / gain_dn_per_e) + rng.normal(0.0, read_e, signal_dn.shape)
    image = np.clip(np.rint(electrons * gain_dn_per_e), 0, 255)
    fitted = noise_level(image)
    assert fitted.shot == pytest.approx(gain_dn_per_e, rel=0.1)
    for level in (20.0, 100.0, 200.0):
        truth = np.sqrt((read_e * gain_dn_per_e) ** 2 + 1 / 12 + gain_dn_per_e * level)
        assert fitted.sigma(level) == pytest.approx(truth, rel=0.1)
