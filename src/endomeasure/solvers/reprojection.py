"""Reprojection of calibration-target corners and its Jacobians, per camera model.

Calibration (:mod:`endomeasure.solvers.calibrate`) minimises pixel reprojection errors
over the model's free parameters and one board pose per image. It needs, for a fixed set
of observations (each a 3D point in the model frame and the half it is seen in), the
projected pixels and two Jacobians: with respect to the free model parameters and with
respect to the 3D point (the pose part follows by the chain rule).

A :class:`Projector` provides them. :func:`projector_for` picks one by model name:

- ``pinhole``: closed-form derivatives of the Brown pinhole projection;
- ``raytrace``: the model's ray aiming, warm-started from the previous call's
  lens coordinates, and derivatives through the aiming by the implicit-function rule;
- any other model: central finite differences of :meth:`CameraModel.project`, so a new
  model works without touching the solvers (slower, but correct).
"""

from __future__ import annotations

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.geometry.distortion import distort, distort_coeff_jacobian, distort_jacobian
from endomeasure.geometry.rotations import rotation_jacobian, rotation_matrix, skew
from endomeasure.models.base import CameraModel

__all__ = [
    "Projector",
    "PinholeProjector",
    "RaytraceProjector",
    "FiniteDifferenceProjector",
    "projector_for",
]

FD_STEP_PARAM = 1e-6
"""Central-difference step for model parameters (rad, mm, or index units). The
truncation error is ~h^2 times the third derivative (~1e-12 relative), the rounding error
~eps/h (~1e-10 relative): both far below what the covariance needs."""
FD_STEP_LENS = 1e-7
"""Central-difference step in normalised lens coordinates (about 2e-5 px)."""


