"""``raytrace``: the paper's Model 2, a lens camera behind a biprism, by vector Snell's law.

One real camera (``fx fy cx cy`` and lens distortion ``k1 k2``, optionally ``k3 p1
p2``, held fixed at zero by default) looks through a prism described by three planes in
the camera frame (SPEC 4.2):

- the rear face, shared by both halves, where rays enter the glass;
- the left and right front faces, where the rays of each half leave it.

Each plane is ``n . x = d`` with the unit normal parameterised by two tilts about the
optical axis, ``n = (tan a, tan b, 1) / |(tan a, tan b, 1)|`` (regular for faces near
perpendicular to the axis, unlike spherical angles), and ``d`` in mm. ``n_glass`` is
the prism's refractive index, held fixed by default because it is strongly correlated
with the face tilts.

Backward tracing (:meth:`RaytraceModel.rays`) is closed form. Forward projection has
none (the faces are not parallel), so :meth:`RaytraceModel.project` aims rays: it solves
for the lens coordinates whose traced ray passes through the point (see
:func:`aim_rays`).
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status
from endomeasure.geometry.distortion import distort, max_monotonic_radius2, undistort
from endomeasure.geometry.rays import intersect_plane, refract
from endomeasure.models.base import CameraModel

__all__ = ["RaytraceModel", "PrismTrace", "plane_normal", "AIM_TOL_PX", "AIM_MAX_ITER"]

AIM_TOL_PX = 1e-9
"""Ray aiming stops when the pixel step falls below this (px). The iteration contracts
by about 1e-3 per step, so the remaining error is far below the 1e-6 px the spec asks."""
AIM_MAX_ITER = 25
UNDISTORT_TOL_PX = 1e-10  # px
_CHUNK = 16384  # points per block in ray aiming: keeps the working set in cache


def plane_normal(a: float, b: float) -> np.ndarray:
    """Unit normal ``(tan a, tan b, 1) / norm`` of a face tilted by ``a`` about y and ``b`` about x."""
    n = np.array([np.tan(a), np.tan(b), 1.0])
    return n / np.linalg.norm(n)


class PrismTrace(NamedTuple):
    """Object-space rays of lens coordinates, with the entry point on the rear face."""

    origins: np.ndarray  # (N, 3) mm, on the half's front face
    directions: np.ndarray  # (N, 3) unit
    status: np.ndarray  # (N,) uint8


class _AimMap(NamedTuple):
    """Per-half polynomial start map for ray aiming (see ``_fit_aim_map``)."""

    centre: np.ndarray  # (3,) mm: point nearest to all the half's object rays
    exponents: np.ndarray  # (F, 3) int: powers of wx, wy, q per feature
    coeffs: np.ndarray  # (F, 2): feature weights -> lens coordinates x, y


class RaytraceModel(CameraModel):
    """Lens camera + biprism traced with vector Snell's law (19 parameters)."""

    NAME: ClassVar[str] = "raytrace"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = (
        "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2",
        "rear_a", "rear_b", "rear_d",
        "left_a", "left_b", "left_d",
        "right_a", "right_b", "right_d",
        "n_glass",
    )  # fmt: skip
    GROUPS: ClassVar[dict[str, slice]] = {
        "camera": slice(0, 9),
        "distortion": slice(4, 9),
        "rear_face": slice(9, 12),
        "left_face": slice(12, 15),
        "right_face": slice(15, 18),
    }
    DEFAULT_FIXED: ClassVar[frozenset[str]] = frozenset({"k3", "p1", "p2", "n_glass"})

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "_cache", {})

    def _check(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError("focal lengths must be positive")
        if self.n_glass <= 1.0:
            raise ValueError("the glass index must exceed 1")
        for face in ("rear", "left", "right"):
            if getattr(self, f"{face}_d") <= 0:
                raise ValueError(f"the {face} face must lie in front of the lens (d > 0)")

    # ----- geometry -------------------------------------------------------------------
    def face(self, name: str) -> tuple[np.ndarray, float]:
        """``(unit normal, distance)`` of the face ``'rear'``, ``'left'`` or ``'right'``."""
        a, b, d = (getattr(self, f"{name}_{k}") for k in "abd")
        return plane_normal(a, b), d

    def _lens_coeffs(self) -> tuple[float, float, float, float, float]:
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    def trace(self, x: np.ndarray, y: np.ndarray, half: Half) -> PrismTrace:
        """Trace undistorted normalised lens coordinates through the prism.

        Parameters
        ----------
        x, y : ndarray, shape (N,)
            Undistorted normalised coordinates of the lens camera (direction
            ``(x, y, 1)`` from the lens centre).
        half : Half
            Selects the front face the rays leave through.

        Returns
        -------
        PrismTrace
            Object-space rays; ``TOTAL_INTERNAL_REFLECTION`` or ``BEHIND`` (a face missed)
            where the trace fails.
        """
        n_rear, d_rear = self.face("rear")
        n_front, d_front = self.face("left" if Half.parse(half) is Half.LEFT else "right")
        d0 = np.stack([x, y, np.ones_like(x)], axis=-1)
        d0 /= np.linalg.norm(d0, axis=-1, keepdims=True)
        entry = intersect_plane(np.zeros(3), d0, n_rear, d_rear)
        inside = refract(d0, n_rear, 1.0 / self.n_glass)
        exit_ = intersect_plane(entry.points, inside.directions, n_front, d_front)
        out = refract(inside.directions, n_front, self.n_glass)
        status = np.maximum.reduce([entry.status, inside.status, exit_.status, out.status])
        return PrismTrace(exit_.points, out.directions, status.astype(STATUS_DTYPE))

    def _rays(self, pixels, half):
        und = undistort(
            (pixels[:, 0] - self.cx) / self.fx,
            (pixels[:, 1] - self.cy) / self.fy,
            self._lens_coeffs(),
            UNDISTORT_TOL_PX / max(self.fx, self.fy),
        )
        traced = self.trace(und.x, und.y, half)
        status = np.where(und.converged, traced.status, Status.NOT_CONVERGED)
        return traced.origins, traced.directions, status.astype(STATUS_DTYPE)

    def _lens_to_pixels(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        xd, yd = distort(x, y, self._lens_coeffs())
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    # ----- forward projection by ray aiming ---------------------------------------------
    def _project(self, points, half):
        x, y, status = aim_rays(self, points, half)
        pixels = self._lens_to_pixels(x, y)
        outside_lens = (x * x + y * y) > max_monotonic_radius2(self.k1, self.k2, self.k3)
        status = np.where((status == Status.OK) & outside_lens, Status.OUTSIDE_HALF, status)
        return pixels, status.astype(STATUS_DTYPE)

    def aim_map(self, half: Half) -> _AimMap:
        """The cached polynomial start map of a half for ray aiming."""
        half = Half.parse(half)
        key = ("aim", half)
        if key not in self._cache:
            self._cache[key] = _fit_aim_map(self, half)
        return self._cache[key]


# ----- ray aiming ----------------------------------------------------------------------

_AIM_DEPTHS_MM = (3.0, 5.0, 8.0, 12.0, 20.0, 35.0, 60.0, 120.0, 400.0)
_AIM_GRID = 41  # samples per axis over a half when fitting the start map
_AIM_MAX_DEGREE = 5  # total degree in (wx, wy) of the start map


def _aim_exponents() -> np.ndarray:
    """Feature powers ``(i, j, k)`` of ``wx^i wy^j q^k`` for the start map."""
    exps = [(i, t - i, 0) for t in range(_AIM_MAX_DEGREE + 1) for i in range(t + 1)]
    exps += [(i, t - i, 1) for t in range(3) for i in range(t + 1)]  # non-centrality ~ q
    exps += [(i, t - i, 2) for t in range(2) for i in range(t + 1)]
    return np.array(exps, dtype=np.int64)


def _aim_features(wx, wy, q, exponents, derivatives: bool = False):
    """Feature matrix (N, F) of the start map and, optionally, its w-derivatives."""
    top = int(exponents.max()) + 1
    px = [np.ones_like(wx)]
    py = [np.ones_like(wy)]
    pq = [np.ones_like(q)]
    for _ in range(1, top):
        px.append(px[-1] * wx)
        py.append(py[-1] * wy)
        pq.append(pq[-1] * q)
    F = np.empty((wx.shape[0], len(exponents)))
    if derivatives:
        Fx = np.zeros_like(F)
        Fy = np.zeros_like(F)
    for col, (i, j, k) in enumerate(exponents):
        yq = py[j] * pq[k]
        F[:, col] = px[i] * yq
        if derivatives:
            if i:
                Fx[:, col] = i * px[i - 1] * yq
            if j:
                Fy[:, col] = j * px[i] * py[j - 1] * pq[k]
    return (F, Fx, Fy) if derivatives else F


def _fit_aim_map(model: RaytraceModel, half: Half) -> _AimMap:
    """Fit the start map ``(wx, wy, q) -> (x, y)`` of one half.

    ``w = (P - C)_xy / (P - C)_z`` are the virtual-camera coordinates of a point P seen
    from the point C nearest to all of the half's rays, and ``q = 1 / (P - C)_z`` lets the
    map follow the model's non-centrality. The fit is only a starting guess and an
    approximate inverse Jacobian; ray aiming makes the answer exact.
    """
    width, height = model.config.image_size
    edge = model.config.split - 0.5
    u_lo, u_hi = (-0.5, edge) if half is Half.LEFT else (edge, width - 0.5)
    margin_u = 0.15 * (u_hi - u_lo)
    margin_v = 0.15 * height
    u = np.linspace(u_lo - margin_u, u_hi + margin_u, _AIM_GRID)
    v = np.linspace(-0.5 - margin_v, height - 0.5 + margin_v, _AIM_GRID)
    uu, vv = np.meshgrid(u, v)
    und = undistort(
        (uu.ravel() - model.cx) / model.fx,
        (vv.ravel() - model.cy) / model.fy,
        model._lens_coeffs(),
        1e-12,
    )
    keep = und.converged
    x, y = und.x[keep], und.y[keep]
    traced = model.trace(x, y, half)
    ok = traced.status == Status.OK
    x, y, o, d = x[ok], y[ok], traced.origins[ok], traced.directions[ok]
    if x.size < 50:
        raise ValueError(f"the {half.label} half traces too few valid rays to aim at")
    # C minimises the sum of squared distances to all rays: sum(I - d d^T) (C - o) = 0
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    centre = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, o))
    xs, ys, wxs, wys, qs = [], [], [], [], []
    for z in _AIM_DEPTHS_MM:
        s = (z - o[:, 2]) / d[:, 2]
        front = s > 0
        P = o[front] + s[front, None] * d[front]
        rel = P - centre
        xs.append(x[front])
        ys.append(y[front])
        wxs.append(rel[:, 0] / rel[:, 2])
        wys.append(rel[:, 1] / rel[:, 2])
        qs.append(1.0 / rel[:, 2])
    exponents = _aim_exponents()
    F = _aim_features(np.concatenate(wxs), np.concatenate(wys), np.concatenate(qs), exponents)
    target = np.stack([np.concatenate(xs), np.concatenate(ys)], axis=-1)
    scale = np.linalg.norm(F, axis=0)
    coeffs, *_ = np.linalg.lstsq(F / scale, target, rcond=None)
    return _AimMap(centre, exponents, coeffs / scale[:, None])


