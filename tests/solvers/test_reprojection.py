"""Projection Jacobians used by calibration, against central differences of model.project."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.geometry.rotations import rotation_jacobian, rotation_matrix, skew
from endomeasure.solvers.reprojection import FiniteDifferenceProjector, projector_for

JAC_REL_TOL = 1e-6  # central differences of model.project carry ~1e-8 relative error


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
    proj = projector_for(model, halves)
    q, ok = proj.project(model, P)
    assert ok.all()
    np.testing.assert_allclose(q, px, atol=1e-6)
    dq_dp, dq_dP = proj.jacobian(model, P)
    ref_p, ref_P = FiniteDifferenceProjector(model, halves).jacobian(model, P)
    assert dq_dp.shape == (P.shape[0], 2, len(model.PARAM_NAMES))
    scale = np.abs(ref_p).max(axis=(0, 1)) + 1e-12
    assert np.max(np.abs(dq_dp - ref_p).max(axis=(0, 1)) / scale) < JAC_REL_TOL
    assert np.max(np.abs(dq_dP - ref_P)) / np.abs(ref_P).max() < JAC_REL_TOL


def test_warm_started_projection_equals_a_cold_one(raytrace_model, rng):
    halves, _, P = _points_seen(raytrace_model, rng)
    proj = projector_for(raytrace_model, halves)
    proj.project(raytrace_model, P)
    moved = P + np.array([0.05, -0.03, 0.2])
    warm, _ = proj.project(raytrace_model, moved)
    cold, _ = projector_for(raytrace_model, halves).project(raytrace_model, moved)
    np.testing.assert_allclose(warm, cold, atol=1e-8)


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
