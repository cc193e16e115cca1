"""``raytrace``: the paper's Model 2, a lens camera behind a biprism, by vector Snell's law.

One real camera looks through a prism described by three planes in the camera frame
(SPEC 4.2):

- the rear face, shared by both halves, where rays enter the glass;
- the left and right front faces, where the rays of each half leave it.

Each plane is ``n . x = d`` with the unit normal parameterised by two tilts about the
optical axis, ``n = (tan a, tan b, 1) / |(tan a, tan b, 1)|`` (regular for faces near
perpendicular to the axis, unlike spherical angles), and ``d`` in mm. ``n_glass`` is
the prism's refractive index, estimated by default: over the wide fields of endoscope
lenses it is not degenerate with the face tilts (a known glass can be held).

The camera is ``fx fy cx cy`` and lens distortion ``k1 k2`` (the paper's), with the
extensions a real endoscope lens may need, all 0 and held fixed by default
(``RaytraceModel.EXTENSIONS``, freed by calibration only when the data call for them):

- ``k3`` and the tangential ``p1 p2`` (Brown-Conrady, OpenCV order);
- ``k4 k5 k6``, the denominator of OpenCV's rational radial factor: strong barrel
  distortion defined from pixel to ray has no short polynomial inverse;
- ``p1_image p2_image``, decentering defined on the image side: the first-order inverse
  of a pixel-to-ray map's tangential terms (:func:`endomeasure.geometry.distortion.distort`);
- ``e1 e2`` (mm), an entrance pupil that moves along the axis with the field angle
  ``theta`` of the lens ray: the ray starts at ``(0, 0, e1 theta^2 + e2 theta^4)``, as
  in CAHVORE's entrance-pupil terms (Gennery 2006); no constant term, which the face
  distances absorb.

Backward tracing (:meth:`RaytraceModel.rays`) is closed form. Forward projection has
none (the faces are not parallel), so :meth:`RaytraceModel.project` aims rays: it solves
for the lens coordinates whose traced ray passes through the point (see
:func:`aim_rays`).
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status
from endomeasure.geometry.distortion import (
    distort_jacobian,
    max_monotonic_radius2,
    undistort,
)
from endomeasure.models import _prism_kernels
from endomeasure.models.base import FD_STEP_PARAM, CameraModel, ParamBatch
from endomeasure.models.lens import (
    FULL_LENS_NAMES,
    IMAGE_TANGENTIAL_NAMES,
    RATIONAL_NAMES,
    lens_jacobians,
    lens_units,
)
from endomeasure.models.projector import Projector, zero_lost_rows

__all__ = [
    "RaytraceModel",
    "PrismTrace",
    "Aim",
    "aim_rays",
    "plane_normal",
    "AIM_TOL_PX",
    "AIM_MAX_ITER",
    "DEFAULT_GLASS_INDEX",
]

DEFAULT_GLASS_INDEX = 1.5168
"""N-BK7 at the helium d-line (587.6 nm), the usual prism glass: the start value of
``n_glass`` unless the user gives one."""

AIM_TOL_PX = 1e-8
"""Ray aiming stops when the pixel step falls below this (px); the iteration converges
superlinearly, so the remaining error is far below the 1e-6 px the spec asks."""
AIM_MAX_ITER = 25
UNDISTORT_TOL_PX = 1e-10  # px


def plane_normal(a, b) -> np.ndarray:
    """Unit normal ``(tan a, tan b, 1) / norm`` of a face tilted by a about y and b about x.

    ``a``, ``b`` floats or arrays of shape (...); returns shape (..., 3).
    """
    if np.ndim(a) == 0 and np.ndim(b) == 0:  # one face: the common case, kept cheap
        n = np.array([np.tan(a), np.tan(b), 1.0])
        return n / np.sqrt(n @ n)
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    n = np.stack([np.tan(a), np.tan(b), np.ones_like(a)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


class PrismTrace(NamedTuple):
    """Object-space rays of lens coordinates, with the entry point on the rear face."""

    origins: np.ndarray  # (N, 3) mm, on the half's front face
    directions: np.ndarray  # (N, 3) unit
    status: np.ndarray  # (N,) uint8


class Aim(NamedTuple):
    """Ray aiming's answer per point (:func:`aim_rays`)."""

    x: np.ndarray  # (N,) undistorted normalised lens coordinates, NaN where not OK
    y: np.ndarray  # (N,)
    status: np.ndarray  # (N,) uint8 Status
    dxy_dp: np.ndarray | None  # (N, 2, 3) d(x, y)/d point, 1/mm, when asked for
    pixels: np.ndarray | None  # (N, 2) px, when asked for


