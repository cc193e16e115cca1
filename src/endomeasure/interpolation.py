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

import numpy as np

__all__ = ["PREFILTER_MARGIN_PX", "bspline_weights", "spline_coefficients", "spline_sample"]

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
