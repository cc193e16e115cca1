"""Compiled per-ray kernels of the ``raytrace`` model: tracing and ray aiming.

Why compiled: forward projection aims every point with several traces and a 2x2
Broyden update each. In numpy that is a few hundred small array operations per block of
points, and the time goes to call overhead and memory traffic rather than to any one
operation; a scalar loop compiled with numba does the same arithmetic in registers
(throughput: ``docs/benchmarks.md``, section ``models``). The formulas are those of
:func:`endomeasure.geometry.rays.refract` (vector Snell) and plane intersection. The
tests check the model built on these kernels against independent oracles
(``tests/models/test_raytrace.py``: Snell's law in its angle form at each face, the
Fermat least-optical-path pixel), not against the numpy functions.

All kernels use numba's ``error_model="numpy"``: a division by zero gives inf/NaN (and
then a status), never an exception out of vectorised code.

Face arrays are ``float64[10]``: rear normal (3), rear distance, front normal (3), front
distance, all in the camera frame (mm), then the entrance pupil's coefficients ``e1, e2``
(mm): the ray of lens coordinates ``(x, y)`` starts on the axis at
``z = e1 theta^2 + e2 theta^4``, ``theta = atan(hypot(x, y))`` its field angle (see
``raytrace``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from endomeasure.conventions import Status

_OK = int(Status.OK)
_TIR = int(Status.TOTAL_INTERNAL_REFLECTION)
_BEHIND = int(Status.BEHIND)
_NOT_CONVERGED = int(Status.NOT_CONVERGED)
_OUTSIDE = int(Status.OUTSIDE_HALF)
_MAX_HALVINGS = 12
_PULL_IN_STEPS = 6  # bisections towards a traceable start: 1/64 of the segment
# Central-difference step in normalised lens coordinates for d(offset)/d(x, y): truncation
# error ~h^2 (1e-14), rounding ~1e-16/h (1e-9 relative).
_JACOBIAN_STEP = 1e-7
_NAN = math.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _refract(dx, dy, dz, nx, ny, nz, eta):
    """Vector Snell for one ray; returns (tx, ty, tz, ok)."""
    cos_n = dx * nx + dy * ny + dz * nz
    c = abs(cos_n)
    k = 1.0 - eta * eta * (1.0 - c * c)
    if not k >= 0.0:
        return _NAN, _NAN, _NAN, False
    coef = eta * c - math.sqrt(k)
    if cos_n >= 0.0:  # m = -n faces the incoming ray
        coef = -coef
    return eta * dx + coef * nx, eta * dy + coef * ny, eta * dz + coef * nz, True


@njit(cache=True, nogil=True, error_model="numpy")
def _trace(x, y, faces, n_glass):
    """Trace lens coordinates (x, y) through the prism: (ox, oy, oz, dx, dy, dz, status).

    The ray leaves the entrance pupil, on the axis at ``z0 = e1 theta^2 + e2 theta^4``
    (exactly 0, and the arithmetic unchanged, when both coefficients are 0)."""
    r2 = x * x + y * y
    inv = 1.0 / math.sqrt(r2 + 1.0)
    d0x, d0y, d0z = x * inv, y * inv, inv
    z0 = 0.0
    if faces[8] != 0.0 or faces[9] != 0.0:  # no arctangent for a fixed pupil
        theta2 = math.atan(math.sqrt(r2)) ** 2
        z0 = theta2 * (faces[8] + theta2 * faces[9])
    t0 = (faces[3] - z0 * faces[2]) / (d0x * faces[0] + d0y * faces[1] + d0z * faces[2])
    if not t0 > 0.0:
        return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN, _BEHIND
    gx, gy, gz, ok = _refract(d0x, d0y, d0z, faces[0], faces[1], faces[2], 1.0 / n_glass)
    if not ok:
        return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN, _TIR
    p1x, p1y, p1z = t0 * d0x, t0 * d0y, z0 + t0 * d0z
    t1 = (faces[7] - (p1x * faces[4] + p1y * faces[5] + p1z * faces[6])) / (
        gx * faces[4] + gy * faces[5] + gz * faces[6]
    )
    if not t1 > 0.0:
        return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN, _BEHIND
    dx, dy, dz, ok = _refract(gx, gy, gz, faces[4], faces[5], faces[6], n_glass)
    if not ok:
        return _NAN, _NAN, _NAN, _NAN, _NAN, _NAN, _TIR
    return p1x + t1 * gx, p1y + t1 * gy, p1z + t1 * gz, dx, dy, dz, _OK


@njit(cache=True, nogil=True, error_model="numpy")
def trace_rays(x, y, faces, n_glass, prism, origins, directions, status):
    """Trace many lens coordinates into ``origins (N,3)``, ``directions (N,3)``, ``status (N,)``.

    ``faces`` (K, 10) and ``n_glass`` (K,) hold K prisms; ``prism`` (N,) int names each
    ray's (empty: prism 0 for all).
    """
    per_ray = prism.shape[0] > 0
    for i in range(x.shape[0]):
        k = prism[i] if per_ray else 0
        ox, oy, oz, dx, dy, dz, st = _trace(x[i], y[i], faces[k], n_glass[k])
        origins[i, 0], origins[i, 1], origins[i, 2] = ox, oy, oz
        directions[i, 0], directions[i, 1], directions[i, 2] = dx, dy, dz
        status[i] = st


@njit(cache=True, nogil=True, error_model="numpy")
def _offset(x, y, faces, n_glass, px, py, pz):
    """Offset of the traced ray from (px, py) in the plane z = pz, and the trace status."""
    ox, oy, oz, dx, dy, dz, st = _trace(x, y, faces, n_glass)
    if st != _OK:
        return _NAN, _NAN, -1.0, st
    s = (pz - oz) / dz
    return ox + s * dx - px, oy + s * dy - py, s, st


@njit(cache=True, nogil=True, error_model="numpy")
def offsets(x, y, points, faces, n_glass, out):
    """``_offset`` of many lens coordinates ``x, y`` (N,) from their points (N, 3), into
    ``out`` (N, 2), mm; NaN where the trace fails."""
    for i in range(points.shape[0]):
        ex, ey, s, st = _offset(x[i], y[i], faces, n_glass, points[i, 0], points[i, 1],
                                points[i, 2])  # fmt: skip
        out[i, 0] = ex
        out[i, 1] = ey


@njit(cache=True, nogil=True, error_model="numpy")
def _poly_start(exponents, coeffs, wx, wy, q, pw_x, pw_y, pw_q):
    """Polynomial start map: ``(x, y, dx/dwx, dx/dwy, dy/dwx, dy/dwy)`` at (wx, wy, q)."""
    top = pw_x.shape[0] - 1
    pw_x[0] = pw_y[0] = pw_q[0] = 1.0
    for p in range(1, top + 1):
        pw_x[p] = pw_x[p - 1] * wx
        pw_y[p] = pw_y[p - 1] * wy
        pw_q[p] = pw_q[p - 1] * q
    x = y = 0.0
    gxx = gxy = gyx = gyy = 0.0
    for f in range(exponents.shape[0]):
        a, b, c = exponents[f, 0], exponents[f, 1], exponents[f, 2]
        yq = pw_y[b] * pw_q[c]
        val = pw_x[a] * yq
        x += val * coeffs[f, 0]
        y += val * coeffs[f, 1]
        if a > 0:
            d = a * pw_x[a - 1] * yq
            gxx += d * coeffs[f, 0]
            gyx += d * coeffs[f, 1]
        if b > 0:
            d = b * pw_x[a] * pw_y[b - 1] * pw_q[c]
            gxy += d * coeffs[f, 0]
            gyy += d * coeffs[f, 1]
    return x, y, gxx, gxy, gyx, gyy


@njit(cache=True, nogil=True, error_model="numpy")
def _lut_start(lut, origin, step, wx, wy, q):
    """Trilinear look-up of the lens coordinates of (wx, wy, q) and their w-derivatives.

    ``lut`` is float64[K, NY, NX, 2] on the regular grid ``origin + index * step``
    (axes q, wy, wx). Outside the grid the nearest cell is extrapolated linearly.
    Returns ``(x, y, dx/dwx, dx/dwy, dy/dwx, dy/dwy, ok)``; ok is False where a corner
    of the cell is NaN (no valid ray there).
    """
    nq, ny, nx = lut.shape[0], lut.shape[1], lut.shape[2]
    fx = (wx - origin[0]) / step[0]
    fy = (wy - origin[1]) / step[1]
    fq = (q - origin[2]) / step[2]
    ix = min(max(int(math.floor(fx)), 0), nx - 2)
    iy = min(max(int(math.floor(fy)), 0), ny - 2)
    iq = min(max(int(math.floor(fq)), 0), nq - 2)
    tx, ty, tq = fx - ix, fy - iy, fq - iq
    x, x_wx, x_wy = _trilinear(lut, 0, iq, iy, ix, tq, ty, tx)
    y, y_wx, y_wy = _trilinear(lut, 1, iq, iy, ix, tq, ty, tx)
    ok = math.isfinite(x + y + x_wx + x_wy + y_wx + y_wy)
    return x, y, x_wx / step[0], x_wy / step[1], y_wx / step[0], y_wy / step[1], ok


@njit(cache=True, nogil=True, error_model="numpy")
def _trilinear(lut, c, iq, iy, ix, tq, ty, tx):
    """Value and index-space derivatives along x and y of channel c in one cell."""
    # interpolate along q first, then y, then x
    a00 = lut[iq, iy, ix, c] + tq * (lut[iq + 1, iy, ix, c] - lut[iq, iy, ix, c])
    a01 = lut[iq, iy, ix + 1, c] + tq * (lut[iq + 1, iy, ix + 1, c] - lut[iq, iy, ix + 1, c])
    a10 = lut[iq, iy + 1, ix, c] + tq * (lut[iq + 1, iy + 1, ix, c] - lut[iq, iy + 1, ix, c])
    a11 = lut[iq, iy + 1, ix + 1, c] + tq * (
        lut[iq + 1, iy + 1, ix + 1, c] - lut[iq, iy + 1, ix + 1, c]
    )
    b0 = a00 + ty * (a10 - a00)
    b1 = a01 + ty * (a11 - a01)
    return b0 + tx * (b1 - b0), b1 - b0, (a10 - a00) + tx * ((a11 - a01) - (a10 - a00))


@njit(cache=True, nogil=True, error_model="numpy")
def _lens_jacobian(x, y, faces, n_glass, px, py, pz, h, out):
    """d(x, y)/dP at a converged aim, into ``out`` (2, 3).

    The offset ``e(x, P) = (o + s d)_xy - P_xy`` with ``s = (P_z - o_z) / d_z`` vanishes at
    the solution, so ``dx/dP = -(de/dx)^-1 de/dP`` with ``de/dP = [[-1, 0, tx], [0, -1, ty]]``
    (``t = d_xy / d_z``, the ray's slope) and ``de/dx`` by central differences of the trace
    (step ``h``, four traces).
    """
    ox, oy, oz, dx, dy, dz, st = _trace(x, y, faces, n_glass)
    tx, ty = dx / dz, dy / dz
    exp, eyp, s, st = _offset(x + h, y, faces, n_glass, px, py, pz)
    exm, eym, s, st = _offset(x - h, y, faces, n_glass, px, py, pz)
    a11, a21 = (exp - exm) / (2.0 * h), (eyp - eym) / (2.0 * h)
    exp, eyp, s, st = _offset(x, y + h, faces, n_glass, px, py, pz)
    exm, eym, s, st = _offset(x, y - h, faces, n_glass, px, py, pz)
    a12, a22 = (exp - exm) / (2.0 * h), (eyp - eym) / (2.0 * h)
    det = a11 * a22 - a12 * a21
    i11, i12, i21, i22 = a22 / det, -a12 / det, -a21 / det, a11 / det
    # dx/dP = (de/dx)^-1 [[1, 0, -tx], [0, 1, -ty]]
    out[0, 0], out[0, 1], out[0, 2] = i11, i12, -(i11 * tx + i12 * ty)
    out[1, 0], out[1, 1], out[1, 2] = i21, i22, -(i21 * tx + i22 * ty)


@njit(cache=True, nogil=True, error_model="numpy")
def lens_jacobians(xy, points, faces, n_glass, dxy_dp):
    """``_lens_jacobian`` at solutions already aimed, ``xy`` (N, 2), into ``dxy_dp``
    (N, 2, 3); rows with NaN lens coordinates get NaN."""
    for i in range(points.shape[0]):
        if math.isfinite(xy[i, 0]) and math.isfinite(xy[i, 1]):
            _lens_jacobian(xy[i, 0], xy[i, 1], faces, n_glass, points[i, 0], points[i, 1],
                           points[i, 2], _JACOBIAN_STEP, dxy_dp[i])  # fmt: skip
        else:
            dxy_dp[i, :, :] = _NAN


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _broyden(x, y, ex, ey, s, b11, b12, b21, b22, faces, n_glass, px, py, pz, tol_x, tol_y,
             max_iter):  # fmt: skip
    """Broyden's iteration from lens coordinates (x, y) with offset (ex, ey) and inverse
    Jacobian ``b``: returns the solution, its ray parameter and its status."""
    result = _NOT_CONVERGED
    sx = -(b11 * ex + b12 * ey)
    sy = -(b21 * ex + b22 * ey)
    if abs(sx) < tol_x and abs(sy) < tol_y:  # a warm start already on the point
        x += sx
        y += sy
        result = _OK if s > 0.0 else _BEHIND
    for _ in range(max_iter if result == _NOT_CONVERGED else 0):
        nex, ney, s, st = _offset(x + sx, y + sy, faces, n_glass, px, py, pz)
        h = 0
        while st != _OK and h < _MAX_HALVINGS:  # keep the ray inside the prism
            sx *= 0.5
            sy *= 0.5
            nex, ney, s, st = _offset(x + sx, y + sy, faces, n_glass, px, py, pz)
            h += 1
        if st != _OK:
            result = st
            break
        # good Broyden update of the inverse Jacobian: B += (s - B f) s^T B / (s^T B f)
        fx, fy = nex - ex, ney - ey
        bfx, bfy = b11 * fx + b12 * fy, b21 * fx + b22 * fy
        den = sx * bfx + sy * bfy
        if den != 0.0:
            ux, uy = (sx - bfx) / den, (sy - bfy) / den
            vx, vy = sx * b11 + sy * b21, sx * b12 + sy * b22
            b11 += ux * vx
            b12 += ux * vy
            b21 += uy * vx
            b22 += uy * vy
        x += sx
        y += sy
        ex, ey = nex, ney
        # The next step is known without another trace; once it is below the
        # tolerance, take it and stop (its own error is far smaller still).
        sx = -(b11 * ex + b12 * ey)
        sy = -(b21 * ex + b22 * ey)
        if abs(sx) < tol_x and abs(sy) < tol_y:
            x += sx
            y += sy
            result = _OK if s > 0.0 else _BEHIND
            break
    return x, y, s, result


@njit(cache=True, nogil=True, error_model="numpy")
def _pull_in(x, y, inner, faces, n_glass, px, py, pz):
    """A traceable start on the segment from an untraceable one ``(x, y)`` to ``inner``.

    Near the field edge the start map may land beyond the critical angle or off a face
    although the solution itself traces: bisection along the segment keeps the traceable
    point nearest the original start (the solution usually lies near that edge too).
    Returns ``(x, y, ex, ey, s, status)`` as ``_offset`` does, the status not OK when
    even ``inner`` does not trace.
    """
    ex, ey, s, st = _offset(inner[0], inner[1], faces, n_glass, px, py, pz)
    if st != _OK:
        return x, y, ex, ey, s, st
    good, bad = 0.0, 1.0
    bx, by, bex, bey, bs = inner[0], inner[1], ex, ey, s
    for _ in range(_PULL_IN_STEPS):
        t = 0.5 * (good + bad)
        tx, ty = inner[0] + t * (x - inner[0]), inner[1] + t * (y - inner[1])
        ex, ey, s, st = _offset(tx, ty, faces, n_glass, px, py, pz)
        if st == _OK:
            good = t
            bx, by, bex, bey, bs = tx, ty, ex, ey, s
        else:
            bad = t
    return bx, by, bex, bey, bs, _OK


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pixel(x, y, result, lens, r2_max):
    """The pixel ``(u, v)`` of a converged aim, NaN unless OK, and the status
    (``OUTSIDE_HALF`` beyond the distortion's fold-back radius ``r2_max``)."""
    if result != _OK:
        return _NAN, _NAN, result
    if lens[12] != 0.0 or lens[13] != 0.0:  # image-side decentering: x + T(h(x)) first
        r2 = x * x + y * y
        radial = 1.0 + r2 * (lens[4] + r2 * (lens[5] + r2 * lens[8]))
        radial /= 1.0 + r2 * (lens[9] + r2 * (lens[10] + r2 * lens[11]))
        hx, hy = x * radial, y * radial
        h2 = hx * hx + hy * hy
        x, y = (x + 2.0 * lens[12] * hx * hy + lens[13] * (h2 + 2.0 * hx * hx),
                y + lens[12] * (h2 + 2.0 * hy * hy) + 2.0 * lens[13] * hx * hy)  # fmt: skip
    r2 = x * x + y * y
    if r2 > r2_max:
        return _NAN, _NAN, _OUTSIDE
    radial = 1.0 + r2 * (lens[4] + r2 * (lens[5] + r2 * lens[8]))
    radial /= 1.0 + r2 * (lens[9] + r2 * (lens[10] + r2 * lens[11]))  # rational: exact 1 if 0
    xd = x * radial + 2.0 * lens[6] * x * y + lens[7] * (r2 + 2.0 * x * x)
    yd = y * radial + lens[6] * (r2 + 2.0 * y * y) + 2.0 * lens[7] * x * y
    return lens[0] * xd + lens[2], lens[1] * yd + lens[3], result


@njit(cache=True, nogil=True, error_model="numpy")
def aim_rays(
    points, faces, n_glass, centre, exponents, coeffs, lut, lut_origin, lut_step, inner,
    start_xy, tol_x, tol_y, max_iter, xy, status, dxy_dp, lens, r2_max, pixels,
):  # fmt: skip
    """Ray aiming for many points by Broyden's method (see ``raytrace.aim_rays``).

    Parameters
    ----------
    points : float64[N, 3]
    faces : float64[10]
    centre : float64[3]
        Virtual centre of the half used by the start map.
    exponents : int64[F, 3], coeffs : float64[F, 2]
        Polynomial start map ``(wx, wy, q) -> (x, y)``, used where the table has no value.
    lut, lut_origin, lut_step
        Start table (see ``_lut_start``); an empty table (K < 2) disables it.
    inner : float64[2]
        Lens coordinates of a ray well inside the half's traceable field: a start that
        cannot be traced (beyond the critical angle, near the field edge) is pulled
        towards it (see ``_pull_in``).
    start_xy : float64[N, 2] or float64[0, 2]
        Warm starts (e.g. the previous solution during an optimisation); rows with NaN,
        or an empty array, start from the table. The inverse Jacobian always starts from
        the table or polynomial at the point.
    tol_x, tol_y : float
        Step tolerances in normalised lens units.
    xy : float64[N, 2] (output)
    status : uint8[N] (output)
    dxy_dp : float64[N, 2, 3] or float64[0, 2, 3] (output)
        Where given, the derivative of the lens coordinates with respect to the point,
        by the implicit-function rule (see ``_lens_jacobian``).
    lens : float64[14], r2_max : float, pixels : float64[N, 2] or float64[0, 2] (output)
        Where ``pixels`` is given, the pixel of each solution through the lens
        ``fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 p1_image p2_image`` (as
        :func:`endomeasure.geometry.distortion.distort`); a solution beyond the fold-back
        radius ``r2_max`` of the distortion is ``OUTSIDE_HALF``.
    """
    n_feat = exponents.shape[0]
    top = 0
    for f in range(n_feat):
        for j in range(3):
            top = max(top, exponents[f, j])
    pw_x = np.empty(top + 1)
    pw_y = np.empty(top + 1)
    pw_q = np.empty(top + 1)
    use_lut = lut.shape[0] >= 2
    want_jac = dxy_dp.shape[0] > 0
    want_pixels = pixels.shape[0] > 0
    warm = start_xy.shape[0] > 0
    inverse = np.empty((2, 3))  # scratch: a start's inverse Jacobian, for the retry
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        xy[i, 0] = _NAN
        xy[i, 1] = _NAN
        if want_pixels:  # a point skipped below keeps NaN
            pixels[i, 0] = _NAN
            pixels[i, 1] = _NAN
        if want_jac:
            dxy_dp[i, :, :] = _NAN
        # the point must lie beyond the front face, and in front of the virtual centre
        rz = pz - centre[2]
        if not (px * faces[4] + py * faces[5] + pz * faces[6] > faces[7] and rz > 0.0):
            status[i] = _BEHIND
            continue
        q = 1.0 / rz
        wx = (px - centre[0]) * q
        wy = (py - centre[1]) * q
        ok = False
        if use_lut:
            x, y, gxx, gxy, gyx, gyy, ok = _lut_start(lut, lut_origin, lut_step, wx, wy, q)
        if not ok:
            x, y, gxx, gxy, gyx, gyy = _poly_start(exponents, coeffs, wx, wy, q, pw_x, pw_y, pw_q)
        # inverse Jacobian of the offset (mm at depth pz): dw = offset * q
        b11, b12, b21, b22 = gxx * q, gxy * q, gyx * q, gyy * q
        ex, ey, s, st = _NAN, _NAN, -1.0, _NOT_CONVERGED
        if warm and math.isfinite(start_xy[i, 0]) and math.isfinite(start_xy[i, 1]):
            ex, ey, s, st = _offset(start_xy[i, 0], start_xy[i, 1], faces, n_glass, px, py, pz)
            if st == _OK:
                x, y = start_xy[i, 0], start_xy[i, 1]
        if st != _OK:
            ex, ey, s, st = _offset(x, y, faces, n_glass, px, py, pz)
        if st != _OK:
            x, y, ex, ey, s, st = _pull_in(x, y, inner, faces, n_glass, px, py, pz)
        if st != _OK:
            status[i] = st
            continue
        x0, y0, ex0, ey0, s0 = x, y, ex, ey, s
        x, y, s, result = _broyden(x, y, ex, ey, s, b11, b12, b21, b22, faces, n_glass,
                                   px, py, pz, tol_x, tol_y, max_iter)  # fmt: skip
        if result == _NOT_CONVERGED:  # a poor start map near the field edge: once more, from the
            # same start with its own inverse Jacobian (central differences of the trace)
            _lens_jacobian(x0, y0, faces, n_glass, px, py, pz, _JACOBIAN_STEP, inverse)
            if math.isfinite(inverse[0, 0] + inverse[0, 1] + inverse[1, 0] + inverse[1, 1]):
                x, y, s, result = _broyden(
                    x0, y0, ex0, ey0, s0, inverse[0, 0], inverse[0, 1], inverse[1, 0],
                    inverse[1, 1], faces, n_glass, px, py, pz, tol_x, tol_y, max_iter,
                )  # fmt: skip
        if want_pixels:
            pixels[i, 0], pixels[i, 1], result = _pixel(x, y, result, lens, r2_max)
        status[i] = result
        if result == _OK:
            xy[i, 0] = x
            xy[i, 1] = y
            if want_jac:
                _lens_jacobian(x, y, faces, n_glass, px, py, pz, _JACOBIAN_STEP, dxy_dp[i])
        elif want_jac:
            dxy_dp[i, :, :] = _NAN