PUPIL_NAMES = ("e1", "e2")
"""The entrance pupil's shift along the axis with the field angle theta,
``z = e1 theta^2 + e2 theta^4`` (mm)."""
DISTORTION_NAMES = FULL_LENS_NAMES[4:]
"""The lens's distortion coefficients in :mod:`endomeasure.geometry.distortion` order."""

_SHARED_TRACE_PARAMS = frozenset({"rear_a", "rear_b", "rear_d", "n_glass", *PUPIL_NAMES})
_TRACE_PARAMS = {half: _SHARED_TRACE_PARAMS | {f"{half.label}_{k}" for k in "abd"} for half in Half}
"""The parameters a half's prism trace depends on (the other front face does not count)."""


class _AimMap(NamedTuple):
    """Per-half start data for ray aiming (see ``_fit_aim_map``)."""

    centre: np.ndarray  # (3,) mm: point nearest to all the half's object rays
    exponents: np.ndarray  # (F, 3) int: powers of wx, wy, q per feature
    coeffs: np.ndarray  # (F, 2): feature weights -> lens coordinates x, y
    lut: np.ndarray  # (K, NY, NX, 2): lens coordinates on a regular (q, wy, wx) grid
    lut_origin: np.ndarray  # (3,): wx, wy, q of lut[0, 0, 0]
    lut_step: np.ndarray  # (3,): grid steps in wx, wy, q
    inner: np.ndarray  # (2,): lens coordinates of a ray well inside the half's traceable field


def _faces(params: np.ndarray, half: Half) -> np.ndarray:
    """Rear and front face of a half for parameter vectors (..., P), packed for the
    kernels: rear normal, rear distance, front normal, front distance and the pupil's
    ``e1 e2``, shape (..., 10)."""

    def col(name):
        return RaytraceModel.column(params, name)

    rear = plane_normal(col("rear_a"), col("rear_b"))
    front = plane_normal(col(f"{half.label}_a"), col(f"{half.label}_b"))
    d_rear, d_front = np.asarray(col("rear_d")), np.asarray(col(f"{half.label}_d"))
    pupil = [np.asarray(col(name))[..., None] for name in PUPIL_NAMES]
    return np.concatenate([rear, d_rear[..., None], front, d_front[..., None], *pupil], axis=-1)


def _trace(
    x: np.ndarray,
    y: np.ndarray,
    faces: np.ndarray,
    n_glass: np.ndarray,
    prism: np.ndarray | None = None,
) -> PrismTrace:
    """Trace lens coordinates (N,) through prisms ``faces`` (K, 10), ``n_glass`` (K,):
    ``prism`` (N,) names each ray's (None: the first for all); see ``_prism_kernels``."""
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
    y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
    origins = np.empty((x.size, 3))
    directions = np.empty((x.size, 3))
    status = np.empty(x.size, dtype=STATUS_DTYPE)
    prism = np.zeros(0, dtype=np.int64) if prism is None else prism.astype(np.int64)
    _prism_kernels.trace_rays(
        x, y, np.ascontiguousarray(faces, dtype=np.float64),
        np.ascontiguousarray(n_glass, dtype=np.float64), prism, origins, directions, status,
    )  # fmt: skip
    return PrismTrace(origins, directions, status)


