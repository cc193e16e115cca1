"""The ray-tracing model against an independent oracle: Fermat's least optical path.

Light from a point P to the lens centre O passes the rear face at P1 and the front face
at P2 where the optical path ``|P1 - O| + n |P2 - P1| + |P - P2|`` is stationary (a
minimum: the path length is convex in the in-plane coordinates of P1 and P2). The
oracle minimises it by Newton's method with an analytic Hessian, which shares no code
with the model's Snell tracing or ray aiming.
"""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import assert_snell

from endomeasure.conventions import Half, Status
from endomeasure.geometry.distortion import distort

FERMAT_TOL_PX = 1e-6  # issue 3 acceptance


def _plane_basis(normal, distance):
    e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return normal * distance, np.stack([e1, e2], axis=-1)  # point on the plane, (3, 2)


def _norm_grad_hess(v):
    r = np.linalg.norm(v, axis=-1)
    u = v / r[:, None]
    H = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / r[:, None, None]
    return u, H


def fermat_pixels(model, points, half):
    """Pixels of ``points`` by least optical path through the prism faces."""
    n = model.n_glass
    front = "left" if half is Half.LEFT else "right"
    o1, B1 = _plane_basis(*model.face("rear"))
    o2, B2 = _plane_basis(*model.face(front))

    # start: where the straight line from the lens centre to P crosses each plane
    def cross(o, B, normal_d):
        normal, d = normal_d
        s = d / (points @ normal)
        return (s[:, None] * points - o) @ B

    z = np.concatenate(
        [cross(o1, B1, model.face("rear")), cross(o2, B2, model.face(front))], axis=1
    )
    for _ in range(50):
        P1 = o1 + z[:, :2] @ B1.T
        P2 = o2 + z[:, 2:] @ B2.T
        ua, Ha = _norm_grad_hess(P1)
        ub, Hb = _norm_grad_hess(P2 - P1)
        uc, Hc = _norm_grad_hess(points - P2)
        g1 = (ua - n * ub) @ B1
        g2 = (n * ub - uc) @ B2
        H11 = B1.T @ (Ha + n * Hb) @ B1
        H12 = -B1.T @ (n * Hb) @ B2
        H22 = B2.T @ (n * Hb + Hc) @ B2
        H = np.block([[H11, H12], [np.swapaxes(H12, 1, 2), H22]])
        step = np.linalg.solve(H, np.concatenate([g1, g2], axis=1)[..., None])[..., 0]
        z -= step
        if np.abs(step).max() < 1e-15:
            break
    P1 = o1 + z[:, :2] @ B1.T
    xd, yd = distort(P1[:, 0] / P1[:, 2], P1[:, 1] / P1[:, 2],
                     (model.k1, model.k2, model.p1, model.p2, model.k3))  # fmt: skip
    return np.stack([model.fx * xd + model.cx, model.fy * yd + model.cy], axis=-1)


def test_ray_aiming_matches_fermat_path(model_factory, rng):
    # a design with every effect switched on: tilted faces in both axes, k3, tangential
    model = model_factory["raytrace"](
        k3=-0.003, p1=2e-4, p2=-1e-4, rear_a=0.01, rear_b=-0.02,
        left_b=0.015, right_a=0.33, right_b=-0.01, right_d=2.05,
    )  # fmt: skip
    n = 1600
    z = rng.uniform(8, 60, n)
    points = np.stack([rng.uniform(-0.9, 0.9, n) * z, rng.uniform(-0.7, 0.7, n) * z, z], axis=-1)
    checked = 0
    for half in Half:
        proj = model.project(points, half)
        ok = proj.status == Status.OK
        oracle = fermat_pixels(model, points[ok], half)
        err = np.linalg.norm(proj.pixels[ok] - oracle, axis=-1)
        assert err.max() < FERMAT_TOL_PX
        checked += ok.sum()
    assert checked >= 1000


def test_rays_obey_snell_at_each_face(raytrace_model, rng):
    """Rebuild the path of each pixel's ray inside the glass from OpenCV's undistortion and
    the faces alone, and check Snell's law in its angle form (n1 sin t1 = n2 sin t2, the
    three vectors coplanar) at the rear and the front face."""
    import cv2

    m = raytrace_model
    q = np.stack([rng.uniform(0, 319, 300), rng.uniform(0, 479, 300)], axis=-1)
    rays = m.rays(q, "left")
    assert np.all(rays.status == Status.OK)
    n_rear, d_rear = m.face("rear")
    n_front, d_front = m.face("left")
    np.testing.assert_allclose(rays.origins @ n_front, d_front, atol=1e-12)
    K = np.array([[m.fx, 0, m.cx], [0, m.fy, m.cy], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    xy = cv2.undistortPoints(q[:, None], K, np.array([m.k1, m.k2, m.p1, m.p2, m.k3]),
                             None, None, None, crit)[:, 0]  # fmt: skip
    lens = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    P1 = lens * (d_rear / (lens @ n_rear))[:, None]  # entry point on the rear face
    air_in = lens / np.linalg.norm(lens, axis=1, keepdims=True)
    glass = rays.origins - P1
    glass /= np.linalg.norm(glass, axis=1, keepdims=True)
    assert_snell([(air_in, glass, n_rear, 1.0, m.n_glass),
                  (glass, rays.directions, n_front, m.n_glass, 1.0)])  # fmt: skip
    # the left half's rays are deviated towards the prism base, i.e. towards +x
    assert np.all(rays.directions[:, 0] / rays.directions[:, 2] > air_in[:, 0] / air_in[:, 2])


def test_glass_index_changes_projection(raytrace_model):
    point = np.array([1.0, 0.5, 20.0])
    base = raytrace_model.project(point, "left").pixels
    names = list(raytrace_model.PARAM_NAMES)
    params = raytrace_model.params.copy()
    params[names.index("n_glass")] = 1.6
    moved = raytrace_model.with_params(params).project(point, "left").pixels
    assert np.linalg.norm(moved - base) > 1.0


def test_glass_index_and_face_rules_hold_per_parameter_vector(raytrace_model):
    """The validity rules of :meth:`valid_params` are the constructor's, row by row."""
    names = ("n_glass", "rear_d", "left_d", "right_d")
    rows = np.repeat(raytrace_model.params[None], len(names) + 1, axis=0)
    for i, name in enumerate(names):
        rows[i + 1, raytrace_model.index(name)] = 1.0 if name == "n_glass" else -0.1
        with pytest.raises(ValueError):
            raytrace_model.with_params(rows[i + 1])
    np.testing.assert_array_equal(raytrace_model.valid_params(rows), [True] + [False] * 4)
