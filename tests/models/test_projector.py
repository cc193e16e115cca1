"""The solver-side projection of every model: the same pixels and validity as
``model.project``, Jacobians against central differences of the model's projection."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.geometry.rotations import rotation_jacobian, rotation_matrix, skew
from endomeasure.models.base import CameraModel

JAC_REL_TOL = 1e-6  # central differences of model.project carry ~1e-8 relative error


def _central_differences(model, P, halves):
    """The contract's generic Jacobians (central differences of ``_project`` over every
    parameter, and of the point), whatever the model overrides."""
    free = np.arange(model.params.size)
    dq_dparams = np.empty((P.shape[0], 2, free.size))
    dq_dp = np.empty((P.shape[0], 2, 3))
    for h in (0, 1):
        sel = halves == h
        half = ("left", "right")[h]
        _, _, dq_dp_h, dq_dparams_h = CameraModel._project_jacobians(
            model, P[sel], _half(half), free
        )
        dq_dp[sel] = CameraModel._project_jacobian(model, P[sel], _half(half))[2]
        dq_dparams[sel] = dq_dparams_h
    return dq_dparams, dq_dp


def _half(label):
    from endomeasure.conventions import Half

    return Half.parse(label)


def _points_seen(model, rng, n=300):
    halves = rng.integers(0, 2, n)
    u = np.where(halves == 0, rng.uniform(200, 300, n), rng.uniform(340, 440, n))
    px = np.stack([u, rng.uniform(60, 420, n)], axis=-1)
    P = np.empty((n, 3))
    for h in (0, 1):
        sel = halves == h
        rays = model.rays(px[sel], h)
        P[sel] = rays.origins + rays.directions * rng.uniform(10, 45, sel.sum())[:, None]
    return halves, px, P


def test_projector_matches_model_project_and_its_differences(any_model, rng):
    model = any_model.with_config(fixed=frozenset())  # differentiate every parameter
    halves, px, P = _points_seen(model, rng)
    proj = model.projector(halves)
    q, ok = proj.project(model, P)
    assert ok.all()
    np.testing.assert_allclose(q, px, atol=1e-6)
    dq_dp, dq_dP = proj.jacobian(model, P)
    ref_p, ref_P = _central_differences(model, P, halves)
    assert dq_dp.shape == (P.shape[0], 2, len(model.PARAM_NAMES))
    scale = np.abs(ref_p).max(axis=(0, 1)) + 1e-12
    assert np.max(np.abs(dq_dp - ref_p).max(axis=(0, 1)) / scale) < JAC_REL_TOL
    assert np.max(np.abs(dq_dP - ref_P)) / np.abs(ref_P).max() < JAC_REL_TOL


def test_warm_started_projection_equals_a_cold_one(raytrace_model, rng):
    halves, _, P = _points_seen(raytrace_model, rng)
    proj = raytrace_model.projector(halves)
    proj.project(raytrace_model, P)
    moved = P + np.array([0.05, -0.03, 0.2])
    warm, _ = proj.project(raytrace_model, moved)
    cold, _ = raytrace_model.projector(halves).project(raytrace_model, moved)
    np.testing.assert_allclose(warm, cold, atol=1e-8)


def test_projector_validity_is_the_models_own(any_model, rng):
    """Points outside their half, behind the probe or beyond the lens's fold-back are
    invalid for the solver exactly when ``model.project`` says so."""
    n = 400
    halves = rng.integers(0, 2, n)
    P = np.stack([rng.uniform(-25, 25, n), rng.uniform(-25, 25, n), rng.uniform(-5, 40, n)], -1)
    q, ok = any_model.projector(halves).project(any_model, P)
    for h in (0, 1):
        sel = halves == h
        ref = any_model.project(P[sel], h)
        np.testing.assert_array_equal(ok[sel], ref.status == 0)
        np.testing.assert_allclose(q[sel][ok[sel]], ref.pixels[ok[sel]], atol=1e-6)
    assert 50 < ok.sum() < n - 50  # both kinds were met


def test_project_jacobians_agree_with_project_jacobian(any_model, rng):
    halves, _, P = _points_seen(any_model, rng, n=50)
    for h in (0, 1):
        sel = halves == h
        full = any_model.project_jacobians(P[sel], h)
        point = any_model.project_jacobian(P[sel], h)
        np.testing.assert_array_equal(full.pixels, point.pixels)
        np.testing.assert_array_equal(full.dq_dp, point.dq_dp)
        assert full.dq_dparams.shape == (sel.sum(), 2, any_model.params.size)


@pytest.mark.parametrize(
    "rvec", [[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [1e-6, 2e-6, 0.0], [2.0, 1.0, -0.5]]
)
def test_rotation_jacobian_is_the_derivative_of_R_X(rvec):
    rvec = np.array(rvec)
    X = np.array([0.7, -1.3, 2.1])
    analytic = -skew(rotation_matrix(rvec) @ X) @ rotation_jacobian(rvec)
    h = 1e-6
    numeric = np.stack(
        [
            (rotation_matrix(rvec + h * e) @ X - rotation_matrix(rvec - h * e) @ X) / (2 * h)
            for e in np.eye(3)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)
