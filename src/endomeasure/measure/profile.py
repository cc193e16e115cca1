"""Depth profiles of a dense surface against a reference plane (SPEC section 7, issue 20).

The videoscopes' *Depth Profile* and *Area Depth Profile*:

- ``profile``: the surface's height along the left-half pixel path between two points,
  against a reference plane: the plane through three reference points
  (:func:`plane_through_points`), or the robust best fit to the dense points near the
  path's two ends (:func:`plane_fit`), which the operator puts on the undamaged
  surface. The deepest and the highest sample, with their +- and their position, and the
  gaps where the surface has no depth.
- ``area-profile``: ``slices`` profiles between two reference lines (two points each,
  either side of a defect), evenly spaced along the lines; the reference plane is the
  best fit to the dense points along both lines (or the three reference points).

Sign convention: that of :mod:`endomeasure.measure.kinds` -- the plane's normal points
towards the probe (the model-frame origin) and a height is **positive in front of the
plane** (a bump towards the viewer) and negative behind it (the bottom of a pit).

Uncertainty
-----------
A plane is three numbers ``theta = (a, b, c)`` in a local frame ``(e1, e2, n0)`` about a
point ``o`` of it: the points ``o + u e1 + v e2 + (a u + b v + c) n0``. Its covariance
comes from the covariances of the points it was made of, by the unscented transform
(:func:`~endomeasure.solvers.uncertainty.unscented`) of the plane construction: the
variances of ``a, b, c`` and of their pairwise sums give the 3x3 covariance. A sample's
height then is the UT of ``(theta, t)``, ``t`` the sample's offset along its own ray
(1-sigma ``sigma_point`` of the dense surface), so both the plane's and the point's
uncertainty enter, to second order.

The dense points of a best-fit plane are not independent: a dense depth comes from a
correlation window, so the errors of pixels closer than a window are nearly the same
error. The fit's covariance treats each reference area as ``max(1, N / window^2)``
independent measurements of ``N`` pixels, not ``N``.

The extreme samples are samples: the deepest point of a profile is the deepest *sample*,
whose error is its own sigma; a gap next to it is reported (``at_gap``), since the true
extreme may lie inside the gap.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.errors import BadInputError
from endomeasure.measure.kinds import COLLINEAR_SIN

if TYPE_CHECKING:
    from endomeasure.measure.dense import DenseSurface
    from endomeasure.models.base import CameraModel

__all__ = [
    "ReferencePlane",
    "ProfileSample",
    "Extreme",
    "Profile",
    "AreaProfile",
    "plane_through_points",
    "plane_fit",
    "path_pixels",
    "profile_of",
    "area_profile_of",
    "slice_ends",
    "point_covariances",
    "disc_pixels",
    "line_pixels",
    "MIN_VALID_SAMPLES",
    "OUTLIER_SIGMAS",
]

MIN_VALID_SAMPLES = 3
"""The fewest samples with a depth that make a profile: an extreme between two others."""
OUTLIER_SIGMAS = 3.0
"""A best-fit point farther from the plane than this many robust standard deviations
(1.4826 MAD, the Gaussian-consistent scale) is an outlier: 0.27 % of Gaussian errors."""
_MAD_SCALE = 1.4826
_FIT_ROUNDS = 10
"""Rounds of the trimmed fit; it stops earlier once the inlier set repeats."""
_FIT_POINTS_PER_AREA = 150
"""Most dense points one reference area (an end disc, a line) puts into the fit's
unscented transform (a regular subsample beyond): its cost grows with the count, and the
correlation over a window makes more of them carry no more information."""


# ----- the reference plane ------------------------------------------------------------------


class ReferencePlane(NamedTuple):
    """A reference plane with its covariance (see the module notes).

    ``origin`` (3,) mm, ``normal`` (3,) unit towards the probe, ``axes`` (2, 3) the
    in-plane ``e1, e2``; ``cov`` (3, 3) of ``theta = (a, b, c)`` (tilts, 1, and offset,
    mm) about ``theta = 0``; ``source`` ``"three points"`` or ``"best fit"``; ``points``
    the number of points fitted and ``rejected`` the outliers left out; ``rms_mm`` the
    fit's RMS distance of the inliers (0 for three points).
    """

    origin: np.ndarray
    normal: np.ndarray
    axes: np.ndarray
    cov: np.ndarray
    source: str
    points: int
    rejected: int
    rms_mm: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "origin_mm": self.origin.tolist(),
            "normal": self.normal.tolist(),
            "offset_sigma_mm": float(math.sqrt(max(self.cov[2, 2], 0.0))),
            "tilt_sigma_rad": [float(math.sqrt(max(self.cov[i, i], 0.0))) for i in (0, 1)],
            "points": self.points,
            "rejected": self.rejected,
            "rms_mm": self.rms_mm,
        }


def _frame(origin: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``normal`` oriented towards the probe and in-plane axes (2, 3)."""
    n = normal / np.linalg.norm(normal)
    if n @ (-origin) < 0:
        n = -n
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return n, np.stack([e1, np.cross(n, e1)])