class Projector:
    """Projects a fixed set of observations and differentiates the projection.

    Parameters
    ----------
    model : CameraModel
        Template: its kind and its ``free_mask`` fix which parameters are differentiated.
    halves : ndarray of int, shape (N,)
        Half (0 left, 1 right) of each observation.

    Notes
    -----
    :meth:`jacobian` refers to the state of the last :meth:`project` call, which must be
    made with the same model and points (the solver always does this).
    """

    def __init__(self, model: CameraModel, halves: np.ndarray, start: np.ndarray | None = None):
        self.halves = np.asarray(halves, dtype=np.int8)
        self.free = np.flatnonzero(model.free_mask)
        self.groups = [np.flatnonzero(self.halves == h) for h in (Half.LEFT, Half.RIGHT)]

    def state(self) -> np.ndarray | None:
        """Internal per-observation state worth carrying to a next problem over the same
        observations (warm starts), shape (N, k), or None."""
        return None

    def project(self, model: CameraModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of the observations' points.

        Parameters
        ----------
        model : CameraModel
        points : ndarray, shape (N, 3), mm
            In the model frame.

        Returns
        -------
        pixels : ndarray, shape (N, 2), px
            Not restricted to the half: a corner that strays a little over the split
            during the optimisation keeps a smooth residual.
        ok : ndarray of bool, shape (N,)
            False where the projection failed (behind the probe, total internal
            reflection, no convergence); those pixels are NaN.
        """
        raise NotImplementedError

    def jacobian(self, model: CameraModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of the pixels at the last projection.

        Returns
        -------
        dq_dparams : ndarray, shape (N, 2, F)
            With respect to the free parameters (``model.free_mask``), px per unit.
        dq_dpoints : ndarray, shape (N, 2, 3), px / mm
        """
        raise NotImplementedError


# ----- shared closed forms ----------------------------------------------------------------


def _lens_pixels_and_jacobians(x, y, fx, fy, cx, cy, coeffs):
    """Pixels of undistorted lens coordinates and their derivatives.

    Returns pixels (N, 2), d q / d(x, y) (N, 2, 2) and d q / d(fx fy cx cy k1 k2 p1 p2 k3)
    (N, 2, 9) in OpenCV intrinsics order.
    """
    xd, yd = distort(x, y, coeffs)
    q = np.stack([fx * xd + cx, fy * yd + cy], axis=-1)
    j11, j12, j21, j22 = distort_jacobian(x, y, coeffs)
    d_dxy = np.stack([np.stack([j11, j12], -1), np.stack([j21, j22], -1)], -2)
    f = np.array([fx, fy])[None, :, None]
    dq_dxy = f * d_dxy
    dq_dintr = np.zeros(x.shape + (2, 9))
    dq_dintr[:, 0, 0] = xd
    dq_dintr[:, 1, 1] = yd
    dq_dintr[:, 0, 2] = 1.0
    dq_dintr[:, 1, 3] = 1.0
    dq_dintr[:, :, 4:9] = f * distort_coeff_jacobian(x, y)  # k1 k2 p1 p2 k3
    return q, dq_dxy, dq_dintr


# ----- pinhole: closed form ------------------------------------------------------------------

_PINHOLE_INTR = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


class PinholeProjector(Projector):
    """Closed-form projection and derivatives of the ``pinhole`` pair."""

    def project(self, model, points):
        self._last = self._evaluate(model, points, with_jacobian=False)
        return self._last[0], self._last[1]

    def jacobian(self, model, points):
        _, _, dq_dparams, dq_dpoints = self._evaluate(model, points, with_jacobian=True)
        return dq_dparams, dq_dpoints

    def _evaluate(self, model, points, with_jacobian):
        n = points.shape[0]
        pixels = np.full((n, 2), np.nan)
        ok = np.zeros(n, dtype=bool)
        P = len(model.PARAM_NAMES)
        dq_dall = np.zeros((n, 2, P)) if with_jacobian else None
        dq_dpoints = np.zeros((n, 2, 3)) if with_jacobian else None
        R, t = model.pose_right_left()
        rvec = np.array(model.rvec_right_left)
        for half, idx in zip((Half.LEFT, Half.RIGHT), self.groups, strict=False):
            if idx.size == 0:
                continue
            X = points[idx]
            cam = X if half is Half.LEFT else X @ R.T + t
            z = cam[:, 2]
            front = z > 0
            zs = np.where(front, z, 1.0)
            x, y = cam[:, 0] / zs, cam[:, 1] / zs
            intr = model.intrinsics(half)
            fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr
            q, dq_dxy, dq_dintr = _lens_pixels_and_jacobians(
                x, y, fx, fy, cx, cy, (k1, k2, p1, p2, k3)
            )
            q[~front] = np.nan
            pixels[idx] = q
            ok[idx] = front
            if not with_jacobian:
                continue
            dxy_dcam = np.zeros((idx.size, 2, 3))
            dxy_dcam[:, 0, 0] = 1.0 / zs
            dxy_dcam[:, 1, 1] = 1.0 / zs
            dxy_dcam[:, 0, 2] = -x / zs
            dxy_dcam[:, 1, 2] = -y / zs
            dq_dcam = dq_dxy @ dxy_dcam
            first = model.index(f"{half.label}_fx")
            dq_dall[idx, :, first : first + 9] = dq_dintr
            if half is Half.LEFT:
                dq_dpoints[idx] = dq_dcam
            else:
                dq_dpoints[idx] = dq_dcam @ R
                RX = X @ R.T
                dcam_drvec = -skew(RX) @ rotation_jacobian(rvec)
                r0 = model.index("rx")
                t0 = model.index("tx")
                dq_dall[idx, :, r0 : r0 + 3] = dq_dcam @ dcam_drvec
                dq_dall[idx, :, t0 : t0 + 3] = dq_dcam
        if with_jacobian:
            dq_dall = dq_dall[:, :, self.free]
        return pixels, ok, dq_dall, dq_dpoints


# ----- raytrace: warm-started ray aiming and the implicit-function rule ---------------------

_CAMERA = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_PRISM = {
    Half.LEFT: ("rear_a", "rear_b", "rear_d", "left_a", "left_b", "left_d", "n_glass"),
    Half.RIGHT: ("rear_a", "rear_b", "rear_d", "right_a", "right_b", "right_d", "n_glass"),
}


def _miss_at_depth(model, x, y, half, P):
    """Where the traced ray of lens coordinates (x, y) crosses the depth of P, minus P.

    Returns ``G`` (N, 2) mm, the ray direction (N, 3) and an ok mask; ``G = 0`` means
    the ray passes through P.
    """
    tr = model.trace(x, y, half)
    o, d = tr.origins, tr.directions
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (P[:, 2] - o[:, 2]) / d[:, 2]
    G = o[:, :2] + s[:, None] * d[:, :2] - P[:, :2]
    ok = (tr.status == Status.OK) & (s > 0) & np.all(np.isfinite(G), axis=-1)
    return G, d, ok


def _miss_jacobian_lens(model, x, y, half, P):
    """``dG/d(x, y)`` by central differences of the trace, shape (N, 2, 2)."""
    h = FD_STEP_LENS
    gxp, _, ok1 = _miss_at_depth(model, x + h, y, half, P)
    gxm, _, ok2 = _miss_at_depth(model, x - h, y, half, P)
    gyp, _, ok3 = _miss_at_depth(model, x, y + h, half, P)
    gym, _, ok4 = _miss_at_depth(model, x, y - h, half, P)
    J = np.stack([(gxp - gxm) / (2 * h), (gyp - gym) / (2 * h)], axis=-1)
    return J, ok1 & ok2 & ok3 & ok4


def _solve2(J, b):
    """Solve the 2x2 systems ``J s = b`` row-wise, J (N, 2, 2), b (N, 2) or (N, 2, K)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    inv = np.empty_like(J)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv[:, 0, 0] = J[:, 1, 1] / det
        inv[:, 1, 1] = J[:, 0, 0] / det
        inv[:, 0, 1] = -J[:, 0, 1] / det
        inv[:, 1, 0] = -J[:, 1, 0] / det
    if b.ndim == 2:
        return np.einsum("nij,nj->ni", inv, b)
    return inv @ b


def _miss_derivative(model, i, x, y, half, P):
    """``dG/d params[i]`` by central differences, one-sided at the edge of the model's
    valid domain (e.g. a face distance within a step of zero)."""
    h = FD_STEP_PARAM
    sides = []
    for sign in (1.0, -1.0):
        p = model.params.copy()
        p[i] += sign * h
        try:
            sides.append(_miss_at_depth(model.with_params(p), x, y, half, P)[0])
        except ValueError:
            sides.append(None)
    if sides[0] is not None and sides[1] is not None:
        return (sides[0] - sides[1]) / (2 * h)
    g0 = _miss_at_depth(model, x, y, half, P)[0]
    return (sides[0] - g0) / h if sides[0] is not None else (g0 - sides[1]) / h


class RaytraceProjector(Projector):
    """Projection through the ``raytrace`` model by warm-started ray aiming.

    Notes
    -----
    Let ``G(x, y; theta, P)`` be the offset from P of the object ray traced from lens
    coordinates ``(x, y)``, taken at the depth of P. Projection solves ``G = 0`` (ray
    aiming) with the model's own :func:`endomeasure.models.raytrace.aim_rays`, started
    from the previous call's solution, which during an optimisation is a few hundredths
    of a pixel away, so two or three traces per point suffice. By the implicit-function rule
    ``d(x, y)/d theta = -G_xy^-1 G_theta`` and ``d(x, y)/dP = -G_xy^-1 G_P`` with
    ``G_P = [[-1, 0, d_x/d_z], [0, -1, d_y/d_z]]``; ``G_xy`` and ``G_theta`` come from
    central differences of the closed-form trace (never of the aiming). The pixel is
    ``q = f * distort(x, y) + c``.
    """

    def __init__(self, model, halves, start=None):
        super().__init__(model, halves)
        n = self.halves.size
        self._x = np.full(n, np.nan)
        self._y = np.full(n, np.nan)
        if start is not None:
            self._x[:], self._y[:] = start[:, 0], start[:, 1]
        self._free_names = {model.PARAM_NAMES[i] for i in self.free}
        self._aim_maps = {}
        self._col = {model.PARAM_NAMES[i]: k for k, i in enumerate(self.free)}

    def state(self):
        return np.stack([self._x, self._y], axis=-1)

    def _aim(self, model, P, half, idx):
        from endomeasure.models.raytrace import aim_rays

        start = np.stack([self._x[idx], self._y[idx]], axis=-1)
        try:
            # The warm starts carry the iteration; the start map only seeds the inverse
            # Jacobian and cold points, so the first model's map serves every later trial
            # model of the optimisation (rebuilding it per trial step dominated the fit).
            if half not in self._aim_maps:
                self._aim_maps[half] = model.aim_map(half)
            x, y, status = aim_rays(model, P, half, aim=self._aim_maps[half], start=start)
        except ValueError:  # a trial model so wild that the half has no valid rays
            x, y, status = start[:, 0], start[:, 1], np.full(idx.size, Status.NOT_CONVERGED)
        ok = status == Status.OK
        x, y = np.where(ok, x, np.nan), np.where(ok, y, np.nan)
        self._x[idx], self._y[idx] = x, y
        return x, y

    def project(self, model, points):
        n = points.shape[0]
        pixels = np.full((n, 2), np.nan)
        for half, idx in zip((Half.LEFT, Half.RIGHT), self.groups, strict=False):
            if idx.size == 0:
                continue
            x, y = self._aim(model, points[idx], half, idx)
            xd, yd = distort(x, y, (model.k1, model.k2, model.p1, model.p2, model.k3))
            pixels[idx, 0] = model.fx * xd + model.cx
            pixels[idx, 1] = model.fy * yd + model.cy
        ok = np.all(np.isfinite(pixels), axis=-1)
        return pixels, ok

    def jacobian(self, model, points):
        n = points.shape[0]
        F = self.free.size
        dq_dparams = np.zeros((n, 2, F))
        dq_dpoints = np.zeros((n, 2, 3))
        coeffs = (model.k1, model.k2, model.p1, model.p2, model.k3)
        for half, idx in zip((Half.LEFT, Half.RIGHT), self.groups, strict=False):
            if idx.size == 0:
                continue
            P = points[idx]
            x, y = self._x[idx], self._y[idx]
            good = np.isfinite(x) & np.isfinite(y)
            x, y = np.where(good, x, 0.0), np.where(good, y, 0.0)
            _, q_dxy, q_dintr = _lens_pixels_and_jacobians(
                x, y, model.fx, model.fy, model.cx, model.cy, coeffs
            )
            for j, name in enumerate(_CAMERA):
                if name in self._free_names:
                    dq_dparams[idx, :, self._col[name]] = q_dintr[:, :, j]
            G_xy, _ = _miss_jacobian_lens(model, x, y, half, P)
            _, d, _ = _miss_at_depth(model, x, y, half, P)
            G_P = np.zeros((idx.size, 2, 3))
            G_P[:, 0, 0] = -1.0
            G_P[:, 1, 1] = -1.0
            G_P[:, 0, 2] = d[:, 0] / d[:, 2]
            G_P[:, 1, 2] = d[:, 1] / d[:, 2]
            names = [nm for nm in _PRISM[half] if nm in self._free_names]
            G_theta = np.zeros((idx.size, 2, len(names)))
            for k, name in enumerate(names):
                G_theta[:, :, k] = _miss_derivative(model, model.index(name), x, y, half, P)
            rhs = np.concatenate([G_theta, G_P], axis=-1)
            dxy = -_solve2(G_xy, rhs)  # (N, 2, K + 3)
            dq = q_dxy @ dxy
            for k, name in enumerate(names):
                dq_dparams[idx, :, self._col[name]] += dq[:, :, k]
            dq_dpoints[idx] = dq[:, :, len(names) :]
            bad = idx[~good]
            dq_dparams[bad] = 0.0
            dq_dpoints[bad] = 0.0
        return dq_dparams, dq_dpoints


# ----- any model: finite differences of the public projection --------------------------------


class FiniteDifferenceProjector(Projector):
    """Central differences of :meth:`CameraModel.project`: the fallback for new models.

    Every parameter step builds a new model, so this costs ``2 (F + 3)`` projections per
    Jacobian; models with a cheaper rule get their own projector.
    """

    def _project_raw(self, model, points):
        n = points.shape[0]
        pixels = np.full((n, 2), np.nan)
        for half, idx in zip((Half.LEFT, Half.RIGHT), self.groups, strict=False):
            if idx.size:
                pixels[idx] = model.project(points[idx], half).pixels
        return pixels

    def project(self, model, points):
        pixels = self._project_raw(model, points)
        return pixels, np.all(np.isfinite(pixels), axis=-1)

    def jacobian(self, model, points):
        n = points.shape[0]
        dq_dparams = np.zeros((n, 2, self.free.size))
        for k, i in enumerate(self.free):
            step = FD_STEP_PARAM * max(1.0, abs(model.params[i]))
            hi, lo = model.params.copy(), model.params.copy()
            hi[i] += step
            lo[i] -= step
            diff = self._project_raw(model.with_params(hi), points)
            diff -= self._project_raw(model.with_params(lo), points)
            dq_dparams[:, :, k] = diff / (2 * step)
        dq_dpoints = np.zeros((n, 2, 3))
        h = 1e-6  # mm
        for k in range(3):
            hi, lo = points.copy(), points.copy()
            hi[:, k] += h
            lo[:, k] -= h
            dq_dpoints[:, :, k] = (self._project_raw(model, hi) - self._project_raw(model, lo)) / (
                2 * h
            )
        bad = ~np.isfinite(dq_dparams).all(axis=(1, 2)) | ~np.isfinite(dq_dpoints).all(axis=(1, 2))
        dq_dparams[bad] = 0.0
        dq_dpoints[bad] = 0.0
        return dq_dparams, dq_dpoints


def projector_for(
    model: CameraModel, halves: np.ndarray, start: np.ndarray | None = None
) -> Projector:
    """The projector of a model kind (closed form or implicit where known, else finite
    differences); ``start`` is a previous projector's :meth:`Projector.state`."""
    kinds = {"pinhole": PinholeProjector, "raytrace": RaytraceProjector}
    return kinds.get(model.NAME, FiniteDifferenceProjector)(model, halves, start)


def board_points_in_model(rvecs: np.ndarray, tvecs: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``R(rvec) X + t`` per observation: rvecs, tvecs (N, 3), X (N, 3) -> (N, 3) mm."""
    R = rotation_matrix(rvecs)
    return np.einsum("nij,nj->ni", R, X) + tvecs