class _AimingProjector(Projector):
    """Projection by ray aiming warm-started from the previous call's lens coordinates.

    During an optimisation a trial step moves each solution only a little, so the last
    one is a far better start than the table and a few traces per point suffice. The
    start maps of the first model serve every later trial model: they only seed the
    iteration, and rebuilding them per trial step would dominate the fit. The state is
    the lens coordinates.
    """

    def __init__(self, template, halves, state=None):
        super().__init__(template, halves)
        self._xy = np.full((self.halves.size, 2), np.nan)
        if state is not None:
            self._xy[:] = state
        self._aim_maps = {}

    def state(self):
        return self._xy.copy()

    def _aim(self, model, points, half, idx) -> Aim:
        try:
            if half not in self._aim_maps:
                self._aim_maps[half] = model.aim_map(half)
            aim = self._aim_maps[half]
            return aim_rays(model, points, half, aim=aim, start=self._xy[idx], pixels=True)
        except ValueError:  # a trial model so wild that the half has no valid rays
            n = idx.size
            nan = np.full(n, np.nan)
            status = np.full(n, Status.NOT_CONVERGED, dtype=STATUS_DTYPE)
            return Aim(nan, nan, status, None, np.full((n, 2), np.nan))

    def project(self, model, points):
        pixels = np.full((points.shape[0], 2), np.nan)
        for half, idx in self.groups:
            aim = self._aim(model, points[idx], half, idx)
            pixels[idx], status = model.valid_projection(aim.pixels, aim.status, half)
            ok = status == Status.OK
            self._xy[idx] = np.where(ok[:, None], np.stack([aim.x, aim.y], axis=-1), np.nan)
        return pixels, np.all(np.isfinite(pixels), axis=-1)

    def jacobian(self, model, points):
        dq_dparams = np.zeros((points.shape[0], 2, self.free.size))
        dq_dp = np.zeros((points.shape[0], 2, 3))
        for half, idx in self.groups:
            idx = idx[np.isfinite(self._xy[idx, 0])]  # the corners the last projection kept
            if idx.size:
                aim = _aimed_at(model, self._xy[idx], points[idx], half)
                dq_dp[idx], dq_dparams[idx] = model._aimed_jacobians(
                    aim, points[idx], half, self.free
                )
        return zero_lost_rows(dq_dparams, dq_dp)


def _aimed_at(model, xy: np.ndarray, points: np.ndarray, half: Half) -> Aim:
    """The :class:`Aim` of lens coordinates ``xy`` (N, 2) already aimed at ``points``
    (N, 3), with ``dxy_dp`` from the kernel's implicit-function rule (no re-aiming)."""
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    points = np.ascontiguousarray(points, dtype=np.float64)
    dxy_dp = np.empty((points.shape[0], 2, 3))
    _prism_kernels.lens_jacobians(xy, points, model.faces_array(half), model.n_glass, dxy_dp)
    status = np.full(points.shape[0], Status.OK, dtype=STATUS_DTYPE)
    return Aim(xy[:, 0], xy[:, 1], status, dxy_dp, None)


