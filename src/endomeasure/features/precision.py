"""Formal precision of the point-symmetric corner fit: each corner's covariance from image noise.

:func:`endomeasure.features.subpixel.symmetric_corners` finds a corner ``c`` (and a
relative illumination gradient ``k``) by weighted least squares on the residuals::

    r_m = I(c + s_m + h_m) - I(c + s_m - h_m) - (k . h_m) (I(c + s_m + h_m) + I(c + s_m - h_m))

``I`` the cubic B-spline interpolant of the image. To first order in the image noise
``n`` the solution moves by ``d theta = -N^-1 J^T W d r`` (``theta = (c, k)``, ``J`` the
Jacobian of the residuals at the solution, ``W`` the window weights, ``N = J^T W J``),
and ``d r = D n`` is linear in the pixel noise: every residual is a difference of two
interpolated samples, each a weighted sum of many pixels (the interpolating spline's
prefilter spreads a pixel over its neighbours). So::

    Cov(c) = [N^-1 J^T W D] Sigma_n [N^-1 J^T W D]^T    (the (u, v) block)

a sandwich, not ``sigma^2 N^-1``: the residuals are neither independent nor of equal
variance, and the weights are not inverse variances. :func:`symmetric_precision`
evaluates it exactly for a diagonal pixel covariance ``Sigma_n`` (independent pixel
noise, constant or per pixel): the two rows of ``N^-1 J^T W`` are spread onto the spline
coefficients with the interpolation weights of every sample (the transpose of
sampling), then onto the pixels by the spline prefilter (the inverse of a symmetric
convolution, so its own transpose away from the box edges).

With the noise estimated from the image (``noise=None``) the pixel noise need not be
independent: demosaicing (each colour pixel interpolated from its neighbours) and lossy
compression correlate it over a few pixels, which concentrates its power at the low
spatial frequencies a corner fit averages over, so the independent-noise sandwich would
understate the corner's covariance. The image's noise autocorrelation ``rho`` is then
estimated from lag differences over its flat pixels (:func:`noise_autocorrelation`), and
both the residual variance and the sandwich use ``Sigma_n = sigma^2 rho(p - q)``.

What it cannot see: errors that do not come from pixel noise (the detector's bias, the
renderer's approximations, a blur that is not point-symmetric), and the noise of the
start points through the window and curvature estimates (second order for the fit).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from endomeasure.features.subpixel import (
    SYMMETRY_SIGMA_SQUARES,
    symmetric_problem,
    symmetric_system,
)
from endomeasure.interpolation import (
    PREFILTER_MARGIN_PX,
    bspline_weights,
    cardinal_weights,
    noise_gain,
)

__all__ = ["CornerPrecision", "noise_autocorrelation", "symmetric_precision"]

CORRELATION_REACH_PX = 2
"""Lags (px, along each axis) of the estimated noise autocorrelation: bilinear demosaicing
correlates pixels up to 2 apart; the lag beyond serves as the uncorrelated reference."""

FLAT_QUANTILE = 0.25
"""Flat pixels, whose differences estimate the noise autocorrelation, have a smoothed
gradient below :data:`FLAT_FACTOR` times this quantile of the image's: at least this
share of a board image is flat (squares' interiors, background), where the gradient is
the noise's alone."""

FLAT_FACTOR = 4.0
"""Far above the noise's own smoothed gradient (its 25th percentile times 4 is beyond
its 99.9th for Gaussian noise), so selecting the flat pixels does not select the noise."""

SAMPLED_PAIRS = 25_000
"""Images of more than four times this many pixels use every other row for the lag
differences (the estimate's standard error stays below 0.01)."""

TRIM_FRACTION = 0.05
"""The largest squared differences dropped per lag (structure that leaked into the flat
pixels); the same share at every lag, so it cancels in the ratio."""


@dataclasses.dataclass(frozen=True)
class CornerPrecision:
    """Per-corner formal precision of the symmetric fit.

    Attributes
    ----------
    covariance : ndarray, shape (n, 2, 2), px^2
        Covariance of (u, v); NaN where the fit is singular.
    noise_variance : ndarray, shape (n,), grey levels^2
        The pixel noise variance used (the window's weighted mean for a per-pixel map,
        the residual estimate for ``noise=None``).
    """

    covariance: np.ndarray
    noise_variance: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        """ndarray, shape (n, 2), px: standard deviations of u and v."""
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))

    @property
    def corr_uv(self) -> np.ndarray:
        """ndarray, shape (n,): correlation of the u and v errors."""
        s = self.sigma
        return self.covariance[:, 0, 1] / (s[:, 0] * s[:, 1])


