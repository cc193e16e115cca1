"""Brown–Conrady lens distortion on normalised image coordinates (OpenCV order).

Normalised coordinates are ``x = X/Z, y = Y/Z`` in the camera frame; distorted
normalised coordinates map to pixels by ``u = fx xd + cx, v = fy yd + cy``.
Coefficient sets, each extending the one before (with the extra coefficients 0 the
results are identical):

- 5, ``(k1, k2, p1, p2, k3)``: OpenCV's default;
- 8, ``(..., k4, k5, k6)``: OpenCV's rational model, whose radial factor has the
  denominator ``1 + k4 r^2 + k5 r^4 + k6 r^6``. Strong barrel distortion that a lens
  defines from pixel to ray (``r_u = r_d (1 + c r_d^2 + ...)``) has no short
  polynomial inverse, but a short rational one;
- 10, ``(..., p1_image, p2_image)``: decentering defined on the image side, the
  first-order inverse of a pixel-to-ray map's tangential terms, which the ray-side
  ``p1 p2`` cannot follow once the radial distortion is strong (see :func:`distort`).
"""

from __future__ import annotations

import functools
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
_SIZES = (5, 8, 10)


def _radial(r2, coeffs):
    """The radial factor and its derivative by ``r^2``."""
    k1, k2, k3 = coeffs[0], coeffs[1], coeffs[4]
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d num / d r2
    if not _is_rational(coeffs):
        return num, dnum
    k4, k5, k6 = coeffs[5], coeffs[6], coeffs[7]
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


def _is_rational(coeffs) -> bool:
    """Whether the coefficients have a rational denominator that is not identically 1."""
    if len(coeffs) not in _SIZES:
        raise ValueError(f"distortion needs 5, 8 or 10 coefficients, got {len(coeffs)}")
    return len(coeffs) > 5 and any(np.ndim(c) or c != 0.0 for c in coeffs[5:8])


def _image_side(coeffs):
    """``(p1_image, p2_image)`` of a 10-coefficient set; None when absent or both 0."""
    if len(coeffs) != 10:
        return None
    q = coeffs[8], coeffs[9]
    return q if any(np.ndim(c) or c != 0.0 for c in q) else None


def _tangential(x, y, p1, p2):
    """Brown's decentering terms ``(2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y)``."""
    r2 = x * x + y * y
    xy2 = 2.0 * x * y
    return p1 * xy2 + p2 * (r2 + 2.0 * x * x), p1 * (r2 + 2.0 * y * y) + p2 * xy2


def _shifted(x, y, coeffs, q):
    """The ray-side point ``x + T_q(h(x))`` (``h`` the radial part), ``h(x)`` and the
    radial Jacobian at ``x`` as ``(a11, a12, a22)``."""
    r2 = x * x + y * y
    radial, dradial = _radial(r2, coeffs)
    hx, hy = x * radial, y * radial
    tx, ty = _tangential(hx, hy, *q)
    h11 = radial + 2.0 * x * x * dradial
    h12 = 2.0 * x * y * dradial
    h22 = radial + 2.0 * y * y * dradial
    return x + tx, y + ty, hx, hy, (h11, h12, h22)


def _brown(x, y, coeffs):
    p1, p2 = coeffs[2], coeffs[3]
    r2 = x * x + y * y
    radial, _ = _radial(r2, coeffs)
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    return xd, yd


def _brown_jacobian(x, y, coeffs):
    p1, p2 = coeffs[2], coeffs[3]
    r2 = x * x + y * y
    radial, dradial = _radial(r2, coeffs)  # dradial: d radial / d r2
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return j11, cross, cross, j22


def _tangential_jacobian(x, y, p1, p2):
    """Jacobian of :func:`_tangential` at ``(x, y)``: ``(a11, a12, a21, a22)``."""
    a12 = 2.0 * p1 * x + 2.0 * p2 * y
    return 2.0 * p1 * y + 6.0 * p2 * x, a12, a12, 6.0 * p1 * y + 2.0 * p2 * x


def _mul(a, b):
    """Product of 2x2 matrices given as ``(m11, m12, m21, m22)`` tuples."""
    return (a[0] * b[0] + a[1] * b[2], a[0] * b[1] + a[1] * b[3],
            a[2] * b[0] + a[3] * b[2], a[2] * b[1] + a[3] * b[3])  # fmt: skip


