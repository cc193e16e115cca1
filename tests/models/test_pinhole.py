"""The pinhole pair against OpenCV, an independent implementation of the same formulas."""

from __future__ import annotations

import cv2
import numpy as np

from endomeasure.conventions import Half, Status

CV2_TOL_PX = 1e-9  # both evaluate the same polynomial in float64


def test_forward_equals_cv2_project_points(pinhole_model, rng):
    n = 5000
    points = np.stack(
        [rng.uniform(-15, 15, n), rng.uniform(-12, 12, n), rng.uniform(8, 60, n)], axis=-1
    )
    R, t = pinhole_model.pose_right_left()
    checked = 0
    for half in Half:
        ours = pinhole_model.project(points, half)
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = pinhole_model.intrinsics(half)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        rvec = np.zeros(3) if half is Half.LEFT else cv2.Rodrigues(R)[0]
        tvec = np.zeros(3) if half is Half.LEFT else t
        ref, _ = cv2.projectPoints(points, rvec, tvec, K, np.array([k1, k2, p1, p2, k3]))
        ok = ours.status == Status.OK
        np.testing.assert_allclose(ours.pixels[ok], ref[ok, 0], atol=CV2_TOL_PX, rtol=0)
        checked += ok.sum()
    assert checked > 3000


def test_backward_matches_cv2_undistort_points(pinhole_model, rng):
    q = np.stack([rng.uniform(0, 319, 500), rng.uniform(0, 479, 500)], axis=-1)
    rays = pinhole_model.rays(q, "left")
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = pinhole_model.left
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    ref = cv2.undistortPoints(q[:, None], K, np.array([k1, k2, p1, p2, k3]), None, None, None, crit)
    ours = rays.directions[:, :2] / rays.directions[:, 2:]
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-9)