def symmetric_precision(
    gray: np.ndarray,
    pixels: np.ndarray,
    steps: np.ndarray,
    curvature: np.ndarray | None = None,
    *,
    noise: float | np.ndarray | None = None,
    sigma_squares: float = SYMMETRY_SIGMA_SQUARES,
    illumination: bool = True,
    correlated: bool | np.ndarray = True,
) -> CornerPrecision:
    """Formal covariance of corners refined by the point-symmetric fit.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
        The grey image the corners were refined in (the half image for split images,
        as the detector sees it); with ``noise=None`` the noise autocorrelation is
        estimated from all of it (the board alone has too few flat pixels).
    pixels : ndarray, shape (n, 2), px
        Refined corners (the fit's solution) in ``gray``'s pixel coordinates.
    steps : ndarray, shape (n, 2, 2), px
        The local affine map the fit used (:func:`~endomeasure.features.subpixel.local_steps`
        or :func:`~endomeasure.features.subpixel.local_quadratic`).
    curvature : ndarray, shape (n, 2, 3), px, optional
        The local curvature the fit used (:func:`~endomeasure.features.subpixel.local_quadratic`);
        None for plain 180-degree pairs.
    noise : float or ndarray, optional
        Pixel noise: a variance in grey levels^2 for every pixel, or an array of shape
        ``gray.shape`` with each pixel's variance (e.g. a sensor model's shot + read +
        quantisation variance). None estimates one variance per corner from the fit's
        weighted residuals (which then also carry any misfit of the model).
    sigma_squares : float
        The fit's window sigma in squares.
    illumination : bool
        Whether the fit estimated the illumination gradient ``k`` (the detector does).
    correlated : bool or ndarray, shape (2 R + 1, 2 R + 1)
        With ``noise=None``: allow for spatially correlated noise, its autocorrelation
        estimated from ``gray`` (:func:`noise_autocorrelation`); False assumes independent
        pixels, as does a given ``noise`` unless an autocorrelation array is given here
        (``rho[R + dv, R + du]``, 1 at the centre; with a noise map, the map's
        influence-weighted mean variance is used).

    Returns
    -------
    CornerPrecision
        ``covariance`` (n, 2, 2) px^2, with ``sigma`` and ``corr_uv``.

    Notes
    -----
    ``k`` at the solution is re-estimated by weighted least squares at the given ``c``
    (the residual is linear in ``k``), so only the corners are needed. With ``A`` the
    (u, v) rows of ``N^-1 J^T W`` (``N = J^T W J`` over the 4 unknowns, so ``k``'s
    estimation is accounted for), a residual's sample at ``x`` enters with weight
    ``A_m (1 -+ k.h_m)``; the weights are scattered onto the B-spline coefficients with
    the sample's interpolation weights and mapped to pixels by the prefilter ``B^-1``:
    ``g = B^-1 S^T a``, and ``Cov = sum_pixels var * g g^T``.

    With ``noise=None`` the variance is ``sum w r^2 / sum w v (1 - w l)``, ``v`` the
    variance of a unit-noise residual (the two samples' interpolation gains,
    :func:`~endomeasure.interpolation.noise_gain`, their correlation neglected) and ``l``
    its leverage ``(J N^-1 J^T)_mm``. With ``correlated``, ``v`` is
    ``w_u^T P_u w_u w_v^T P_v w_v`` (``w`` a sample's cardinal-spline pixel weights along
    each axis, ``P`` the axis' autocorrelation matrix) and the covariance is
    ``sigma^2 sum_lags rho(d) sum_p g_p g_{p+d}^T``.
    """
    gray = np.asarray(gray)
    c = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    steps = np.asarray(steps, dtype=np.float64)
    n = len(c)
    if steps.shape != (n, 2, 2):
        raise ValueError(f"steps must have shape ({n}, 2, 2), not {steps.shape}")
    problem = symmetric_problem(gray, c, steps, curvature, sigma_squares)
    k = _illumination_gradient(problem, c) if illumination else None
    fit = _linearised_fit(problem, c, k)
    points, sample_weights, factor = _residual_samples(problem, c, k, fit.gain_rows)
    influence = _pixel_influence(c, points, sample_weights)
    patches = influence.patches
    size = patches.shape[-1]
    rho = None
    if not isinstance(correlated, (bool, np.bool_)):
        rho = np.asarray(correlated, dtype=np.float64)
        if rho.ndim != 2 or rho.shape[0] != rho.shape[1] or rho.shape[0] % 2 != 1:
            raise ValueError(f"correlated must be a square array of odd size, not {rho.shape}")
    elif correlated and noise is None and n:
        rho = noise_autocorrelation(gray)
    if noise is None:
        variance = _residual_variance(
            fit.residual, fit.jacobian, problem.weights, fit.inverse, points, rho, factor
        )
        covariance = variance[:, None, None] * _lagged_products(patches, rho)
    elif np.ndim(noise) == 0:
        variance = np.full(n, float(noise))
        covariance = variance[:, None, None] * _lagged_products(patches, rho)
    else:
        variance, pixel_var = _noise_map_variance(noise, gray.shape, influence)
        if rho is None:
            covariance = np.einsum(
                "nayx,nbyx,nyx->nab", patches, patches, pixel_var * np.ones((1, size, size))
            )
        else:
            covariance = variance[:, None, None] * _lagged_products(patches, rho)
    covariance[~fit.finite] = np.nan
    return CornerPrecision(covariance, variance)


