"""Ray kernels: plane intersection, vector refraction (Snell), common perpendicular.

All functions are vectorised over leading dimensions and never raise for a single bad
ray: they return NaN and a :class:`~endomeasure.conventions.Status` code instead.
Directions are unit vectors unless a docstring says otherwise.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Status

__all__ = [
    "PlaneHit",
    "Refraction",
    "Perpendicular",
    "intersect_plane",
    "plane_through",
    "refract",
    "refract_xyz",
    "common_perpendicular",
    "normalize",
    "dot",
]

_PARALLEL_EPS = 1e-12  # |cos| below this: ray parallel to a plane / two rays parallel


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis, broadcasting, shape (...)."""
    a = np.asarray(a)
    b = np.asarray(b)
    if b.ndim == 1:
        return a @ b
    if a.ndim == 1:
        return b @ a
    return np.einsum("...i,...i->...", a, b) if a.shape == b.shape else np.sum(a * b, axis=-1)


def normalize(v: np.ndarray) -> np.ndarray:
    """``v / |v|`` over the last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class PlaneHit(NamedTuple):
    """Where rays meet a plane: ``points = origins + t * directions``."""

    t: np.ndarray  # (...,), mm along the (unit) direction
    points: np.ndarray  # (..., 3), mm
    status: np.ndarray  # (...,), uint8


def intersect_plane(
    origins: np.ndarray, directions: np.ndarray, normal: np.ndarray, distance: float | np.ndarray
) -> PlaneHit:
    """Intersect rays with the plane ``normal . x = distance``.

    Parameters
    ----------
    origins : ndarray, shape (..., 3), mm
    directions : ndarray, shape (..., 3)
    normal : ndarray, shape (3,) or (..., 3), unit normal
    distance : float or ndarray, shape (...), mm

    Returns
    -------
    PlaneHit
        ``status`` is ``BEHIND`` where the plane lies behind the origin (t <= 0) or the
        ray is parallel to it; those points are NaN.
    """
    denom = dot(directions, normal)
    parallel = np.abs(denom) < _PARALLEL_EPS
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (distance - dot(origins, normal)) / np.where(parallel, np.nan, denom)
    bad = ~(t > 0)  # also catches NaN
    t = np.where(bad, np.nan, t)
    status = np.where(bad, Status.BEHIND, Status.OK).astype(STATUS_DTYPE)
    return PlaneHit(t, origins + t[..., None] * directions, status)


def plane_through(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plane ``normal . x = distance`` through three points.

    Parameters
    ----------
    p0, p1, p2 : ndarray, shape (..., 3), mm

    Returns
    -------
    normal : ndarray, shape (..., 3)
        Unit normal ``(p1 - p0) x (p2 - p0) / |...|``; NaN for collinear points.
    distance : ndarray, shape (...), mm
        ``normal . p0``.
    """
    n = np.cross(p1 - p0, p2 - p0)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return n, np.sum(n * p0, axis=-1)


class Refraction(NamedTuple):
    directions: np.ndarray  # (..., 3) unit refracted directions, NaN where TIR
    status: np.ndarray  # (...,) uint8: OK or TOTAL_INTERNAL_REFLECTION


def refract(directions: np.ndarray, normal: np.ndarray, eta: float | np.ndarray) -> Refraction:
    """Refract unit directions at a surface by the vector form of Snell's law.

    Parameters
    ----------
    directions : ndarray, shape (..., 3)
        Unit incident directions ``d``.
    normal : ndarray, shape (3,) or (..., 3)
        Unit surface normal, either orientation (it is flipped to face the incoming
        ray, ``m . d < 0``).
    eta : float or ndarray, shape (...)
        Ratio of refractive indices ``n1 / n2`` (incident over transmitted medium).

    Returns
    -------
    Refraction

    Notes
    -----
    With ``c = -m.d`` and ``k = 1 - eta^2 (1 - c^2)``, the transmitted direction is
    ``t = eta d + (eta c - sqrt(k)) m``; ``k < 0`` is total internal reflection
    (SPEC 4.2). ``t`` is a unit vector when ``d`` and ``m`` are.
    """
    d = np.asarray(directions, dtype=np.float64)
    m = np.asarray(normal, dtype=np.float64)
    tx, ty, tz, tir = refract_xyz(
        d[..., 0], d[..., 1], d[..., 2], m[..., 0], m[..., 1], m[..., 2], eta
    )
    status = np.where(tir, Status.TOTAL_INTERNAL_REFLECTION, Status.OK).astype(STATUS_DTYPE)
    return Refraction(np.stack([tx, ty, tz], axis=-1), status)


