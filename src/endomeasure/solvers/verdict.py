"""The verdict on a calibration: ok, warning or failed, with its reasons (SPEC 5).

A fit is judged against what the detections allow, not against a fixed pixel figure:

- **RMS against the noise floor.** Each detected corner carries the detector's formal
  covariance ``C_i`` (:mod:`endomeasure.features.precision`). A model that describes the
  optics leaves residuals of that size: ``E[SSR] = (m - n) / m * sum_i tr C_i`` for ``m``
  residual components and ``n`` unknowns, so the formal floor is
  ``sqrt((m - n) / m * mean_i tr C_i)`` as an RMS residual length. The ratio RMS / floor
  is 1 within ``1 / sqrt(2 m)`` (a percent for a few thousand corners) when the model is
  adequate; model error adds in quadrature, so a ratio of ``r`` means a misfit of
  ``sqrt(r^2 - 1)`` times the noise. Up to :data:`OK_RMS_RATIO` is ok (misfit at most
  three quarters of the noise), up to :data:`FAILED_RMS_RATIO` a warning, above it the
  calibration failed: its errors are dominated by what the model cannot describe.
- **The scatter floor.** The formal floor cannot see errors of the corners that are not
  pixel noise (a board's print errors, blur that is not point-symmetric, compression, a
  renderer's sampling), which no model can fit either. They differ from model error in
  one way that the data show: model error is a smooth function over the field, the
  same for neighbouring corners, while these are independent from corner to corner. So
  the second differences of the residuals along the rows and columns of one board view
  estimate the per-corner error a correct model would leave, whatever its source
  (:func:`scatter_floor`). The verdict's floor is the larger of the two; both are
  reported.
- **Outliers.** More than :data:`OUTLIER_WARNING_FRACTION` of the corners dropped is a
  sign of trouble (mrcal's rule of thumb); where they are (field edge, next to the
  split, one image, per half) and how far they miss is reported.
- **Residual structure.** The inlier residuals are averaged over a grid of cells per half;
  a cell whose mean residual is both significant (:data:`STRUCTURE_Z` standard errors)
  and large against the noise (:data:`STRUCTURE_NOISE_FRACTION` of the per-axis floor)
  shows a systematic misfit in that part of the field.
- **Undetermined combinations.** A correlation matrix of the free parameters with an
  eigenvalue below :data:`MIN_CORRELATION_EIGENVALUE` has a combination the data hardly
  see (its standard deviation inflated a thousand-fold against independent parameters).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

__all__ = [
    "Verdict",
    "judge",
    "noise_floor",
    "scatter_floor",
    "second_differences",
    "VERDICT_LEVELS",
    "OK_RMS_RATIO",
    "FAILED_RMS_RATIO",
    "OUTLIER_WARNING_FRACTION",
    "MIN_CORRELATION_EIGENVALUE",
]

VERDICT_LEVELS = ("ok", "warning", "failed")
OK_RMS_RATIO = 1.25
"""RMS / floor up to this is ok: a misfit of at most 0.75 of the noise."""
FAILED_RMS_RATIO = 2.0
"""RMS / floor above this fails: a misfit of more than 1.7 times the noise."""
OUTLIER_WARNING_FRACTION = 0.03
STRUCTURE_CELLS = 4
"""Cells per axis of each half for the residual-structure check."""
STRUCTURE_MIN_CORNERS = 20
STRUCTURE_Z = 5.0
STRUCTURE_NOISE_FRACTION = 0.5
MIN_CORRELATION_EIGENVALUE = 1e-6
MIN_KNOWN_FRACTION = 0.5
"""At least this fraction of the inlier corners must carry a formal covariance for the
floor to be computed (the others get the median of the known ones)."""
EDGE_RADIUS_FRACTION = 0.7
"""Outliers beyond this fraction of a half's centre-to-corner radius are "at the field edge"."""
BAND_WIDTH_FRACTION = 0.1
"""Outliers within this fraction of a half's width of the split are "next to the band"."""
ONE_IMAGE_FRACTION = 0.5
"""An image holding more than this fraction of the outliers is named."""


MIN_NEIGHBOUR_PAIRS = 30
"""Runs of three neighbouring corners needed for the scatter floor."""


