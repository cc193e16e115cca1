"""What a calibration's residuals, parameters and error map say about where to trust it.

The numbers behind ``endomeasure report`` (no drawing, no storage): residual bias per
field region tested against the noise, how much of each half the calibration corners
covered, the residual histogram against the Gaussian the noise floor predicts, per-image
RMS for pruning, strong parameter correlations, the stereo baseline with its +-, and the
trust bands of a predicted error map. Residuals are ``model - observed`` pixels, as the
calibration stores them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from endomeasure.conventions import Half

__all__ = [
    "BIAS_SIGNIFICANCE",
    "RegionBias",
    "TRUST_LABELS",
    "coverage",
    "effective_baseline",
    "half_box",
    "image_rms_table",
    "region_bias",
    "residual_histogram",
    "strong_correlations",
    "trust_bands",
]

BIAS_SIGNIFICANCE = 1e-3
"""False-alarm probability per region of the residual-bias test: with the report's 6 x 4
regions per half (48 per model), pure noise outlines a region in about one report in
twenty."""

TRUST_LABELS = ("green", "yellow", "red")
"""Bands of a trust map: within the first limit, within the second, beyond it or not
measurable (a point one half does not see)."""


def half_box(image_size: Sequence[int], split: int, half: Half) -> tuple[float, ...]:
    """``(u0, u1, v0, v1)``: the pixel extent of a half, px (pixel centres at integers)."""
    width, height = image_size
    u0, u1 = (-0.5, split - 0.5) if half == Half.LEFT else (split - 0.5, width - 0.5)
    return u0, u1, -0.5, height - 0.5


def _cell_index(pixels: np.ndarray, box, cells: tuple[int, int]) -> tuple[np.ndarray, ...]:
    u0, u1, v0, v1 = box
    n_u, n_v = cells
    iu = np.clip(((pixels[:, 0] - u0) / (u1 - u0) * n_u).astype(int), 0, n_u - 1)
    iv = np.clip(((pixels[:, 1] - v0) / (v1 - v0) * n_v).astype(int), 0, n_v - 1)
    return iu, iv


def coverage(pixels: np.ndarray, box, cells: tuple[int, int] = (8, 6)) -> float:
    """Fraction of the ``cells`` regions of ``box`` that hold at least one corner."""
    if pixels.shape[0] == 0:
        return 0.0
    iu, iv = _cell_index(pixels, box, cells)
    return float(np.unique(iv * cells[0] + iu).size / (cells[0] * cells[1]))


@dataclass(frozen=True)
class RegionBias:
    """Mean residual per field region of one half, and whether it exceeds the noise.

    Arrays are (n_v, n_u); ``mean`` (n_v, n_u, 2) px. ``significant``: the mean vector is
    unlikely under zero-mean noise of ``sigma_px`` per coordinate (``n |mean|^2 /
    sigma^2`` is chi-square with 2 degrees of freedom; false alarms
    :data:`BIAS_SIGNIFICANCE` per region). Regions with fewer than 3 corners are NaN.
    """

    box: tuple[float, float, float, float]
    count: np.ndarray
    mean: np.ndarray
    significant: np.ndarray
    sigma_px: float

    @property
    def magnitude(self) -> np.ndarray:
        return np.linalg.norm(self.mean, axis=-1)

    @property
    def n_significant(self) -> int:
        return int(self.significant.sum())


def region_bias(
    pixels: np.ndarray,
    residuals: np.ndarray,
    box,
    sigma_px: float,
    cells: tuple[int, int] = (6, 4),
) -> RegionBias:
    """:class:`RegionBias` of the corners ``pixels`` (N, 2) with ``residuals`` (N, 2)."""
    n_u, n_v = cells
    count = np.zeros((n_v, n_u), dtype=int)
    total = np.zeros((n_v, n_u, 2))
    if pixels.shape[0]:
        iu, iv = _cell_index(pixels, box, cells)
        np.add.at(count, (iv, iu), 1)
        np.add.at(total, (iv, iu), residuals)
    enough = count >= 3
    mean = np.full((n_v, n_u, 2), np.nan)
    mean[enough] = total[enough] / count[enough][:, None]
    chi2 = np.zeros((n_v, n_u))
    if sigma_px > 0:
        chi2[enough] = count[enough] * np.sum(mean[enough] ** 2, axis=-1) / sigma_px**2
    limit = stats.chi2.isf(BIAS_SIGNIFICANCE, 2)
    return RegionBias(box, count, mean, enough & (chi2 > limit), float(sigma_px))


def residual_histogram(
    residuals: np.ndarray, sigma_px: float, bins: int = 41
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(edges, counts, expected)`` of the residual coordinates (both axes pooled)
    against a zero-mean Gaussian of ``sigma_px``, over +-5 sigma (or the data's span
    if wider); the outer bins hold the tails."""
    r = residuals[np.isfinite(residuals)].ravel()
    span = max(5.0 * sigma_px, float(np.percentile(np.abs(r), 99.5)) if r.size else 0.0, 1e-9)
    edges = np.linspace(-span, span, bins + 1)
    counts = np.histogram(np.clip(r, -span, span), edges)[0]
    cdf = stats.norm.cdf(edges, scale=max(sigma_px, 1e-12))
    cdf[0], cdf[-1] = 0.0, 1.0  # the outer bins take the tails, as the clip does
    return edges, counts, r.size * np.diff(cdf)


