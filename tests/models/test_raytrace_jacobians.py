"""Every raytrace parameter's analytic Jacobian column against central differences of
``project``: with the lens extensions at their default 0 (where the kernels skip the
pupil's arctangent and the rational and image-side terms) and with all of them on, for
:meth:`project_jacobians` and for the aiming projector the solvers use, in both halves.

Oracle: central differences of the public ``project`` (ray aiming to convergence), one
parameter at a time, all 26 free.
"""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.conventions import Half, Status
from endomeasure.models import RaytraceModel

JACOBIAN_REL_TOL = 1e-5  # relative to the column's largest entry
TINY_COLUMN = 1e-6  # px per unit: below this a column is compared with this absolute scale
EXTENSIONS = ("k3", "p1", "p2", "k4", "k5", "k6", "e1", "e2", "p1_image", "p2_image")
EXTENSIONS_ON = dict(
    k3=0.001, p1=2e-4, p2=-1e-4, k4=0.03, k5=-0.004, k6=0.0005,
    e1=0.06, e2=-0.01, p1_image=-3e-4, p2_image=2e-4,
)  # fmt: skip


def _field_points(model, half, rng, n=120):
    """Points over the whole half's field (from its pixels, traced back to random
    depths), so the edges and the centre are both checked."""
    width, height = model.config.image_size
    edge = model.config.split - 0.5
    lo, hi = (0.0, edge - 1.0) if half is Half.LEFT else (edge + 1.0, width - 1.0)
    q = np.stack([rng.uniform(lo, hi, n), rng.uniform(0.0, height - 1.0, n)], -1)
    rays = model.rays(q, half)
    ok = rays.status == Status.OK
    depth = rng.uniform(6.0, 80.0, ok.sum())
    s = (depth - rays.origins[ok, 2]) / rays.directions[ok, 2]
    return rays.origins[ok] + s[:, None] * rays.directions[ok]


def _numeric_column(model, i, points, half):
    step = 1e-6 * max(1.0, abs(model.params[i]))
    shifted = []
    for sign in (1.0, -1.0):
        p = model.params.copy()
        p[i] += sign * step
        shifted.append(model.with_params(p).project(points, half).pixels)
    return (shifted[0] - shifted[1]) / (2 * step)


@pytest.mark.parametrize("extensions", ["zero", "on"])
@pytest.mark.parametrize("half", list(Half))
def test_every_free_parameter_column_matches_central_differences(
    model_factory, half, extensions, rng
):
    values = dict.fromkeys(EXTENSIONS, 0.0) if extensions == "zero" else EXTENSIONS_ON
    model = model_factory["raytrace"](**values).with_config(fixed=frozenset())
    assert model.free_mask.all() and model.params.size == len(RaytraceModel.PARAM_NAMES) == 26
    assert all(getattr(model, k) == values[k] for k in EXTENSIONS)
    points = _field_points(model, half, rng)
    free = np.flatnonzero(model.free_mask)
    jac = model.project_jacobians(points, half, free)
    ok = jac.status == Status.OK
    assert ok.sum() > 0.9 * points.shape[0] > 80
    projector = model.projector(np.full(points.shape[0], int(half)))
    pixels, valid = projector.project(model, points)
    np.testing.assert_array_equal(valid, ok)
    dq_dparams, dq_dp = projector.jacobian(model, points)
    np.testing.assert_allclose(dq_dp[ok], jac.dq_dp[ok], atol=1e-9, rtol=0)
    for k, i in enumerate(free):
        name = model.PARAM_NAMES[i]
        numeric = _numeric_column(model, i, points, half)[ok]
        scale = max(np.abs(numeric).max(), TINY_COLUMN)
        if name in ("e1", "e2"):  # the pupil moves every ray: its column is not tiny
            assert np.abs(numeric).max() > 1e-3, name
        for which, analytic in (("project_jacobians", jac.dq_dparams), ("projector", dq_dparams)):
            np.testing.assert_allclose(
                analytic[ok, :, k], numeric, atol=JACOBIAN_REL_TOL * scale, rtol=0,
                err_msg=f"{which}: {name}",
            )  # fmt: skip


@pytest.mark.parametrize("half", list(Half))
def test_pupil_columns_are_one_sided_where_a_step_would_pass_the_rear_face(
    model_factory, half, rng
):
    """A rear face at the lens (a fit can reach it): moving the pupil forward by any step
    puts it in front of the face and the rays off the axis miss it, so the derivative must
    come from the other side instead of being lost (a lost derivative zeroes the corner's
    row in calibration, and with every row lost the solver stops at once)."""
    model = model_factory["raytrace"](rear_d=1e-9).with_config(fixed=frozenset())
    points = _field_points(model, half, rng, n=60)
    free = np.flatnonzero(model.free_mask)
    jac = model.project_jacobians(points, half, free)
    ok = jac.status == Status.OK
    assert ok.sum() > 0.9 * points.shape[0] > 40
    assert np.isfinite(jac.dq_dparams[ok]).all()
    projector = model.projector(np.full(points.shape[0], int(half)))
    projector.project(model, points)
    dq_dparams, _ = projector.jacobian(model, points)
    for name in ("e1", "e2"):
        i = model.index(name)
        h = 1e-6
        shifted = [model.with_values({name: -k * h}).project(points, half) for k in (0, 1, 2)]
        forward = model.with_values({name: h}).project(points, half).status[ok]
        assert np.mean(forward != Status.OK) > 0.8  # all but the rays nearest the axis
        q0, q1, q2 = (s.pixels[ok] for s in shifted)
        numeric = (3.0 * q0 - 4.0 * q1 + q2) / (2.0 * h)  # one-sided, second order
        scale = np.abs(numeric).max()
        assert scale > 1e-3
        for analytic in (jac.dq_dparams, dq_dparams):
            np.testing.assert_allclose(
                analytic[ok, :, list(free).index(i)], numeric, atol=JACOBIAN_REL_TOL * scale,
                rtol=0, err_msg=name,
            )  # fmt: skip