def noise_autocorrelation(gray: np.ndarray, reach: int = CORRELATION_REACH_PX) -> np.ndarray:
    """The image noise's autocorrelation ``rho(dv, du)`` at lags up to ``reach`` px.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    reach : int, px

    Returns
    -------
    ndarray, shape (2 reach + 1, 2 reach + 1)
        ``rho[reach + dv, reach + du]``, 1 at the centre, symmetric; the identity's
        (independent pixels) when the image shows no noise.

    Notes
    -----
    On flat pixels (:data:`FLAT_QUANTILE`, :data:`FLAT_FACTOR`; both ends of a pair) the
    mean squared difference at lag ``d`` is ``2 (C(0) - C(d))``, ``C`` the noise
    autocovariance (the variogram); at the lag ``reach + 1`` along each axis the noise is
    taken as uncorrelated, which gives ``C(0)``. Means over the squares with the
    largest :data:`TRIM_FRACTION` dropped, so leaked structure does not count.
    """
    from scipy.ndimage import gaussian_gradient_magnitude

    g = np.asarray(gray, dtype=np.float64)
    white = np.zeros((2 * reach + 1, 2 * reach + 1))
    white[reach, reach] = 1.0
    height, width = g.shape
    far = reach + 1
    if height <= 2 * far or width <= 2 * far:
        return white
    slope = gaussian_gradient_magnitude(g, 1.5)
    flat = slope <= FLAT_FACTOR * np.quantile(slope, FLAT_QUANTILE)

    rows = 2 if g.size > 4 * SAMPLED_PAIRS else 1  # every other row is plenty

    def variogram(dv: int, du: int) -> float:
        v0, v1 = max(0, -dv), height - max(0, dv)
        u0, u1 = max(0, -du), width - max(0, du)
        a = g[v0:v1:rows, u0:u1]
        b = g[v0 + dv : v1 + dv : rows, u0 + du : u1 + du]
        both = flat[v0:v1:rows, u0:u1] & flat[v0 + dv : v1 + dv : rows, u0 + du : u1 + du]
        d2 = (a[both] - b[both]) ** 2
        if d2.size < 100:
            return float("nan")
        keep = d2 <= np.quantile(d2, 1.0 - TRIM_FRACTION)
        return 0.5 * float(np.mean(d2[keep]))

    reference = 0.5 * (variogram(0, far) + variogram(far, 0))
    if not reference > 0:
        return white
    rho = np.ones_like(white)
    for dv in range(0, reach + 1):
        for du in range(-reach, reach + 1):
            if (dv, du) <= (0, 0):
                continue
            value = 1.0 - variogram(dv, du) / reference
            value = float(np.clip(value, -1.0, 1.0)) if np.isfinite(value) else 0.0
            rho[reach + dv, reach + du] = rho[reach - dv, reach - du] = value
    return rho