def image_rms_table(
    image: np.ndarray,
    half: np.ndarray,
    residuals: np.ndarray,
    names: Sequence[str],
    boards: Sequence[str] | None = None,
) -> list[dict]:
    """Per calibration image: RMS residual length per half and both, corners used; the
    worst image first (the ones to look at, or to drop, before recalibrating)."""
    length2 = np.sum(residuals**2, axis=-1)
    rows = []
    for i, name in enumerate(names):
        sel = image == i
        if not sel.any():
            continue
        row = {"image": str(name), "board": None if boards is None else str(boards[i])}
        for h in Half:
            part = sel & (half == h)
            row[f"rms_{h.label}"] = float(np.sqrt(length2[part].mean())) if part.any() else None
        row["rms"] = float(np.sqrt(length2[sel].mean()))
        row["corners"] = int(sel.sum())
        rows.append(row)
    return sorted(rows, key=lambda r: -r["rms"])


def strong_correlations(
    names: Sequence[str], correlation: np.ndarray, limit: float = 0.9
) -> list[tuple[str, str, float]]:
    """Pairs of free parameters whose correlation exceeds ``limit`` in magnitude, the
    strongest first: parameters the images cannot tell apart."""
    c = np.asarray(correlation, dtype=float)
    i, j = np.triu_indices(c.shape[0], k=1)
    strong = np.abs(c[i, j]) > limit
    pairs = [
        (str(names[a]), str(names[b]), float(c[a, b]))
        for a, b in zip(i[strong], j[strong], strict=True)
    ]
    return sorted(pairs, key=lambda p: -abs(p[2]))


def _ray_centre(model, half: Half, params: np.ndarray | None = None, n: int = 9) -> np.ndarray:
    """The point closest (least squares) to the rays of a grid of pixels over a half: the
    camera centre of a central model, the effective viewpoint of a non-central one."""
    u0, u1, v0, v1 = half_box(model.config.image_size, model.config.split, half)
    du, dv = 0.1 * (u1 - u0), 0.1 * (v1 - v0)
    u, v = np.meshgrid(np.linspace(u0 + du, u1 - du, n), np.linspace(v0 + dv, v1 - dv, n))
    pixels = np.stack([u.ravel(), v.ravel()], axis=-1)
    m = model if params is None else model.with_params(params)
    rays = m.rays(pixels, half)
    ok = np.all(np.isfinite(rays.directions), axis=-1)
    o, d = rays.origins[ok], rays.directions[ok]
    if o.shape[0] < 2:
        return np.full(3, np.nan)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return np.linalg.solve(proj.sum(axis=0), np.einsum("nij,nj->i", proj, o))


def effective_baseline(model, param_cov: np.ndarray | None = None) -> tuple[float, float]:
    """``(baseline, std)``, mm: distance between the two halves' effective viewpoints
    (:func:`_ray_centre`), the same quantity for every model; the std propagates the free
    parameters' covariance linearly (central differences, steps of a hundredth of each
    parameter's own std), NaN without a covariance."""

    def baseline(params=None) -> float:
        left = _ray_centre(model, Half.LEFT, params)
        return float(np.linalg.norm(_ray_centre(model, Half.RIGHT, params) - left))

    value = baseline()
    if param_cov is None:
        return value, float("nan")
    free = np.flatnonzero(model.free_mask)
    std = np.sqrt(np.clip(np.diag(param_cov), 0.0, None))
    jac = np.zeros(free.size)
    for k, (i, s) in enumerate(zip(free, std, strict=True)):
        if s == 0:
            continue
        step = 1e-2 * s
        up, down = np.array(model.params), np.array(model.params)
        up[i] += step
        down[i] -= step
        jac[k] = (baseline(up) - baseline(down)) / (2 * step)
    return value, float(np.sqrt(max(jac @ param_cov @ jac, 0.0)))


def trust_bands(relative_percent: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """The :data:`TRUST_LABELS` index of each point: 0 within ``limits[0]`` %, 1 within
    ``limits[1]`` %, 2 beyond or NaN (not measurable there)."""
    r = np.asarray(relative_percent, dtype=float)
    band = np.full(r.shape, 2, dtype=np.int8)
    band[r <= limits[1]] = 1
    band[r <= limits[0]] = 0
    return band
