"""Is a stored calibration still right? The statistics of ``endomeasure verify``.

A few images of a known board are measured through the stored model (the board test of
:mod:`endomeasure.measure.board_runs`: every x- and y-segment between neighbouring
corners and every square's area), and each error ``e_i`` is set against its own
prediction, bias ``b_i`` and standard deviation ``s_i`` (image noise, calibration
covariance and model misfit, :func:`~endomeasure.measure.board_runs.board_predictions`).
A calibration that still describes the probe gives normalised errors
``z_i = (e_i - b_i) / s_i`` with mean 0 and variance 1; one that does not shows either

- a **common length bias**: every length off by the same fraction (a baseline or a
  prism distance that moved, a scaled world), tested by :func:`bias_test`; or
- **too large errors**: errors spread wider than predicted (distortion or prism
  angles that moved, a model that no longer fits), tested by :func:`dispersion_test`.

Each test has the level ``alpha / 2`` (Bonferroni), so a calibration that is right is
sent for recalibration with a probability of at most about ``alpha`` (``VERIFY_ALPHA``,
1 %). The fraction of errors inside the 2-sigma band is reported too; it is no part of
the verdict (its errors are correlated through shared corners and the common
calibration, so the fraction has no simple distribution).

How correlations are treated
----------------------------
The calibration and misfit parts of the errors are common to all measurements (one
calibration made them), the image-noise parts are independent between images and, up to
the corners neighbouring measurements share, between measurements. Both tests treat the
common parts as fully correlated and the image parts as independent, which is what a
calibration error and detection noise do; correlation through shared corners is taken
into account with the correlation of two segments that share one end (``-1/2`` for
independent end points, :data:`SHARED_CORNER_RHO2`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from endomeasure.errors import BadInputError
from endomeasure.measure.board_runs import BAND_SIGMAS
from endomeasure.measure.board_test import BOARD_KINDS

__all__ = [
    "SHARED_CORNER_RHO2",
    "VERIFY_ALPHA",
    "VERIFY_KINDS",
    "BiasTest",
    "DispersionTest",
    "VerifyStatistics",
    "bias_test",
    "dispersion_test",
    "verify_statistics",
]

VERIFY_ALPHA = 0.01
"""Probability with which a right calibration is sent for recalibration: the family-wise
level of the two tests (each at ``alpha / 2``)."""

VERIFY_KINDS = ("x-segment", "y-segment", "area")
"""The board-test measurements ``verify`` checks: lengths and areas, whose true values
the board's pitch gives (the point-to-plane distance is 0 and tests flatness only)."""

LENGTH_KINDS = tuple(k for k in VERIFY_KINDS if BOARD_KINDS[k] == "length")

SHARED_CORNER_RHO2 = 0.25
"""Squared correlation of the image-noise errors of two measurements that share a corner:
two collinear segments ``x1 - x0`` and ``x2 - x1`` with independent end points correlate
by ``-1/2``; measurements at right angles share less."""


class _Test:
    """A test passes when its p-value ``p`` is at least its significance level ``alpha``
    (fields of the dataclasses below)."""

    @property
    def passed(self) -> bool:
        return bool(self.p >= self.alpha)

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "passed": self.passed}


@dataclasses.dataclass(frozen=True)
class BiasTest(_Test):
    """The mean relative length error against its predicted standard deviation.

    ``mean_relative`` and ``predicted_std``: fractions (0.005 is 0.5 %); ``z`` their ratio,
    ``p`` the two-sided p-value of a normal ``z``.
    """

    n: int
    mean_relative: float
    predicted_std: float
    predicted_std_image: float
    predicted_std_systematic: float
    z: float
    p: float
    alpha: float


@dataclasses.dataclass(frozen=True)
class DispersionTest(_Test):
    """The sum of squared normalised errors against its predicted distribution.

    ``rms_z`` is ``sqrt(q / n)``; ``dof`` the effective degrees of freedom of ``q``
    (Satterthwaite), ``scale`` its factor (``q ~ scale chi2(dof)``), ``p`` the upper-tail
    p-value.
    """

    n: int
    rms_z: float
    q: float
    dof: float
    scale: float
    p: float
    alpha: float
    rms_z_limit: float