def aim_rays(model: RaytraceModel, points: np.ndarray, half: Half) -> tuple[np.ndarray, ...]:
    """Lens coordinates whose traced ray passes through each point (ray aiming).

    Parameters
    ----------
    model : RaytraceModel
    points : ndarray, shape (N, 3), mm
        Finite points in the camera frame.
    half : Half

    Returns
    -------
    x, y : ndarray, shape (N,)
        Undistorted normalised lens coordinates, NaN where status is not OK.
    status : ndarray, shape (N,), uint8
        ``BEHIND`` for points not in front of the half's front face, ``NOT_CONVERGED``
        where the iteration did not reach ``AIM_TOL_PX``, or the trace failure
        (``TOTAL_INTERNAL_REFLECTION``) at the last iterate.

    Notes
    -----
    A chord (fixed-Jacobian Newton) iteration in the two lens coordinates. With the
    start map ``g`` (see ``_fit_aim_map``) and ``A = dg/dw`` evaluated at the target
    point P, each step traces the current ray, takes its point Q at the depth of P and
    moves ``x <- x - A (w(Q) - w(P))``. At a fixed point Q = P, i.e. the ray passes
    through P exactly; the contraction factor per step is the relative error of ``A``
    (about 1e-3 here), so two to four traces per point suffice.
    """
    n = points.shape[0]
    x = np.full(n, np.nan)
    y = np.full(n, np.nan)
    status = np.full(n, Status.OK, dtype=STATUS_DTYPE)
    aim = model.aim_map(half)
    n_front, d_front = model.face("left" if half is Half.LEFT else "right")
    for start in range(0, n, _CHUNK):
        sl = slice(start, min(start + _CHUNK, n))
        x[sl], y[sl], status[sl] = _aim_block(model, points[sl], half, aim, n_front, d_front)
    return x, y, status


