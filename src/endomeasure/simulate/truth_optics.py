"""The simulator's own ground-truth optics: a lens and a biprism traced by code of its own.

The probe the simulator renders must not be the model later fitted to its images, or no
test ever meets optics the model does not share. This module traces the truth with its
own lens maps, ray-plane intersections, vector Snell's law and ray-aiming solver; it
imports nothing from :mod:`endomeasure.models`. It holds effects the calibrated models
lack:

- lens distortion defined in either direction (``ray_to_pixel``: Brown-Conrady on the
  ideal ray, radial up to ``r^8`` and tangential ``p1 p2``; ``pixel_to_ray``: the same
  polynomial form taking the distorted normalised coordinates to the ideal ones, as
  some lens designs specify it), with an off-centre principal point;
- an entrance pupil that moves along the axis with the field angle: the lens ray of
  field angle ``theta`` starts at ``(0, 0, pupil_shift_mm (theta / theta_edge)^2)``;
- a prism of three general planes (rear, left front, right front), each with its own
  unit normal and distance, glass index ``n``; TIR and missed faces flagged per ray.

Backward (:meth:`TruthOptics.rays`) is closed form after the lens map's inverse (Newton,
checked per pixel); forward (:meth:`TruthOptics.project`) aims rays by Newton's method on
the ideal lens coordinates with a central-difference Jacobian, converged per point.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property
from typing import NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status, in_half

__all__ = [
    "DISTORTION_DIRECTIONS",
    "LensMap",
    "TruthLens",
    "Plane",
    "TruthConfig",
    "TruthRays",
    "TracePath",
    "TruthProjection",
    "TruthOptics",
    "refract_vectors",
    "AIM_TOL_PX",
]

DISTORTION_DIRECTIONS = ("ray_to_pixel", "pixel_to_ray")

AIM_TOL_PX = 1e-11
"""Ray aiming stops when the pixel step falls below this, px (double precision on lens
coordinates of order 1 and focal lengths of order 1000 px allows about 1e-12 px)."""
AIM_MAX_ITER = 60
_AIM_RESTARTS = 3  # further starts (the next nearest grid rays) for points aiming missed
_RESTART_MISS = 0.05  # restart where the stalled ray misses by under this fraction of z
_AIM_HALVINGS = 10  # step halvings before aiming gives up on a point (no descent left)
AIM_FD_STEP = 1e-7  # central-difference step on the ideal lens coordinates (normalised)
LENS_TOL = 1e-15  # Newton tolerance of the lens map inverse, normalised units
LENS_MAX_ITER = 40
_START_GRID = (33, 25)  # backward-traced pixels per half that seed ray aiming
_APEX_SCAN = 513  # columns scanned per row for the apex crossing


class TruthRays(NamedTuple):
    """Object-space rays: origins (N, 3) mm on the exit face, unit directions, status."""

    origins: np.ndarray
    directions: np.ndarray
    status: np.ndarray  # (N,) uint8 Status


class TracePath(NamedTuple):
    """The segments of a trace, each (N, 3): lens ray, inside the glass, object space."""

    lens_origins: np.ndarray  # on the axis (the pupil point of each ray's field angle), mm
    lens_directions: np.ndarray
    rear_points: np.ndarray  # where the ray enters the glass, mm
    glass_directions: np.ndarray
    front_points: np.ndarray  # where it leaves through the half's front face, mm
    out_directions: np.ndarray
    status: np.ndarray  # (N,) uint8 Status


class TruthProjection(NamedTuple):
    """Pixels (N, 2) px, NaN where the status (N,) is not OK."""

    pixels: np.ndarray
    status: np.ndarray


def _poly_map(x, y, radial, p1, p2):
    """Brown-Conrady form ``(x, y) -> (x R(r^2) + tangential)`` and its Jacobian entries.

    ``R = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8`` with ``radial = (k1, k2, k3, k4)``;
    tangential ``(2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y)``.
    Returns ``mx, my, j11, j12, j21, j22``.
    """
    k1, k2, k3, k4 = radial
    r2 = x * x + y * y
    R = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    dR = k1 + r2 * (2.0 * k2 + r2 * (3.0 * k3 + r2 * 4.0 * k4))  # dR / d r^2
    mx = x * R + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    my = y * R + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    cross = 2.0 * x * y * dR + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = R + 2.0 * x * x * dR + 2.0 * p1 * y + 6.0 * p2 * x
    j22 = R + 2.0 * y * y * dR + 6.0 * p1 * y + 2.0 * p2 * x
    return mx, my, j11, cross, cross, j22


def _monotonic_radius(radial) -> float:
    """Largest radius up to which ``r R(r^2)`` grows (the radial map is one-to-one)."""
    k1, k2, k3, k4 = radial
    # d/dr [r R] = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 + 9 k4 s^4, s = r^2
    roots = np.roots([9.0 * k4, 7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]) if any(radial) else []
    positive = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-9 and r.real > 0]
    return float(np.sqrt(min(positive))) if positive else float("inf")


@dataclasses.dataclass(frozen=True)
class LensMap:
    """One polynomial lens map and its inverse on normalised coordinates.

    ``apply`` is the closed form; ``invert`` is Newton's method from the identity,
    converged per point, restricted to the one-to-one part of the radial map.
    """

    radial: tuple[float, float, float, float]
    p1: float
    p2: float

    @cached_property
    def max_radius(self) -> float:
        """Input radius beyond which the map folds (inf if never); inputs past it fail."""
        return _monotonic_radius(self.radial)

    def apply(self, x: np.ndarray, y: np.ndarray):
        mx, my, *_ = _poly_map(x, y, self.radial, self.p1, self.p2)
        return mx, my

    def invert(self, mx: np.ndarray, my: np.ndarray):
        """``(x, y, converged)`` with ``apply(x, y) = (mx, my)``."""
        mx = np.asarray(mx, dtype=np.float64)
        my = np.asarray(my, dtype=np.float64)
        x, y = mx.copy(), my.copy()
        done = np.zeros(mx.shape, dtype=bool)
        active = np.isfinite(mx) & np.isfinite(my)
        for _ in range(LENS_MAX_ITER):
            if not active.any():
                break
            fx, fy, j11, j12, j21, j22 = _poly_map(
                x[active], y[active], self.radial, self.p1, self.p2
            )
            ex, ey = fx - mx[active], fy - my[active]
            det = j11 * j22 - j12 * j21
            with np.errstate(divide="ignore", invalid="ignore"):
                sx = (j22 * ex - j12 * ey) / det
                sy = (j11 * ey - j21 * ex) / det
            x[active] -= sx
            y[active] -= sy
            small = np.maximum(np.abs(sx), np.abs(sy)) <= LENS_TOL * (1.0 + np.abs(mx[active]))
            idx = np.flatnonzero(active)
            done[idx[small]] = True
            active[idx[small | ~np.isfinite(sx + sy)]] = False
        done &= np.hypot(x, y) <= self.max_radius
        return np.where(done, x, np.nan), np.where(done, y, np.nan), done


@dataclasses.dataclass(frozen=True)
class TruthLens:
    """The truth lens: pinhole ``fx fy cx cy``, a distortion map in either direction and
    an entrance pupil moving along the axis with the field angle."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: LensMap
    direction: str = "ray_to_pixel"  # which way ``distortion`` maps (DISTORTION_DIRECTIONS)
    pupil_shift_mm: float = 0.0  # pupil z at the field edge, mm
    pupil_edge_rad: float = 1.0  # field angle theta_edge of the pupil law, rad

    def __post_init__(self):
        if self.direction not in DISTORTION_DIRECTIONS:
            raise ValueError(f"distortion direction must be one of {DISTORTION_DIRECTIONS}")
        if not (self.fx > 0 and self.fy > 0 and self.pupil_edge_rad > 0):
            raise ValueError("focal lengths and the pupil's edge angle must be positive")

    def ideal_to_pixel(self, x: np.ndarray, y: np.ndarray):
        """Pixels ``(u, v, ok)`` of ideal normalised lens coordinates (direction (x, y, 1))."""
        if self.direction == "ray_to_pixel":
            ok = np.hypot(x, y) <= self.distortion.max_radius
            xd, yd = self.distortion.apply(x, y)
        else:
            xd, yd, ok = self.distortion.invert(x, y)
        return self.fx * xd + self.cx, self.fy * yd + self.cy, ok

    def pixel_to_ideal(self, u: np.ndarray, v: np.ndarray):
        """Ideal normalised lens coordinates ``(x, y, ok)`` of pixels."""
        xd = (np.asarray(u, dtype=np.float64) - self.cx) / self.fx
        yd = (np.asarray(v, dtype=np.float64) - self.cy) / self.fy
        if self.direction == "ray_to_pixel":
            return self.distortion.invert(xd, yd)
        ok = np.hypot(xd, yd) <= self.distortion.max_radius
        x, y = self.distortion.apply(xd, yd)
        return x, y, ok & np.isfinite(x) & np.isfinite(y)

    def lens_rays(self, x: np.ndarray, y: np.ndarray):
        """Origins (N, 3) on the axis and unit directions (N, 3) of the lens rays.

        Notes
        -----
        Direction ``(x, y, 1) / |(x, y, 1)|``, field angle ``theta = atan(hypot(x, y))``,
        origin ``(0, 0, pupil_shift_mm (theta / pupil_edge_rad)^2)``.
        """
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.zeros_like(d)
        if self.pupil_shift_mm:
            theta = np.arctan(np.hypot(x, y))
            o[:, 2] = self.pupil_shift_mm * (theta / self.pupil_edge_rad) ** 2
        return o, d


