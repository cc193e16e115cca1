"""Cubic B-spline interpolation of images, shared by the corner refinement
(:mod:`endomeasure.features.subpixel`) and the correspondence search
(:mod:`endomeasure.measure.correspondence`).

The interpolant passes through the pixel values (the image is prefiltered into B-spline
coefficients) and has continuous first derivatives, so sub-pixel fits get exact
gradients; unlike bilinear interpolation its smoothing hardly depends on the sub-pixel
phase, which would otherwise pull least-squares fits towards whole pixels.

Coefficients are computed on a box around the points of interest only, in float32 (the
sums over many samples are the costly part; float32 keeps about 1e-5 grey levels, far
below any image noise). The prefilter's mirror boundary leaves a transient that decays
as ``0.268^d`` with the distance ``d`` from the box edge, below 1e-5 after
:data:`PREFILTER_MARGIN_PX`.

Pixel convention: (u, v) in image pixels, the centre of the top-left pixel at (0, 0)
(:mod:`endomeasure.conventions`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

__all__ = [
    "CARDINAL_REACH",
    "PREFILTER_MARGIN_PX",
    "bspline_weights",
    "cardinal_weights",
    "gaussian_taps",
    "NoiseTransfer",
    "noise_gain",
    "noise_transfer",
    "spline_coefficients",
    "spline_sample",
]

PREFILTER_MARGIN_PX = 9
"""Extra pixels around the points whose coefficients are computed: the prefilter's
boundary transient is below 1e-5 there (``0.268^9 = 7e-6``)."""


def bspline_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline weights and their d/dt of the taps -1, 0, 1, 2 at fraction ``t``.

    Returns two float32 arrays of shape ``t.shape + (4,)``.
    """
    weights = np.stack(
        [(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3], axis=-1
    )
    slopes = np.stack(
        [-3 * (1 - t) ** 2, 9 * t**2 - 12 * t, -9 * t**2 + 6 * t + 3, 3 * t**2], axis=-1
    )
    return (weights / 6.0).astype(np.float32), (slopes / 6.0).astype(np.float32)


def spline_coefficients(
    image: np.ndarray,
    points: np.ndarray,
    reach: float = 0.0,
    cols: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline coefficients of the part of ``image`` around ``points``.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    points : ndarray, shape (..., 2), px
        Where samples will be taken (NaN ignored).
    reach : float, px
        How far from the points samples may fall (e.g. a window's half-size).
    cols : (int, int), optional
        First and last image column the box may use (one half of a split image), so
        that the other half never leaks into the interpolant.

    Returns
    -------
    coeffs : ndarray, shape (h, w), float32
    origin : ndarray, shape (2,), int
        (u, v) of the box's first sample in image pixels.
    """
    from scipy.ndimage import spline_filter

    height, width = image.shape
    c0, c1 = cols if cols is not None else (0, width - 1)
    pad = int(np.ceil(reach)) + 3 + PREFILTER_MARGIN_PX
    flat = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lo = np.floor(np.nanmin(flat, axis=0)).astype(int) - pad
    hi = np.ceil(np.nanmax(flat, axis=0)).astype(int) + pad + 1
    lo = np.maximum(lo, [c0, 0])
    hi = np.minimum(hi, [c1 + 1, height])
    box = np.asarray(image[lo[1] : hi[1], lo[0] : hi[0]], dtype=np.float64)
    return spline_filter(box, order=3, mode="mirror").astype(np.float32), lo


def spline_sample(
    coeffs: np.ndarray, origin: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interpolated value and gradient (d/du, d/dv) at ``points`` (..., 2), px.

    ``coeffs``, ``origin`` from :func:`spline_coefficients`; points outside the box are
    clamped to its edge (callers keep their samples inside). Returns three float64
    arrays of shape ``points.shape[:-1]``.
    """
    box_h, box_w = coeffs.shape
    local = np.asarray(points, dtype=np.float64) - origin
    base = np.floor(local).astype(int)
    frac = local - base
    taps = np.arange(-1, 3)
    rows_ = np.clip(base[..., 1, None] + taps, 0, box_h - 1)
    cols_ = np.clip(base[..., 0, None] + taps, 0, box_w - 1)
    patch = coeffs[rows_[..., :, None], cols_[..., None, :]].astype(np.float64)  # (..., 4, 4)
    wx, dwx = (a.astype(np.float64) for a in bspline_weights(frac[..., 0]))
    wy, dwy = (a.astype(np.float64) for a in bspline_weights(frac[..., 1]))
    along_x = np.einsum("...ij,...j->...i", patch, wx)
    slope_x = np.einsum("...ij,...j->...i", patch, dwx)
    values = np.einsum("...i,...i->...", along_x, wy)
    grad_v = np.einsum("...i,...i->...", along_x, dwy)
    grad_u = np.einsum("...i,...i->...", slope_x, wy)
    return values, grad_u, grad_v


# ----- the interpolant as weights on the pixels (what noise propagation needs) ----------

_SPLINE_POLE = np.sqrt(3.0) - 2.0
"""Pole of the cubic B-spline's interpolation prefilter: the cardinal cubic spline is
``eta(x) = sum_k sqrt(3) z^|k| beta3(x - k)`` with this ``z``."""
CARDINAL_REACH = 10
"""Pixels either side whose weights :func:`cardinal_weights` keeps (``0.268^10 < 2e-6``)."""


def _bspline3(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cubic B-spline ``beta3(x)`` and its derivative."""
    a = np.abs(x)
    inner = a < 1.0
    outer = (a >= 1.0) & (a < 2.0)
    far = np.where(outer, (2.0 - a) ** 3 / 6.0, 0.0)
    value = np.where(inner, 2.0 / 3.0 - a**2 + a**3 / 2.0, far)
    slope = np.where(inner, -2.0 * a + 1.5 * a**2, np.where(outer, -0.5 * (2.0 - a) ** 2, 0.0))
    return value, np.sign(x) * slope


def cardinal_weights(phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights of the pixels ``j = -R..R`` (``R`` = :data:`CARDINAL_REACH`) in the cubic
    spline interpolation at ``j0 + phase``, and their derivatives, shape (..., 2R + 1):
    the interpolated value is ``sum_j w_j I(j0 + j)`` (prefilter included)."""
    j = np.arange(-CARDINAL_REACH, CARDINAL_REACH + 1, dtype=np.float64)
    x = np.asarray(phase, dtype=np.float64)[..., None] - j  # (..., 2R+1)
    base = np.floor(x)
    weight = np.zeros_like(x)
    slope = np.zeros_like(x)
    for shift in (-1.0, 0.0, 1.0, 2.0):
        k = base + shift
        b, db = _bspline3(x - k)
        c = np.sqrt(3.0) * _SPLINE_POLE ** np.abs(k)
        weight += c * b
        slope += c * db
    return weight, slope


_GAIN_PHASES = np.linspace(0.0, 1.0, 1025)


class NoiseTransfer(NamedTuple):
    """How white pixel noise passes a separable prefilter and then the cubic spline.

    ``table`` holds, at the phases ``0, 1/1024, .., 1``, the variance per axis of the
    interpolant of unit white noise (prefiltered by ``kernel``): ``sum_i (w * k)_i^2``
    with ``w`` the spline's weights at that phase; ``derivative`` is the mean variance of
    the interpolant's derivative along any unit direction in 2-D (per px^2). Without a
    prefilter the gain is 1 at a pixel and 0.756 half-way, the derivative's about 2.16;
    a Gaussian prefilter of 1 px cuts both (the noise it leaves is correlated, which
    :meth:`gain` does not describe: it gives each sample's variance alone).
    """

    kernel: tuple
    table: np.ndarray
    slopes: np.ndarray
    derivative: float

    def correlated_share(self, g: np.ndarray, window: int) -> np.ndarray:
        """``sum g (r * g) / sum g^2`` over each ``window`` x ``window`` box of the field
        ``g`` (h, w), ``r`` the prefilter's autocorrelation (in [0, 1]; 1 without one):
        a weighted sum ``sum g n`` of the prefiltered noise ``n`` has that share of the
        variance it would have were the noise white with the raw variance."""
        if len(self.kernel) == 1:
            return np.ones(g.shape)
        import cv2

        taps = np.asarray(self.kernel)
        r = np.convolve(taps, taps[::-1])
        rg = cv2.sepFilter2D(g, cv2.CV_64F, r, r, borderType=cv2.BORDER_REFLECT)
        box = (window, window)
        num = cv2.boxFilter(g * rg, cv2.CV_64F, box, borderType=cv2.BORDER_REFLECT)
        den = cv2.boxFilter(g * g, cv2.CV_64F, box, borderType=cv2.BORDER_REFLECT)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.clip(np.where(den > 0, num / den, 1.0), 0.0, 1.0)

    def gain(self, frac: np.ndarray) -> np.ndarray:
        """The per-axis variance at sub-pixel phase ``frac`` (...,); a 2-D sample's is the
        product of its two axes'. Periodic and smooth in the phase, so read from the
        table (cubic Hermite: within 1e-9 of the exact sum, about a hundred times faster
        than summing the weights per sample)."""
        x = np.mod(np.asarray(frac, dtype=np.float64), 1.0) * (_GAIN_PHASES.size - 1)
        i = np.minimum(x.astype(np.int64), _GAIN_PHASES.size - 2)
        t = x - i
        h = _GAIN_PHASES[1] - _GAIN_PHASES[0]
        y0, y1 = self.table[i], self.table[i + 1]
        m0, m1 = self.slopes[i] * h, self.slopes[i + 1] * h
        t2, t3 = t * t, t * t * t
        h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + t, 3 * t2 - 2 * t3, t3 - t2
        return h00 * y0 + h10 * m0 + h01 * y1 + h11 * m1


@functools.lru_cache(maxsize=8)
def noise_transfer(kernel: tuple = (1.0,)) -> NoiseTransfer:
    """The :class:`NoiseTransfer` of the separable prefilter with 1-D taps ``kernel``
    (odd length, centred; the default is no prefilter)."""
    taps = np.asarray(kernel, dtype=np.float64)
    weight, slope = cardinal_weights(_GAIN_PHASES)
    through = np.stack([np.convolve(row, taps) for row in weight])
    d_through = np.stack([np.convolve(row, taps) for row in slope])
    table = np.sum(through**2, axis=-1)
    d_table = np.sum(d_through**2, axis=-1)
    # along a unit direction (cos a, sin a) the derivative is cos a d/du + sin a d/dv; the
    # cross term averages out over directions, each axis's term is its derivative's
    # variance times the other axis's value variance (the phases independent, uniform)
    derivative = float(np.mean(d_table[:-1]) * np.mean(table[:-1]))
    slopes = np.gradient(table, _GAIN_PHASES, edge_order=2)
    return NoiseTransfer(tuple(float(t) for t in taps), table, slopes, derivative)


def gaussian_taps(sigma_px: float) -> tuple:
    """Normalised taps of a sampled Gaussian of ``sigma_px`` (to 4 sigma; ``(1.0,)`` for 0)."""
    if sigma_px <= 0:
        return (1.0,)
    reach = int(np.ceil(4.0 * sigma_px))
    x = np.arange(-reach, reach + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / sigma_px) ** 2)
    return tuple(float(t) for t in taps / taps.sum())


def noise_gain(frac: np.ndarray) -> np.ndarray:
    """Variance of the interpolant of unit white pixel noise at sub-pixel phase ``frac``
    (...,) along one axis: ``sum_j w_j^2``, 1 at a pixel, 0.756 half-way between pixels
    (:meth:`NoiseTransfer.gain` without a prefilter). A 2-D sample's gain is the product
    of its two axes' gains."""
    return noise_transfer().gain(frac)
