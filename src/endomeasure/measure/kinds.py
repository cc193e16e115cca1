"""Measurement kinds: pure functions of triangulated points (SPEC section 7).

The vocabulary of commercial videoscopes:

=========== ======== ==============================================================
kind        points   value
=========== ======== ==============================================================
length      2        distance between the points, mm
point-line  3        distance from the 3rd point to the line through the first two, mm
depth       4        signed distance from the 4th point to the plane through the
                     first three, mm (sign convention below)
area        >= 3     area of the polygon, mm^2
polyline    >= 2     total length of the path, mm
profile     2        the surface's height along the path between the points against a
                     reference plane (+3 reference points, or a best fit); deepest and
                     highest point (:mod:`endomeasure.measure.profile`)
area-prof.  4        profiles between two reference lines (points 1-2 and 3-4); the
                     slice holding the extreme (``area-profile``)
=========== ======== ==============================================================

``profile`` and ``area-profile`` are measured on the dense surface, not from the
triangulated points alone (``KindSpec.dense``): their function refuses to be evaluated.

Two layers:

- ``length``, ``point_line``, ``depth``, ``area``, ``polyline`` are vectorised over
  leading dimensions (points ``(..., n, 3)`` -> values ``(...)``), never raise for a
  single degenerate set (they return NaN or the limit value), and are what the
  uncertainty propagation evaluates thousands of times;
- :func:`measure` checks one set of points (count, coincident, collinear) and raises
  :class:`~endomeasure.errors.BadInputError` with a clear message before computing.

The measurement plane
---------------------
The ``--plane`` modifier of videoscopes (SPEC section 7): the points of a length,
point-line, polyline or area, and the 4th point of a depth, are not triangulated but
placed where their left ray meets a plane through three other points
(:func:`projected_points`, :func:`plane_of`, :func:`ray_plane`), so that an edge that
is burnt off or a corner that is missing can be measured where it was.

Depth sign convention
---------------------
The plane's normal is oriented towards the probe: towards the origin of the model frame
(the lens centre of ``raytrace``, the left virtual camera of ``pinhole``; both sit in
the probe). The depth is **positive when the 4th point lies on the probe's side of the
plane** (in front of the surface, e.g. a bump towards the viewer) and negative behind
it (e.g. the bottom of a pit or dent seen through the surface plane).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from endomeasure.defaults import MAX_POINTS_PER_MEASUREMENT
from endomeasure.errors import BadInputError

__all__ = [
    "check_count",
    "KINDS",
    "KindSpec",
    "POINT_KINDS",
    "kind_spec",
    "length",
    "point_line",
    "depth",
    "area",
    "polyline",
    "measure",
    "validate",
    "evaluate",
    "COINCIDENT_MM",
    "COLLINEAR_SIN",
    "PLANE_POINTS",
    "plane_of",
    "projected_points",
    "ray_plane",
]

COINCIDENT_MM = 1e-6
"""Points closer than this (mm) are the same point: far below any detectable distance
(a pixel at 10 mm spans about 0.05 mm), so only a repeated click gets here."""

COLLINEAR_SIN = 1e-6
"""Three points whose triangle has ``|cross| <= COLLINEAR_SIN * (longest edge)^2`` (the sine
of the smallest angle, up to a factor of order one) are collinear: they define no
plane. Nearly collinear sets above this are accepted; their uncertainty shows how bad
the geometry is."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.cross(a, b)


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum(v * v, axis=-1))


def length(points: np.ndarray) -> np.ndarray:
    """Distance between two points.

    Parameters
    ----------
    points : ndarray, shape (..., 2, 3), mm

    Returns
    -------
    ndarray, shape (...), mm
    """
    p = np.asarray(points, dtype=np.float64)
    return _norm(p[..., 1, :] - p[..., 0, :])