@dataclasses.dataclass(frozen=True)
class Plane:
    """The plane ``normal . x = d`` (unit normal towards +z, the object side), mm."""

    normal: np.ndarray
    d: float

    @classmethod
    def make(cls, normal, d: float) -> Plane:
        n = np.asarray(normal, dtype=np.float64).reshape(3)
        n = n / np.linalg.norm(n)
        if n[2] <= 0:
            raise ValueError("a prism face's normal must point towards the object (n_z > 0)")
        return cls(n, float(d))


@dataclasses.dataclass(frozen=True)
class TruthConfig:
    """Image size (width, height) px and split (first column of the right half)."""

    image_size: tuple[int, int]
    split: int


def refract_vectors(d: np.ndarray, normal: np.ndarray, eta: float):
    """Vector Snell's law: refracted unit directions (N, 3) and a TIR flag (N,).

    Parameters
    ----------
    d : ndarray, shape (N, 3)
        Unit incident directions.
    normal : ndarray, shape (3,)
        Unit face normal, either orientation.
    eta : float
        ``n_incident / n_transmitted``.

    Notes
    -----
    With ``m`` the normal facing the incoming ray (``m . d < 0``), ``c = -m . d``:
    ``t = eta d + (eta c - sqrt(1 - eta^2 (1 - c^2))) m``; TIR where the root is negative.
    """
    cos_n = d @ normal
    m = np.where(cos_n[:, None] > 0, -normal, normal)
    c = np.abs(cos_n)
    k = 1.0 - eta * eta * (1.0 - c * c)
    tir = ~(k >= 0)
    root = np.sqrt(np.where(tir, 0.0, k))
    t = eta * d + (eta * c - root)[:, None] * m
    t[tir] = np.nan
    return t, tir


