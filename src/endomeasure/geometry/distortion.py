"""Brown–Conrady lens distortion on normalised image coordinates (OpenCV order).

Normalised coordinates are ``x = X/Z, y = Y/Z`` in the camera frame; distorted
normalised coordinates map to pixels by ``u = fx xd + cx, v = fy yd + cy``.
Coefficients are ``(k1, k2, p1, p2, k3)`` as in OpenCV.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = [
    "distort",
    "distort_jacobian",
    "distort_coeff_jacobian",
    "undistort",
    "Undistortion",
    "max_monotonic_radius2",
]

UNDISTORT_MAX_ITER = 30


def distort(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Apply Brown–Conrady distortion.

    Parameters
    ----------
    x, y : ndarray, shape (...)
        Undistorted normalised coordinates.
    coeffs : sequence of 5 floats
        ``k1, k2, p1, p2, k3``.

    Returns
    -------
    xd, yd : ndarray, shape (...)

    Notes
    -----
    ``xd = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)``,
    ``yd = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y``
    (Brown 1966; OpenCV's ``projectPoints`` with five coefficients).
    """
    k1, k2, p1, p2, k3 = coeffs
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    return xd, yd


def distort_jacobian(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, ...]:
    """Partial derivatives of :func:`distort`: ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)``, each (...)."""
    k1, k2, p1, p2, k3 = coeffs
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return j11, cross, cross, j22


def distort_coeff_jacobian(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Derivatives of :func:`distort` by ``(k1, k2, p1, p2, k3)``, shape (..., 2, 5).

    The distortion is linear in its coefficients, so these do not depend on them.
    """
    r2 = x * x + y * y
    r4 = r2 * r2
    xy2 = 2.0 * x * y
    d_dx = np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x, x * r4 * r2], axis=-1)
    d_dy = np.stack([y * r2, y * r4, r2 + 2.0 * y * y, xy2, y * r4 * r2], axis=-1)
    return np.stack([d_dx, d_dy], axis=-2)


class Undistortion(NamedTuple):
    x: np.ndarray  # (...,) undistorted normalised x, NaN where not converged
    y: np.ndarray
    converged: np.ndarray  # (...,) bool


def undistort(xd: np.ndarray, yd: np.ndarray, coeffs, tol, r2_max=None) -> Undistortion:
    """Invert :func:`distort` by Newton's method, reporting convergence per point.

    Parameters
    ----------
    xd, yd : ndarray, shape (...)
        Distorted normalised coordinates.
    coeffs : sequence of 5 floats or of 5 arrays of shape (...)
        ``k1, k2, p1, p2, k3``, one set for all points or one per point (a batch of
        lens models, e.g. the sigma points of a calibration covariance).
    tol : float or ndarray, shape (...)
        Convergence threshold on the distorted-coordinate residual, in normalised
        units (a pixel tolerance divided by the focal length).
    r2_max : float or ndarray, shape (...), optional
        :func:`max_monotonic_radius2` of the coefficients, when the caller has it (a
        batch of lens models computes it once per model, not per point).

    Returns
    -------
    Undistortion
        Points whose residual stays above ``tol`` after ``UNDISTORT_MAX_ITER`` Newton
        steps, or that leave the monotonic part of the radial polynomial, are NaN with
        ``converged`` False: the inverse is not unique there.
    """
    shape = np.broadcast(np.asarray(xd), np.asarray(yd)).shape
    xd = np.broadcast_to(np.asarray(xd, dtype=np.float64), shape).reshape(-1)
    yd = np.broadcast_to(np.asarray(yd, dtype=np.float64), shape).reshape(-1)

    def per_point(c):  # a scalar, or per-point values as a flat array
        return np.broadcast_to(c, shape).reshape(-1) if np.ndim(c) else c

    coeffs = [per_point(c) for c in coeffs]
    tol = per_point(tol)
    if r2_max is None:
        r2_max = max_monotonic_radius2(*coeffs[:2], coeffs[4])
    r2_max = per_point(r2_max)
    x = xd.copy()
    y = yd.copy()
    converged = np.zeros(x.size, dtype=bool)
    # Newton on the compacted arrays of the points still iterating
    idx = np.flatnonzero(np.isfinite(xd) & np.isfinite(yd))

    def take(values, rows):
        return [v[rows] if np.ndim(v) else v for v in values]

    xa, ya, xda, yda = x[idx], y[idx], xd[idx], yd[idx]
    cs, tol_a = take(coeffs, idx), take([tol], idx)[0]
    for _ in range(UNDISTORT_MAX_ITER):
        if idx.size == 0:
            break
        ex, ey = distort(xa, ya, cs)
        ex -= xda
        ey -= yda
        done = np.maximum(np.abs(ex), np.abs(ey)) < tol_a
        converged[idx[done]] = True
        x[idx[done]], y[idx[done]] = xa[done], ya[done]
        j11, j12, j21, j22 = distort_jacobian(xa, ya, cs)
        det = j11 * j22 - j12 * j21
        with np.errstate(divide="ignore", invalid="ignore"):
            xa = xa - (j22 * ex - j12 * ey) / det
            ya = ya - (j11 * ey - j21 * ex) / det
        go_on = ~done & np.isfinite(xa) & np.isfinite(ya)
        idx, xa, ya, xda, yda = idx[go_on], xa[go_on], ya[go_on], xda[go_on], yda[go_on]
        cs, tol_a = take(cs, go_on), take([tol_a], go_on)[0]
    converged &= (x * x + y * y) <= r2_max
    x = np.where(converged, x, np.nan).reshape(shape)
    y = np.where(converged, y, np.nan).reshape(shape)
    return Undistortion(x, y, converged.reshape(shape))


def max_monotonic_radius2(k1, k2, k3):
    """Largest ``r^2`` up to which the radial map ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` grows.

    Beyond it the distortion folds back and one distorted radius has two preimages, so
    projections there are not trustworthy. ``inf`` where the map grows for all r.

    Parameters
    ----------
    k1, k2, k3 : float or ndarray, shape (...)

    Returns
    -------
    float, or ndarray of shape (...) for array coefficients

    Notes
    -----
    ``d/dr [r + k1 r^3 + k2 r^5 + k3 r^7] = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3`` with
    ``s = r^2``; the answer is its smallest positive real root, found once per distinct
    coefficient set.
    """
    if not (np.ndim(k1) or np.ndim(k2) or np.ndim(k3)):
        return _max_monotonic_radius2(float(k1), float(k2), float(k3))
    k = np.stack(np.broadcast_arrays(k1, k2, k3), axis=-1).astype(np.float64)
    distinct, inverse = np.unique(k.reshape(-1, 3), axis=0, return_inverse=True)
    r2 = np.array([_max_monotonic_radius2(*row) for row in distinct.tolist()])
    return r2[inverse.reshape(-1)].reshape(k.shape[:-1])


def _max_monotonic_radius2(k1: float, k2: float, k3: float) -> float:
    roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]) if any((k1, k2, k3)) else []
    positive = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    return float(min(positive)) if positive else float("inf")