def point_line(points: np.ndarray) -> np.ndarray:
    """Distance from the 3rd point to the (infinite) line through the first two.

    Parameters
    ----------
    points : ndarray, shape (..., 3, 3), mm

    Returns
    -------
    ndarray, shape (...), mm
        NaN where the first two points coincide.

    Notes
    -----
    ``|(p2 - p0) x (p1 - p0)| / |p1 - p0|``.
    """
    p = np.asarray(points, dtype=np.float64)
    a = p[..., 1, :] - p[..., 0, :]
    b = p[..., 2, :] - p[..., 0, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return _norm(_cross(b, a)) / _norm(a)


def depth(points: np.ndarray, towards: np.ndarray | None = None) -> np.ndarray:
    """Signed distance from the 4th point to the plane through the first three.

    Parameters
    ----------
    points : ndarray, shape (..., 4, 3), mm
    towards : ndarray, shape (3,) or (..., 3), mm, optional
        The viewpoint that defines the positive side; the model-frame origin (the
        probe) by default.

    Returns
    -------
    ndarray, shape (...), mm
        Positive when the 4th point lies on the viewpoint's side of the plane (see the
        module docstring). NaN for collinear plane points.

    Notes
    -----
    ``n = (p1 - p0) x (p2 - p0)``, flipped so that ``n . (towards - p0) > 0``; the
    value is ``n . (p3 - p0) / |n|``.
    """
    p = np.asarray(points, dtype=np.float64)
    eye = np.zeros(3) if towards is None else np.asarray(towards, dtype=np.float64)
    n = _cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    side = np.sum(n * (eye - p[..., 0, :]), axis=-1)
    n = n * np.where(side < 0, -1.0, 1.0)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sum(n * (p[..., 3, :] - p[..., 0, :]), axis=-1) / _norm(n)


def area(points: np.ndarray) -> np.ndarray:
    """Area of the polygon through the points (in order), as a sum of triangles.

    Parameters
    ----------
    points : ndarray, shape (..., n, 3), mm, n >= 3

    Returns
    -------
    ndarray, shape (...), mm^2

    Notes
    -----
    The vector area ``A = 1/2 sum_{i=1}^{n-2} (p_i - p_0) x (p_{i+1} - p_0)`` (the fan of
    triangles from the first vertex, each with its orientation) and the value ``|A|``.
    For a planar simple polygon, convex or not, this is its exact area; for a slightly
    non-planar one it is the area projected onto the best-fitting plane. For the
    board test's squares this is the paper's "area of the square as the sum of two
    triangle areas".
    """
    p = np.asarray(points, dtype=np.float64)
    e = p[..., 1:, :] - p[..., :1, :]
    vector_area = 0.5 * np.sum(_cross(e[..., :-1, :], e[..., 1:, :]), axis=-2)
    return _norm(vector_area)


def polyline(points: np.ndarray) -> np.ndarray:
    """Total length of the path through the points (in order).

    Parameters
    ----------
    points : ndarray, shape (..., n, 3), mm, n >= 2

    Returns
    -------
    ndarray, shape (...), mm
    """
    p = np.asarray(points, dtype=np.float64)
    return np.sum(_norm(np.diff(p, axis=-2)), axis=-1)


class KindSpec(NamedTuple):
    """A measurement kind: its function, point count and unit."""

    name: str
    function: Callable[[np.ndarray], np.ndarray]
    min_points: int
    max_points: int | None  # None: any number >= min_points
    unit: str
    description: str
    dense: bool = False
    """Measured on the dense surface (:mod:`endomeasure.measure.profile`), not a function
    of the points."""


def _dense_only(kind: str) -> Callable[[np.ndarray], np.ndarray]:
    def refuse(points: np.ndarray) -> np.ndarray:
        raise BadInputError(
            f"{kind} is measured on the dense surface, not from its points alone",
            hint=f"use `endomeasure measure SESSION --image NAME --kind {kind} --left U,V ...`",
        )

    return refuse


KINDS: dict[str, KindSpec] = {
    k.name: k
    for k in (
        KindSpec("length", length, 2, 2, "mm", "distance between two points"),
        KindSpec(
            "point-line", point_line, 3, 3, "mm",
            "distance from the 3rd point to the line through the first two",
        ),
        KindSpec(
            "depth", depth, 4, 4, "mm",
            "signed distance from the 4th point to the plane through the first three "
            "(positive towards the probe)",
        ),
        KindSpec("area", area, 3, None, "mm^2", "area of the polygon through the points"),
        KindSpec("polyline", polyline, 2, None, "mm", "total length of the path"),
        KindSpec(
            "profile", _dense_only("profile"), 2, 2, "mm",
            "the surface's height along the path between the two points against a reference "
            "plane (positive towards the probe)", dense=True,
        ),
        KindSpec(
            "area-profile", _dense_only("area-profile"), 4, 4, "mm",
            "profiles between reference line 1 (points 1-2) and line 2 (points 3-4)",
            dense=True,
        ),
    )
}  # fmt: skip

POINT_KINDS = tuple(name for name, spec in KINDS.items() if not spec.dense)
"""The kinds that are functions of their triangulated points (what ``predict-error``
propagates)."""


def kind_spec(kind: str) -> KindSpec:
    """The :class:`KindSpec` of a kind name; unknown names are a :class:`BadInputError`."""
    try:
        return KINDS[kind]
    except KeyError:
        raise BadInputError(
            f"unknown measurement kind {kind!r}",
            hint=f"use one of {', '.join(KINDS)}",
        ) from None


def _count_hint(spec: KindSpec) -> str:
    if spec.max_points == spec.min_points:
        return f"exactly {spec.min_points}"
    return f"at least {spec.min_points}"


def check_count(kind: str, n: int, what: str = "points") -> None:
    """BadInputError unless ``n`` points can be measured as ``kind`` (``what`` names how
    the user gives them, for the hint)."""
    spec = kind_spec(kind)
    if n > MAX_POINTS_PER_MEASUREMENT:
        raise BadInputError(
            f"{n} points is more than {MAX_POINTS_PER_MEASUREMENT} in one measurement, far "
            "more than an outline needs",
            hint="measure it in parts, or with fewer points",
        )
    if n < spec.min_points or (spec.max_points is not None and n > spec.max_points):
        raise BadInputError(
            f"{kind} needs {_count_hint(spec)} points, got {n}",
            hint=f"give {_count_hint(spec)} {what} ({spec.description})",
        )


def _collinear(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    longest = max(_norm(b - a), _norm(c - a), _norm(c - b))
    return bool(_norm(_cross(b - a, c - a)) <= COLLINEAR_SIN * longest**2)


def validate(kind: str, points: np.ndarray) -> np.ndarray:
    """Check that one set of points can be measured as ``kind``.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`.
    points : ndarray, shape (n, 3), mm

    Returns
    -------
    ndarray, shape (n, 3)
        The points as float64.

    Raises
    ------
    BadInputError
        Unknown kind; wrong number of points; non-finite points; coincident
        neighbouring points (a zero segment in length, polyline or area, or a
        point-line whose line points coincide); collinear plane points of a depth;
        an area polygon whose points are all collinear.
    """
    kind_spec(kind)  # an unknown kind is refused before the shape is looked at
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise BadInputError(f"{kind} needs points of shape (n, 3), got {p.shape}")
    n = p.shape[0]
    check_count(kind, n)
    if not np.all(np.isfinite(p)):
        bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1)) + 1
        raise BadInputError(
            f"{kind}: point(s) {', '.join(map(str, bad))} could not be triangulated",
            hint="check that each point is seen in both halves",
        )
    if kind in ("length", "polyline", "area"):
        ring = kind == "area"
        nxt = np.roll(p, -1, axis=0) if ring else p[1:]
        cur = p if ring else p[:-1]
        short = np.flatnonzero(_norm(nxt - cur) < COINCIDENT_MM)
        if short.size:
            i = int(short[0])
            raise BadInputError(
                f"{kind}: points {i + 1} and {(i + 1) % n + 1} coincide",
                hint="pick distinct points",
            )
    if kind == "point-line" and _norm(p[1] - p[0]) < COINCIDENT_MM:
        raise BadInputError(
            "point-line: the two points of the line coincide, so they define no line",
            hint="pick two distinct points for the line",
        )
    if kind == "depth" and _collinear(p[0], p[1], p[2]):
        raise BadInputError(
            "depth: the first three points are collinear, so they define no plane",
            hint="pick three reference points that span a triangle",
        )
    if kind == "depth":
        n = _cross(p[1] - p[0], p[2] - p[0])
        if abs(float(n @ (-p[0]))) <= COLLINEAR_SIN * _norm(n) * _norm(p[0]):
            raise BadInputError(
                "depth: the reference plane passes through the probe (seen edge-on), so "
                "its sides are undefined",
                hint="pick reference points on a surface that faces the probe",
            )
    if kind == "area" and all(_collinear(p[0], p[i], p[i + 1]) for i in range(1, n - 1)):
        raise BadInputError(
            "area: the points are collinear, so they enclose no area",
            hint="pick points around the region",
        )
    return p