def distort(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Apply Brown–Conrady distortion.

    Parameters
    ----------
    x, y : ndarray, shape (...)
        Undistorted normalised coordinates.
    coeffs : sequence of 5, 8 or 10 floats (or arrays of shape (...))
        ``k1, k2, p1, p2, k3``, optionally ``k4, k5, k6``, then ``p1_image, p2_image``.

    Returns
    -------
    xd, yd : ndarray, shape (...)

    Notes
    -----
    ``xd = x R + 2 p1 x y + p2 (r^2 + 2 x^2)``,
    ``yd = y R + p1 (r^2 + 2 y^2) + 2 p2 x y`` with
    ``R = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``
    (Brown 1966; OpenCV's ``projectPoints`` with five or eight coefficients). The
    image-side pair first moves the point to ``x + T(h(x))``, with ``T`` Brown's
    decentering terms of ``(p1_image, p2_image)`` and ``h(x) = x R`` the radial map: a
    lens whose map from pixel to ray is ``u = g(x_d) + T_p(x_d)`` has the inverse
    ``x_d = g^-1(u - T_p(x_d)) ~ h(u + T_(-p)(h(u)))`` to first order in ``p``.
    """
    q = _image_side(coeffs)
    if q is not None:
        x, y = _shifted(x, y, coeffs, q)[:2]
    return _brown(x, y, coeffs)


def distort_jacobian(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, ...]:
    """Partial derivatives of :func:`distort`: ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)``, each (...)."""
    q = _image_side(coeffs)
    if q is None:
        return _brown_jacobian(x, y, coeffs)
    xs, ys, hx, hy, (h11, h12, h22) = _shifted(x, y, coeffs, q)
    t = _tangential_jacobian(hx, hy, *q)
    inner = _mul(t, (h11, h12, h12, h22))
    shift = (1.0 + inner[0], inner[1], inner[2], 1.0 + inner[3])  # d(x + T(h(x))) / dx
    return _mul(_brown_jacobian(xs, ys, coeffs), shift)


def distort_coeff_jacobian(x: np.ndarray, y: np.ndarray, coeffs=None) -> np.ndarray:
    """Derivatives of :func:`distort` by its coefficients, shape (..., 2, C).

    Without ``coeffs`` (or with 5): by ``(k1, k2, p1, p2, k3)``, which do not depend on
    the coefficients (the distortion is linear in them). With 8 or 10: by all of them
    at those coefficients (the rational factor and the image-side pair make the
    distortion non-linear in its coefficients).
    """
    if coeffs is None or len(coeffs) == 5:
        return _polynomial_coeff_jacobian(x, y)
    q = _image_side(coeffs)
    if len(coeffs) == 8:
        return _rational_coeff_jacobian(x, y, coeffs)
    zero = (0.0, 0.0)
    xs, ys, hx, hy, _ = _shifted(x, y, coeffs, zero if q is None else q)
    if q is None:
        xs, ys = x, y  # exactly the point itself, as distort takes it
    outer = _rational_coeff_jacobian(xs, ys, coeffs)  # (..., 2, 8) at the moved point
    F = np.stack(_brown_jacobian(xs, ys, coeffs), axis=-1).reshape(*np.shape(xs), 2, 2)
    sh = hx * hx + hy * hy
    hxy2 = 2.0 * hx * hy
    dT_dq = np.stack([np.stack([hxy2, sh + 2.0 * hx * hx], -1),
                      np.stack([sh + 2.0 * hy * hy, hxy2], -1)], -2)  # fmt: skip
    columns = [outer, F @ dT_dq]
    if q is not None:  # the radial coefficients also move the point through h
        t = np.stack(_tangential_jacobian(hx, hy, *q), -1).reshape(*np.shape(xs), 2, 2)
        dh = _rational_coeff_jacobian(x, y, (*coeffs[:2], 0.0, 0.0, *coeffs[4:8]))
        radial = [0, 1, 4, 5, 6, 7]
        outer[..., radial] += F @ t @ dh[..., radial]
    return np.concatenate(columns, axis=-1)


def _polynomial_coeff_jacobian(x, y):
    r2 = x * x + y * y
    r4 = r2 * r2
    xy2 = 2.0 * x * y
    d_dx = np.stack([x * r2, x * r4, xy2, r2 + 2.0 * x * x, x * r4 * r2], axis=-1)
    d_dy = np.stack([y * r2, y * r4, r2 + 2.0 * y * y, xy2, y * r4 * r2], axis=-1)
    return np.stack([d_dx, d_dy], axis=-2)


def _rational_coeff_jacobian(x, y, coeffs):
    """By ``(k1, k2, p1, p2, k3, k4, k5, k6)``: the numerator terms divided by the
    denominator ``D``, the denominator terms ``-x R r^2k / D``."""
    r2 = x * x + y * y
    r4 = r2 * r2
    xy2 = 2.0 * x * y
    k4, k5, k6 = coeffs[5], coeffs[6], coeffs[7]
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial, _ = _radial(r2, coeffs[:8])
    tangential_x = [xy2, r2 + 2.0 * x * x]
    tangential_y = [r2 + 2.0 * y * y, xy2]
    columns = []
    for c, tangential in ((x, tangential_x), (y, tangential_y)):
        terms = (c * r2, c * r4, c * r4 * r2)  # the polynomial form's columns, rounded alike
        num = [t / den for t in terms]
        denominator = [-radial * t / den for t in terms]
        columns.append(np.stack([num[0], num[1], *tangential, num[2], *denominator], axis=-1))
    return np.stack(columns, axis=-2)


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
    coeffs : sequence of 5, 8 or 10 floats, or of arrays of shape (...)
        As :func:`distort` takes them, one set for all points or one per
        point (a batch of lens models, e.g. the sigma points of a calibration covariance).
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
    if not any(np.ndim(c) for c in (*coeffs, tol, r2_max)):
        return _undistort_compiled(xd, yd, coeffs, tol, r2_max, shape)

    def per_point(c):  # a scalar, or per-point values as a flat array
        return np.broadcast_to(c, shape).reshape(-1) if np.ndim(c) else c

    coeffs = [per_point(c) for c in coeffs]
    tol = per_point(tol)
    if r2_max is None:
        r2_max = max_monotonic_radius2(*coeffs[:2], *coeffs[4:8])
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
        # a diverging point overflows to inf/NaN and leaves the iteration just below
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ex, ey = distort(xa, ya, cs)
            ex -= xda
            ey -= yda
            done = np.maximum(np.abs(ex), np.abs(ey)) < tol_a
            converged[idx[done]] = True
            x[idx[done]], y[idx[done]] = xa[done], ya[done]
            j11, j12, j21, j22 = distort_jacobian(xa, ya, cs)
            det = j11 * j22 - j12 * j21
            xa = xa - (j22 * ex - j12 * ey) / det
            ya = ya - (j11 * ey - j21 * ex) / det
        go_on = ~done & np.isfinite(xa) & np.isfinite(ya)
        idx, xa, ya, xda, yda = idx[go_on], xa[go_on], ya[go_on], xda[go_on], yda[go_on]
        cs, tol_a = take(cs, go_on), take([tol_a], go_on)[0]
    converged &= (x * x + y * y) <= r2_max
    x = np.where(converged, x, np.nan).reshape(shape)
    y = np.where(converged, y, np.nan).reshape(shape)
    return Undistortion(x, y, converged.reshape(shape))


def _undistort_compiled(xd, yd, coeffs, tol, r2_max, shape) -> Undistortion:
    """:func:`undistort` for one coefficient set, by the compiled per-point loop."""
    from endomeasure.geometry._distortion_kernels import undistort_points

    _is_rational(coeffs)  # checks the number of coefficients
    c = np.zeros(10)
    c[: len(coeffs)] = [float(v) for v in coeffs]
    if r2_max is None:
        r2_max = max_monotonic_radius2(*c[:2], *c[4:8])
    x, y = np.empty_like(xd), np.empty_like(yd)
    converged = np.empty(xd.shape, dtype=bool)
    undistort_points(np.ascontiguousarray(xd), np.ascontiguousarray(yd), c, float(tol),
                     float(r2_max), UNDISTORT_MAX_ITER, x, y, converged)  # fmt: skip
    return Undistortion(x.reshape(shape), y.reshape(shape), converged.reshape(shape))


def max_monotonic_radius2(k1, k2, k3, k4=0.0, k5=0.0, k6=0.0):
    """Largest ``r^2`` up to which the radial map ``r R(r^2)`` grows (see :func:`distort`).

    Beyond it the distortion folds back and one distorted radius has two preimages, so
    projections there are not trustworthy; a rational factor's pole (its denominator's
    first positive root) ends the valid range too. ``inf`` where the map grows for all r.

    Parameters
    ----------
    k1, k2, k3 : float or ndarray, shape (...)
    k4, k5, k6 : float or ndarray, shape (...), optional
        The rational denominator's coefficients (default: none).

    Returns
    -------
    float, or ndarray of shape (...) for array coefficients

    Notes
    -----
    With ``s = r^2``, ``N = 1 + k1 s + k2 s^2 + k3 s^3`` and ``D = 1 + k4 s + k5 s^2 +
    k6 s^3``, ``d/dr [r N / D] = ((N + 2 s N') D - 2 s N D') / D^2``; the answer is the
    smallest positive real root of the numerator polynomial or of ``D``, found once per
    distinct coefficient set. For ``D = 1`` the numerator is
    ``1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3``.
    """
    ks = (k1, k2, k3, k4, k5, k6)
    if not any(np.ndim(k) for k in ks):
        return _max_monotonic_radius2(*(float(k) for k in ks))
    k = np.stack(np.broadcast_arrays(*ks), axis=-1).astype(np.float64)
    distinct, inverse = np.unique(k.reshape(-1, 6), axis=0, return_inverse=True)
    r2 = np.array([_max_monotonic_radius2(*row) for row in distinct.tolist()])
    return r2[inverse.reshape(-1)].reshape(k.shape[:-1])


@functools.lru_cache(maxsize=4096)  # an optimiser asks again for each trace of a model
def _max_monotonic_radius2(k1, k2, k3, k4=0.0, k5=0.0, k6=0.0) -> float:
    if not any((k4, k5, k6)):  # a plain polynomial: the derivative's cubic
        roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]) if any((k1, k2, k3)) else []
        return _smallest_positive(roots)
    P = np.polynomial.Polynomial
    num, den = P([1.0, k1, k2, k3]), P([1.0, k4, k5, k6])
    s = P([0.0, 1.0])
    slope = (num + 2.0 * s * num.deriv()) * den - 2.0 * s * num * den.deriv()
    # np.roots, not Polynomial.roots: it stays accurate when a leading coefficient is tiny
    return min(_smallest_positive(np.roots(c.coef[::-1])) for c in (slope, den))


def _smallest_positive(roots) -> float:
    positive = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    return float(min(positive)) if positive else float("inf")
