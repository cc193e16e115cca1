"""The statistics of ``verify`` on synthetic board-test tables whose errors are drawn
from a known model: a common (calibration) part and independent (image) parts."""

from __future__ import annotations

import numpy as np
import pytest

from endomeasure.measure.board_test import BoardTestTable
from endomeasure.measure.predict import PredictedErrors
from endomeasure.measure.verify import VERIFY_ALPHA, verify_statistics

N_ROWS = 200
SIGMA_IMAGE = 0.01  # mm, each segment's own
SIGMA_COMMON = 0.002  # mm, shared by all (a calibration error): 4x the image part of the mean
TRIALS = 300
MAX_FALSE_ALARMS = 10
"""Of 300 right calibrations at alpha 1 %: 3 expected, more than 10 has probability
below 1e-3 (binomial). Ignoring the common part would send about half of them back."""


def _table(rng, *, common_sigma=SIGMA_COMMON, bias=0.0, inflate=1.0):
    """N_ROWS 1 mm x-segments with disjoint corners, errors drawn as the predictions say
    (the image part times ``inflate``), plus a common relative ``bias``."""
    e = rng.normal(0, common_sigma) + bias + inflate * rng.normal(0, SIGMA_IMAGE, N_ROWS)
    corners = np.full((N_ROWS, 4), -1)
    corners[:, :2] = np.arange(2 * N_ROWS).reshape(-1, 2)
    table = BoardTestTable(
        np.zeros(N_ROWS, dtype=int), np.full(N_ROWS, "x-segment"), corners, np.ones(N_ROWS),
        1 + e, e, np.full(N_ROWS, 20.0), np.zeros((N_ROWS, 2)),
    )  # fmt: skip
    predicted = PredictedErrors(
        1 + e, np.zeros(N_ROWS), np.full(N_ROWS, np.hypot(SIGMA_IMAGE, common_sigma)),
        np.full(N_ROWS, SIGMA_IMAGE), np.full(N_ROWS, common_sigma), np.full(N_ROWS, np.nan),
    )  # fmt: skip
    return table, predicted


def test_right_calibrations_are_rarely_sent_back(rng):
    failed = sum(not verify_statistics(*_table(rng)).passed for _ in range(TRIALS))
    assert failed <= MAX_FALSE_ALARMS


def test_a_common_length_bias_fails_the_bias_test(rng):
    # 0.5 % with a common part of 0.04 % (the sample calibration's) is 6 sigma; with the
    # 0.2 % of the other tests it would be 2.5, no proof at this level
    stats = verify_statistics(*_table(rng, common_sigma=0.0004, bias=0.005))
    assert verify_statistics(*_table(rng, bias=0.005)).bias.z < 3.0
    assert not stats.bias.passed and stats.bias.mean_relative > 0.004
    assert "common length bias" in stats.reasons[0]


def test_errors_wider_than_predicted_fail_the_dispersion_test(rng):
    stats = verify_statistics(*_table(rng, common_sigma=0.0004, inflate=1.5))
    assert not stats.dispersion.passed and stats.dispersion.rms_z > 1.3
    assert stats.bias.passed


def test_the_levels_are_split_between_the_two_tests(rng):
    stats = verify_statistics(*_table(rng))
    assert stats.bias.alpha == stats.dispersion.alpha == VERIFY_ALPHA / 2
    assert stats.verdict == ("pass" if stats.passed else "recalibrate")


def test_too_few_segments_are_refused(rng):
    from endomeasure.errors import BadInputError

    table, predicted = _table(rng)
    keep = np.arange(N_ROWS) < 1
    with pytest.raises(BadInputError, match="too few"):
        verify_statistics(table.select(keep), PredictedErrors(*(a[keep] for a in predicted)))