def evaluate(kind: str, points: np.ndarray) -> np.ndarray:
    """The value of ``kind`` for points ``(..., n, 3)`` without validation (vectorised).

    Raises only for an unknown kind or a wrong point count (a programming error);
    degenerate sets give NaN or the limit value.
    """
    spec = kind_spec(kind)
    n = np.shape(points)[-2]
    if n < spec.min_points or (spec.max_points is not None and n > spec.max_points):
        raise BadInputError(f"{kind} needs {_count_hint(spec)} points, got {n}")
    return spec.function(points)


def measure(kind: str, points: np.ndarray) -> float:
    """Validate one set of points and return its ``kind`` value.

    Parameters
    ----------
    kind : str
    points : ndarray, shape (n, 3), mm

    Returns
    -------
    float
        mm, or mm^2 for ``area``.
    """
    points = validate(kind, points)
    return float(KINDS[kind].function(points))


# ----- the measurement plane --------------------------------------------------------------------

PLANE_POINTS = 3
"""A measurement plane is given by three points."""


def projected_points(kind: str, n: int) -> np.ndarray:
    """Which of a ``kind``'s ``n`` points a measurement plane places (bool (n,)): the 4th
    of a depth (its first three span the reference plane), every point of the others."""
    kind_spec(kind)
    mask = np.ones(n, dtype=bool)
    if kind == "depth":
        mask[:3] = False
    return mask