def refract_xyz(dx, dy, dz, nx, ny, nz, eta):
    """Component form of :func:`refract` for hot loops (no stacking of (N, 3) arrays).

    Parameters
    ----------
    dx, dy, dz : ndarray, shape (...)
        Unit incident direction components.
    nx, ny, nz : float or ndarray, shape (...)
        Unit normal components, either orientation.
    eta : float or ndarray
        ``n1 / n2``.

    Returns
    -------
    tx, ty, tz : ndarray, shape (...)
        Refracted unit direction, NaN where total internal reflection.
    tir : ndarray of bool, shape (...)
    """
    cos_n = dx * nx + dy * ny + dz * nz
    c = np.abs(cos_n)
    k = 1.0 - eta * eta * (1.0 - c * c)
    tir = ~(k >= 0)  # also catches NaN
    with np.errstate(invalid="ignore"):
        coef = eta * c - np.sqrt(k)
    # m = +-normal faces the incoming ray (m.d < 0): t = eta d + coef m
    coef = np.where(cos_n < 0, coef, -coef)
    return eta * dx + coef * nx, eta * dy + coef * ny, eta * dz + coef * nz, tir


class Perpendicular(NamedTuple):
    """The common perpendicular of two rays."""

    midpoint: np.ndarray  # (..., 3) mm, midpoint of the common perpendicular
    gap: np.ndarray  # (...,) mm, length of the common perpendicular (ray gap)
    s1: np.ndarray  # (...,) mm, parameter of the foot point on ray 1
    s2: np.ndarray  # (...,) mm, parameter of the foot point on ray 2
    status: np.ndarray  # (...,) uint8: OK, PARALLEL


def common_perpendicular(
    o1: np.ndarray, d1: np.ndarray, o2: np.ndarray, d2: np.ndarray
) -> Perpendicular:
    """Midpoint and length of the common perpendicular of two rays (lines).

    Parameters
    ----------
    o1, o2 : ndarray, shape (..., 3), mm
        Ray origins.
    d1, d2 : ndarray, shape (..., 3)
        Unit ray directions.

    Returns
    -------
    Perpendicular
        For (near) parallel rays, status ``PARALLEL`` and NaN.

    Notes
    -----
    The feet ``o1 + s1 d1`` and ``o2 + s2 d2`` solve the 2x2 normal equations
    ``[[1, -b], [b, -1]] [s1, s2]^T = [-d1.w, -d2.w]`` with ``w = o1 - o2`` and
    ``b = d1.d2``; the determinant is ``1 - b^2``.
    """
    w = o1 - o2
    b = dot(d1, d2)
    e = dot(d1, w)
    f = dot(d2, w)
    det = 1.0 - b * b
    parallel = ~(det > _PARALLEL_EPS)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(parallel, np.nan, det)
    s1 = (b * f - e) * inv
    s2 = (f - b * e) * inv
    p1 = o1 + s1[..., None] * d1
    p2 = o2 + s2[..., None] * d2
    status = np.where(parallel, Status.PARALLEL, Status.OK).astype(STATUS_DTYPE)
    return Perpendicular((p1 + p2) / 2.0, np.linalg.norm(p1 - p2, axis=-1), s1, s2, status)
