"""Compiled per-pixel kernel of the dense search: the other half sampled along each
pixel's epipolar curve.

Why compiled: the refinement samples the other half once per pixel and candidate depth,
several hundred thousand pixels a dozen times. Projecting every pixel exactly (ray
aiming) and sampling the spline in numpy spent most of a frame's time on temporaries;
here each pixel's curve point comes from a table of exact projections over a grid of
pixels and the sweep's inverse-depth levels (Catmull-Rom cubic in all three), and the
spline is sampled in registers.

The table ``field`` (K, gh, gw, 2) holds the exact other-half pixel of grid node
``(gy, gx)`` on the constant-z plane of inverse depth ``w0 + k dw``, continued smoothly
a few nodes beyond the other half's edges so that the cubic stencil is whole there;
``seen`` (K, gh, gw) says which nodes the other half really sees; ``mx`` (w,) and
``my`` (h,) are each image column's and row's fractional grid coordinate. The spline
taps and weights are those of :func:`endomeasure.interpolation.bspline_weights` (taps
-1..2 about the floor).
The tests check the table against exact projections and the samples against
:func:`endomeasure.interpolation.spline_sample`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


def catmull_rom_weights(t):
    """Catmull-Rom weights of the taps -1..2 at fraction ``t`` and their d/dt (scalars or
    arrays alike: the kernels compile it, :func:`endomeasure.measure.dense._smooth_base`
    calls it on arrays). It reproduces quadratics exactly."""
    t2 = t * t
    t3 = t2 * t
    w = (
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    )
    d = (
        0.5 * (-3.0 * t2 + 4.0 * t - 1.0),
        0.5 * (9.0 * t2 - 10.0 * t),
        0.5 * (-9.0 * t2 + 8.0 * t + 1.0),
        0.5 * (3.0 * t2 - 2.0 * t),
    )
    return w, d


_catmull_rom = njit(cache=True, nogil=True, error_model="numpy", inline="always")(
    catmull_rom_weights
)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bspline(t):
    """Cubic B-spline weights of the taps -1..2 at fraction ``t`` and their d/dt."""
    s = 1.0 - t
    w = (s * s * s / 6.0, (3.0 * t**3 - 6.0 * t * t + 4.0) / 6.0,
         (-3.0 * t**3 + 3.0 * t * t + 3.0 * t + 1.0) / 6.0, t**3 / 6.0)  # fmt: skip
    d = (-0.5 * s * s, (9.0 * t * t - 12.0 * t) / 6.0, (-9.0 * t * t + 6.0 * t + 3.0) / 6.0,
         0.5 * t * t)  # fmt: skip
    return w, d


@njit(cache=True, nogil=True, error_model="numpy")
def _curve_point(field, seen, gx, gy, k):
    """Other-half pixel and its d/dk at grid coordinates (gx, gy), level ``k`` (float):
    Catmull-Rom in all three (bilinear in space where a node of the 4 x 4 stencil is
    missing). NaN unless the four nodes around the point are ``seen`` on both levels
    around ``k``."""
    n_levels, gh, gw = field.shape[0], field.shape[1], field.shape[2]
    if not math.isfinite(k):
        return math.nan, math.nan, math.nan, math.nan
    ix = min(max(int(math.floor(gx)), 1), gw - 3)
    iy = min(max(int(math.floor(gy)), 1), gh - 3)
    ik = int(math.floor(k))
    if ik < 0 or ik > n_levels - 2:
        return math.nan, math.nan, math.nan, math.nan
    for level in (ik, ik + 1):
        for b in range(2):
            for c in range(2):
                if not seen[level, iy + b, ix + c]:
                    return math.nan, math.nan, math.nan, math.nan
    wk, dk = _catmull_rom(k - ik)
    wx, _ = _catmull_rom(gx - ix)
    wy, _ = _catmull_rom(gy - iy)
    qu = qv = du = dv = 0.0
    for a in range(4):
        level = min(max(ik - 1 + a, 0), n_levels - 1)
        su = sv = 0.0
        for b in range(4):
            for c in range(4):
                wxy = wy[b] * wx[c]
                su += wxy * field[level, iy - 1 + b, ix - 1 + c, 0]
                sv += wxy * field[level, iy - 1 + b, ix - 1 + c, 1]
        if not (math.isfinite(su) and math.isfinite(sv)):
            fx, fy = gx - ix, gy - iy
            su = sv = 0.0
            for b in range(2):
                for c in range(2):
                    wxy = (fy if b else 1.0 - fy) * (fx if c else 1.0 - fx)
                    su += wxy * field[level, iy + b, ix + c, 0]
                    sv += wxy * field[level, iy + b, ix + c, 1]
        qu += wk[a] * su
        qv += wk[a] * sv
        du += dk[a] * su
        dv += dk[a] * sv
    return qu, qv, du, dv


@njit(cache=True, nogil=True, error_model="numpy")
def _spline_at(coeffs, lu, lv):
    """Spline value and gradient (d/du, d/dv) at box coordinates (lu, lv)."""
    box_h, box_w = coeffs.shape
    bu = int(math.floor(lu))
    bv = int(math.floor(lv))
    wu, dwu = _bspline(lu - bu)
    wv, dwv = _bspline(lv - bv)
    val = gu = gv = 0.0
    for a in range(4):
        row = min(max(bv - 1 + a, 0), box_h - 1)
        along = slope = 0.0
        for b in range(4):
            col = min(max(bu - 1 + b, 0), box_w - 1)
            cf = coeffs[row, col]
            along += cf * wu[b]
            slope += cf * dwu[b]
        val += along * wv[a]
        gv += along * dwv[a]
        gu += slope * wv[a]
    return val, gu, gv


@njit(cache=True, parallel=True, error_model="numpy")
def curve_samples(field, seen, mx, my, w0, dw, w, coeffs, origin_u, origin_v, umin, umax,
                  vmax):  # fmt: skip
    """The other half along each pixel's curve at inverse depth ``w`` (h, w).

    Returns the curve point ``q`` (h, w, 2), its derivative ``dq/dw`` (h, w, 2), the
    spline value there and the image gradient (h, w, 2) (d/du, d/dv); NaN where the
    curve point is not in the table or outside ``umin <= u <= umax, 0 <= v <= vmax``.
    Rows run in parallel.
    """
    h, wd = w.shape
    q = np.full((h, wd, 2), np.nan)
    dq = np.full((h, wd, 2), np.nan)
    value = np.full((h, wd), np.nan)
    grad = np.full((h, wd, 2), np.nan)
    for i in prange(h):
        for j in range(wd):
            point = _curve_point(field, seen, mx[j], my[i], (w[i, j] - w0) / dw)
            q[i, j, 0] = point[0]
            q[i, j, 1] = point[1]
            dq[i, j, 0] = point[2] / dw
            dq[i, j, 1] = point[3] / dw
            if umin <= point[0] <= umax and 0.0 <= point[1] <= vmax:  # False for NaN
                sample = _spline_at(coeffs, point[0] - origin_u, point[1] - origin_v)
                value[i, j] = sample[0]
                grad[i, j, 0] = sample[1]
                grad[i, j, 1] = sample[2]
    return q, dq, value, grad


@njit(cache=True, parallel=True, error_model="numpy")
def curve_values(field, seen, mx, my, w0, dw, w, coeffs, origin_u, origin_v, umin, umax,
                 vmax):  # fmt: skip
    """The spline's values of :func:`curve_samples` alone (h, w): what a correlation at
    a candidate depth needs, without the curve's derivative and the image gradient."""
    h, wd = w.shape
    value = np.full((h, wd), np.nan)
    for i in prange(h):
        for j in range(wd):
            point = _curve_point(field, seen, mx[j], my[i], (w[i, j] - w0) / dw)
            if umin <= point[0] <= umax and 0.0 <= point[1] <= vmax:  # False for NaN
                value[i, j] = _spline_at(coeffs, point[0] - origin_u, point[1] - origin_v)[0]
    return value
