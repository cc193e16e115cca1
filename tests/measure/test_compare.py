"""Two calibrations compared over the working volume: closed-form cases (a model with
itself, the same model in a world scaled by a known factor, two different designs)."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import scaled_world

from endomeasure.measure.compare import compare_models, rms_z_limit

DEPTHS = (15.0, 25.0)
GRID = (8, 6)
SCALE = 1.01
EXACT = 1e-9
"""Relative tolerance of closed-form identities (triangulation converges far below it)."""


def _cov(model, relative):
    std = relative * np.maximum(np.abs(model.params[model.free_mask]), 1.0)
    return np.diag(std**2)


@pytest.mark.parametrize("kind", ["pinhole", "raytrace"])
def test_a_model_agrees_exactly_with_itself(model_factory, kind):
    m = model_factory[kind]()
    c = compare_models(m, m, DEPTHS, GRID, cov_a=_cov(m, 1e-5), cov_b=_cov(m, 1e-5))
    rows = c.per_depth()
    assert len(rows) == len(DEPTHS) and sum(r["n"] for r in rows) >= 20
    for r in rows:
        assert r["left_max_px"] == 0 and r["right_max_px"] == 0
        assert r["length_diff_max_mm"] == 0 and r["rms_z"] == 0 and r["agree"]
    assert c.agree


@pytest.mark.parametrize("kind", ["pinhole", "raytrace"])
def test_a_scaled_baseline_disagrees_by_its_scale(model_factory, kind):
    m = model_factory[kind]()
    scaled = scaled_world(m, SCALE)
    tight = compare_models(m, scaled, DEPTHS, GRID, cov_a=_cov(m, 1e-5), cov_b=_cov(m, 1e-5))
    ok = np.isfinite(tight.length_b)
    assert ok.sum() >= 20
    np.testing.assert_allclose(tight.length_b[ok] / tight.length_a[ok], SCALE, rtol=EXACT)
    np.testing.assert_allclose(tight.length_a[ok], 1.0, rtol=1e-6)  # A measures its own truth
    assert not tight.agree
    for r in tight.per_depth():
        assert r["length_diff_mean_mm"] == pytest.approx(SCALE - 1, rel=1e-6)
        assert r["right_rms_px"] > 0
    # the same difference inside a +- a hundred times wider is no disagreement
    loose = compare_models(m, scaled, DEPTHS, GRID, cov_a=_cov(m, 1e-3), cov_b=_cov(m, 1e-3))
    assert loose.agree
    np.testing.assert_allclose(loose.length_diff, tight.length_diff, equal_nan=True)


def test_one_sided_covariance_counts_once(model_factory):
    m = model_factory["pinhole"]()
    both = compare_models(m, m, DEPTHS, GRID, cov_a=_cov(m, 1e-5), cov_b=_cov(m, 1e-5))
    one = compare_models(m, m, DEPTHS, GRID, cov_a=_cov(m, 1e-5))
    np.testing.assert_allclose(both.sigma, np.sqrt(2) * one.sigma, rtol=1e-12)
    assert np.all(one.sigma_b == 0)


def test_two_different_designs_disagree(model_factory):
    a = model_factory["raytrace"]()
    b = model_factory["raytrace"](fx=235.0, left_a=a.left_a * 1.02)
    c = compare_models(a, b, DEPTHS, GRID, cov_a=_cov(a, 1e-5), cov_b=_cov(b, 1e-5))
    assert not c.agree
    assert all(r["left_max_px"] > 1 for r in c.per_depth())


def test_the_limit_is_the_bonferroni_normal_quantile():
    # one depth at alpha 0.01: the two-sided 99 % quantile 2.5758; three depths: 2.9352
    assert rms_z_limit(0.01, 1) == pytest.approx(2.5758293, abs=1e-6)
    assert rms_z_limit(0.01, 3) == pytest.approx(2.9351994, abs=1e-6)


def test_another_sensor_and_no_covariance_are_refused(model_factory):
    from endomeasure.errors import BadInputError

    a = model_factory["pinhole"]()
    with pytest.raises(BadInputError, match="image size"):
        compare_models(a, a.with_config(image_size=(800, 600)), DEPTHS, GRID, cov_a=_cov(a, 1e-5))
    # another split is another probe's, not an error
    moved = compare_models(a, a.with_config(split=300), DEPTHS, GRID, cov_a=_cov(a, 1e-5))
    assert moved.per_depth()
    with pytest.raises(BadInputError, match="covariance"):
        compare_models(a, a, DEPTHS, GRID)