@dataclasses.dataclass(frozen=True)
class VerifyStatistics:
    """Both tests, the 2-sigma band and the verdict (``pass`` or ``recalibrate``)."""

    n: int
    per_kind: list[dict[str, Any]]
    within_band: float
    bias: BiasTest
    dispersion: DispersionTest
    alpha: float

    @property
    def passed(self) -> bool:
        return self.bias.passed and self.dispersion.passed

    @property
    def verdict(self) -> str:
        return "pass" if self.passed else "recalibrate"

    @property
    def reasons(self) -> list[str]:
        """Why it failed, one sentence per failed test (empty when it passed)."""
        out = []
        b, d = self.bias, self.dispersion
        if not b.passed:
            out.append(
                f"lengths are {100 * b.mean_relative:+.3f} % off on average, "
                f"{abs(b.z):.1f} times their predicted +-{100 * b.predicted_std:.3f} % "
                f"(p = {b.p:.1e} < {b.alpha:g}): a common length bias, as a changed "
                "baseline gives"
            )
        if not d.passed:
            out.append(
                f"errors are {d.rms_z:.2f} times their predicted sigma (RMS; limit "
                f"{d.rms_z_limit:.2f} at p = {d.alpha:g}, p = {d.p:.1e}): the calibration "
                "no longer describes the probe"
            )
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "reasons": self.reasons,
            "alpha": self.alpha,
            "n": self.n,
            "within_band": self.within_band,
            "band_sigmas": BAND_SIGMAS,
            "per_kind": self.per_kind,
            "bias_test": self.bias.to_dict(),
            "dispersion_test": self.dispersion.to_dict(),
        }


def _systematic_std(predicted, rows: np.ndarray) -> np.ndarray:
    """The common (calibration and misfit) part of each row's predicted std (0 for a part
    not propagated)."""
    cal = np.nan_to_num(predicted.std_calibration[rows])
    model = np.nan_to_num(predicted.std_model[rows])
    return np.sqrt(cal**2 + model**2)


def _image_std(predicted, rows: np.ndarray) -> np.ndarray:
    """The image-noise part of each row's std (the whole std less the common parts, when
    the image part itself was not reported)."""
    image = predicted.std_image[rows]
    rest = np.sqrt(np.maximum(predicted.std[rows] ** 2 - _systematic_std(predicted, rows) ** 2, 0))
    return np.where(np.isfinite(image), image, rest)


def bias_test(table, predicted, rows: np.ndarray, alpha: float) -> BiasTest:
    """The common length bias (module docstring) of the length ``rows`` of a board test.

    ``r_i = (e_i - b_i) / L_i``, relative to the true length. Its mean's predicted
    variance is ``(mean_i c_i)^2 + sum_i (g_i / L_i)^2 / n^2`` with ``c_i`` the relative
    common std (calibration and misfit, fully correlated: the largest variance any
    correlation gives) and ``g_i`` the image-noise std (independent; neighbouring
    segments of one line anti-correlate, so this errs on the large side).
    """
    from scipy.stats import norm

    true = table.true[rows]
    r = (table.error[rows] - predicted.bias[rows]) / true
    n = int(r.size)
    common = float(np.mean(_systematic_std(predicted, rows) / true))
    image = float(np.sqrt(np.sum((_image_std(predicted, rows) / true) ** 2)) / n)
    std = math.hypot(common, image)
    mean = float(np.mean(r))
    z = mean / std if std > 0 else math.copysign(math.inf, mean) if mean else 0.0
    return BiasTest(n, mean, std, image, common, float(z), float(2 * norm.sf(abs(z))), alpha)


def _shared_corner_counts(table, rows: np.ndarray) -> np.ndarray:
    """For each row, how many other rows of the same image share a corner with it."""
    counts = np.zeros(rows.size)
    images = table.image[rows]
    for image in np.unique(images):
        sel = np.flatnonzero(images == image)
        corners = table.corners[rows[sel]]
        top = int(corners.max()) + 1
        member = np.zeros((sel.size, top), dtype=bool)
        for col in range(corners.shape[1]):
            ok = corners[:, col] >= 0
            member[np.flatnonzero(ok), corners[ok, col]] = True
        shared = member.astype(np.int32) @ member.T.astype(np.int32)  # corners in common
        counts[sel] = np.count_nonzero(shared > 0, axis=1) - 1
    return counts