def scatter_floor(
    board_points, image, half, residuals, min_runs: int = MIN_NEIGHBOUR_PAIRS
) -> float:
    """RMS residual length left by errors independent from corner to corner, px.

    ``sqrt(mean |r_a - 2 r_b + r_c|^2 / 6)`` over runs of three corners one square apart
    along a board row or column, in the same half of the same image: a misfit that is
    smooth over the board (constant or linear across three corners) cancels in the second
    difference, independent errors of variance ``s^2`` give ``6 s^2`` (NaN with fewer
    than ``min_runs`` runs).

    Parameters
    ----------
    board_points : ndarray, shape (K, 3), mm
        Corners in the board frame (on a square grid, z = 0).
    image, half : ndarray, shape (K,), int
    residuals : ndarray, shape (K, 2), px
    """
    total, runs = 0.0, 0
    keys = np.asarray(image, dtype=np.int64) * 2 + np.asarray(half, dtype=np.int64)
    for key in np.unique(keys):
        sel = np.flatnonzero(keys == key)
        second = second_differences(board_points[sel], residuals[sel])
        total += float(np.sum(second * second))
        runs += second.shape[0]
    return float(np.sqrt(total / (6 * runs))) if runs >= min_runs else float("nan")


def second_differences(board_points, residuals) -> np.ndarray:
    """``r_a - 2 r_b + r_c`` over every run of three corners one square apart along a
    row or column of one board in one image half (:func:`scatter_floor`).

    ``board_points`` (K, 3), mm, board frame; ``residuals`` (K, C). Returns (R, C), the
    runs along the board's first axis, then its second; the same corners give the same
    runs in the same order, so two halves' runs pair up.
    """
    residuals = np.asarray(residuals, dtype=np.float64)
    if board_points.shape[0] < 3:
        return np.zeros((0, residuals.shape[1]))
    X = board_points[:, :2]
    d = np.linalg.norm(X[:, None, :] - X[None, :, :], axis=-1)
    step = d[np.triu_indices(X.shape[0], 1)].min()
    cell = np.rint((X - X.min(axis=0)) / step).astype(np.int64)
    grid = np.full(tuple(cell.max(axis=0) + 1), -1, dtype=np.int64)
    grid[cell[:, 0], cell[:, 1]] = np.arange(X.shape[0])
    out = []
    for axis in (0, 1):
        lo = np.moveaxis(grid, axis, 0)
        a, b, c = lo[:-2], lo[1:-1], lo[2:]
        ok = (a >= 0) & (b >= 0) & (c >= 0)
        out.append(residuals[a[ok]] - 2 * residuals[b[ok]] + residuals[c[ok]])
    return np.concatenate(out)


@dataclasses.dataclass(frozen=True)
class Verdict:
    """The judgement of one calibration.

    Attributes
    ----------
    level : str
        ``ok``, ``warning`` or ``failed``.
    reasons : tuple of str
        One sentence per finding (empty when ok).
    floor_px : float
        The RMS residual length a correct model would leave, px: the larger of
        ``formal_px`` and ``scatter_px`` (NaN when both are unknown).
    rms_ratio : float
        The fit's RMS over the floor (NaN when the floor is unknown).
    outlier_fraction : float
    formal_px : float
        The floor from the detector's formal covariance (:func:`noise_floor`).
    scatter_px : float
        The floor from the scatter of neighbouring corners' residuals (:func:`scatter_floor`).
    """

    level: str
    reasons: tuple[str, ...]
    floor_px: float
    rms_ratio: float
    outlier_fraction: float
    formal_px: float = float("nan")
    scatter_px: float = float("nan")

    @property
    def usable(self) -> bool:
        return self.level != "failed"

    def to_dict(self) -> dict:
        return {
            "level": self.level,
            "reasons": list(self.reasons),
            "floor_px": self.floor_px,
            "rms_ratio": self.rms_ratio,
            "outlier_fraction": self.outlier_fraction,
            "formal_px": self.formal_px,
            "scatter_px": self.scatter_px,
        }