def _derivative(centre, plus, minus, h: float) -> np.ndarray:
    """Central difference, one-sided where a probe fell into TIR (next to its edge)."""
    out = (plus - minus) / (2 * h)
    bad = ~np.isfinite(out)
    out[bad] = np.where(np.isfinite(plus), plus - centre, centre - minus)[bad] / h
    return out


def _hit(o: np.ndarray, d: np.ndarray, plane: Plane):
    """Distance along unit rays to a plane (N,); NaN where the plane is behind or parallel."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane.d - o @ plane.normal) / (d @ plane.normal)
    return np.where(t > 0, t, np.nan)


@dataclasses.dataclass(frozen=True, eq=False)
class TruthOptics:
    """A lens behind a biprism: the simulator's ground truth (see the module docstring).

    ``rays`` and ``project`` follow the camera-model contract the renderer relies on:
    full-image pixels of a half, the half chosen by column against ``config.split``.
    """

    lens: TruthLens
    rear: Plane
    left: Plane
    right: Plane
    n_glass: float
    config: TruthConfig

    def __post_init__(self):
        if not self.n_glass > 1.0:
            raise ValueError("the glass index must exceed 1")

    def with_split(self, split: int) -> TruthOptics:
        return dataclasses.replace(self, config=TruthConfig(self.config.image_size, int(split)))

    def front(self, half: Half) -> Plane:
        return self.left if Half.parse(half) is Half.LEFT else self.right

    # ----- tracing -------------------------------------------------------------------
    def trace_path(self, x: np.ndarray, y: np.ndarray, half: Half) -> TracePath:
        """Every segment of the trace of ideal lens coordinates (N,) through the rear face
        and the half's front face (NaN where the status is not OK)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        status = np.full(x.size, Status.OK, dtype=STATUS_DTYPE)
        status[~(np.isfinite(x) & np.isfinite(y))] = Status.INVALID_INPUT
        o0, d0 = self.lens.lens_rays(np.nan_to_num(x), np.nan_to_num(y))
        t0 = _hit(o0, d0, self.rear)
        p1 = o0 + t0[:, None] * d0
        g, tir1 = refract_vectors(d0, self.rear.normal, 1.0 / self.n_glass)
        front = self.front(half)
        t1 = _hit(p1, g, front)
        p2 = p1 + t1[:, None] * g
        out, tir2 = refract_vectors(g, front.normal, self.n_glass)
        ok = status == Status.OK
        status[ok & ~np.isfinite(t0)] = Status.BEHIND
        status[(status == Status.OK) & tir1] = Status.TOTAL_INTERNAL_REFLECTION
        status[(status == Status.OK) & ~np.isfinite(t1)] = Status.BEHIND
        status[(status == Status.OK) & tir2] = Status.TOTAL_INTERNAL_REFLECTION
        bad = status != Status.OK
        for v in (p1, g, p2, out):
            v[bad] = np.nan
        return TracePath(o0, d0, p1, g, p2, out, status)

    def trace(self, x: np.ndarray, y: np.ndarray, half: Half) -> TruthRays:
        """Trace ideal lens coordinates (N,) through the rear face and the half's front face.

        Returns object-space rays leaving the front face; ``BEHIND`` where a face is
        missed, ``TOTAL_INTERNAL_REFLECTION`` where Snell's law has no solution.
        """
        path = self.trace_path(x, y, half)
        return TruthRays(path.front_points, path.out_directions, path.status)

    def rays(self, pixels: np.ndarray, half: Half | str) -> TruthRays:
        """Backward: the object-space ray each full-image pixel (N, 2) of a half sees."""
        half = Half.parse(half)
        q = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        x, y, ok = self.lens.pixel_to_ideal(q[:, 0], q[:, 1])
        traced = self.trace(np.where(ok, x, 0.0), np.where(ok, y, 0.0), half)
        status = traced.status.copy()
        status[~ok] = Status.NOT_CONVERGED
        status[~np.all(np.isfinite(q), axis=-1)] = Status.INVALID_INPUT
        inside = in_half(q, half, self.config.split, self.config.image_size)
        status[(status != Status.INVALID_INPUT) & ~inside] = Status.OUTSIDE_HALF
        bad = status != Status.OK
        o, d = traced.origins.copy(), traced.directions.copy()
        o[bad] = np.nan
        d[bad] = np.nan
        return TruthRays(o, d, status)

    # ----- forward: ray aiming ---------------------------------------------------------
    def _miss(self, x, y, points, half):
        """Offset (N, 2) mm of the traced ray from each point in the plane z = point z."""
        tr = self.trace(x, y, half)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (points[:, 2] - tr.origins[:, 2]) / tr.directions[:, 2]
        hit = tr.origins[:, :2] + s[:, None] * tr.directions[:, :2] - points[:, :2]
        hit[~(s > 0)] = np.nan
        return hit

    @cached_property
    def _starts(self) -> dict:
        """Per half: ideal lens coordinates and object rays of a coarse pixel grid."""
        width, height = self.config.image_size
        out = {}
        for half in Half:
            lo, hi = (-0.5, self.config.split - 0.5) if half is Half.LEFT else (
                self.config.split - 0.5, width - 0.5)  # fmt: skip
            uu, vv = np.meshgrid(
                np.linspace(lo, hi, _START_GRID[0] + 2)[1:-1],
                np.linspace(-0.5, height - 0.5, _START_GRID[1] + 2)[1:-1],
            )
            x, y, ok = self.lens.pixel_to_ideal(uu.ravel(), vv.ravel())
            tr = self.trace(x[ok], y[ok], half)
            good = tr.status == Status.OK
            out[half] = (x[ok][good], y[ok][good], tr.origins[good], tr.directions[good])
        return out

    def _start(self, points: np.ndarray, half: Half, rank: int = 0):
        """Lens coordinates of the grid ray passing ``rank``-th nearest each point (N, 3)."""
        x, y, o, d = self._starts[half]
        if x.size == 0:
            nan = np.full(points.shape[0], np.nan)
            return nan, nan.copy()
        best = np.empty(points.shape[0], dtype=np.int64)
        for i in range(0, points.shape[0], 4096):
            rel = points[i : i + 4096, None, :] - o[None]
            along = np.einsum("nkj,kj->nk", rel, d)
            dist2 = np.einsum("nkj,nkj->nk", rel, rel) - along**2
            dist2[along <= 0] = np.inf
            order = np.argpartition(dist2, min(rank, x.size - 1), axis=1)
            best[i : i + 4096] = order[:, min(rank, x.size - 1)]
        return x[best].copy(), y[best].copy()

    def _aim(self, points: np.ndarray, half: Half, rank: int = 0):
        """Ideal lens coordinates ``(x, y, converged)`` whose traced rays pass the points,
        aimed from the ``rank``-th nearest grid ray."""
        x, y = self._start(points, half, rank)
        n = points.shape[0]
        done = np.zeros(n, dtype=bool)
        active = np.isfinite(x)
        scale = max(self.lens.fx, self.lens.fy)
        h = AIM_FD_STEP
        for _ in range(AIM_MAX_ITER):
            idx = np.flatnonzero(active)
            if idx.size == 0:
                break
            p, xa, ya = points[idx], x[idx], y[idx]
            e = self._miss(xa, ya, p, half)
            jx = _derivative(e, self._miss(xa + h, ya, p, half), self._miss(xa - h, ya, p, half), h)
            jy = _derivative(e, self._miss(xa, ya + h, p, half), self._miss(xa, ya - h, p, half), h)
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                sx = (jy[:, 1] * e[:, 0] - jy[:, 0] * e[:, 1]) / det
                sy = (jx[:, 0] * e[:, 1] - jx[:, 1] * e[:, 0]) / det
            # damp steps that would leave the traceable region or grow the miss
            norm_e = np.hypot(e[:, 0], e[:, 1])
            lam = np.ones(idx.size)
            worse = np.zeros(idx.size, dtype=bool)
            for _ in range(_AIM_HALVINGS):
                trial = self._miss(xa - lam * sx, ya - lam * sy, p, half)
                worse = ~(np.hypot(trial[:, 0], trial[:, 1]) <= norm_e * (1 - 1e-4 * lam))
                worse &= np.maximum(np.abs(sx), np.abs(sy)) * lam * scale > 1e-6
                if not worse.any():
                    break
                lam[worse] *= 0.5
            x[idx] = xa - lam * sx
            y[idx] = ya - lam * sy
            step_px = np.maximum(np.abs(sx), np.abs(sy)) * lam * scale
            finished = step_px < AIM_TOL_PX
            done[idx[finished & (lam == 1.0)]] = True
            # no descent left: the point lies beyond what the half's rays reach
            failed = ~np.isfinite(step_px) | ~np.isfinite(norm_e) | worse
            active[idx[finished | failed]] = False
        return x, y, done

    def project(self, points: np.ndarray, half: Half | str) -> TruthProjection:
        """Forward: the pixel (N, 2) of each point (N, 3) mm in a half, by ray aiming.

        Status ``NOT_CONVERGED`` where no lens ray of that half reaches the point (or
        aiming fails), ``OUTSIDE_HALF`` where the solution's pixel is not in the half;
        NaN pixels wherever the status is not OK.
        """
        half = Half.parse(half)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        status = np.full(p.shape[0], Status.OK, dtype=STATUS_DTYPE)
        finite = np.all(np.isfinite(p), axis=-1)
        status[~finite] = Status.INVALID_INPUT
        status[finite & ~(p[:, 2] > 0)] = Status.BEHIND
        pixels = np.full((p.shape[0], 2), np.nan)
        idx = np.flatnonzero(status == Status.OK)
        if idx.size:
            x, y, done = self._aim(p[idx], half)
            # a start across a TIR patch (near the apex's ends) can leave no descent:
            # retry those points from the next nearest grid rays
            for rank in range(1, _AIM_RESTARTS + 1):
                # stalled close to the point (or in TIR), not far outside the half's field
                miss = np.hypot(*self._miss(x, y, p[idx], half).T)
                again = np.flatnonzero(~done & ~(miss >= _RESTART_MISS * p[idx, 2]))
                if again.size == 0:
                    break
                x2, y2, done2 = self._aim(p[idx[again]], half, rank)
                x[again], y[again], done[again] = x2, y2, done2
            u, v, ok = self.lens.ideal_to_pixel(np.where(done, x, 0.0), np.where(done, y, 0.0))
            good = done & ok
            pixels[idx[good]] = np.stack([u[good], v[good]], axis=-1)
            status[idx[~good]] = Status.NOT_CONVERGED
        inside = in_half(pixels, half, self.config.split, self.config.image_size)
        status[(status == Status.OK) & ~inside] = Status.OUTSIDE_HALF
        pixels[status != Status.OK] = np.nan
        return TruthProjection(pixels, status)

    # ----- the apex image --------------------------------------------------------------
    def _apex_gap(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``t_left - t_right`` inside the glass for the lens rays of pixels (any shape)."""
        shape = np.shape(u)
        x, y, ok = self.lens.pixel_to_ideal(np.ravel(u), np.ravel(v))
        o0, d0 = self.lens.lens_rays(np.where(ok, x, 0.0), np.where(ok, y, 0.0))
        p1 = o0 + _hit(o0, d0, self.rear)[:, None] * d0
        g, _ = refract_vectors(d0, self.rear.normal, 1.0 / self.n_glass)
        with np.errstate(invalid="ignore", divide="ignore"):
            t_l = (self.left.d - p1 @ self.left.normal) / (g @ self.left.normal)
            t_r = (self.right.d - p1 @ self.right.normal) / (g @ self.right.normal)
        return np.where(ok, t_l - t_r, np.nan).reshape(shape)

    def apex_columns(self, rows: np.ndarray) -> np.ndarray:
        """Column ``u`` (R,) where each row's lens rays meet both front faces at once.

        Scans the whole row for the first change of ``t_left - t_right`` from negative
        (the left face first) to positive, then bisects it to 1e-10 px; NaN where the
        row has none.
        """
        rows = np.asarray(rows, dtype=np.float64).reshape(-1)
        width = self.config.image_size[0]
        u = np.linspace(-0.5, width - 0.5, _APEX_SCAN)
        g = self._apex_gap(*np.meshgrid(u, rows))
        change = (g[:, :-1] < 0) & (g[:, 1:] > 0)
        has = change.any(axis=1)
        k = np.argmax(change, axis=1)
        a, b = u[k], u[k + 1]
        for _ in range(60):
            m = 0.5 * (a + b)
            neg = self._apex_gap(m, rows) < 0
            a, b = np.where(neg, m, a), np.where(neg, b, m)
            if np.max(b - a) < 1e-10:
                break
        return np.where(has, 0.5 * (a + b), np.nan)

    def apex_split(self) -> int:
        """First column of the right half: the column boundary nearest the apex image of
        the middle row (boundaries lie at ``k + 0.5``)."""
        height = self.config.image_size[1]
        u = self.apex_columns(np.array([(height - 1) / 2.0]))[0]
        if not np.isfinite(u):
            raise ValueError("the apex does not image inside the middle row")
        return int(np.floor(u + 1.0))