def _local(points: np.ndarray, origin, normal, axes) -> np.ndarray:
    """Local coordinates ``(u, v, w)`` (..., 3) of points in the frame ``(e1, e2, n0)``."""
    rel = np.asarray(points) - origin
    return np.stack([rel @ axes[0], rel @ axes[1], rel @ normal], axis=-1)


def _theta_of_normal(n_local: np.ndarray, w_offset: np.ndarray) -> np.ndarray:
    """``theta`` (..., 3) of the plane with local normal ``n_local`` (..., 3) through the
    local point whose ``n_local . x`` is ``w_offset`` (...)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        n3 = n_local[..., 2]
        return np.stack([-n_local[..., 0] / n3, -n_local[..., 1] / n3, w_offset / n3], axis=-1)


def _theta_three(local: np.ndarray) -> np.ndarray:
    """``theta`` (..., 3) of the plane through three local points (..., 3, 3)."""
    n = np.cross(local[..., 1, :] - local[..., 0, :], local[..., 2, :] - local[..., 0, :])
    return _theta_of_normal(n, np.sum(n * local[..., 0, :], axis=-1))


def _theta_fit(local: np.ndarray) -> np.ndarray:
    """``theta`` (..., 3) of the least-squares (orthogonal) plane of local points (..., N, 3)."""
    centre = local.mean(axis=-2)
    rel = local - centre[..., None, :]
    scatter = np.einsum("...ni,...nj->...ij", rel, rel)
    _, vectors = np.linalg.eigh(scatter)
    n = vectors[..., :, 0]  # the smallest eigenvalue's vector
    n = n * np.where(n[..., 2] < 0, -1.0, 1.0)[..., None]
    return _theta_of_normal(n, np.sum(n * centre, axis=-1))


_COMBINATIONS = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]], dtype=np.float64
)
"""Rows: the combinations of ``theta`` whose variances give its covariance."""


def _covariance_from_variances(var: np.ndarray) -> np.ndarray:
    """The 3x3 covariance from the variances of :data:`_COMBINATIONS` (nearest PSD)."""
    cov = np.diag(var[:3])
    for k, (i, j) in zip((3, 4, 5), ((0, 1), (0, 2), (1, 2)), strict=True):
        cov[i, j] = cov[j, i] = 0.5 * (var[k] - var[i] - var[j])
    values, vectors = np.linalg.eigh(cov)
    return (vectors * np.maximum(values, 0.0)) @ vectors.T


def _theta_covariance(theta_of, x0: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of ``theta_of(X (..., L)) -> (..., 3)`` at ``x0`` (L,) by the
    unscented transform of each combination of :data:`_COMBINATIONS`."""
    from endomeasure.solvers.uncertainty import unscented

    def f(X):  # X (6, K, L): row m is combination m
        return np.einsum("mkj,mj->mk", theta_of(X), _COMBINATIONS)

    prop = unscented(f, np.broadcast_to(x0, (6, x0.size)).copy(), cov, cross=None)
    if not np.all(np.isfinite(prop.std)):
        raise BadInputError(
            "the reference plane's uncertainty cannot be propagated (its points are nearly "
            "collinear or seen edge-on)",
            hint="pick reference points that span a triangle facing the probe",
        )
    return _covariance_from_variances(prop.std**2)