def plane_of(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane through three triangulated points, ``normal . x = distance``.

    Parameters
    ----------
    points : ndarray, shape (3, 3), mm

    Returns
    -------
    normal : ndarray, shape (3,)
        Unit normal.
    distance : float, mm

    Raises
    ------
    BadInputError
        Non-finite or collinear points (:data:`COLLINEAR_SIN`).
    """
    from endomeasure.geometry.rays import plane_through

    p = np.asarray(points, dtype=np.float64)
    if p.shape != (PLANE_POINTS, 3) or not np.all(np.isfinite(p)):
        raise BadInputError(f"a measurement plane needs {PLANE_POINTS} finite points (3,)")
    if _collinear(p[0], p[1], p[2]):
        raise BadInputError(
            "--plane: the three plane points are collinear, so they define no plane",
            hint="pick three plane points that span a triangle",
        )
    normal, distance = plane_through(p[0], p[1], p[2])
    return normal, float(distance)


def ray_plane(
    origins: np.ndarray,
    directions: np.ndarray,
    normal: np.ndarray,
    distance: float,
    first: int = 1,
) -> np.ndarray:
    """Where rays meet a measurement plane, refusing rays that cannot.

    Parameters
    ----------
    origins, directions : ndarray, shape (m, 3)
        Rays (mm, unit directions; non-central: one origin each).
    normal : ndarray, shape (3,)
        Unit normal of the plane ``normal . x = distance`` (:func:`plane_of`).
    distance : float, mm
    first : int
        The number of the first ray's point, for the messages.

    Returns
    -------
    ndarray, shape (m, 3), mm

    Raises
    ------
    BadInputError
        A ray parallel to the plane (the sine of its angle to the plane at most
        :data:`COLLINEAR_SIN`, the degenerate geometry of three collinear points), or
        meeting it behind its origin (the plane lies behind the probe there).

    Notes
    -----
    ``t = (distance - normal . o) / (normal . d)``, point ``o + t d`` with ``t > 0``.
    """
    from endomeasure.geometry.rays import intersect_plane

    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    sine = np.abs(d @ normal)
    for i in np.flatnonzero(~(sine > COLLINEAR_SIN)):
        raise BadInputError(
            f"--plane: the ray of point {first + i} is parallel to the plane, so it meets it "
            "nowhere (or everywhere)",
            hint="pick plane points on the surface the point lies on, facing the probe",
        )
    hit = intersect_plane(o, d, normal, distance)
    for i in np.flatnonzero(~(hit.t > 0)):
        raise BadInputError(
            f"--plane: the ray of point {first + i} meets the plane behind the probe",
            hint="pick plane points on the surface the point lies on, facing the probe",
        )
    return hit.points