def noise_floor(covariance: np.ndarray, m: int, n: int) -> float:
    """Expected RMS residual length of a correct model, px (NaN without enough covariances).

    Parameters
    ----------
    covariance : ndarray, shape (K, 2, 2), px^2
        Formal covariance of each fitted corner; NaN where unknown.
    m, n : int
        Residual components and unknowns of the fit.
    """
    trace = np.trace(np.asarray(covariance, dtype=np.float64), axis1=1, axis2=2)
    known = np.isfinite(trace) & (trace > 0)
    if trace.size == 0 or known.mean() < MIN_KNOWN_FRACTION or m <= n:
        return float("nan")
    trace = np.where(known, trace, np.median(trace[known]))
    return float(np.sqrt((m - n) / m * trace.mean()))


def _half_bounds(half: int, split: int, image_size) -> tuple[float, float, float, float]:
    width, height = image_size
    lo, hi = (-0.5, split - 0.5) if half == 0 else (split - 0.5, width - 0.5)
    return lo, hi, -0.5, height - 0.5


def _where(result, dropped: np.ndarray, floor: float) -> str:
    """Where the dropped corners lie and how far they miss: at the field edge, next to
    the split (the apex band), in one image, per half; their residuals against the floor.

    A cluster in one place is structure the model or the detector misses there, not
    random outliers; saying where lets the user tell a bad image from a lens edge.
    """
    config = result.model.config
    pixels, halves = result.obs_pixels[dropped], result.obs_half[dropped]
    edge = band = 0
    for h in (0, 1):
        sel = halves == h
        if not sel.any():
            continue
        u0, u1, v0, v1 = _half_bounds(h, config.split, config.image_size)
        centre = np.array([(u0 + u1) / 2, (v0 + v1) / 2])
        radius = np.hypot((u1 - u0) / 2, (v1 - v0) / 2)
        r = np.linalg.norm(pixels[sel] - centre, axis=1) / radius
        edge += int((r > EDGE_RADIUS_FRACTION).sum())
        inner = u1 if h == 0 else u0  # the half's edge at the split
        band += int((np.abs(pixels[sel, 0] - inner) < BAND_WIDTH_FRACTION * (u1 - u0)).sum())
    n = int(dropped.sum())
    parts = [
        f"{edge} of them at the field edge (beyond {EDGE_RADIUS_FRACTION:.0%} of each half's "
        f"radius)",
        f"{band} within {BAND_WIDTH_FRACTION:.0%} of a half's width of the split",
        f"left {int((halves == 0).sum())}, right {int((halves == 1).sum())}",
    ]
    images = np.bincount(result.obs_image[dropped], minlength=len(result.image_names))
    worst = int(np.argmax(images))
    if images[worst] > ONE_IMAGE_FRACTION * n:
        parts.append(f"{images[worst]} in image {result.image_names[worst]!r}")
    size = np.linalg.norm(result.residuals[dropped], axis=1)
    size = size[np.isfinite(size)]  # corners that no longer project have no residual
    if size.size:
        lo, mid, hi = np.percentile(size, [10, 50, 90])
        text = f"residuals {lo:.2f}-{hi:.2f} px (10th-90th percentile), median {mid:.2f} px"
        if np.isfinite(floor) and floor > 0:
            text += f" ({mid / floor:.0f} times the noise floor)"
        parts.append(text)
    return "; ".join(parts)


_ROWS = ("top", "upper middle", "lower middle", "bottom")
_COLS = ("left", "centre-left", "centre-right", "right")


def _structure(
    pixels: np.ndarray, residuals: np.ndarray, halves: np.ndarray, split: int, image_size,
    sigma_axis: float,
) -> str | None:  # fmt: skip
    """The worst systematic cell of the residual field, or None."""
    worst = None
    for h in (0, 1):
        sel = halves == h
        u0, u1, v0, v1 = _half_bounds(h, split, image_size)
        last = STRUCTURE_CELLS - 1
        cu = np.clip(((pixels[sel, 0] - u0) / (u1 - u0) * STRUCTURE_CELLS).astype(int), 0, last)
        cv = np.clip(((pixels[sel, 1] - v0) / (v1 - v0) * STRUCTURE_CELLS).astype(int), 0, last)
        r = residuals[sel]
        for i in range(STRUCTURE_CELLS):
            for j in range(STRUCTURE_CELLS):
                cell = (cv == i) & (cu == j)
                k = int(cell.sum())
                if k < STRUCTURE_MIN_CORNERS:
                    continue
                mean = r[cell].mean(axis=0)
                size = float(np.linalg.norm(mean))
                se = sigma_axis / np.sqrt(k)
                if size > STRUCTURE_Z * se and size > STRUCTURE_NOISE_FRACTION * sigma_axis:
                    if worst is None or size > worst[0]:
                        worst = (size, h, _ROWS[i], _COLS[j], k)
    if worst is None:
        return None
    size, h, row, col, k = worst
    half = "left" if h == 0 else "right"
    return (
        f"systematic residuals: the mean residual of the {k} corners in the {row} {col} of the "
        f"{half} half is {size:.3f} px ({size / sigma_axis:.1f} times the noise per axis), "
        "a part of the field the model does not describe"
    )