def _check_faces_probe(origin: np.ndarray, normal: np.ndarray) -> None:
    if abs(float(normal @ origin)) <= COLLINEAR_SIN * float(np.linalg.norm(origin)):
        raise BadInputError(
            "the reference plane passes through the probe (seen edge-on), so its sides are "
            "undefined",
            hint="pick reference points on a surface that faces the probe",
        )


def plane_through_points(points: np.ndarray, covariances: np.ndarray) -> ReferencePlane:
    """The reference plane through three points, with its covariance.

    Parameters
    ----------
    points : ndarray, shape (3, 3), mm
    covariances : ndarray, shape (3, 3, 3), mm^2
        Each point's covariance.

    Raises
    ------
    BadInputError
        Non-finite or collinear points (:data:`~endomeasure.measure.kinds.COLLINEAR_SIN`,
        as a depth's reference plane), or a plane through the probe.
    """
    from endomeasure.measure.kinds import _collinear

    p = np.asarray(points, dtype=np.float64)
    if p.shape != (3, 3) or not np.all(np.isfinite(p)):
        raise BadInputError("a reference plane needs three finite points")
    if _collinear(p[0], p[1], p[2]):
        raise BadInputError(
            "the three reference points are collinear, so they define no plane",
            hint="pick three --ref points that span a triangle on the undamaged surface",
        )
    origin = p.mean(axis=0)
    normal, axes = _frame(origin, np.cross(p[1] - p[0], p[2] - p[0]))
    _check_faces_probe(origin, normal)
    cov = np.zeros((9, 9))
    for i in range(3):
        cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = covariances[i]

    def theta_of(X):
        return _theta_three(_local(X.reshape(*X.shape[:-1], 3, 3), origin, normal, axes))

    theta_cov = _theta_covariance(theta_of, p.reshape(-1), cov)
    return ReferencePlane(origin, normal, axes, theta_cov, "three points", 3, 0, 0.0)


class _Area(NamedTuple):
    points: np.ndarray  # (N, 3) mm
    directions: np.ndarray  # (N, 3) unit ray directions
    sigma: np.ndarray  # (N,) mm along the ray


def plane_fit(
    areas: list[tuple[np.ndarray, np.ndarray, np.ndarray]], window_px: int
) -> ReferencePlane:
    """The robust best-fit plane of the dense points of reference areas.

    Parameters
    ----------
    areas : list of (points (N, 3) mm, directions (N, 3), sigma (N,) mm)
        The valid dense points of each reference area (an end disc, a reference line),
        their ray directions and 1-sigma along the ray.
    window_px : int
        The dense search's correlation window: the correlation length of its errors.

    Returns
    -------
    ReferencePlane
        Fitted to the inliers (orthogonal least squares after trimming at
        :data:`OUTLIER_SIGMAS` robust sigmas), with the covariance of the module notes.

    Raises
    ------
    BadInputError
        An area without three valid points, or all points on a line.
    """
    for k, (p, _, _) in enumerate(areas, 1):
        if len(p) < 3:
            raise BadInputError(
                f"reference area {k} has {len(p)} points with a depth, too few for a plane",
                hint="put the ends (or lines) on textured, undamaged surface both halves see, "
                "or give three --ref points",
            )
    pts = np.concatenate([a[0] for a in areas])
    keep = np.ones(len(pts), dtype=bool)
    for _ in range(_FIT_ROUNDS):
        origin = pts[keep].mean(axis=0)
        _, s, vt = np.linalg.svd(pts[keep] - origin, full_matrices=False)
        if s[1] <= COLLINEAR_SIN * s[0]:
            raise BadInputError(
                "the reference points lie on a line, so they define no plane",
                hint="give three --ref points that span a triangle",
            )
        dist = (pts - origin) @ vt[2]
        resid = dist[keep]
        scale = _MAD_SCALE * np.median(np.abs(resid - np.median(resid)))
        new = np.abs(dist - np.median(resid)) <= OUTLIER_SIGMAS * scale if scale > 0 else keep
        if np.array_equal(new, keep) or new.sum() < 3:
            break
        keep = new
    origin = pts[keep].mean(axis=0)
    normal, axes = _frame(origin, np.linalg.svd(pts[keep] - origin, full_matrices=False)[2][2])
    _check_faces_probe(origin, normal)
    rms = float(np.sqrt(np.mean(((pts[keep] - origin) @ normal) ** 2)))
    # the uncertainty: each area's inliers, subsampled, propagated alone (at their own
    # sigma, so that the sigma points stay where the fit is linear) and its covariance
    # scaled to max(1, N / window^2) independent measurements of the N inliers
    used, scale, start = [], [], 0
    for p, d, s in areas:
        inl = np.flatnonzero(keep[start : start + len(p)])
        start += len(p)
        pick = inl[:: max(1, math.ceil(inl.size / _FIT_POINTS_PER_AREA))]
        used.append(_Area(p[pick], d[pick], s[pick]))
        scale.append(pick.size / max(1.0, inl.size / window_px**2))
    p0 = np.concatenate([a.points for a in used])
    d0 = np.concatenate([a.directions for a in used])
    sizes = np.cumsum([0] + [len(a.points) for a in used])

    def theta_of(X):  # X (..., N): each point's offset along its ray
        moved = p0 + X[..., None] * d0
        return _theta_fit(_local(moved, origin, normal, axes))

    theta_cov = np.zeros((3, 3))
    for k, area in enumerate(used):
        var = np.zeros(len(p0))
        var[sizes[k] : sizes[k + 1]] = area.sigma**2
        theta_cov += scale[k] * _theta_covariance(theta_of, np.zeros(len(p0)), np.diag(var))
    return ReferencePlane(origin, normal, axes, theta_cov, "best fit", int(keep.sum()),
                          int((~keep).sum()), rms)  # fmt: skip


