"""Triangulation of left/right correspondences for any camera model.

Two methods, both through the model contract only (:meth:`CameraModel.rays`), so they
work for central and non-central models alike:

- ``'midpoint'``: the midpoint of the common perpendicular of the two back-projected
  rays (closed form; the classical start value);
- ``'ml'`` (default): maximum likelihood under isotropic, independent Gaussian pixel
  noise, i.e. the 3D point whose projections are nearest (in the summed squared
  reprojection error of both halves) to the observed pixels (SPEC section 7; the
  paper's Section 2, refs. [7, 8, 17, 18]).

Why the ML solve runs in pixel space
------------------------------------
Minimising the reprojection error over the three point coordinates needs the forward
projection, which for the ``raytrace`` model is an iterative ray aiming, and a
Gauss-Newton loop with a finite-difference Jacobian needs several of them per point and
step. The same optimum can be found from backward rays alone, which are closed form: a
point ``p`` seen in both halves is the same thing as a pair of pixels ``(q_L, q_R)``
whose rays intersect. So the ML problem is

    minimise |q_L - q_L_obs|^2 + |q_R - q_R_obs|^2   subject to   g(q_L, q_R) = 0,

with ``g = (o_L - o_R) . (d_L x d_R)`` the coplanarity of the two rays (zero exactly
when they meet), and the point is the intersection of the rays of the optimal pixels.
Linearising ``g`` at the current pixels ``x`` gives the closed-form step (Sampson's
correction, iterated)

    x' = x_obs - grad g(x) * (g(x) + grad g(x) . (x_obs - x)) / |grad g(x)|^2

whose fixed points are exactly the Lagrange conditions of the constrained problem,
i.e. the ML point (not an approximation of it). Each iteration costs one batched
backward trace per half: of the pixel and, while the ray derivatives are renewed (see
:data:`JET_REFRESH_PX`), its two forward-difference neighbours for ``grad g``.

Status per point (:class:`~endomeasure.conventions.Status`): a pixel outside its half
is ``OUTSIDE_HALF``, a NaN pixel ``INVALID_INPUT``, a failed trace the model's code,
(near) parallel rays ``PARALLEL``, an intersection behind a ray origin ``BEHIND``, no
convergence within ``ML_MAX_ITER`` steps ``NOT_CONVERGED``. Failed points are NaN.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from endomeasure.conventions import STATUS_DTYPE, Half, Status
from endomeasure.geometry.rays import common_perpendicular
from endomeasure.models.base import ParamBatch

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = [
    "Triangulation",
    "triangulate",
    "METHODS",
    "ML_TOL_PX",
    "ML_MAX_ITER",
    "FD_STEP_PX",
]

METHODS = ("ml", "midpoint")

ML_TOL_PX = 1e-6
"""The ML iteration stops when no pixel moves by more than this (px). The iteration
contracts by the curvature of the coplanarity function times the residual per step, a
small factor, so the error left after stopping is far below this step."""

JET_REFRESH_PX = 1e-3
"""The ray derivatives are renewed only while the pixels still move by more than this
(px); smaller steps reuse the previous ones (a chord step), which saves the neighbour
traces of the last steps. Those derivatives come from pixels within this distance of the
optimum and only set the direction of the final correction, so the optimum hardly moves."""

ML_MAX_ITER = 20
"""Steps before a point is declared ``NOT_CONVERGED`` (well-posed points need a few)."""

FD_STEP_PX = 1e-4
"""Forward-difference step of the coplanarity gradient (px): it balances truncation
(step times curvature) against round-off (trace precision over step), both of order 1e-6
relative. The gradient only sets the direction of the ML correction, so such an error
moves the optimum by the same fraction of the residual."""


class Triangulation(NamedTuple):
    """Triangulated points with per-point diagnostics (leading shape ``(...)`` of the input)."""

    points: np.ndarray
    """(..., 3) mm, in the model frame; NaN where ``status != OK``."""
    status: np.ndarray
    """(...,) uint8 :class:`~endomeasure.conventions.Status`."""
    gap: np.ndarray
    """(...,) mm: distance between the rays of the *observed* pixels (a consistency check:
    a wrong match or a bad calibration shows up as a large gap)."""
    rms: np.ndarray
    """(...,) px: reprojection RMS over both halves, ``sqrt((|r_L|^2 + |r_R|^2) / 2)``.
    NaN for ``'midpoint'`` with ``reproject=False``."""
    pixels_left: np.ndarray
    """(..., 2) px: the reprojection of the point into the left half (the ML-corrected
    pixel); NaN where not computed."""
    pixels_right: np.ndarray
    """(..., 2) px: the same for the right half."""
    iterations: np.ndarray
    """(...,) int: ML steps taken (0 for ``'midpoint'``)."""


# ----- small vector helpers (faster than np.cross / einsum on (N, 3)) -------------------


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(axis=-1)


def _inward_steps(x: np.ndarray, half: Half, model: CameraModel) -> np.ndarray:
    """Signed forward-difference steps (N, 2) that keep ``x + step`` inside the half."""
    width, height = model.config.image_size
    u_hi = model.config.split - 0.5 if half is Half.LEFT else width - 0.5
    steps = np.full(x.shape, FD_STEP_PX)
    steps[:, 0] = np.where(x[:, 0] + FD_STEP_PX < u_hi, FD_STEP_PX, -FD_STEP_PX)
    steps[:, 1] = np.where(x[:, 1] + FD_STEP_PX < height - 0.5, FD_STEP_PX, -FD_STEP_PX)
    return steps


class _RayJet(NamedTuple):
    """Rays at pixels plus their derivatives along u and v."""

    o: np.ndarray  # (N, 3)
    d: np.ndarray  # (N, 3)
    do: np.ndarray  # (N, 2, 3) d origin / d (u, v), mm per px
    dd: np.ndarray  # (N, 2, 3) d direction / d (u, v), per px
    status: np.ndarray  # (N,)

    def take(self, index) -> _RayJet:
        return _RayJet(*(a[index] for a in self))


def _trace_jets(
    model: CameraModel,
    x: np.ndarray,
    half: Half,
    refresh: np.ndarray,
    previous: _RayJet | None,
    params: ParamBatch | None,
) -> _RayJet:
    """Rays at pixels ``x`` (N, 2) in one batched backward trace.

    Where ``refresh`` is True the two forward-difference neighbours are traced too and
    the derivatives renewed; elsewhere the derivatives of ``previous`` are kept (a
    chord step: they were taken less than ``JET_REFRESH_PX`` away). ``params``: a
    parameter vector per pixel, or None for the model's own.
    """
    n = x.shape[0]
    fresh = np.flatnonzero(refresh)
    h = _inward_steps(x[fresh], half, model)
    neighbours = np.repeat(x[fresh, None, :], 2, axis=1)
    neighbours[:, 0, 0] += h[:, 0]
    neighbours[:, 1, 1] += h[:, 1]
    if params is not None:
        params = params.take(np.concatenate([np.arange(n), np.repeat(fresh, 2)]))
    r = model.rays(np.concatenate([x, neighbours.reshape(-1, 2)]), half, params)
    o, d = r.origins[:n], r.directions[:n]
    status = r.status[:n].copy()
    if previous is None:
        do = np.full((n, 2, 3), np.nan)
        dd = np.full((n, 2, 3), np.nan)
    else:
        do, dd = previous.do.copy(), previous.dd.copy()
    on = r.origins[n:].reshape(-1, 2, 3)
    dn = r.directions[n:].reshape(-1, 2, 3)
    do[fresh] = (on - o[fresh, None]) / h[:, :, None]
    dd[fresh] = (dn - d[fresh, None]) / h[:, :, None]
    # A neighbour that fails while the pixel itself traces (a pixel on the very edge of
    # the traceable field) leaves no usable gradient.
    sn = r.status[n:].reshape(-1, 2).max(axis=1)
    edge = (sn != Status.OK) & (status[fresh] == Status.OK)
    status[fresh[edge]] = sn[edge]
    return _RayJet(o, d, do, dd, status)


def _coplanarity_gradient(jl: _RayJet, jr: _RayJet) -> tuple[np.ndarray, np.ndarray]:
    """``g = (o_L - o_R) . (d_L x d_R)`` (N,) and its gradient (N, 4) in ``(u_L, v_L, u_R, v_R)``.

    The chain rule through the ray derivatives: ``dg/dq_L = do_L . n + w . (dd_L x d_R)``
    and ``dg/dq_R = -do_R . n + w . (d_L x dd_R)`` with ``w = o_L - o_R``, ``n = d_L x d_R``.
    """
    w = jl.o - jr.o
    n = _cross(jl.d, jr.d)
    g = _dot(w, n)
    grad = np.empty((g.shape[0], 4))
    for k in range(2):
        grad[:, k] = _dot(jl.do[:, k], n) + _dot(w, _cross(jl.dd[:, k], jr.d))
        grad[:, 2 + k] = -_dot(jr.do[:, k], n) + _dot(w, _cross(jl.d, jr.dd[:, k]))
    return g, grad


def _advance(jet: _RayJet, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ray at ``pixel + delta`` to first order (delta tiny at convergence)."""
    o = jet.o + delta[:, :1] * jet.do[:, 0] + delta[:, 1:] * jet.do[:, 1]
    d = jet.d + delta[:, :1] * jet.dd[:, 0] + delta[:, 1:] * jet.dd[:, 1]
    return o, d / np.linalg.norm(d, axis=-1, keepdims=True)


