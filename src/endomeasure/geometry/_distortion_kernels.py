"""Compiled Newton inversion of the distortion, for one coefficient set.

Why compiled: :func:`endomeasure.geometry.distortion.undistort` on numpy arrays spends its
time in the call overhead of a few dozen small array operations per Newton step, which
dominates the backward rays of a calibration's many small batches (a few hundred
corners each). The formulas are those of ``distortion.distort`` and
``distortion.distort_jacobian`` written per point; the tests check the compiled path
against the numpy one and against ``cv2.undistortPoints``.

Coefficients are ``float64[10]``: ``k1 k2 p1 p2 k3 k4 k5 k6 p1_image p2_image``.
"""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _radial(r2, c):
    """The radial factor and its derivative by ``r^2``."""
    num = 1.0 + r2 * (c[0] + r2 * (c[1] + r2 * c[4]))
    dnum = c[0] + r2 * (2.0 * c[1] + 3.0 * c[4] * r2)
    den = 1.0 + r2 * (c[5] + r2 * (c[6] + r2 * c[7]))
    dden = c[5] + r2 * (2.0 * c[6] + 3.0 * c[7] * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _brown(x, y, c):
    """Brown's map of the point and its Jacobian ``(xd, yd, j11, j12, j21, j22)``."""
    p1, p2 = c[2], c[3]
    r2 = x * x + y * y
    radial, dradial = _radial(r2, c)
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j11, cross, cross, j22


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _distort(x, y, c):
    """``distort`` and ``distort_jacobian`` of one point."""
    q1, q2 = c[8], c[9]
    if q1 == 0.0 and q2 == 0.0:
        return _brown(x, y, c)
    # image-side decentering: Brown's map of x + T_q(h(x)), h the radial part
    r2 = x * x + y * y
    radial, dradial = _radial(r2, c)
    hx, hy = x * radial, y * radial
    h2 = hx * hx + hy * hy
    hxy2 = 2.0 * hx * hy
    xs = x + q1 * hxy2 + q2 * (h2 + 2.0 * hx * hx)
    ys = y + q1 * (h2 + 2.0 * hy * hy) + q2 * hxy2
    h11 = radial + 2.0 * x * x * dradial
    h12 = 2.0 * x * y * dradial
    h22 = radial + 2.0 * y * y * dradial
    t11 = 2.0 * q1 * hy + 6.0 * q2 * hx
    t12 = 2.0 * q1 * hx + 2.0 * q2 * hy
    t22 = 6.0 * q1 * hy + 2.0 * q2 * hx
    s11 = 1.0 + t11 * h11 + t12 * h12
    s12 = t11 * h12 + t12 * h22
    s21 = t12 * h11 + t22 * h12
    s22 = 1.0 + t12 * h12 + t22 * h22
    xd, yd, b11, b12, b21, b22 = _brown(xs, ys, c)
    return (xd, yd, b11 * s11 + b12 * s21, b11 * s12 + b12 * s22,
            b21 * s11 + b22 * s21, b21 * s12 + b22 * s22)  # fmt: skip


@njit(cache=True, nogil=True, error_model="numpy")
def undistort_points(xd, yd, c, tol, r2_max, max_iter, x_out, y_out, converged):
    """Newton's method per point, as ``distortion.undistort``: a point converges when
    the distorted residual is below ``tol`` in both coordinates within ``max_iter``
    steps and lies inside ``r2_max``; others are NaN with ``converged`` False."""
    for i in range(xd.shape[0]):
        x, y = xd[i], yd[i]
        x_out[i] = math.nan
        y_out[i] = math.nan
        converged[i] = False
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        for _ in range(max_iter):
            ex, ey, j11, j12, j21, j22 = _distort(x, y, c)
            ex -= xd[i]
            ey -= yd[i]
            if max(abs(ex), abs(ey)) < tol:
                if x * x + y * y <= r2_max:
                    x_out[i] = x
                    y_out[i] = y
                    converged[i] = True
                break
            det = j11 * j22 - j12 * j21
            x, y = x - (j22 * ex - j12 * ey) / det, y - (j11 * ey - j21 * ex) / det
            if not (math.isfinite(x) and math.isfinite(y)):
                break