# ----- reference-point covariances ----------------------------------------------------------


def point_covariances(model, ql, qr, noise, param_cov=None, misfit=None) -> np.ndarray:
    """Covariances (n, 3, 3), mm^2, of triangulated points, by the unscented transform of
    their pixels' noise (an :class:`~endomeasure.measure.predict.ImageNoise` of the n
    points), the calibration covariance and the model misfit, as ``measure`` predicts a
    measurement's +-: the variances of x, y, z and of their pairwise sums."""
    from endomeasure.solvers.uncertainty import MeasurementFunction, propagate

    ql = np.asarray(ql, dtype=np.float64)
    qr = np.asarray(qr, dtype=np.float64)
    out = np.empty((ql.shape[0], 3, 3))
    offsets = misfit is not None and misfit.present
    for i in range(ql.shape[0]):
        one = (
            noise
            if noise.pixel_std is None
            else type(noise).per_point(noise.pixel_std[i : i + 1], noise.source)
        )
        model_cov = misfit.covariance(ql[i : i + 1]) if offsets else None
        cov, blocks = one.covariance(1, param_cov, model_cov)
        var = []
        for c in _COMBINATIONS:
            f = MeasurementFunction(
                model, lambda p, c=c: p[..., 0, :] @ c, 1,
                with_params=param_cov is not None, with_offsets=offsets,
            )  # fmt: skip
            x0 = f.inputs(ql[i : i + 1][None], qr[i : i + 1][None])
            var.append(float(propagate(f, x0, cov, "ut", blocks=blocks).std[0] ** 2))
        out[i] = _covariance_from_variances(np.array(var))
    return out


# ----- paths on the dense surface -------------------------------------------------------------


def path_pixels(start, end, samples: int | None = None) -> np.ndarray:
    """Pixels (n, 2) of the straight left-half path from ``start`` to ``end``: ``samples``
    points, by default about one per pixel (``ceil(length) + 1``)."""
    a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    length = float(np.linalg.norm(b - a))
    if length < 1.0:
        raise BadInputError(
            f"the path's two points {a[0]:g},{a[1]:g} and {b[0]:g},{b[1]:g} are less than a "
            "pixel apart",
            hint="pick two distinct points either side of the defect",
        )
    n = int(math.ceil(length)) + 1 if samples is None else int(samples)
    if n < MIN_VALID_SAMPLES:
        raise BadInputError(f"a profile needs at least {MIN_VALID_SAMPLES} samples, not {n}")
    return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)


