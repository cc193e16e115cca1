"""Lens extensions chosen by the data (``CameraModel.EXTENSIONS``, solvers/calibrate.py).

Detections are projections through a known raytrace model with a term the default fit
holds at zero (a moving entrance pupil, or third-order radial distortion) plus seeded
noise: the selection must free exactly the group that the truth has, reach the noise
floor with it, and free nothing when the truth has none of them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tests.solvers.calibration_data import perturbed_raytrace_truth, synthetic_views

from endomeasure.conventions import Half
from endomeasure.solvers.calibrate import CalibrationOptions, calibrate

NOISE_PX = 0.03


def _views(truth, seed):
    data = synthetic_views(truth, np.random.default_rng(seed), n_images=10, noise_px=NOISE_PX)
    cov = np.eye(2) * NOISE_PX**2
    views = [
        dataclasses.replace(v, covariance=tuple(np.tile(cov, (len(v.ids[h]), 1, 1)) for h in Half))
        for v in data.views
    ]
    return views, data.boards


@pytest.mark.parametrize(
    ("extra", "group"),
    [({"k3": -0.08}, ("k3",)), ({"e1": 0.4}, ("e1", "e2"))],
)
def test_the_group_the_truth_has_is_freed_and_reaches_the_floor(extra, group):
    truth = perturbed_raytrace_truth().with_values(extra)
    views, boards = _views(truth, 3)
    cfg = truth.config
    result = calibrate("raytrace", views, boards, cfg.image_size, cfg.split)
    assert set(group) <= set(result.extensions), result.selection
    assert result.verdict.rms_ratio == pytest.approx(1.0, abs=0.08)
    # held at zero the same data are fitted worse than the noise
    zero = CalibrationOptions(values=dict.fromkeys(group, 0.0), fixed=truth.DEFAULT_FIXED)
    held = calibrate("raytrace", views, boards, cfg.image_size, cfg.split, zero, start=result)
    assert held.verdict.rms_ratio > result.verdict.rms_ratio
    # and the freed term is found where the truth has it (within 4 predicted sigmas)
    name = group[0]
    fitted = result.model.named_params()[name]
    assert abs(fitted - extra[name]) < 4 * result.named_std()[name]


def test_nothing_is_freed_when_the_truth_has_none_of_them():
    truth = perturbed_raytrace_truth()
    views, boards = _views(truth, 4)
    cfg = truth.config
    result = calibrate("raytrace", views, boards, cfg.image_size, cfg.split)
    assert result.extensions == (), result.selection
    assert len(result.selection) == len(truth.EXTENSIONS)


@pytest.mark.parametrize("extra", [{}, {"k3": -0.08}, {"e1": 0.4}])
def test_the_linearised_gain_predicts_the_refined_one(extra):
    """The screen's premise: from a converged fit, one Gauss-Newton step predicts the
    criterion's gain of freeing each group to within a factor of 1 / SCREEN_FRACTION of
    what the refinement reaches (a group is skipped only when its prediction is below
    that fraction of the threshold)."""
    from endomeasure.models.start import Fit
    from endomeasure.solvers import calibrate as module
    from endomeasure.solvers.bundle import refine
    from endomeasure.solvers.calibrate import SCREEN_FRACTION, _capped_cost, _collect

    truth = perturbed_raytrace_truth().with_values(extra)
    views, boards = _views(truth, 5)
    cfg = truth.config
    base = calibrate("raytrace", views, boards, cfg.image_size, cfg.split,
                     CalibrationOptions(fixed=truth.DEFAULT_FIXED))  # fmt: skip
    obs, _ = _collect(views, boards, cfg.image_size, cfg.split)
    fit = Fit(base.model, np.array(base.rvecs), np.array(base.tvecs), 1, "", 0, None)
    use = np.asarray(base.inliers)
    cap = base.outlier_threshold_px**2
    cost = _capped_cost(fit, obs, cap)
    m = 2 * use.size
    for group in truth.EXTENSIONS:
        trial_model = base.model.with_config(fixed=base.model.config.fixed - set(group))
        predicted = module._linearised_gain(trial_model, obs, fit, use, cost, m)
        trial = refine(trial_model, obs, fit.rvecs, fit.tvecs, use, 200, fit.state)
        actual = m * np.log(cost / _capped_cost(trial, obs, cap))
        threshold = len(group) * np.log(m)
        if actual > threshold:  # a group the criterion keeps is never screened out
            assert predicted > SCREEN_FRACTION * threshold, (group, predicted, actual)
        assert actual < predicted / SCREEN_FRACTION + 1.0, (group, predicted, actual)


def test_a_held_pupil_the_data_cannot_rule_out_is_in_the_depth_uncertainty():
    """A moving entrance pupil too small for the criterion to free trades against the
    face distances: the fit holds it at zero and puts the model frame's origin off the
    truth's along the axis, far beyond the fitted parameters' own sigma. The covariance a
    measurement uses (``uncertainty_covariance``, with the held groups free) holds that
    error; the fit's own covariance does not."""
    from endomeasure.measure.dense import _calibration_sigma
    from endomeasure.solvers.triangulate import triangulate

    truth = perturbed_raytrace_truth().with_values({"e1": 0.2})
    views, boards = _views(truth, 3)
    cfg = truth.config
    result = calibrate("raytrace", views, boards, cfg.image_size, cfg.split)
    assert "e1" not in result.extensions and {"e1", "e2"} <= set(result.uncertain)
    model = result.uncertainty_model
    assert model.params.tolist() == result.model.params.tolist()
    assert int(model.free_mask.sum()) == result.measurement_covariance.shape[0]
    gu, gv = np.meshgrid(np.linspace(0.15, 0.9, 6) * cfg.split,
                         np.linspace(0.15, 0.85, 5) * cfg.image_size[1])  # fmt: skip
    left = np.stack([gu, gv], -1).reshape(-1, 2)
    rays = truth.rays(left, Half.LEFT)
    for z in (10.0, 20.0):
        t = (z - rays.origins[:, 2]) / rays.directions[:, 2]
        right = truth.project(rays.origins + t[:, None] * rays.directions, Half.RIGHT)
        ok = right.status == 0
        error = np.median(triangulate(result.model, left[ok], right.pixels[ok]).points[:, 2] - z)
        fit_sigma = _calibration_sigma(result.model, result.covariance, None, left[ok],
                                       right.pixels[ok])  # fmt: skip
        sigma = _calibration_sigma(model, result.measurement_covariance, None, left[ok],
                                   right.pixels[ok])  # fmt: skip
        assert abs(error) > 3 * np.median(fit_sigma), z
        assert abs(error) < 2 * np.median(sigma), z