def _aim_block(model, P, half, aim, n_front, d_front):
    n = P.shape[0]
    x = np.full(n, np.nan)
    y = np.full(n, np.nan)
    rel = P - aim.centre
    # A point must lie beyond the front face to be reached by a ray leaving it.
    status = np.where(P @ n_front > d_front, Status.OK, Status.BEHIND).astype(STATUS_DTYPE)
    status[~(rel[:, 2] > 0)] = Status.BEHIND
    idx = np.flatnonzero(status == Status.OK)
    if idx.size == 0:
        return x, y, status
    depth = rel[idx, 2]
    wx, wy, q = rel[idx, 0] / depth, rel[idx, 1] / depth, 1.0 / depth
    F, Fx, Fy = _aim_features(wx, wy, q, aim.exponents, derivatives=True)
    xk, yk = (F @ aim.coeffs).T
    # A = d(x, y)/d(wx, wy); the step in w is the offset at P's depth divided by depth,
    # fold the 1/depth into A once.
    gx = Fx @ aim.coeffs  # (N, 2): d(x, y)/d wx
    gy = Fy @ aim.coeffs  # (N, 2): d(x, y)/d wy
    a11, a21 = gx[:, 0] * q, gx[:, 1] * q
    a12, a22 = gy[:, 0] * q, gy[:, 1] * q
    target = P[idx]
    tol_x = AIM_TOL_PX / model.fx
    tol_y = AIM_TOL_PX / model.fy
    active = np.arange(idx.size)
    last_fail = np.zeros(idx.size, dtype=STATUS_DTYPE)
    done = np.zeros(idx.size, dtype=bool)
    prev_x, prev_y = xk.copy(), yk.copy()
    for _ in range(AIM_MAX_ITER):
        if active.size == 0:
            break
        tr = model.trace(xk[active], yk[active], half)
        good = tr.status == Status.OK
        last_fail[active] = np.where(good, Status.OK, tr.status)
        # Failed traces (a step into the TIR region): go back half way and try again.
        bad = active[~good]
        xk[bad] = 0.5 * (xk[bad] + prev_x[bad])
        yk[bad] = 0.5 * (yk[bad] + prev_y[bad])
        act = active[good]
        o, d = tr.origins[good], tr.directions[good]
        tgt = target[act]
        s = (tgt[:, 2] - o[:, 2]) / d[:, 2]
        ex = o[:, 0] + s * d[:, 0] - tgt[:, 0]
        ey = o[:, 1] + s * d[:, 1] - tgt[:, 1]
        dx = -(a11[act] * ex + a12[act] * ey)
        dy = -(a21[act] * ex + a22[act] * ey)
        prev_x[act], prev_y[act] = xk[act], yk[act]
        xk[act] += dx
        yk[act] += dy
        conv = (np.abs(dx) < tol_x) & (np.abs(dy) < tol_y) & (s > 0)
        done[act[conv]] = True
        active = np.concatenate([act[~conv], bad])
    ok = done
    sub = np.where(ok, Status.OK, np.where(last_fail != Status.OK, last_fail, Status.NOT_CONVERGED))
    status[idx] = sub
    x[idx] = np.where(ok, xk, np.nan)
    y[idx] = np.where(ok, yk, np.nan)
    return x, y, status