def _lagged_products(patches: np.ndarray, rho: np.ndarray | None) -> np.ndarray:
    """``sum_d rho(d) sum_p g_p g_{p+d}^T`` (n, 2, 2) for the influence patches (n, 2, S, S);
    ``sum_p g_p g_p^T`` for independent pixels (``rho`` None). Falls back to the latter
    where the correlated sum is not positive definite (an estimate of ``rho`` that no
    covariance has)."""
    white = np.einsum("nayx,nbyx->nab", patches, patches)
    if rho is None:
        return white
    reach = rho.shape[0] // 2
    size = patches.shape[-1]
    total = np.zeros_like(white)
    for dv in range(-reach, reach + 1):
        for du in range(-reach, reach + 1):
            weight = rho[reach + dv, reach + du]
            if weight == 0.0:
                continue
            a = patches[..., max(0, -dv) : size - max(0, dv), max(0, -du) : size - max(0, du)]
            b = patches[..., max(0, dv) : size - max(0, -dv), max(0, du) : size - max(0, -du)]
            total += weight * np.einsum("nayx,nbyx->nab", a, b)
    total = 0.5 * (total + total.transpose(0, 2, 1))
    bad = ~(np.linalg.eigvalsh(np.nan_to_num(total))[:, 0] > 0)
    total[bad] = white[bad]
    return total


def _illumination_gradient(problem, c: np.ndarray) -> np.ndarray:
    """The illumination gradient ``k`` (n, 2) at the corners ``c``, by weighted least
    squares (the residual is linear in ``k``)."""
    weights = problem.weights  # (n, M)
    offsets = problem.window.offsets  # (M, 2)
    hx, hy = offsets[:, 0], offsets[:, 1]
    _, _, plus, minus = symmetric_system(problem, c, None)
    total = plus + minus
    design = np.stack([hx[None] * total, hy[None] * total], axis=-1)  # (n, M, 2)
    wd = design * weights[..., None]
    k_normal = wd.transpose(0, 2, 1) @ design
    ridge = 1e-12 * np.trace(k_normal, axis1=1, axis2=2)[:, None, None] + 1e-300
    k_rhs = wd.transpose(0, 2, 1) @ (plus - minus)[..., None]
    return np.linalg.solve(k_normal + ridge * np.eye(2), k_rhs)[..., 0]


class _Linearised(NamedTuple):
    """The weighted fit linearised at the solution."""

    residual: np.ndarray  # (n, M)
    jacobian: np.ndarray  # (n, M, p)
    inverse: np.ndarray  # (n, p, p) N^-1, NaN where singular
    finite: np.ndarray  # (n,) bool, N regular
    gain_rows: np.ndarray  # (n, 2, M) d c / d r_m, the (u, v) rows of N^-1 J^T W


def _linearised_fit(problem, c: np.ndarray, k: np.ndarray | None) -> _Linearised:
    residual, jacobian, _, _ = symmetric_system(problem, c, k)
    weighted = jacobian * problem.weights[..., None]
    normal = weighted.transpose(0, 2, 1) @ jacobian  # (n, p, p)
    finite = np.isfinite(normal).all(axis=(1, 2))
    finite[finite] &= np.linalg.matrix_rank(normal[finite]) == normal.shape[-1]
    inverse = np.full_like(normal, np.nan)
    inverse[finite] = np.linalg.inv(normal[finite])
    gain_rows = (inverse @ weighted.transpose(0, 2, 1))[:, :2]  # (n, 2, M): d c / d r_m
    return _Linearised(residual, jacobian, inverse, finite, gain_rows)


