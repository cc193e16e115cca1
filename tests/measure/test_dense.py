"""Dense correspondence against a textured plane rendered through a known model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tests.conftest import make_raytrace_model
from tests.measure.dense_data import render_plane

from endomeasure.errors import BadInputError
from endomeasure.measure.dense import DenseSettings, DenseStatus, dense_surface, gates_at

DEPTH_MM = 18.0
REGION = (250, 200, 310, 260)  # where both halves of the test model overlap at 12-30 mm
SETTINGS = DenseSettings(depth_range_mm=(12.0, 30.0), window_px=15)
"""A 15 px window: the 60 px region lies near the edge of the overlap, where a larger
window leaves the right half."""
MIN_VALID = 0.85
"""Share of the region's pixels measured: the plane is textured everywhere and both
halves see it, so only texture-poor windows may be refused."""
MIN_INSIDE_2SIGMA = 0.85
"""Share of depth errors inside the predicted 2 sigma (95 % for a Gaussian error; the
margin holds the sampling of some 5000 correlated pixels)."""


@pytest.fixture(scope="module")
def plane():
    model = make_raytrace_model()
    image = render_plane(model, DEPTH_MM, np.random.default_rng(7))
    return model, image, dense_surface(model, image, REGION, SETTINGS)


def test_dense_depth_of_a_textured_plane_is_right_within_its_sigma(plane):
    _, _, surface = plane
    ok = surface.status == DenseStatus.OK
    assert surface.depth.shape == (60, 60)
    assert ok.mean() >= MIN_VALID
    err = surface.depth[ok] - DEPTH_MM
    assert np.mean(np.abs(err) <= 2 * surface.sigma_depth[ok]) >= MIN_INSIDE_2SIGMA
    assert np.median(np.abs(err)) < 0.01 * DEPTH_MM
    assert np.all(np.isnan(surface.depth[~ok]))
    # the points lie on their left rays at that depth
    assert np.allclose(surface.points[ok][:, 2], surface.depth[ok])


def _plane_w(model, depth_mm):
    width, height = model.config.image_size
    return np.full((height, model.config.split), 1.0 / depth_mm)


def test_the_gates_at_the_true_plane_bound_the_search(plane):
    """At the true surface the gates pass every pixel the search measured (it found
    nearly that surface) and more than the test's coverage; at a surface 6 mm off the
    windows no longer correlate."""
    model, image, surface = plane
    truth = gates_at(model, image, _plane_w(model, DEPTH_MM), REGION, SETTINGS)
    assert truth.passed.shape == surface.status.shape
    ok = surface.status == DenseStatus.OK
    assert truth.passed.mean() >= max(MIN_VALID, ok.mean() - 0.01)
    assert np.all(truth.precision_px[truth.passed] <= SETTINGS.max_precision_px)
    wrong = gates_at(model, image, _plane_w(model, DEPTH_MM + 6.0), REGION, SETTINGS)
    assert wrong.passed.mean() < 0.05
    blank = np.full_like(image, 100)
    assert not gates_at(model, blank, _plane_w(model, DEPTH_MM), REGION, SETTINGS).passed.any()


def test_a_blank_frame_is_refused_not_guessed():
    model = make_raytrace_model()
    image = np.full((480, 640), 100, dtype=np.uint8)
    surface = dense_surface(model, image, REGION, SETTINGS)
    assert not np.any(surface.status == DenseStatus.OK)
    assert np.all(np.isnan(surface.depth))


@pytest.mark.parametrize("region", [(400, 10, 500, 100), (10, 10, 10, 50), (0, 500, 50, 600)])
def test_a_region_outside_the_left_half_is_refused(plane, region):
    model, image, _ = plane
    with pytest.raises(BadInputError):
        dense_surface(model, image, region, SETTINGS)


def test_a_region_the_right_half_does_not_see_is_refused_as_input(plane):
    """Outside the overlap (the test model's right half sees none of the left half's
    outer edge at 12-30 mm) nothing can be measured whatever the image: bad input, not a
    failed measurement; the same region moved into the overlap is searched."""
    model, image, _ = plane
    outside = (0, 240, 40, 280)
    with pytest.raises(BadInputError, match="outside the overlap"):
        dense_surface(model, image, outside, SETTINGS)
    with pytest.raises(BadInputError, match="outside the overlap"):
        gates_at(model, image, _plane_w(model, DEPTH_MM), outside, SETTINGS)
    inside = (outside[0] + 250, *outside[1:2], outside[2] + 250, *outside[3:])
    assert dense_surface(model, image, inside, SETTINGS).status.shape == (40, 40)


def test_an_illumination_ramp_that_differs_between_the_halves_does_not_shift_the_depth():
    """Vignetting and the light's fall-off multiply each half's view of a point by a
    different smooth field; the windows' trend removal keeps the depth unbiased."""
    model = make_raytrace_model()
    rng = np.random.default_rng(11)
    flat = render_plane(model, DEPTH_MM, rng, noise_dn=0.0).astype(np.float64)
    width, height = model.config.image_size
    uu, vv = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    right = uu >= model.config.split
    # brightness falls by a third across each half, in opposite directions
    ramp = np.where(right, 1.0 - 0.33 * (uu - 320) / 320, 0.67 + 0.33 * uu / 320)
    shaded = flat * ramp * (1.0 + 0.1 * np.sin(vv / 40.0))
    surface = dense_surface(model, shaded, REGION, SETTINGS)
    ok = surface.status == DenseStatus.OK
    assert ok.mean() >= MIN_VALID
    err = surface.depth[ok] - DEPTH_MM
    # unbiased: the median error is a small part of the predicted sigma
    assert abs(np.median(err)) < 0.25 * np.median(surface.sigma_depth[ok])
    assert np.mean(np.abs(err) <= 2 * surface.sigma_depth[ok]) >= MIN_INSIDE_2SIGMA


