"""The calibration verdict against the noise the detections carry (solvers/verdict.py).

Detections are exact projections through a known raytrace model plus seeded Gaussian
noise of a known sigma, with that sigma given as each corner's covariance: the floor is
then known in closed form, and the verdict must say ok for the model that generated the
data, failed for a model that cannot describe it, and warn where it should.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tests.solvers.calibration_data import perturbed_raytrace_truth, synthetic_views

from endomeasure.conventions import Half
from endomeasure.solvers.calibrate import calibrate
from endomeasure.solvers.verdict import (
    FAILED_RMS_RATIO,
    OUTLIER_WARNING_FRACTION,
    noise_floor,
    scatter_floor,
)

NOISE_PX = 0.05  # per axis


def _with_covariance(views, sigma_px):
    out = []
    for v in views:
        cov = tuple(np.tile(np.eye(2) * sigma_px**2, (len(v.ids[h]), 1, 1)) for h in Half)
        out.append(dataclasses.replace(v, covariance=cov))
    return out


@pytest.fixture(scope="module")
def truth_and_views():
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(11), n_images=10, noise_px=NOISE_PX)
    return truth, data


@pytest.fixture(scope="module")
def fitted(truth_and_views):
    truth, data = truth_and_views
    views = _with_covariance(data.views, NOISE_PX)
    cfg = truth.config
    return calibrate("raytrace", views, data.boards, cfg.image_size, cfg.split)


def test_noise_floor_closed_form():
    # K corners of covariance s^2 I: E[SSR] = (m - n) / m * K * 2 s^2, per corner 2 s^2
    cov = np.tile(np.eye(2) * 0.01, (100, 1, 1))
    assert noise_floor(cov, 200, 20) == pytest.approx(np.sqrt(180 / 200 * 0.02))
    # unknown covariances get the median of the known ones; too few known: no floor
    cov[:30] = np.nan
    assert noise_floor(cov, 200, 20) == pytest.approx(np.sqrt(180 / 200 * 0.02))
    cov[:60] = np.nan
    assert np.isnan(noise_floor(cov, 200, 20))


def test_the_generating_model_is_ok_at_the_floor(fitted):
    v = fitted.verdict
    assert v.level == "ok", v.reasons
    # the RMS of the true model's fit is the floor within sampling error (1 / sqrt(2 m))
    assert v.rms_ratio == pytest.approx(1.0, abs=0.05)
    assert v.floor_px == pytest.approx(NOISE_PX * np.sqrt(2.0), rel=0.05)


def test_a_model_that_cannot_describe_the_probe_fails():
    # the pinhole pair misses the prism's non-central geometry by a few hundredths of a
    # pixel: with a detector ten times better than that it fails
    truth = perturbed_raytrace_truth()
    data = synthetic_views(truth, np.random.default_rng(12), n_images=14, noise_px=0.004)
    views = _with_covariance(data.views, 0.004)
    pinhole = calibrate("pinhole", views, data.boards, truth.config.image_size, truth.config.split)
    v = pinhole.verdict
    assert v.rms_ratio > FAILED_RMS_RATIO
    assert v.level == "failed" and not v.usable
    assert "times the noise floor" in v.reasons[0]


def test_the_floor_is_the_larger_of_the_formal_and_the_scatter(truth_and_views, fitted):
    # a detector that understates its noise three-fold does not fail a correct model: the
    # corners' scatter shows the real noise; an overstated formal noise sets the floor
    truth, data = truth_and_views
    cfg = truth.config
    low = calibrate("raytrace", _with_covariance(data.views, NOISE_PX / 3), data.boards,
                    cfg.image_size, cfg.split, start=fitted)  # fmt: skip
    assert low.verdict.formal_px == pytest.approx(fitted.verdict.formal_px / 3, rel=0.01)
    assert low.verdict.floor_px == low.verdict.scatter_px
    assert low.verdict.level == "ok" and low.verdict.rms_ratio == pytest.approx(1.0, abs=0.1)
    high = calibrate("raytrace", _with_covariance(data.views, NOISE_PX * 3), data.boards,
                     cfg.image_size, cfg.split, start=fitted)  # fmt: skip
    assert high.verdict.floor_px == high.verdict.formal_px
    assert high.verdict.rms_ratio == pytest.approx(1 / 3, rel=0.1)


def test_scatter_floor_sees_independent_errors_not_smooth_ones():
    rng = np.random.default_rng(3)
    c, r = np.meshgrid(np.arange(9.0), np.arange(7.0))
    X = np.stack([c.ravel(), r.ravel(), np.zeros(c.size)], axis=1) * 1.5  # 1.5 mm squares
    images = np.repeat(np.arange(40), len(X))
    X = np.tile(X, (40, 1))
    halves = np.zeros(len(X), dtype=int)
    noise = 0.05 * rng.standard_normal((len(X), 2))
    white = scatter_floor(X, images, halves, noise)
    assert white == pytest.approx(0.05 * np.sqrt(2), rel=0.03)
    # a misfit linear over each board view leaves it as it was
    tilt = np.outer(X[:, 0] - 3 * X[:, 1], [0.02, -0.01]) + 0.3
    assert scatter_floor(X, images, halves, noise + tilt) == pytest.approx(white, rel=1e-9)
    assert np.isnan(scatter_floor(X[:5], images[:5], halves[:5], noise[:5]))


def test_without_covariance_the_scatter_sets_the_floor(truth_and_views, fitted):
    truth, data = truth_and_views
    cfg = truth.config
    result = calibrate("raytrace", data.views, data.boards, cfg.image_size, cfg.split,
                       start=fitted)  # fmt: skip
    assert np.isnan(result.verdict.formal_px)
    assert result.verdict.floor_px == pytest.approx(NOISE_PX * np.sqrt(2), rel=0.1)
    assert result.verdict.level == "ok"


def test_outliers_over_three_percent_warn_and_say_where(truth_and_views, fitted):
    truth, data = truth_and_views
    cfg = truth.config
    rng = np.random.default_rng(5)
    views = []
    for v in _with_covariance(data.views, NOISE_PX):
        pixels = []
        for h in Half:
            q = np.array(v.pixels[h])
            bad = rng.uniform(size=len(q)) < 0.06
            q[bad] += rng.choice([-1.0, 1.0], size=(bad.sum(), 2)) * 3.0  # 3 px off
            lo, hi = (0, cfg.split) if h is Half.LEFT else (cfg.split, cfg.image_size[0])
            q[:, 0] = np.clip(q[:, 0], lo, hi - 1)
            q[:, 1] = np.clip(q[:, 1], 0, cfg.image_size[1] - 1)
            pixels.append(q)
        views.append(dataclasses.replace(v, pixels=tuple(pixels)))
    result = calibrate("raytrace", views, data.boards, cfg.image_size, cfg.split, start=fitted)
    v = result.verdict
    assert v.outlier_fraction > OUTLIER_WARNING_FRACTION
    assert v.level == "warning"
    (reason,) = [r for r in v.reasons if "dropped as outliers" in r]
    assert "field edge" in reason and "of the split" in reason
    # the 3 px moves are 42 times the per-corner length of the noise, 0.07 px
    median = float(reason.split("median ")[1].split(" px")[0])
    assert 2.5 < median < 4.5
    assert "in image" not in reason  # spread over every image
    # every corner moved by 3 px (60 sigma) is among those dropped
    pairs = [(a.pixels[h], b.pixels[h]) for a, b in zip(views, data.views, strict=True)
             for h in Half]  # fmt: skip
    moved = np.concatenate([np.linalg.norm(np.asarray(p) - q, axis=1) for p, q in pairs])
    assert result.outlier_count >= int((moved > 1.0).sum())


def test_outliers_in_one_image_name_it(truth_and_views, fitted):
    truth, data = truth_and_views
    cfg = truth.config
    views = _with_covariance(data.views, NOISE_PX)
    rng = np.random.default_rng(8)
    bad = views[3]
    shifted = []
    for h in Half:  # 40 % of the view's corners 3 px off, in random directions
        q = np.array(bad.pixels[h])
        moved = rng.uniform(size=len(q)) < 0.4
        q[moved] += rng.choice([-1.0, 1.0], size=(moved.sum(), 2)) * 3.0
        shifted.append(q)
    views[3] = dataclasses.replace(bad, pixels=tuple(shifted))
    result = calibrate("raytrace", views, data.boards, cfg.image_size, cfg.split, start=fitted)
    (reason,) = [r for r in result.verdict.reasons if "dropped as outliers" in r]
    assert f"in image {bad.name!r}" in reason