class RaytraceModel(CameraModel):
    """Lens camera + biprism traced with vector Snell's law (26 parameters; see the
    module docstring). The first 19 are the earlier version's, in its order."""

    NAME: ClassVar[str] = "raytrace"
    PARAM_NAMES: ClassVar[tuple[str, ...]] = (
        "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2",
        "rear_a", "rear_b", "rear_d",
        "left_a", "left_b", "left_d",
        "right_a", "right_b", "right_d",
        "n_glass",
        "k4", "k5", "k6", "e1", "e2", "p1_image", "p2_image",
    )  # fmt: skip
    GROUPS: ClassVar[dict[str, slice]] = {
        # no "distortion" group: k3 sits before p1 p2 here, not in OpenCV's order
        "rear_face": slice(9, 12),
        "left_face": slice(12, 15),
        "right_face": slice(15, 18),
    }
    PARAM_UNITS: ClassVar[dict[str, str]] = {
        **lens_units(names=FULL_LENS_NAMES),
        **{name: "mm" for name in PUPIL_NAMES},
        **{f"{face}_{k}": "mm" if k == "d" else "rad"
           for face in ("rear", "left", "right") for k in "abd"},
        "n_glass": "1",
    }  # fmt: skip
    DEFAULT_FIXED: ClassVar[frozenset[str]] = frozenset(
        {"k3", "p1", "p2", *RATIONAL_NAMES, *PUPIL_NAMES, *IMAGE_TANGENTIAL_NAMES}
    )
    EXTENSIONS: ClassVar[tuple[tuple[str, ...], ...]] = (
        ("k3",), ("k4", "k5"), PUPIL_NAMES, ("p1", "p2"), IMAGE_TANGENTIAL_NAMES, ("k6",),
    )  # fmt: skip
    ABSORBED_EXTENSIONS: ClassVar[tuple[tuple[str, ...], ...]] = (PUPIL_NAMES,)
    SEEDED_FROM: ClassVar[str | None] = "pinhole"
    PROJECTOR: ClassVar[type[Projector]] = _AimingProjector

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "_cache", {})

    @classmethod
    def _constraints(cls, params):
        def col(name):
            return cls.column(params, name)

        return [
            ((col("fx") > 0) & (col("fy") > 0), "focal lengths must be positive"),
            (col("n_glass") > 1.0, "the glass index must exceed 1"),
            *(
                (col(f"{face}_d") > 0, f"the {face} face must lie in front of the lens (d > 0)")
                for face in ("rear", "left", "right")
            ),
        ]

    # ----- geometry -------------------------------------------------------------------
    def face(self, name: str) -> tuple[np.ndarray, float]:
        """``(unit normal, distance)`` of the face ``'rear'``, ``'left'`` or ``'right'``."""
        a, b, d = (getattr(self, f"{name}_{k}") for k in "abd")
        return plane_normal(a, b), d

    def lens(self) -> np.ndarray:
        """The lens camera ``fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 p1_image p2_image``
        (:data:`~endomeasure.models.lens.FULL_LENS_NAMES` order), (14,)."""
        return np.array([getattr(self, n) for n in FULL_LENS_NAMES])

    def _lens_coeffs(self) -> tuple[float, ...]:
        return tuple(getattr(self, k) for k in DISTORTION_NAMES)

    def _lens_needed(self, names) -> np.ndarray:
        """:meth:`lens` cut to the shortest form (9, 12 or 14 terms) that holds every
        non-zero term and every parameter in ``names``: the shorter forms' Jacobians are
        the same numbers, computed with less work."""
        lens = self.lens()
        needed = {n for n, v in zip(FULL_LENS_NAMES, lens, strict=True) if v != 0.0}
        needed |= set(names)
        for size in (9, 12):
            if not needed & set(FULL_LENS_NAMES[size:]):
                return lens[:size]
        return lens

    def fold_back_radius2(self) -> float:
        """The largest squared undistorted radius where the lens's radial map still grows
        (:func:`~endomeasure.geometry.distortion.max_monotonic_radius2`)."""
        if "r2_max" not in self._cache:
            radial = (getattr(self, k) for k in ("k1", "k2", "k3", *RATIONAL_NAMES))
            self._cache["r2_max"] = max_monotonic_radius2(*radial)
        return self._cache["r2_max"]

    def faces_array(self, half: Half) -> np.ndarray:
        """Rear and front face of a half (and the pupil) packed for the kernels, float64[10]."""
        half = Half.parse(half)
        key = ("faces", half)
        if key not in self._cache:
            self._cache[key] = _faces(self.params, half)
        return self._cache[key]

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
            where the trace fails, NaN there.

        Notes
        -----
        lens direction ``(x, y, 1)/norm`` -> rear face, refract air to glass
        (``eta = 1/n_glass``) -> the half's front face, refract glass to air
        (``eta = n_glass``); SPEC 4.2.
        """
        return _trace(x, y, self.faces_array(half)[None], np.array([self.n_glass]))

    def _rays(self, pixels, half):
        return self._rays_rows(pixels, half, ParamBatch(self.params[None], None))

    def _rays_rows(self, pixels, half, batch):
        """Rays with a parameter vector per pixel (``batch``; index None: its only vector)."""
        p = {k: batch.per_item(self.index(k)) for k in FULL_LENS_NAMES}
        one = batch.table.shape[0] == 1
        radial = ("k1", "k2", "k3", *RATIONAL_NAMES)
        r2 = max_monotonic_radius2(*(self.column(batch.table, k) for k in radial))
        und = undistort(
            (pixels[:, 0] - p["cx"]) / p["fx"],
            (pixels[:, 1] - p["cy"]) / p["fy"],
            tuple(p[k] for k in DISTORTION_NAMES),
            UNDISTORT_TOL_PX / np.maximum(p["fx"], p["fy"]),
            r2_max=float(r2[0]) if one else r2[batch.index],
        )
        own = one and np.array_equal(batch.table[0], self.params)
        faces = self.faces_array(half)[None] if own else _faces(batch.table, half)
        n_glass = self.column(batch.table, "n_glass")
        traced = _trace(und.x, und.y, faces, n_glass, None if one else batch.index)
        status = np.where(und.converged, traced.status, Status.NOT_CONVERGED)
        return traced.origins, traced.directions, status.astype(STATUS_DTYPE)

    # ----- forward projection by ray aiming ---------------------------------------------
    def _project(self, points, half):
        aim = aim_rays(self, points, half, pixels=True)
        return aim.pixels, aim.status

    def _project_jacobian(self, points, half):
        aim = aim_rays(self, points, half, jacobian=True, pixels=True)
        return aim.pixels, aim.status, self._point_jacobian(aim)

    def _point_jacobian(self, aim: Aim) -> np.ndarray:
        """d pixel / d point (N, 2, 3) at the aimed lens coordinates."""
        j11, j12, j21, j22 = distort_jacobian(aim.x, aim.y, self._lens_coeffs())
        D = np.stack([np.stack([j11, j12], -1), np.stack([j21, j22], -1)], -2)
        return np.array([self.fx, self.fy])[:, None] * (D @ aim.dxy_dp)

    def _project_jacobians(self, points, half, free):
        aim = aim_rays(self, points, half, jacobian=True, pixels=True)
        return aim.pixels, aim.status, *self._aimed_jacobians(aim, points, half, free)

    def _aimed_jacobians(self, aim: Aim, points, half, free) -> tuple[np.ndarray, np.ndarray]:
        """``dq_dp`` (N, 2, 3) and ``dq_dparams`` (N, 2, F) at converged aims.

        Notes
        -----
        With ``G(x, theta, P)`` the offset from P of the ray traced from lens coordinates
        ``x``, taken at the depth of P, aiming solves ``G = 0``; by the implicit-function
        rule ``dx/dtheta = -G_x^-1 G_theta``. The kernel's ``dxy_dp = -G_x^-1 G_P`` with
        ``G_P = [-I | t]`` already holds ``G_x^-1`` in its first two columns, so only
        ``G_theta`` is differenced (closed-form traces, never the aiming). Lens
        parameters enter the pixel directly: ``q = f distort(x) + c``.
        """
        dq_dp = self._point_jacobian(aim)
        good = np.isfinite(aim.x) & np.isfinite(aim.y)
        x, y = np.where(good, aim.x, 0.0), np.where(good, aim.y, 0.0)
        names = [self.PARAM_NAMES[i] for i in free]
        dq_dxy, dq_dlens = lens_jacobians(x, y, self._lens_needed(names))
        dq_dparams = np.zeros((points.shape[0], 2, free.size))
        lens_cols = [k for k, name in enumerate(names) if name in FULL_LENS_NAMES]
        dq_dparams[:, :, lens_cols] = dq_dlens[
            :, :, [FULL_LENS_NAMES.index(names[k]) for k in lens_cols]
        ]
        prism_cols = [k for k, name in enumerate(names) if name in _TRACE_PARAMS[half]]
        if prism_cols:
            G_theta = np.stack(
                [self._miss_derivative(free[k], x, y, half, points) for k in prism_cols], axis=-1
            )  # (N, 2, K)
            dq_dparams[:, :, prism_cols] = -(dq_dxy @ aim.dxy_dp[:, :, :2]) @ G_theta
        dq_dparams[~good] = np.nan
        return dq_dp, dq_dparams

    def _miss_derivative(self, i: int, x, y, half, points) -> np.ndarray:
        """``dG / d params[i]`` (N, 2) by central differences of the kernel's offset ``G``
        (where the ray of lens coordinates (x, y) crosses the depth of each point, minus
        the point), one-sided at the edge of the valid domain: of the parameters (e.g. a
        face distance within a step of zero) or of a ray (a step that makes it miss a
        face, e.g. the pupil moving past a rear face at the lens)."""
        x, y = np.ascontiguousarray(x), np.ascontiguousarray(y)
        points = np.ascontiguousarray(points, dtype=np.float64)
        n_glass = self.index("n_glass")

        def offsets(params):
            if not self.valid_params(params):
                return None
            out = np.empty((points.shape[0], 2))
            faces = np.ascontiguousarray(_faces(params, half))
            _prism_kernels.offsets(x, y, points, faces, float(params[n_glass]), out)
            return out

        step = FD_STEP_PARAM * max(1.0, abs(float(self.params[i])))
        stepped = []
        for sign in (1.0, -1.0):
            p = self.params.copy()
            p[i] += sign * step
            stepped.append(offsets(p))
        plus, minus = stepped
        if plus is not None and minus is not None:
            central = (plus - minus) / (2.0 * step)
            if np.isfinite(central).all():  # the usual case: no third trace
                return central
        return _per_ray_difference(plus, offsets(self.params), minus, step)

    def with_params(self, params: np.ndarray) -> RaytraceModel:
        """A new model with other parameters.

        When every parameter moves by less than ``_INHERIT_START_REL`` (relative, or
        absolute below 1), the new model reuses this one's ray-aiming start maps: they
        only seed the iteration, which converges to the new model's exact answer, and
        rebuilding them would dominate finite-difference Jacobians in calibration.
        """
        new = super().with_params(params)
        change = np.abs(new.params - self.params) / np.maximum(np.abs(self.params), 1.0)
        if change.max() < _INHERIT_START_REL:
            for key, value in self._cache.items():
                if key[0] == "aim":
                    new._cache[key] = value
        return new

    def aim_map(self, half: Half, table: bool = False) -> _AimMap:
        """The cached ray-aiming start data of a half: the polynomial, and with ``table``
        the look-up table too, worth its building time only for large batches of points
        (``_TABLE_MIN_POINTS``).
        """
        half = Half.parse(half)
        key = ("aim", half, bool(table))
        if key not in self._cache:
            self._cache[key] = _fit_aim_map(self, half, _LUT_STEP_W if table else None)
        return self._cache[key]


def _per_ray_difference(plus, centre, minus, step: float) -> np.ndarray:
    """:func:`~endomeasure.models.base.finite_difference` entry by entry: central where
    both sides traced, one-sided where only one did (None: that side left the valid
    parameter domain), NaN where neither did."""
    nan = np.full_like(centre, np.nan)
    plus = nan if plus is None else plus
    minus = nan if minus is None else minus
    out = (plus - minus) / (2.0 * step)
    out = np.where(np.isfinite(out), out, (plus - centre) / step)
    return np.where(np.isfinite(out), out, (centre - minus) / step)


# ----- ray aiming ----------------------------------------------------------------------

_INHERIT_START_REL = 1e-3

_AIM_DEPTHS_MM = (3.0, 5.0, 8.0, 12.0, 20.0, 35.0, 60.0, 120.0, 400.0)
_AIM_GRID = 41  # samples per axis over a half when fitting the start map
_AIM_MAX_DEGREE = 5  # total degree in (wx, wy) of the start map


def _aim_exponents() -> np.ndarray:
    """Feature powers ``(i, j, k)`` of ``wx^i wy^j q^k`` for the start map."""
    exps = [(i, t - i, 0) for t in range(_AIM_MAX_DEGREE + 1) for i in range(t + 1)]
    exps += [(i, t - i, 1) for t in range(3) for i in range(t + 1)]  # non-centrality ~ q
    exps += [(i, t - i, 2) for t in range(2) for i in range(t + 1)]
    return np.array(exps, dtype=np.int64)


def _aim_features(wx, wy, q, exponents):
    """Feature matrix (N, F) of the start map: ``wx^i wy^j q^k`` per exponent row."""
    return np.stack([wx**i * wy**j * q**k for i, j, k in exponents], axis=-1)


def _fit_aim_map(model: RaytraceModel, half: Half, step: float | None) -> _AimMap:
    """Fit the start map ``(wx, wy, q) -> (x, y)`` of one half, and tabulate exact
    solutions with spacing ``step`` unless it is None.

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
    middle = np.argmin(np.hypot(x - np.median(x), y - np.median(y)))
    inner = np.array([x[middle], y[middle]])
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
    Fs = F / scale  # unit columns: the normal equations stay well conditioned
    coeffs = np.linalg.solve(Fs.T @ Fs, Fs.T @ target) / scale[:, None]
    wx_all, wy_all = np.concatenate(wxs), np.concatenate(wys)
    no_lut = (np.full((1, 1, 1, 2), np.nan, dtype=np.float32), np.zeros(3), np.ones(3))
    poly = _AimMap(centre, exponents, coeffs, *no_lut, inner)
    if step is None:
        return poly
    return poly._replace(**_build_aim_table(model, half, poly, wx_all, wy_all, step))


