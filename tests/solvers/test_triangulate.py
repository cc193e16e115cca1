"""Triangulation: the oracle of noise-free correspondences, ML optimality against an
independent least-squares solve over the point, and per-point status codes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from tests.conftest import make_pinhole_model

from endomeasure.conventions import Status
from endomeasure.solvers.triangulate import triangulate

ORACLE_TOL_MM = 1e-6
"""Noise-free correspondences must give back the points (issue 7's acceptance); the
models trace and aim to ~1e-9 px, which is ~1e-8 mm at 60 mm."""

ML_AGREEMENT_PX = 1e-6
"""ML pixels against an independent solve in point space; both reach ~1e-8 px, the
bound leaves room for the finite-difference Jacobian of the reference solve."""


def visible_points(model, rng, n, z_range=(8.0, 60.0)):
    """Random points in the overlap of both halves, with their exact pixels."""
    z = rng.uniform(*z_range, 6 * n)
    p = np.stack([rng.uniform(-0.5, 0.5, z.size) * z, rng.uniform(-0.4, 0.4, z.size) * z, z], -1)
    pl = model.project(p, "left")
    pr = model.project(p, "right")
    ok = (pl.status == Status.OK) & (pr.status == Status.OK)
    assert ok.sum() >= n, "the test design sees too few points in both halves"
    idx = np.flatnonzero(ok)[:n]
    return p[idx], pl.pixels[idx], pr.pixels[idx]


@pytest.mark.parametrize("method", ["ml", "midpoint"])
def test_noise_free_correspondences_give_back_the_points(any_model, rng, method):
    points, ql, qr = visible_points(any_model, rng, 400)
    result = triangulate(any_model, ql, qr, method)
    assert np.all(result.status == Status.OK)
    err = np.linalg.norm(result.points - points, axis=-1)
    assert err.max() < ORACLE_TOL_MM
    assert result.gap.max() < ORACLE_TOL_MM  # noise-free rays meet
    assert result.rms.max() < 1e-6


def _reprojection_residuals(model, p, ql, qr):
    fl = model.project(p, "left").pixels
    fr = model.project(p, "right").pixels
    return np.concatenate([fl - ql, fr - qr])


def test_ml_matches_an_independent_solve_over_the_point(any_model, rng):
    # Reference: scipy's least_squares over the three coordinates through model.project,
    # started from the true point (so it cannot share a failure of the solver under test).
    points, ql, qr = visible_points(any_model, rng, 12)
    ql = ql + rng.normal(0.0, 0.4, ql.shape)
    qr = qr + rng.normal(0.0, 0.4, qr.shape)
    result = triangulate(any_model, ql, qr)
    assert np.all(result.status == Status.OK)
    checked = 0
    for i in range(points.shape[0]):
        ref = least_squares(
            lambda p, i=i: _reprojection_residuals(any_model, p, ql[i], qr[i]),
            points[i],
            x_scale=1.0,
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            diff_step=1e-7,
        )
        fl = any_model.project(ref.x, "left").pixels
        fr = any_model.project(ref.x, "right").pixels
        assert np.abs(result.pixels_left[i] - fl).max() < ML_AGREEMENT_PX
        assert np.abs(result.pixels_right[i] - fr).max() < ML_AGREEMENT_PX
        rms_ref = np.sqrt(np.sum(ref.fun**2) / 2.0)
        assert result.rms[i] == pytest.approx(rms_ref, rel=1e-6, abs=1e-9)
        checked += 1
    assert checked == 12


def test_ml_pixels_are_the_projections_of_the_ml_points(any_model, rng):
    points, ql, qr = visible_points(any_model, rng, 200)
    result = triangulate(any_model, ql + rng.normal(0, 0.3, ql.shape), qr)
    ok = result.status == Status.OK
    assert ok.sum() > 190
    fl = any_model.project(result.points[ok], "left").pixels
    fr = any_model.project(result.points[ok], "right").pixels
    assert np.abs(fl - result.pixels_left[ok]).max() < 1e-6
    assert np.abs(fr - result.pixels_right[ok]).max() < 1e-6


def test_ml_never_reprojects_worse_than_the_midpoint(any_model, rng):
    points, ql, qr = visible_points(any_model, rng, 300)
    ql = ql + rng.normal(0.0, 0.5, ql.shape)
    qr = qr + rng.normal(0.0, 0.5, qr.shape)
    ml = triangulate(any_model, ql, qr)
    mid = triangulate(any_model, ql, qr, "midpoint")
    ok = (ml.status == Status.OK) & (mid.status == Status.OK)
    assert ok.sum() > 250
    assert np.all(ml.rms[ok] <= mid.rms[ok] + 1e-9)
    # and the observed ray gap is the same figure for both methods
    np.testing.assert_allclose(ml.gap[ok], mid.gap[ok], rtol=1e-9, atol=1e-12)


def test_batch_shapes_are_kept(raytrace_model, rng):
    _, ql, qr = visible_points(raytrace_model, rng, 6)
    result = triangulate(raytrace_model, ql.reshape(2, 3, 2), qr.reshape(2, 3, 2))
    assert result.points.shape == (2, 3, 3)
    assert result.status.shape == (2, 3)
    assert result.pixels_right.shape == (2, 3, 2)
    flat = triangulate(raytrace_model, ql, qr)
    np.testing.assert_array_equal(result.points.reshape(6, 3), flat.points)


def test_bad_points_get_a_status_and_do_not_spoil_the_others(raytrace_model, rng):
    _, ql, qr = visible_points(raytrace_model, rng, 4)
    ql[1] = (400.0, 200.0)  # a "left" pixel in the right half
    qr[2, 0] = np.nan
    result = triangulate(raytrace_model, ql, qr)
    assert result.status[1] == Status.OUTSIDE_HALF
    assert result.status[2] == Status.INVALID_INPUT
    assert np.all(np.isnan(result.points[1:3]))
    assert np.all(result.status[[0, 3]] == Status.OK)
    assert np.all(np.isfinite(result.points[[0, 3]]))


def test_parallel_and_diverging_rays():
    # Two identical, parallel, untilted cameras 0.9 mm apart: the same pixel offset in
    # both halves sees parallel rays; a negative disparity makes them meet behind.
    model = make_pinhole_model(
        rx=0.0, ry=0.0, rz=0.0, ty=0.0, right_fy=230.0, left_fy=230.0, right_p1=1e-4,
        right_p2=-2e-4, left_p1=1e-4, left_p2=-2e-4,
    )  # fmt: skip
    ql = np.array([[200.0, 240.0], [200.0, 240.0], [200.0, 240.0]])
    qr = np.array([[520.0, 240.0], [530.0, 240.0], [500.0, 240.0]])
    for method in ("ml", "midpoint"):
        result = triangulate(model, ql, qr, method)
        assert result.status[0] == Status.PARALLEL
        assert result.status[1] == Status.BEHIND
        assert result.status[2] == Status.OK
        # a 20 px disparity at fx = 230 with a 0.9 mm baseline: z = 230 * 0.9 / 20
        assert result.points[2, 2] == pytest.approx(230.0 * 0.9 / 20.0, rel=1e-2)


def test_mismatched_inputs_are_rejected(raytrace_model):
    with pytest.raises(ValueError, match="same shape"):
        triangulate(raytrace_model, np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="method"):
        triangulate(raytrace_model, np.zeros((1, 2)), np.zeros((1, 2)), "dlt")


@pytest.mark.parametrize("method", ["ml", "midpoint"])
def test_a_parameter_vector_per_correspondence_equals_each_models_triangulation(
    any_model, rng, method
):
    """The batched solve under many models (the UT's calibration sigma points) gives each
    correspondence the point its own model gives it; an invalid vector fails alone."""
    _, ql, qr = visible_points(any_model, rng, 12)
    scale = np.maximum(np.abs(any_model.params), 1e-2)
    params = any_model.params + 1e-4 * scale * rng.standard_normal((12, any_model.params.size))
    params[5, 0] = -1.0  # fx (pinhole: left fx) not positive
    batched = triangulate(any_model, ql, qr, method, reproject=False, params=params)
    for i in range(12):
        if i == 5:
            assert batched.status[i] == Status.INVALID_INPUT
            continue
        own = triangulate(any_model.with_params(params[i]), ql[i], qr[i], method, reproject=False)
        assert batched.status[i] == own.status == Status.OK
        np.testing.assert_allclose(batched.points[i], own.points, rtol=0, atol=ORACLE_TOL_MM)
    with pytest.raises(ValueError, match="reproject=False"):
        triangulate(any_model, ql, qr, "midpoint", params=params)