def disc_pixels(centre, radius: float) -> np.ndarray:
    """Integer pixels (n, 2) within ``radius`` of ``centre``."""
    c = np.asarray(centre, dtype=np.float64)
    r = int(math.ceil(radius))
    du, dv = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1))
    base = np.rint(c)
    pix = np.stack([base[0] + du.ravel(), base[1] + dv.ravel()], -1)
    return pix[np.hypot(pix[:, 0] - c[0], pix[:, 1] - c[1]) <= radius]


def line_pixels(start, end) -> np.ndarray:
    """The distinct nearest pixels (n, 2) of the segment ``start``-``end``."""
    pix = np.rint(path_pixels(start, end))
    _, first = np.unique(pix, axis=0, return_index=True)
    return pix[np.sort(first)]


def _lookup(surface: DenseSurface, pixels: np.ndarray):
    """Row/column indices of the nearest region pixel of each pixel and whether it is
    inside the region."""
    u0, v0, u1, v1 = surface.region
    iu = np.rint(pixels[:, 0]).astype(np.int64) - u0
    iv = np.rint(pixels[:, 1]).astype(np.int64) - v0
    inside = (iu >= 0) & (iu < u1 - u0) & (iv >= 0) & (iv < v1 - v0)
    return np.clip(iv, 0, v1 - v0 - 1), np.clip(iu, 0, u1 - u0 - 1), inside


def area_points(model: CameraModel, surface: DenseSurface, pixels: np.ndarray):
    """The valid dense points (N, 3), their ray directions and sigma at ``pixels``."""
    from endomeasure.measure.dense import DenseStatus

    iv, iu, inside = _lookup(surface, pixels)
    ok = inside & (surface.status[iv, iu] == DenseStatus.OK)
    rays = model.rays(np.stack([iu[ok] + surface.region[0], iv[ok] + surface.region[1]], -1)
                      .astype(np.float64), Half.LEFT)  # fmt: skip
    return surface.points[iv[ok], iu[ok]], rays.directions, surface.sigma_point[iv[ok], iu[ok]]


# ----- one profile ------------------------------------------------------------------------------


class ProfileSample(NamedTuple):
    """The samples of a profile (arrays (n,)): pixel (n, 2) px, ``status`` the dense
    status of its pixel (0 with a depth), ``height``/``sigma`` mm (NaN in gaps),
    ``position_mm`` along the path in the reference plane, ``position_px``."""

    pixels: np.ndarray
    status: np.ndarray
    height: np.ndarray
    sigma: np.ndarray
    sigma_plane: np.ndarray
    position_mm: np.ndarray
    position_px: np.ndarray
    points: np.ndarray  # (n, 3) mm, NaN in gaps


class Extreme(NamedTuple):
    """The deepest or highest sample: its index, height +- sigma, position, pixel, and
    whether a gap (or the path's end beyond a gap) touches it."""

    index: int
    height_mm: float
    sigma_mm: float
    position_mm: float
    position_px: float
    pixel: tuple[float, float]
    at_gap: bool

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "height_mm": self.height_mm,
            "sigma_mm": self.sigma_mm,
            "position_mm": self.position_mm,
            "position_px": self.position_px,
            "pixel": list(self.pixel),
            "at_gap": self.at_gap,
        }


class Profile(NamedTuple):
    """A profile: its samples, the deepest and highest, the gaps (runs of samples
    without depth: first and last index), the share of samples with a depth and the
    path's length in the reference plane."""

    samples: ProfileSample
    deepest: Extreme
    highest: Extreme
    gaps: list[tuple[int, int]]
    coverage: float
    length_mm: float

    @property
    def extreme(self) -> Extreme:
        """The deepest or the highest, whichever is farther from the plane."""
        return self.deepest if -self.deepest.height_mm >= self.highest.height_mm else self.highest

    def to_dict(self, samples: bool = True) -> dict[str, Any]:
        from endomeasure.measure.dense import DenseStatus

        s = self.samples
        out: dict[str, Any] = {
            "deepest": self.deepest.to_dict(),
            "highest": self.highest.to_dict(),
            "coverage": self.coverage,
            "length_mm": self.length_mm,
            "gaps": [
                {
                    "first": a,
                    "last": b,
                    "from_px": float(s.position_px[a]),
                    "to_px": float(s.position_px[b]),
                    "reasons": sorted({DenseStatus(int(k)).label for k in s.status[a : b + 1]}),
                }
                for a, b in self.gaps
            ],  # fmt: skip
        }
        if samples:
            out["samples"] = {
                "pixel": s.pixels.tolist(),
                "status": s.status.astype(int).tolist(),
                "height_mm": s.height.tolist(),
                "sigma_mm": s.sigma.tolist(),
                "sigma_plane_mm": s.sigma_plane.tolist(),
                "position_mm": s.position_mm.tolist(),
                "position_px": s.position_px.tolist(),
            }
        return out