_LUT_STEP_W = 0.015
"""Table spacing in virtual-camera tangent units (about 5 px at f = 300 px)."""
_TABLE_MIN_POINTS = 200_000
"""Smallest batch that builds the start table. The table's start saves Broyden traces per
point (see ``_build_aim_table``), a fraction of a microsecond, against a build that aims
tens of thousands of nodes: worth it only for batches of this order (build times and
throughput in docs/benchmarks.md, ``bench/bench_models.py``). Calibration's few
thousand corners per model never build it: there the table cost more than all the
projections it served."""
_LUT_DEPTHS_MM = (4.0, 1000.0)  # nearest and farthest slice of the table, from the centre C
_LUT_SLICES = 10


def _build_aim_table(model, half, start: _AimMap, wx, wy, step: float) -> dict:
    """Tabulate exact aiming solutions on a regular (q, wy, wx) grid.

    A trilinear look-up in this table starts ray aiming within a few hundredths of a
    pixel, with a Jacobian from the same cell, so Broyden needs about three traces
    instead of six from the polynomial start (whose error is pixels: the map of a
    55-degree prism half is far from polynomial near the field edges). Nodes without a
    valid ray hold NaN; points there fall back to the polynomial.
    """
    lo = np.array([wx.min(), wy.min()]) - step
    hi = np.array([wx.max(), wy.max()]) + step
    n_x, n_y = (np.ceil((hi - lo) / step).astype(int) + 1).tolist()
    q_near, q_far = 1.0 / _LUT_DEPTHS_MM[0], 1.0 / _LUT_DEPTHS_MM[1]
    qs = np.linspace(q_far, q_near, _LUT_SLICES)
    gq, gy, gx = np.meshgrid(qs, lo[1] + step * np.arange(n_y),
                             lo[0] + step * np.arange(n_x), indexing="ij")  # fmt: skip
    nodes = start.centre + np.stack([gx, gy, np.ones_like(gx)], axis=-1) / gq[..., None]
    aimed = aim_rays(model, nodes.reshape(-1, 3), half, start)
    table = np.stack([aimed.x, aimed.y], axis=-1).reshape(_LUT_SLICES, n_y, n_x, 2)
    return dict(
        lut=np.ascontiguousarray(table, dtype=np.float32),  # a start only: halves the cache load
        lut_origin=np.array([lo[0], lo[1], q_far]),
        lut_step=np.array([step, step, qs[1] - qs[0]]),
    )