def _residual_samples(
    problem, c: np.ndarray, k: np.ndarray | None, gain_rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The positions of the residuals' samples (n, 2M, 2), px, their weights in the
    corner (n, 2, 2M): ``A_m (1 -+ k.h_m)``, and their factors in the residual (n, 2M):
    ``1 - k.h_m`` and ``-(1 + k.h_m)``."""
    weights = problem.weights
    offsets = problem.window.offsets
    hx, hy = offsets[:, 0], offsets[:, 1]
    shift = problem.shift if problem.shift is not None else np.zeros((len(c), len(offsets), 2))
    centre = c[:, None] + shift  # (n, M, 2)
    tilt = np.zeros_like(weights) if k is None else k[:, :1] * hx[None] + k[:, 1:] * hy[None]
    points = np.concatenate([centre + offsets[None], centre - offsets[None]], axis=1)
    factor = np.concatenate([1.0 - tilt, -(1.0 + tilt)], axis=1)  # (n, 2M)
    sample_weights = np.concatenate([gain_rows, gain_rows], axis=2) * factor[:, None]
    return points, sample_weights, factor


class _Influence(NamedTuple):
    """Each pixel's weight in a corner's (u, v), on a square patch per corner."""

    patches: np.ndarray  # (n, 2, size, size): g = B^-1 S^T a, for u and v
    corner0: np.ndarray  # (n, 2) int, pixel (u, v) of each patch's first entry


def _pixel_influence(c: np.ndarray, points: np.ndarray, sample_weights: np.ndarray) -> _Influence:
    """Scatter the sample weights onto the B-spline coefficients with each sample's
    interpolation weights, then onto the pixels by the prefilter (module notes)."""
    from scipy.ndimage import spline_filter1d

    n = len(c)
    reach = np.abs(points - np.round(c)[:, None]).max(initial=0.0) if n else 0.0
    half = int(np.ceil(reach)) + 2 + PREFILTER_MARGIN_PX
    size = 2 * half + 1
    corner0 = np.round(c).astype(int) - half  # (n, 2) patch origin (u, v)
    local = points - corner0[:, None]
    base = np.floor(local).astype(int)
    wu = bspline_weights(local[..., 0] - base[..., 0])[0].astype(np.float64)  # (n, 2M, 4)
    wv = bspline_weights(local[..., 1] - base[..., 1])[0].astype(np.float64)
    taps = np.arange(-1, 3)
    rows = base[..., 1, None, None] + taps[:, None]  # (n, 2M, 4, 1)
    cols = base[..., 0, None, None] + taps[None, :]  # (n, 2M, 1, 4)
    spread = wv[..., :, None] * wu[..., None, :]  # (n, 2M, 4, 4)
    patches = np.zeros((n, 2, size, size))
    corner_idx = np.arange(n)[:, None, None, None]
    rows_b, cols_b = np.broadcast_arrays(rows, cols)
    for axis in range(2):
        values = np.nan_to_num(sample_weights[:, axis, :, None, None] * spread)
        np.add.at(patches[:, axis], (corner_idx, rows_b, cols_b), values)
    # B^-T = B^-1 away from the patch edges (a symmetric convolution's inverse)
    for axis in (2, 3):
        patches = spline_filter1d(patches, order=3, axis=axis, mode="mirror")
    return _Influence(patches, corner0)


def _noise_map_variance(
    noise, shape: tuple[int, int], influence: _Influence
) -> tuple[np.ndarray, np.ndarray]:
    """For a per-pixel noise map: each corner's influence-weighted mean variance (n,)
    and the map's values on its patch (n, size, size), grey levels^2."""
    noise = np.asarray(noise, dtype=np.float64)
    if noise.shape != shape:
        raise ValueError(f"noise must be a scalar or of shape {shape}, not {noise.shape}")
    patches, corner0 = influence
    size = patches.shape[-1]
    height, width = noise.shape
    span = np.arange(size)
    vv = np.clip(corner0[:, 1, None] + span, 0, height - 1)
    uu = np.clip(corner0[:, 0, None] + span, 0, width - 1)
    pixel_var = noise[vv[:, :, None], uu[:, None, :]]  # (n, size, size)
    weight = patches[:, 0] ** 2 + patches[:, 1] ** 2
    variance = np.sum(pixel_var * weight, axis=(1, 2)) / np.maximum(
        np.sum(weight, axis=(1, 2)), 1e-300
    )
    return variance, pixel_var


def _residual_variance(
    residual: np.ndarray,
    jacobian: np.ndarray,
    weights: np.ndarray,
    inverse: np.ndarray,
    points: np.ndarray,
    rho: np.ndarray | None = None,
    factor: np.ndarray | None = None,
) -> np.ndarray:
    """Pixel noise variance per corner from the weighted residuals of the fit, (n,).

    Independent pixels (``rho`` None): a residual's two samples taken as independent.
    Correlated: the exact variance of ``f_1 I(x_1) + f_2 I(x_2)`` under the separable
    autocorrelation ``rho_u(du) rho_v(dv)`` (the two samples' own gains and their
    covariance, which the correlation makes large for nearby samples)."""
    m = residual.shape[1]
    if rho is None:
        frac = points - np.floor(points)
        gain = noise_gain(frac[..., 0]) * noise_gain(frac[..., 1])
        unit = gain[:, :m] + gain[:, m:]  # variance of a residual under unit pixel noise
    else:
        reach = rho.shape[0] // 2
        axes = (rho[reach], rho[:, reach])
        f1, f2 = (np.ones_like(residual), -np.ones_like(residual)) if factor is None else (
            factor[:, :m], factor[:, m:])  # fmt: skip
        p1, p2 = points[:, :m], points[:, m:]

        def cov(a, b):
            return _pair_covariance(a[..., 0], b[..., 0], axes[0]) * _pair_covariance(
                a[..., 1], b[..., 1], axes[1]
            )

        unit = f1**2 * cov(p1, p1) + f2**2 * cov(p2, p2) + 2 * f1 * f2 * cov(p1, p2)
    leverage = np.einsum("nmp,npq,nmq->nm", jacobian, inverse, jacobian) * weights
    expected = np.sum(weights * unit * (1.0 - leverage), axis=1)
    return np.sum(weights * residual**2, axis=1) / np.maximum(expected, 1e-300)


def _cardinal_table() -> tuple[np.ndarray, np.ndarray]:
    """The cardinal cubic spline ``eta(x)`` (a pixel's weight in the interpolant at ``x``
    px from it, prefilter included) tabulated at 1/1024 px."""
    phases = np.linspace(0.0, 1.0, 1025)[:-1]
    weights = cardinal_weights(phases)[0]  # w_j = eta(phase - j), j = -R..R
    reach = weights.shape[-1] // 2
    x = phases[:, None] - np.arange(-reach, reach + 1)[None, :]
    order = np.argsort(x, axis=None)
    return x.ravel()[order], weights.ravel()[order]


_ETA_X, _ETA = _cardinal_table()
_PAIR_TAPS = np.arange(-6, 7)
"""Pixels either side of a sample in :func:`_pair_covariance` (``eta`` is below 4e-4
beyond)."""


def _pair_covariance(x1: np.ndarray, x2: np.ndarray, rho_axis: np.ndarray) -> np.ndarray:
    """Covariance along one axis of two interpolated samples at ``x1`` and ``x2`` px of
    unit-variance noise with the autocorrelation ``rho_axis`` (lags -R..R):
    ``sum_j sum_l rho(l) eta(x1 - j) eta(x2 - j - l)``."""
    reach = len(rho_axis) // 2
    j = np.floor(x1)[..., None] + _PAIR_TAPS
    e1 = np.interp(x1[..., None] - j, _ETA_X, _ETA, left=0.0, right=0.0)
    total = np.zeros(np.shape(x1))
    for lag in range(-reach, reach + 1):
        if rho_axis[reach + lag] != 0.0:
            e2 = np.interp(x2[..., None] - j - lag, _ETA_X, _ETA, left=0.0, right=0.0)
            total += rho_axis[reach + lag] * np.sum(e1 * e2, axis=-1)
    return total