def _heights(local: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Signed distance of local points (..., 3) from the plane ``theta`` (..., 3)."""
    a, b, c = theta[..., 0], theta[..., 1], theta[..., 2]
    return (local[..., 2] - a * local[..., 0] - b * local[..., 1] - c) / np.sqrt(1 + a * a + b * b)


def _on_plane(model, plane: ReferencePlane, pixels: np.ndarray) -> np.ndarray:
    """Where the left rays of ``pixels`` meet the plane (NaN where they do not)."""
    rays = model.rays(pixels, Half.LEFT)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((plane.origin - rays.origins) @ plane.normal) / (rays.directions @ plane.normal)
    hit = np.where(((rays.status == Status.OK) & (t > 0))[:, None],
                   rays.origins + t[:, None] * rays.directions, np.nan)  # fmt: skip
    return hit


def _gaps(valid: np.ndarray) -> list[tuple[int, int]]:
    runs, start = [], None
    for i, ok in enumerate(valid):
        if not ok and start is None:
            start = i
        if ok and start is not None:
            runs.append((start, i - 1))
            start = None
    if start is not None:
        runs.append((start, valid.size - 1))
    return runs


def profile_of(
    model: CameraModel, surface: DenseSurface, plane: ReferencePlane, pixels: np.ndarray
) -> Profile:
    """The profile of ``surface`` along left-half ``pixels`` (n, 2) against ``plane``.

    Each sample takes the dense point of its nearest pixel (never interpolated across a
    pixel without depth). ``position_mm`` is the distance, along the path's direction in
    the plane, from where the first pixel's ray meets the plane.

    Raises
    ------
    BadInputError
        Fewer than :data:`MIN_VALID_SAMPLES` samples have a depth (the region is
        untextured, not seen by the right half, or outside the dense region).
    """
    from endomeasure.measure.dense import DenseStatus
    from endomeasure.solvers.uncertainty import unscented

    pixels = np.asarray(pixels, dtype=np.float64)
    iv, iu, inside = _lookup(surface, pixels)
    status = np.where(inside, surface.status[iv, iu], DenseStatus.NOT_SEEN).astype(np.uint8)
    valid = status == DenseStatus.OK
    if valid.sum() < MIN_VALID_SAMPLES:
        reasons = sorted({DenseStatus(int(k)).label for k in status[~valid]})
        raise BadInputError(
            f"the profile has a depth at {int(valid.sum())} of {valid.size} samples, fewer "
            f"than {MIN_VALID_SAMPLES} ({', '.join(reasons)}): no profile",
            hint="draw the path over textured surface both halves see",
        )
    points = np.where(valid[:, None], surface.points[iv, iu], np.nan)
    sigma_t = np.where(valid, surface.sigma_point[iv, iu], np.nan)
    directions = model.rays(pixels, Half.LEFT).directions
    # heights and sigma: UT of (theta, t), theta about 0 with the plane's covariance
    local = _local(points[valid], plane.origin, plane.normal, plane.axes)
    d_local = directions[valid] @ np.stack([*plane.axes, plane.normal]).T
    x0 = np.zeros((local.shape[0], 4))
    cov = np.zeros((local.shape[0], 4, 4))
    cov[:, :3, :3] = plane.cov
    cov[:, 3, 3] = sigma_t[valid] ** 2

    def f(X):  # X (M, K, 4)
        moved = local[:, None, :] + X[..., 3:4] * d_local[:, None, :]
        return _heights(moved, X[..., :3])

    prop = unscented(f, x0, cov, blocks={"plane": slice(0, 3), "surface": slice(3, 4)})
    height = np.full(valid.size, np.nan)
    sigma = np.full(valid.size, np.nan)
    sigma_plane = np.full(valid.size, np.nan)
    height[valid], sigma[valid] = prop.value, prop.std
    if "plane" in prop.parts:
        sigma_plane[valid] = prop.parts["plane"][1]
    # positions: along the path's direction in the plane, from the first pixel's ray
    ends = _on_plane(model, plane, pixels[[0, -1]])
    axis = ends[1] - ends[0]
    length = float(np.linalg.norm(axis))
    rel = np.where(valid[:, None], points, _on_plane(model, plane, pixels)) - ends[0]
    in_plane = rel - np.outer(rel @ plane.normal, plane.normal)
    position_mm = in_plane @ (axis / length) if length > 0 else np.full(valid.size, np.nan)
    position_px = np.linalg.norm(pixels - pixels[0], axis=1)
    samples = ProfileSample(pixels, status, height, sigma, sigma_plane, position_mm,
                            position_px, points)  # fmt: skip
    gaps = _gaps(valid)

    def extreme(i: int) -> Extreme:
        touching = (i > 0 and not valid[i - 1]) or (i < valid.size - 1 and not valid[i + 1])
        return Extreme(
            int(i), float(height[i]), float(sigma[i]), float(position_mm[i]),
            float(position_px[i]), tuple(map(float, pixels[i])), bool(touching),
        )  # fmt: skip

    return Profile(
        samples,
        extreme(int(np.nanargmin(height))),
        extreme(int(np.nanargmax(height))),
        gaps,
        float(valid.mean()),
        length,
    )


# ----- area profiles ------------------------------------------------------------------------------


class AreaProfile(NamedTuple):
    """The slices of an area profile and the one holding the overall extreme."""

    slices: list[Profile]
    ends: np.ndarray  # (N, 2, 2) px: each slice's start and end pixel
    extreme_slice: int

    @property
    def extreme(self) -> Extreme:
        return self.slices[self.extreme_slice].extreme


def slice_ends(line1: np.ndarray, line2: np.ndarray, slices: int) -> np.ndarray:
    """Start and end pixels (N, 2, 2) of ``slices`` slices from line 1 to line 2, at the
    same fractions (evenly spaced, ends included) along both lines."""
    if slices < 1:
        raise BadInputError(f"an area profile needs at least one slice, not {slices}")
    f = np.linspace(0.0, 1.0, slices) if slices > 1 else np.array([0.5])
    a = line1[0] + f[:, None] * (line1[1] - line1[0])
    b = line2[0] + f[:, None] * (line2[1] - line2[0])
    return np.stack([a, b], axis=1)


def area_profile_of(
    model: CameraModel,
    surface: DenseSurface,
    plane: ReferencePlane,
    ends: np.ndarray,
    samples: int | None = None,
) -> AreaProfile:
    """Profiles of ``surface`` between the slice ends (N, 2, 2) px against ``plane``.

    Raises
    ------
    BadInputError
        A slice without :data:`MIN_VALID_SAMPLES` samples with a depth: the area's
        extreme is not known while a slice of it has no profile.
    """
    profiles, refused = [], []
    for k, (a, b) in enumerate(ends):
        try:
            profiles.append(profile_of(model, surface, plane, path_pixels(a, b, samples)))
        except BadInputError as exc:
            refused.append((k, exc))
            profiles.append(None)
    if not any(p is not None for p in profiles):
        raise BadInputError(
            f"no slice of the area profile has a depth at {MIN_VALID_SAMPLES} samples or "
            f"more ({refused[0][1].what})",
            hint="put the region over textured surface both halves see",
        )
    if refused:
        k, exc = refused[0]
        raise BadInputError(
            f"slice {k + 1} of {len(ends)} has no profile: {exc.what}",
            hint="move the reference lines so that every slice crosses textured surface, "
            "or use fewer --slices",
        )
    size = [max(-p.deepest.height_mm, p.highest.height_mm) for p in profiles]
    return AreaProfile(profiles, np.asarray(ends), int(np.argmax(size)))