def aim_rays(
    model: RaytraceModel,
    points: np.ndarray,
    half: Half,
    aim: _AimMap | None = None,
    jacobian: bool = False,
    start: np.ndarray | None = None,
    pixels: bool = False,
) -> Aim:
    """Lens coordinates whose traced ray passes through each point (ray aiming).

    Parameters
    ----------
    model : RaytraceModel
    points : ndarray, shape (N, 3), mm
        Finite points in the camera frame.
    half : Half
    aim : _AimMap, optional
        Start data; the model's own by default.
    jacobian : bool
        Also return ``dxy_dp``, shape (N, 2, 3): the derivative of the lens coordinates
        with respect to the point (implicit-function rule at the solution).
    start : ndarray, shape (N, 2), optional
        Warm-start lens coordinates (rows of NaN start from the table), e.g. the
        previous solution while an optimiser moves the parameters a little.
    pixels : bool
        Also return the pixels of the solutions (computed in the same pass), shape
        (N, 2); solutions beyond the distortion's fold-back radius are ``OUTSIDE_HALF``.

    Returns
    -------
    Aim
        ``x, y`` (N,): undistorted normalised lens coordinates, NaN where status is not
        OK; ``status`` (N,): ``BEHIND`` for points not in front of the half's front face,
        ``NOT_CONVERGED`` where the iteration did not reach ``AIM_TOL_PX`` in
        ``AIM_MAX_ITER`` traces, or the trace failure (``TOTAL_INTERNAL_REFLECTION``)
        where no step keeps the ray inside the prism; ``dxy_dp`` and ``pixels`` when
        asked for, else None.

    Notes
    -----
    The unknowns are the two lens coordinates ``x``; the residual ``e(x)`` is the offset,
    in the plane ``z = P_z``, of the traced ray from the point P. Broyden's method solves
    ``e(x) = 0``: the start ``x0 = g(w(P))`` and the start inverse Jacobian
    ``dg/dw / (P - C)_z`` come from the start map ``g`` of ``_fit_aim_map`` (a table of
    exact solutions, or a polynomial); each step traces once and updates the 2x2 inverse
    Jacobian by the rank-one ("good") Broyden formula, which converges superlinearly.
    A step that leaves the prism (TIR, missed face) is halved until it stays inside.
    The loop runs per point in :mod:`endomeasure.models._prism_kernels`.
    """
    half = Half.parse(half)
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if aim is None:
        aim = model.aim_map(half, table=points.shape[0] >= _TABLE_MIN_POINTS)
    xy = np.empty((points.shape[0], 2))
    status = np.empty(points.shape[0], dtype=STATUS_DTYPE)
    dxy_dp = np.empty((points.shape[0] if jacobian else 0, 2, 3))
    start = np.empty((0, 2)) if start is None else np.ascontiguousarray(start, dtype=np.float64)
    q = np.empty((points.shape[0] if pixels else 0, 2))  # the kernel NaNs skipped rows
    lens = model.lens()
    r2_max = model.fold_back_radius2()
    _prism_kernels.aim_rays(
        points, model.faces_array(half), model.n_glass, aim.centre, aim.exponents, aim.coeffs,
        aim.lut, aim.lut_origin, aim.lut_step, aim.inner, start,
        AIM_TOL_PX / model.fx, AIM_TOL_PX / model.fy, AIM_MAX_ITER,
        xy, status, dxy_dp, lens, r2_max, q,
    )  # fmt: skip
    return Aim(xy[:, 0], xy[:, 1], status, dxy_dp if jacobian else None, q if pixels else None)