def dispersion_test(table, predicted, rows: np.ndarray, alpha: float) -> DispersionTest:
    """Whether the errors of ``rows`` spread as predicted (module docstring).

    ``q = sum z_i^2`` has mean n when the predictions hold. Its variance
    ``2 sum_ij rho_ij^2`` counts the correlations: with ``f_i`` the common share of row
    i's variance, ``rho_ij^2`` is ``f_i f_j`` from the common part (fully correlated) and
    :data:`SHARED_CORNER_RHO2` ``(1 - f_i)(1 - f_j)`` from the image part of rows that
    share a corner. Then ``q ~ g chi2(nu)`` with ``g = var / (2 n)``, ``nu = 2 n^2 / var``
    (Satterthwaite, Biometrics Bull. 2, 1946); one-sided: errors smaller than predicted
    are no reason to recalibrate.
    """
    from scipy.stats import chi2

    z = (table.error[rows] - predicted.bias[rows]) / predicted.std[rows]
    n = int(z.size)
    f = np.clip(_systematic_std(predicted, rows) ** 2 / predicted.std[rows] ** 2, 0.0, 1.0)
    shared = _shared_corner_counts(table, rows)
    image = float(np.sum((1 - f) ** 2 * (1 + SHARED_CORNER_RHO2 * shared)))
    var = 2.0 * (float(np.sum(f)) ** 2 + image)
    scale, dof = var / (2 * n), 2 * n**2 / var
    q = float(np.sum(z**2))
    limit = math.sqrt(scale * float(chi2.isf(alpha, dof)) / n)
    return DispersionTest(n, math.sqrt(q / n), q, dof, scale, float(chi2.sf(q / scale, dof)),
                          alpha, limit)  # fmt: skip


def _per_kind(table, predicted, rows: np.ndarray) -> list[dict[str, Any]]:
    out = []
    for kind in VERIFY_KINDS:
        sel = rows[table.kind[rows] == kind]
        if sel.size == 0:
            continue
        e, b, s = table.error[sel], predicted.bias[sel], predicted.std[sel]
        true = float(table.true[sel][0])
        out.append(
            {
                "kind": kind,
                "n": int(sel.size),
                "true": true,
                "mean_error": float(np.mean(e)),
                "relative_mean_percent": float(100 * np.mean(e) / true),
                "rms_error": float(np.sqrt(np.mean(e**2))),
                "predicted_std_rms": float(np.sqrt(np.mean(s**2))),
                "rms_z": float(np.sqrt(np.mean(((e - b) / s) ** 2))),
                "within_band": float(np.mean(np.abs(e - b) <= BAND_SIGMAS * s)),
            }
        )
    return out


def verify_statistics(table, predicted, alpha: float = VERIFY_ALPHA) -> VerifyStatistics:
    """The verdict of ``verify`` from a board test's table and its predictions.

    Parameters
    ----------
    table : BoardTestTable
    predicted : PredictedErrors
        One entry per row of ``table`` (:func:`~endomeasure.measure.board_runs.board_predictions`).
    alpha : float
        Family-wise level, in (0, 1).

    Returns
    -------
    VerifyStatistics
        Over the rows of :data:`VERIFY_KINDS` with a finite error and a positive
        predicted std.
    """
    if not 0 < alpha < 1:
        raise BadInputError(f"the significance level must lie in (0, 1), not {alpha}")
    ok = (
        np.isin(table.kind, VERIFY_KINDS)
        & np.isfinite(table.error)
        & np.isfinite(predicted.bias)
        & (predicted.std > 0)
    )
    rows = np.flatnonzero(ok)
    lengths = rows[np.isin(table.kind[rows], LENGTH_KINDS)]
    if lengths.size < 2:
        raise BadInputError(
            f"only {lengths.size} board segments could be measured and predicted: too few "
            "to check a calibration",
            hint="give images where the whole board is seen in both halves",
        )
    s = predicted.std[rows]
    within = float(np.mean(np.abs(table.error[rows] - predicted.bias[rows]) <= BAND_SIGMAS * s))
    return VerifyStatistics(
        int(rows.size), _per_kind(table, predicted, rows), within,
        bias_test(table, predicted, lengths, alpha / 2),
        dispersion_test(table, predicted, rows, alpha / 2), float(alpha),
    )  # fmt: skip
