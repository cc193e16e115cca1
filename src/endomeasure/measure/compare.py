"""Where and by how much two calibrations disagree: the maths of ``endomeasure compare``.

Two calibrated models A and B (two calibrations of one probe, two models of one
calibration, or two probes) are compared over a grid of the working volume: the pixels
of a regular grid over A's left half, each cut with the planes ``z = depth``
(:func:`~endomeasure.measure.predict.volume_grid`; rays with their origins, so
non-central models are traced as they are).

In pixels
    every grid point is projected through A and through B into both halves; the
    difference ``q_B - q_A`` is the absolute disagreement (nothing is fitted away: a
    common shift of the halves counts too).

In mm
    a 1 mm segment along x centred on each grid point is projected through A into both
    halves and triangulated from those pixels by both models; ``d = L_B - L_A`` is what
    the same pixels would measure differently. Its predicted spread, when both
    calibrations are right (they differ only by their own calibration errors), is
    ``sigma = hypot(sigma_A, sigma_B)``, each calibration's std of that length from its
    parameter covariance (:func:`~endomeasure.measure.predict.predict_measurement_error`,
    image noise left out: the same pixels go through both).

Verdict
-------
``z = d / sigma`` is normal with variance 1 at every point when both calibrations are
right, but strongly correlated over the field (one calibration error makes the whole
map). For any correlation, ``mean(z^2)`` over the field has mean 1 and exceeds ``c^2``
no more often than ``|z|`` of a single point does once ``c`` is beyond about 1.5 (a
sum of weighted chi-square(1) terms has its heaviest tail with one term), so "the RMS of
z at a depth exceeds ``z_(1 - alpha / 2D)``" is a test of level at most ``alpha`` over
the D depths (Bonferroni). The fraction of the field outside the pointwise 2-sigma band
and the largest ``|z|`` are reported, not tested.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from endomeasure.conventions import Status
from endomeasure.errors import BadInputError

__all__ = [
    "BAND_SIGMAS",
    "COMPARE_ALPHA",
    "Comparison",
    "compare_models",
    "rms_z_limit",
]

COMPARE_ALPHA = 0.01
"""Probability with which two right calibrations of one probe are called ``disagree``
(at most; family-wise over the depths)."""
BAND_SIGMAS = 2.0
"""Half-width of the reported pointwise band, in combined sigma."""
TEMPLATE = "x-segment"


@dataclasses.dataclass(frozen=True)
class Comparison:
    """Two models compared at K grid points (arrays (K, ...)), depth-major.

    Attributes
    ----------
    depths : ndarray, shape (D,), mm
    depth_index : ndarray, shape (K,), int
    pixels : ndarray, shape (K, 2), px
        The grid point's pixel in A's left half.
    centres : ndarray, shape (K, 3), mm
        The grid points (A's back-projection).
    diff_left, diff_right : ndarray, shape (K, 2), px
        ``q_B - q_A`` of the grid point in each half (NaN where B does not project it).
    length_a, length_b : ndarray, shape (K,), mm
        The segment triangulated by each model from A's pixels (NaN where it fails).
    sigma_a, sigma_b : ndarray, shape (K,), mm
        Each calibration's std of that length (0 for a model without covariance).
    size_mm : float
    alpha : float
    """

    depths: np.ndarray
    depth_index: np.ndarray
    pixels: np.ndarray
    centres: np.ndarray
    diff_left: np.ndarray
    diff_right: np.ndarray
    length_a: np.ndarray
    length_b: np.ndarray
    sigma_a: np.ndarray
    sigma_b: np.ndarray
    size_mm: float
    alpha: float = COMPARE_ALPHA

    @property
    def length_diff(self) -> np.ndarray:
        """``L_B - L_A``, mm."""
        return self.length_b - self.length_a

    @property
    def sigma(self) -> np.ndarray:
        """The combined std ``hypot(sigma_A, sigma_B)``, mm."""
        return np.hypot(self.sigma_a, self.sigma_b)

    @property
    def z(self) -> np.ndarray:
        """``(L_B - L_A) / sigma``, NaN where either is not finite."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.length_diff / self.sigma

    @property
    def rms_z_limit(self) -> float:
        return rms_z_limit(self.alpha, self.depths.size)

    def per_depth(self) -> list[dict[str, Any]]:
        """One summary per depth plane: pixel and length disagreement, normalised."""
        rows = []
        z, d = self.z, self.length_diff
        for k, depth in enumerate(self.depths):
            at = self.depth_index == k
            ok = at & np.isfinite(z)
            if not ok.any():
                continue
            row = {"z_mm": float(depth), "n": int(ok.sum())}
            for half, diff in (("left", self.diff_left), ("right", self.diff_right)):
                norm = np.linalg.norm(diff[at], axis=1)
                norm = norm[np.isfinite(norm)]
                row[f"{half}_rms_px"] = float(np.sqrt(np.mean(norm**2))) if norm.size else None
                row[f"{half}_max_px"] = float(np.max(norm)) if norm.size else None
            row.update(
                length_diff_rms_mm=float(np.sqrt(np.mean(d[ok] ** 2))),
                length_diff_max_mm=float(np.max(np.abs(d[ok]))),
                length_diff_mean_mm=float(np.mean(d[ok])),
                sigma_rms_mm=float(np.sqrt(np.mean(self.sigma[ok] ** 2))),
                rms_z=float(np.sqrt(np.mean(z[ok] ** 2))),
                max_abs_z=float(np.max(np.abs(z[ok]))),
                outside_band=float(np.mean(np.abs(z[ok]) > BAND_SIGMAS)),
            )
            row["agree"] = bool(row["rms_z"] <= self.rms_z_limit)
            rows.append(row)
        return rows

    @property
    def agree(self) -> bool:
        rows = self.per_depth()
        return bool(rows) and all(r["agree"] for r in rows)


def rms_z_limit(alpha: float, n_depths: int) -> float:
    """The RMS of z over one depth's field beyond which the calibrations disagree:
    ``z_(1 - alpha / (2 D))`` (module docstring)."""
    from scipy.stats import norm

    return float(norm.isf(alpha / (2 * max(n_depths, 1))))


def _length_sigma(model, ql, qr, param_cov) -> np.ndarray:
    """The calibration part of the std of the segments with pixels ``ql``, ``qr``
    (K, 2, 2), mm; 0 without a covariance."""
    from endomeasure.measure.predict import ImageNoise, predict_measurement_error

    if param_cov is None:
        return np.zeros(ql.shape[0])
    pred = predict_measurement_error(model, "length", ql, qr, noise=ImageNoise(0.0),
                                     param_cov=param_cov, method="linear")  # fmt: skip
    return np.asarray(pred.parts["calibration"][1] if "calibration" in pred.parts else pred.std)


def _diff(model_a, model_b, points, half) -> np.ndarray:
    qa = model_a.project(points, half).pixels
    qb = model_b.project(points, half).pixels
    return qb - qa


def compare_models(
    model_a,
    model_b,
    depths,
    grid: tuple[int, int] = (16, 12),
    *,
    cov_a: np.ndarray | None = None,
    cov_b: np.ndarray | None = None,
    size_mm: float = 1.0,
    alpha: float = COMPARE_ALPHA,
) -> Comparison:
    """Compare two calibrated models over the working volume (module docstring).

    Parameters
    ----------
    model_a, model_b : CameraModel
        Of one image size (any kinds and splits).
    depths : sequence of float, mm
    grid : (int, int)
        Pixels per row and column over A's left half.
    cov_a, cov_b : ndarray, shape (F, F), optional
        Each model's free-parameter covariance; at least one.
    size_mm : float
        The segment's length.
    alpha : float

    Returns
    -------
    Comparison
    """
    from endomeasure.measure.kinds import evaluate
    from endomeasure.measure.predict import template_points, volume_grid
    from endomeasure.solvers.triangulate import triangulate

    # another split is fine (each model projects into its own halves); another sensor is not
    size_a, size_b = tuple(model_a.config.image_size), tuple(model_b.config.image_size)
    if size_a != size_b:
        raise BadInputError(
            f"the two calibrations have another image size ({size_a} and {size_b})",
            hint="compare calibrations of the same sensor",
        )
    if cov_a is None and cov_b is None:
        raise BadInputError(
            "neither calibration carries a parameter covariance, so their disagreement "
            "cannot be set against a +-",
            hint="re-run `endomeasure calibrate` for at least one of them",
        )
    z = np.asarray(depths, dtype=np.float64).reshape(-1)
    if z.size == 0 or not np.all(np.isfinite(z) & (z > 0)):
        raise BadInputError(f"depths must be positive numbers of mm, got {list(z)}")
    centres = volume_grid(model_a, z, *grid)
    if centres.shape[0] == 0:
        raise BadInputError("no grid point of these depths is seen by both halves of A",
                            hint="choose depths inside the working range")  # fmt: skip
    depth_index = np.argmin(np.abs(centres[:, 2:3] - z[None, :]), axis=1)
    pts = template_points(TEMPLATE, centres, size_mm)  # (K, 2, 3)
    pl, pr = model_a.project(pts, "left"), model_a.project(pts, "right")
    seen = np.all((pl.status == Status.OK) & (pr.status == Status.OK), axis=1)
    ql, qr = pl.pixels, pr.pixels
    lengths = []
    for model in (model_a, model_b):
        tri = triangulate(model, ql, qr, "ml")
        length = np.full(ql.shape[0], np.nan)
        good = seen & np.all(tri.status == Status.OK, axis=1)
        length[good] = evaluate("length", tri.points[good])
        lengths.append(length)
    sigmas = []
    for model, cov in ((model_a, cov_a), (model_b, cov_b)):
        s = np.full(ql.shape[0], np.nan)
        s[seen] = _length_sigma(model, ql[seen], qr[seen], cov)
        sigmas.append(s)
    pixels = model_a.project(centres, "left").pixels
    return Comparison(
        z, depth_index, pixels, centres, _diff(model_a, model_b, centres, "left"),
        _diff(model_a, model_b, centres, "right"), lengths[0], lengths[1], sigmas[0],
        sigmas[1], float(size_mm), float(alpha),
    )  # fmt: skip


def verdict_word(agree: bool) -> str:
    return "agree" if agree else "disagree"
