"""The outlier rule of the bundle adjustment: wrong poses are re-fitted, early drops return.

Detections are exact projections of a known pinhole pair plus seeded noise; the checks
are against that truth and against the closed-form geometry of a plane's two poses.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tests.conftest import make_pinhole_model
from tests.solvers.calibration_data import synthetic_views

from endomeasure.geometry.rotations import rotation_matrix
from endomeasure.solvers.bundle import all_residuals, fit_with_outliers, mirrored_pose
from endomeasure.solvers.calibrate import _collect, calibrate

SIZE = (640, 480)
SPLIT = 320
NOISE_PX = 0.1


def _board(cols=4, rows=3, pitch=1.0):
    g = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2) * pitch
    return np.c_[g, np.zeros(len(g))]


@pytest.mark.parametrize("rvec", [(0.5, 0.2, 0.1), (-0.3, 0.6, 2.5), (0.05, -0.02, 0.0)])
def test_the_mirrored_pose_looks_alike_and_flips_the_depths(rvec):
    """Across the line of sight the board's offsets stay (to first order in size over
    distance), along it they change sign; the centre stays put; the pose is rigid."""
    board = _board()
    centre = board.mean(axis=0)
    rv, tv = np.array(rvec), np.array([3.0, 2.0, 200.0])
    rv2, tv2 = mirrored_pose(rv, tv, centre)
    P1 = board @ rotation_matrix(rv).T + tv
    P2 = board @ rotation_matrix(rv2).T + tv2
    c = rotation_matrix(rv) @ centre + tv
    np.testing.assert_allclose(rotation_matrix(rv2) @ centre + tv2, c, atol=1e-12)
    sight = c / np.linalg.norm(c)
    d1, d2 = (P1 - c) @ sight, (P2 - c) @ sight
    np.testing.assert_allclose(d2, -d1, atol=1e-12)
    across1 = (P1 - c) - d1[:, None] * sight
    across2 = (P2 - c) - d2[:, None] * sight
    np.testing.assert_allclose(across2, across1, atol=1e-12)
    size = np.linalg.norm(board - centre, axis=-1).max()
    image1, image2 = P1[:, :2] / P1[:, 2:], P2[:, :2] / P2[:, 2:]
    assert np.abs(image2 - image1).max() < 5 * (size / c[2]) ** 2  # second order only


@pytest.fixture(scope="module")
def pinhole_case():
    truth = make_pinhole_model()
    data = synthetic_views(truth, np.random.default_rng(21), n_images=12, noise_px=NOISE_PX)
    res = calibrate("pinhole", data.views, data.boards, SIZE, SPLIT)
    obs, _ = _collect(data.views, data.boards, SIZE, SPLIT)
    return res, obs


def _refit(res, obs, rvecs, tvecs, max_nfev=200):
    return fit_with_outliers(res.model, obs, rvecs, tvecs, max_nfev=max_nfev, outlier_sigmas=5.0,
                             max_rounds=3)  # fmt: skip


def test_a_view_at_its_mirrored_pose_is_re_posed_not_dropped(pinhole_case):
    res, obs = pinhole_case
    assert res.outlier_count == 0
    rvecs, tvecs = np.array(res.rvecs), np.array(res.tvecs)
    image = 4
    centre = obs.board_points[obs.image == image].mean(axis=0)
    rvecs[image], tvecs[image] = mirrored_pose(rvecs[image], tvecs[image], centre)
    r = all_residuals(res.model, obs, rvecs, tvecs)
    assert np.nanmedian(np.linalg.norm(r[obs.image == image], axis=-1)) > 1.0  # visibly off
    out = _refit(res, obs, rvecs, tvecs)
    assert out.inliers.all()
    np.testing.assert_allclose(out.fit.rvecs[image], res.rvecs[image], atol=1e-4)
    np.testing.assert_allclose(out.fit.tvecs[image], res.tvecs[image], atol=1e-3)


def test_good_corners_dropped_next_to_gross_errors_come_back(pinhole_case):
    """A third of one view's corners mis-detected by 8 px pull that view's pose in the
    first round, so its good corners miss too and are dropped; once the gross ones are
    out the pose fits again, and the final inliers are exactly the corners within the
    final threshold: every good one."""
    res, obs = pinhole_case
    rows = np.flatnonzero(obs.image == 4)
    gross = rows[::3]
    pixels = obs.pixels.copy()
    pixels[gross] += np.array([8.0, -6.0]) / np.sqrt(2)
    obs = dataclasses.replace(obs, pixels=pixels)
    out = _refit(res, obs, np.array(res.rvecs), np.array(res.tvecs))
    within = np.linalg.norm(out.residuals, axis=-1) <= out.threshold_px
    np.testing.assert_array_equal(out.inliers, within)
    good = np.ones(obs.image.size, dtype=bool)
    good[gross] = False
    np.testing.assert_array_equal(out.inliers, good)