FAINT_NOISE_DN = 30.0
"""Noise of the faint-texture test: the texture's gradient (some 20 DN/px rms) is below
it, and the noise of the interpolated derivative dominates the plain windows' error."""


def test_faint_texture_is_measured_on_the_prefiltered_halves_within_its_sigma():
    """Where the plain windows refuse a noisy texture as too imprecise, the prefiltered
    ladder measures it, with errors inside the predicted sigma and no larger."""
    import dataclasses

    model = make_raytrace_model()
    image = render_plane(model, DEPTH_MM, np.random.default_rng(7), noise_dn=FAINT_NOISE_DN)
    plain = dense_surface(model, image, REGION, dataclasses.replace(SETTINGS, prefilter_px=0.0))
    both = dense_surface(model, image, REGION, SETTINGS)
    ok_plain, ok = plain.status == DenseStatus.OK, both.status == DenseStatus.OK
    assert ok_plain.mean() < 0.25 < 0.5 < ok.mean()
    err = both.depth[ok] - DEPTH_MM
    assert np.mean(np.abs(err) <= 2 * both.sigma_depth[ok]) >= MIN_INSIDE_2SIGMA
    assert np.median(np.abs(err)) <= np.median(np.abs(plain.depth[ok_plain] - DEPTH_MM))