def _undetermined(free_names: Sequence[str], correlation: np.ndarray) -> str | None:
    if correlation.size == 0 or not np.all(np.isfinite(correlation)):
        return None
    values, vectors = np.linalg.eigh(correlation)
    if values[0] >= MIN_CORRELATION_EIGENVALUE:
        return None
    weights = np.abs(vectors[:, 0])
    top = [free_names[i] for i in np.argsort(-weights)[:3]]
    return (
        f"nearly undetermined: the combination of {', '.join(top)} is hardly constrained by "
        f"the data (correlation eigenvalue {values[0]:.1e}); fix one of them or add images "
        "with more tilt and distance"
    )


def judge(result, n_unknowns: int) -> Verdict:
    """Judge a calibration (a ``CalibrationResult``) against its detections' noise.

    Parameters
    ----------
    result : CalibrationResult
        With ``obs_covariance``, the detector's formal covariance of every observation
        (NaN where unknown).
    n_unknowns : int
        Unknowns of the final fit (free parameters and board poses).
    """
    inl = np.asarray(result.inliers, dtype=bool)
    m = 2 * int(inl.sum())
    given = result.obs_covariance
    cov = np.full((inl.size, 2, 2), np.nan) if given is None else np.asarray(given)
    formal = noise_floor(cov[inl], m, n_unknowns)
    scatter = scatter_floor(result.obs_board_points[inl], result.obs_image[inl],
                            result.obs_half[inl], result.residuals[inl])  # fmt: skip
    floor = float(np.nanmax([formal, scatter])) if np.isfinite([formal, scatter]).any() else np.nan
    rms = result.rms
    ratio = rms / floor if np.isfinite(floor) and floor > 0 else float("nan")
    outlier_fraction = 1.0 - inl.mean() if inl.size else 0.0
    config = result.model.config
    failed, warnings = [], []
    floors = f"the larger of the detector's formal {formal:.4f} px and the corners' scatter " \
             f"{scatter:.4f} px"  # fmt: skip
    if not np.isfinite(ratio):
        warnings.append(
            "the noise floor is unknown (detections without the detector's precision, and too "
            f"few neighbouring corners): the fit's RMS {rms:.4f} px cannot be judged"
        )
    elif ratio > FAILED_RMS_RATIO:
        failed.append(
            f"RMS {rms:.4f} px is {ratio:.1f} times the noise floor {floor:.4f} px ({floors}; "
            f"limit {FAILED_RMS_RATIO:g}): the model does not describe this probe, or the "
            "fit stopped in a wrong minimum"
        )
    elif ratio > OK_RMS_RATIO:
        warnings.append(
            f"RMS {rms:.4f} px is {ratio:.2f} times the noise floor {floor:.4f} px ({floors}; "
            f"ok up to {OK_RMS_RATIO:g}): part of the residual is model error"
        )
    if outlier_fraction > OUTLIER_WARNING_FRACTION:
        where = _where(result, ~inl, floor)
        warnings.append(
            f"{outlier_fraction:.1%} of the corners were dropped as outliers (over "
            f"{OUTLIER_WARNING_FRACTION:.0%}): {where}"
        )
    sigma_axis = (floor if np.isfinite(floor) else rms) / np.sqrt(2.0)
    structure = _structure(result.obs_pixels[inl], result.residuals[inl], result.obs_half[inl],
                           config.split, config.image_size, sigma_axis)  # fmt: skip
    if structure:
        warnings.append(structure)
    undetermined = _undetermined(result.free_names, result.correlation)
    if undetermined:
        warnings.append(undetermined)
    level = "failed" if failed else ("warning" if warnings else "ok")
    return Verdict(level, tuple(failed + warnings), floor, ratio, float(outlier_fraction),
                   formal, scatter)  # fmt: skip