def _first_failure(*statuses: np.ndarray) -> np.ndarray:
    """Per point, the first non-OK status in the order given (the cause, not a symptom)."""
    out = np.array(statuses[0], dtype=STATUS_DTYPE)
    for s in statuses[1:]:
        out = np.where(out == Status.OK, s, out).astype(STATUS_DTYPE)
    return out


def _intersection(o1, d1, o2, d2):
    """Midpoint, gap and status (PARALLEL / BEHIND) of the common perpendicular."""
    perp = common_perpendicular(o1, d1, o2, d2)
    status = perp.status.copy()
    behind = (status == Status.OK) & ~((perp.s1 > 0) & (perp.s2 > 0))
    status[behind] = Status.BEHIND
    return perp.midpoint, perp.gap, status


def triangulate(
    model: CameraModel,
    pixels_left: np.ndarray,
    pixels_right: np.ndarray,
    method: str = "ml",
    *,
    reproject: bool = True,
    params: np.ndarray | ParamBatch | None = None,
) -> Triangulation:
    """Triangulate correspondences between the left and right halves.

    Parameters
    ----------
    model : CameraModel
        Any model; only :meth:`~CameraModel.rays` (and, for ``'midpoint'`` with
        ``reproject``, :meth:`~CameraModel.project`) is used.
    pixels_left, pixels_right : ndarray, shape (..., 2), px
        Full-image pixel coordinates of the same points in the left and right halves
        (same leading shape).
    method : {'ml', 'midpoint'}
        Maximum likelihood (default) or the midpoint of the common perpendicular.
    reproject : bool
        For ``'midpoint'`` only: project the midpoints to fill ``rms`` and the pixel
        fields (costs one forward projection per half). ``'ml'`` gets them for free.
    params : ndarray, shape (..., P), or ParamBatch with index of shape (...), optional
        A parameter vector of the model's kind per correspondence (the leading shape
        of the pixels) instead of the model's own: triangulates under many models in
        one batched solve, e.g. the sigma points of a calibration covariance. Not
        with ``'midpoint'`` and ``reproject``. Invalid vectors give ``INVALID_INPUT``.

    Returns
    -------
    Triangulation

    Notes
    -----
    See the module docstring for the ML formulation. The ML points of noise-free
    correspondences are the true points; the start (iteration 0) is the observed pixel
    pair, whose rays give the midpoint and the observed ray gap.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
    ql = np.asarray(pixels_left, dtype=np.float64)
    qr = np.asarray(pixels_right, dtype=np.float64)
    if ql.shape != qr.shape or ql.shape[-1:] != (2,):
        raise ValueError(
            f"pixels_left and pixels_right must have the same shape (..., 2), got "
            f"{ql.shape} and {qr.shape}"
        )
    shape = ql.shape[:-1]
    ql = ql.reshape(-1, 2)
    qr = qr.reshape(-1, 2)
    if params is not None:
        params = ParamBatch.for_items(params, shape, model.params.size)
        if method == "midpoint" and reproject:
            raise ValueError("per-correspondence params need reproject=False with 'midpoint'")
    if method == "midpoint":
        out = _midpoint(model, ql, qr, reproject, params)
    else:
        out = _maximum_likelihood(model, ql, qr, params)
    return Triangulation(
        out.points.reshape(*shape, 3),
        out.status.reshape(shape),
        out.gap.reshape(shape),
        out.rms.reshape(shape),
        out.pixels_left.reshape(*shape, 2),
        out.pixels_right.reshape(*shape, 2),
        out.iterations.reshape(shape),
    )


def _rms(ql, qr, fl, fr) -> np.ndarray:
    return np.sqrt((np.sum((fl - ql) ** 2, axis=-1) + np.sum((fr - qr) ** 2, axis=-1)) / 2.0)


def _midpoint(model, ql, qr, reproject, params) -> Triangulation:
    n = ql.shape[0]
    rl = model.rays(ql, Half.LEFT, params)
    rr = model.rays(qr, Half.RIGHT, params)
    points, gap, status = _intersection(rl.origins, rl.directions, rr.origins, rr.directions)
    status = _first_failure(rl.status, rr.status, status)
    bad = status != Status.OK
    points[bad] = np.nan
    gap[bad] = np.nan
    fl = np.full((n, 2), np.nan)
    fr = np.full((n, 2), np.nan)
    rms = np.full(n, np.nan)
    if reproject:
        pl = model.project(points, Half.LEFT)
        pr = model.project(points, Half.RIGHT)
        fl, fr = pl.pixels, pr.pixels
        rms = _rms(ql, qr, fl, fr)
    return Triangulation(points, status, gap, rms, fl, fr, np.zeros(n, dtype=np.int64))


def _maximum_likelihood(model, ql, qr, params) -> Triangulation:
    n = ql.shape[0]
    x_obs = np.concatenate([ql, qr], axis=1)  # (N, 4): u_L, v_L, u_R, v_R
    x = x_obs.copy()
    points = np.full((n, 3), np.nan)
    gap = np.full(n, np.nan)
    status = np.full(n, Status.OK, dtype=STATUS_DTYPE)
    iterations = np.zeros(n, dtype=np.int64)
    final = np.full((n, 4), np.nan)
    active = np.arange(n)
    refresh = np.ones(n, dtype=bool)
    jl = jr = None
    for it in range(ML_MAX_ITER + 1):
        if active.size == 0:
            break
        xa = x[active]
        pa = None if params is None else params.take(active)
        jl = _trace_jets(model, xa[:, :2], Half.LEFT, refresh, jl, pa)
        jr = _trace_jets(model, xa[:, 2:], Half.RIGHT, refresh, jr, pa)
        trace_status = _first_failure(jl.status, jr.status)
        if it == 0:
            # The rays of the observed pixels: their gap is the consistency figure.
            _, g0, s0 = _intersection(jl.o, jl.d, jr.o, jr.d)
            gap[active] = g0
            parallel = np.where(s0 == Status.PARALLEL, s0, Status.OK)
            trace_status = _first_failure(trace_status, parallel)
        if it == ML_MAX_ITER:
            trace_status[trace_status == Status.OK] = Status.NOT_CONVERGED
        failed = trace_status != Status.OK
        status[active[failed]] = trace_status[failed]
        if failed.any():
            keep = ~failed
            active, xa, jl, jr = active[keep], xa[keep], jl.take(keep), jr.take(keep)
        if active.size == 0:
            break
        g, grad = _coplanarity_gradient(jl, jr)
        xo = x_obs[active]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (g + _dot(grad, xo - xa)) / _dot(grad, grad)
        x_new = xo - grad * lam[:, None]
        step = x_new - xa
        size = np.max(np.abs(step), axis=1)
        iterations[active] = it + 1
        conv = size < ML_TOL_PX
        if conv.any():
            # The rays at the (sub-tolerance) updated pixels follow to first order from
            # the rays and derivatives already traced: no further trace needed.
            idx = active[conv]
            o1, d1 = _advance(jl.take(conv), step[conv, :2])
            o2, d2 = _advance(jr.take(conv), step[conv, 2:])
            p, _, s = _intersection(o1, d1, o2, d2)
            points[idx] = p
            status[idx] = s
            final[idx] = x_new[conv]
        x[active] = x_new
        lost = ~np.isfinite(size)
        status[active[lost]] = Status.NOT_CONVERGED
        go_on = ~conv & ~lost
        active = active[go_on]
        refresh = size[go_on] > JET_REFRESH_PX
        jl, jr = jl.take(go_on), jr.take(go_on)
    bad = status != Status.OK
    points[bad] = np.nan
    final[bad] = np.nan
    gap[bad] = np.nan
    rms = _rms(ql, qr, final[:, :2], final[:, 2:])
    return Triangulation(points, status, gap, rms, final[:, :2], final[:, 2:], iterations)