def test_the_calibrations_share_of_the_depth_sigma_matches_monte_carlo(plane):
    """The unscented transform of the parameters' covariance and the misfit's pixel
    offsets through triangulation, against sampling both and triangulating."""
    from endomeasure.measure.dense import _calibration_sigma
    from endomeasure.solvers.triangulate import triangulate

    model, _, surface = plane
    ok = np.argwhere(surface.status == DenseStatus.OK)
    ok = ok[:: ok.shape[0] // 4][:4]  # spread over the region
    u0, v0 = surface.region[:2]
    left = ok[:, ::-1].astype(float) + [u0, v0]
    right = surface.right[ok[:, 0], ok[:, 1]]
    free = np.flatnonzero(model.free_mask)
    rng = np.random.default_rng(5)
    scale = 1e-3 * np.maximum(np.abs(model.params[free]), 1e-2)
    param_cov = np.diag(scale**2)
    misfit_cov = np.diag([0.02, 0.01, 0.03, 0.01]) ** 2
    predicted = _calibration_sigma(model, param_cov, misfit_cov, left, right)
    draws = 4000
    params = np.broadcast_to(model.params, (draws, model.params.size)).copy()
    params[:, free] += rng.normal(size=(draws, free.size)) * scale
    offsets = rng.multivariate_normal(np.zeros(4), misfit_cov, size=draws)
    for k in range(left.shape[0]):
        tri = triangulate(model, left[k] + offsets[:, :2], right[k] + offsets[:, 2:], params=params)
        assert predicted[k] == pytest.approx(np.std(tri.points[:, 2]), rel=0.1)


def test_the_calibrations_share_survives_sigma_points_that_leave_the_half(plane):
    """A match next to the split: the misfit's spread pushes some of its sigma points
    across into the right half, so the transform retries that match alone with a
    narrower spread; the others keep theirs, and the retried one gets the sigma it gets
    on its own."""
    from endomeasure.measure.dense import _calibration_sigma

    model, _, surface = plane
    ok = np.argwhere(surface.status == DenseStatus.OK)
    ok = ok[:: ok.shape[0] // 4][:4]
    u0, v0 = surface.region[:2]
    left = ok[:, ::-1].astype(float) + [u0, v0]
    right = surface.right[ok[:, 0], ok[:, 1]]
    left[0, 0] = model.config.split - 0.6  # 0.1 px from the split: sigma points cross it
    misfit_cov = np.diag([1.0, 0.01, 0.01, 0.01])
    together = _calibration_sigma(model, None, misfit_cov, left, right)
    alone = [_calibration_sigma(model, None, misfit_cov, left[k : k + 1], right[k : k + 1])[0]
             for k in range(left.shape[0])]  # fmt: skip
    assert np.all(np.isfinite(together))
    assert together == pytest.approx(alone, rel=1e-9)


# ----- the pieces: curve table and kernel, window choice, start surface -------------------

TABLE_TOLERANCE_PX = 2e-3
"""Largest error of an interpolated curve point against the exact projection, px: the
map is smooth (tricubic interpolation error ~1e-5 px inside the overlap); the matches'
own precision is some 0.02 px at best, so the table adds nothing visible."""


def test_curve_table_points_and_samples_match_exact_projections_and_the_spline():
    from endomeasure.conventions import Half
    from endomeasure.interpolation import spline_coefficients, spline_sample
    from endomeasure.measure import dense

    model = make_raytrace_model()
    image = render_plane(model, DEPTH_MM, np.random.default_rng(3)).astype(np.float64)
    width, height = model.config.image_size
    split = model.config.split
    frame = dense._Frame(*REGION)
    levels = dense._levels(model, frame, SETTINGS)
    table = dense._curve_table(model, frame, levels, SETTINGS.grid_px)
    coeffs, origin = spline_coefficients(
        image, np.array([[split, 0], [width - 1, height - 1]], float), cols=(split, width - 1)
    )
    right = dense._RightHalf(coeffs, origin, split, width, height)
    rng = np.random.default_rng(5)
    u0, v0, u1, v1 = REGION
    w = rng.uniform(levels[1], levels[-2], size=(v1 - v0, u1 - u0))
    along = right.along(table, w)
    assert np.array_equal(right.values_along(table, w), along.values, equal_nan=True)
    uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    rays = model.rays(np.stack([uu, vv], -1), Half.LEFT)
    exact = model.project(dense._ray_points(rays, w), Half.RIGHT).pixels
    both = np.isfinite(exact).all(-1) & np.isfinite(along.q).all(-1)
    assert both.sum() > 0.9 * w.size  # not a vacuous comparison
    assert np.max(np.abs(along.q[both] - exact[both])) < TABLE_TOLERANCE_PX
    # dq/dw against a central difference of the exact projections
    h = 1e-4 * w
    plus = model.project(dense._ray_points(rays, w + h), Half.RIGHT).pixels
    minus = model.project(dense._ray_points(rays, w - h), Half.RIGHT).pixels
    slope = (plus - minus) / (2 * h[..., None])
    rate = np.linalg.norm(slope[both], axis=-1)
    assert np.max(np.linalg.norm(along.dq_dw[both] - slope[both], axis=-1) / rate) < 1e-3
    # the compiled spline samples are the numpy interpolant's (whose weights are float32)
    inside = both & np.isfinite(along.values)
    values, gu, gv = spline_sample(coeffs, origin, along.q[inside])
    assert np.allclose(along.values[inside], values, rtol=1e-5, atol=1e-4)
    assert np.allclose(along.gradient[inside], np.stack([gu, gv], -1), rtol=1e-5, atol=1e-4)


def _candidate(w, sigma, status=None):
    from endomeasure.measure.dense import _Candidate

    w, sigma = np.asarray(w, float), np.asarray(sigma, float)
    status = np.zeros(w.shape, np.uint8) if status is None else np.asarray(status, np.uint8)
    nan = np.full(w.shape, np.nan)
    return _Candidate(w, sigma, np.full((*w.shape, 2), np.nan), nan, nan, status,
                      np.zeros(w.shape, np.uint16), np.zeros(w.shape, np.float32))  # fmt: skip


def test_window_choice_grows_while_the_intervals_intersect():
    """Four pixels, three sizes: all agree (the largest), the largest leaves the smaller
    ones' common interval (the middle one), the smallest is refused (skipped), none
    matched (-1)."""
    from endomeasure.measure.dense import _ICI_GAMMA, _choose_window

    far = 3 * _ICI_GAMMA  # sigmas apart: intervals of half-width gamma sigma cannot meet
    small = _candidate([1.0, 1.0, 5.0, 1.0], [1.0, 1.0, 1.0, 1.0], [0, 0, DenseStatus.LOW_SCORE, 3])
    middle = _candidate([1.5, 1.5, 1.2, 1.0], [0.5, 0.5, 0.5, 0.5], [0, 0, 0, 3])
    large = _candidate([1.4, 1.5 + far * 0.5, 1.1, 1.0], [0.1, 0.1, 0.1, 0.1], [0, 0, 0, 4])
    chosen = _choose_window({15: small, 31: middle, 63: large})
    assert chosen.tolist() == [2, 1, 2, -1]


def test_an_unmatched_pixel_gives_the_reason_of_the_largest_window_the_other_half_saw():
    """Three unmatched pixels near the overlap's edge: the largest window leaves the other
    half, so the smaller ones' reasons stand (imprecise; the larger of two refusals);
    not seen only where no window was."""
    from endomeasure.measure.dense import _picked

    NS, UT, END = DenseStatus.NOT_SEEN, DenseStatus.UNTEXTURED, DenseStatus.AT_RANGE_END
    candidates = {
        15: _candidate([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [UT, UT, NS]),
        31: _candidate([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [NS, END, NS]),
        63: _candidate([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [NS, NS, NS]),
    }
    picked = _picked(candidates, np.array([-1, -1, -1]))
    assert picked.status.tolist() == [UT, END, NS]


def test_the_prefiltered_ladder_answers_only_where_the_plain_one_matched_nothing():
    """Three pixels: the plain ladder matched (its choice stands, though the prefiltered
    one is more precise), matched nothing (the prefiltered ladder's choice), neither."""
    from endomeasure.measure.dense import _chosen_rung, _Rung

    refused = [0, DenseStatus.UNTEXTURED, DenseStatus.UNTEXTURED]
    plain = [_Rung(15, 0.0), _Rung(31, 0.0)]
    filtered = [_Rung(15, 1.0), _Rung(31, 1.0)]
    candidates = {
        plain[0]: _candidate([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], refused),
        plain[1]: _candidate([1.0, 1.0, 1.0], [0.5, 0.5, 0.5], refused),
        filtered[0]: _candidate([1.0, 1.0, 1.0], [0.2, 0.2, 0.2], [0, 0, 2]),
        filtered[1]: _candidate([1.0, 1.0, 1.0], [0.1, 0.1, 0.1], [0, 0, 2]),
    }
    assert _chosen_rung(candidates, [plain, filtered]).tolist() == [1, 3, -1]


@pytest.mark.parametrize("side", [61, 253])  # every pixel; every 7th and interpolated
def test_start_surface_reproduces_a_quadratic_through_holes(side):
    """The local quadratic fit is exact for a quadratic surface, also where depths are
    missing (holes carry no weight, nothing is filled in) and between the nodes of a
    decimated fit (Catmull-Rom interpolation reproduces quadratics)."""
    from endomeasure.measure.dense import _smooth_base

    vv, uu = np.mgrid[0:90, 0:120].astype(float)
    w = 0.05 + 1e-4 * uu - 2e-4 * vv + 3e-7 * uu**2 - 1e-7 * uu * vv + 2e-7 * vv**2
    holes = w.copy()
    holes[30:50, 40:70] = np.nan  # a hole inside the fit's reach
    holes[::7, ::5] = np.nan
    fitted = _smooth_base(holes, smooth_px=1, side=side)
    assert np.max(np.abs(fitted - w)) < 1e-9


def test_a_chosen_window_that_departs_from_the_smaller_ones_carries_the_departure():
    """Its sigma grows by the departure beyond the smaller window's noise (a smoothed
    pit); where the two agree within that noise it keeps its own sigma."""
    from endomeasure.measure.dense import _choose_window, _picked

    small = _candidate([1.0, 1.0], [1.0, 1.0])
    large = _candidate([2.5, 1.2], [0.1, 0.1])
    candidates = {15: small, 31: large}
    chosen = _choose_window(candidates)
    assert chosen.tolist() == [1, 1]
    picked = _picked(candidates, chosen)
    assert np.allclose(picked.sigma_w, [np.sqrt(0.1**2 + 1.5**2 - 1.0), 0.1])


@pytest.mark.parametrize("levels_off", [1.0, 2.25])
def test_the_refinement_finds_the_surface_from_a_start_beyond_the_near_stretch(plane, levels_off):
    """A start off by more than ``fine_reach`` but within ``wide_reach`` sweep levels
    still finds the plane (the fringe of the measured part, where the start is carried on
    from farther inside); searched only within ``fine_reach`` it ends at the stretch's end
    and keeps its start there, refused. The smallest window, where it is seen whole: the
    windows reach into the margin the other half does not see, which keeps the start,
    uniformly off in this test (in the search the start is smooth across it)."""
    from endomeasure.measure.dense import _prepare, _refine

    model, image, _ = plane
    _, region, search = _prepare(model, image, REGION, SETTINGS)
    f = search.frame
    inner = f.crop(region)
    w_true = 1.0 / DEPTH_MM
    start = np.full((f.v1 - f.v0, f.u1 - f.u0), w_true + levels_off * search.table.dw)
    bases = {size: start for size in SETTINGS.windows()}
    size = min(SETTINGS.windows())

    def smallest(settings):
        out = _refine(search.table, bases, search.refs, search.images, settings)
        return next(c for rung, c in out.items() if rung.blur == 0 and rung.size == size)

    c = smallest(SETTINGS)
    status, w, sigma_w = c.status[inner], c.w[inner], c.sigma_w[inner]
    ok, seen = status == DenseStatus.OK, status != DenseStatus.NOT_SEEN
    assert ok.sum() >= MIN_VALID * seen.sum()
    assert np.mean(np.abs(w[ok] - w_true) <= 2 * sigma_w[ok]) >= MIN_INSIDE_2SIGMA
    if levels_off > SETTINGS.fine_reach:
        near = smallest(dataclasses.replace(SETTINGS, wide_reach=SETTINGS.fine_reach))
        end = near.status[inner] == DenseStatus.AT_RANGE_END
        assert end.sum() >= MIN_VALID * seen.sum()
        assert np.all(near.w[inner][end] == start[inner][end])
