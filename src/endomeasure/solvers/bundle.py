"""Bundle adjustment of a camera model and one board pose per image (SPEC 6).

The same cost for every model: the reprojection error in pixels of every corner seen
in either half (maximum likelihood under Gaussian pixel noise). :func:`refine` fits the
model's free parameters and the poses; :func:`fit_with_outliers` repeats it without the
outliers; both use only the model contract (the model's own
:meth:`~endomeasure.models.base.CameraModel.projector`), so they serve calibration and
every model's initialiser alike.

Outliers: after a fit, a corner whose residual length exceeds ``outlier_sigmas`` times
the robust per-axis noise ``sigma = 1.4826 * median(|r|)`` (over all residual
components; never below ``OUTLIER_FLOOR_PX``) is dropped, and the fit is repeated from
its solution until the set of corners within the threshold no longer changes. Every
decision is made on every corner: one dropped by an early, rougher fit comes back when
the later fit explains it (else the first round's misfit would stay hidden as
"outliers"). For Gaussian noise a 5-sigma residual length has probability
exp(-12.5) ~ 4e-6, so clean data lose nothing.

A view most of whose corners fail that test has a wrong pose, not wrong corners (a
corner detector does not err on a whole board at once): an excluded view's pose is no
longer refined, so it would stay wrong and its corners lost for good. Before each
decision such a view's pose is re-fitted alone to its corners with the model held
(:func:`_repose`, by least trimmed squares), from its current pose and from its mirror
image about the line of sight (the two-fold ambiguity of a small or distant plane's
pose: both look alike in the image to first order, and a per-half pose start may pick
the wrong one); its corners that then fit take part again.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from endomeasure.errors import CalibrationError
from endomeasure.geometry.rotations import (
    rotation_jacobian,
    rotation_matrix,
    rotation_vector,
    skew,
)
from endomeasure.models.base import CameraModel
from endomeasure.models.start import Fit, Observations

__all__ = [
    "BundleProblem",
    "OutlierFit",
    "refine",
    "all_residuals",
    "fit_with_outliers",
    "scaled_normal_matrix",
    "OUTLIER_FLOOR_PX",
]

OUTLIER_FLOOR_PX = 0.1
"""Residuals below this are never called outliers: no corner detector is more accurate,
and exact synthetic data would otherwise make rounding noise look like outliers."""
FAILED_RESIDUAL_PX = 1e3
"""Residual given to a corner whose projection fails during the optimisation (ray aiming
lost, behind the probe): large and constant, so steps into failure are rejected."""
INVALID_MODEL_RESIDUAL_PX = 1e6
"""Residual of every corner for a trial step outside the model's valid domain (a face
behind the lens): larger than any real cost, so such a step is never accepted."""


class BundleProblem:
    """The bundle problem over a subset of observations: parameters + one pose per image."""

    def __init__(
        self, model: CameraModel, obs: Observations, use: np.ndarray, state: np.ndarray | None
    ):
        self.template = model
        self.free = np.flatnonzero(model.free_mask)
        self.F = self.free.size
        self.rows = np.flatnonzero(use)
        images = np.unique(obs.image[self.rows])
        self.images = images
        self.pose_of_obs = np.searchsorted(images, obs.image[self.rows])
        self.X = obs.board_points[self.rows]
        self.q = obs.pixels[self.rows]
        self.projector = model.projector(
            obs.half[self.rows], None if state is None else state[self.rows]
        )
        self.n = self.F + 6 * images.size
        self.m = 2 * self.rows.size
        # sparsity pattern: each residual pair touches the F parameters and its pose's 6
        M = self.rows.size
        cols = np.concatenate(
            [
                np.broadcast_to(np.arange(self.F), (M, self.F)),
                self.F + 6 * self.pose_of_obs[:, None] + np.arange(6)[None, :],
            ],
            axis=1,
        )
        self._cols = np.repeat(cols, 2, axis=0).reshape(-1)
        self._indptr = np.arange(0, 2 * M * (self.F + 6) + 1, self.F + 6)
        self._last = None  # (x, model, rvecs, points) of the last valid residuals

    def pack(self, model, rvecs, tvecs) -> np.ndarray:
        poses = np.concatenate([rvecs[self.images], tvecs[self.images]], axis=1)
        return np.concatenate([model.params[self.free], poses.reshape(-1)])

    def unpack(self, x: np.ndarray):
        p = self.template.params.copy()
        p[self.free] = x[: self.F]
        poses = x[self.F :].reshape(-1, 6)
        return self.template.with_params(p), poses[:, :3], poses[:, 3:]

    def points(self, rv, tv):
        R = rotation_matrix(rv)[self.pose_of_obs]
        return np.einsum("nij,nj->ni", R, self.X) + tv[self.pose_of_obs]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        self._last = None
        try:
            model, rv, tv = self.unpack(x)
            P = self.points(rv, tv)
            q, ok = self.projector.project(model, P)
        except ValueError:
            # a trial step outside the model's valid domain (a face behind the lens, a
            # negative focal length): a large constant cost makes the solver reject it
            return np.full(self.m, INVALID_MODEL_RESIDUAL_PX)
        r = q - self.q
        r[~ok] = FAILED_RESIDUAL_PX
        self._last = (x.copy(), model, rv, P)
        return r.reshape(-1)

    def jacobian_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-observation Jacobians: parameters (M, 2, F) and own pose (M, 2, 6); zero
        outside the model's valid domain (where the cost is constant)."""
        if not (self._last is not None and np.array_equal(self._last[0], x)):
            self.residuals(x)
        if self._last is None:
            return np.zeros((self.rows.size, 2, self.F)), np.zeros((self.rows.size, 2, 6))
        _, model, rv, P = self._last
        # a corner whose derivative cannot be traced (at the edge of total internal
        # reflection) comes back zero: it contributes nothing to the step
        dq_dparams, dq_dp = self.projector.jacobian(model, P)
        # d P / d(rvec, t) = [-[R X]_x J_l(rvec), I]
        RX = P - x[self.F :].reshape(-1, 6)[self.pose_of_obs, 3:]
        dP_drv = -skew(RX) @ rotation_jacobian(rv)[self.pose_of_obs]
        return dq_dparams, np.concatenate([dq_dp @ dP_drv, dq_dp], axis=-1)

    def jacobian(self, x: np.ndarray):
        """Sparse residual Jacobian, shape (m, n): each row pair has F + 6 entries."""
        import scipy.sparse as sp

        dq_dparams, dq_dpose = self.jacobian_blocks(x)
        blocks = np.concatenate([dq_dparams, dq_dpose], axis=-1)  # (M, 2, F + 6)
        return sp.csr_matrix((blocks.reshape(-1), self._cols, self._indptr), shape=(self.m, self.n))

    def blocks(self, x: np.ndarray):
        """Row-wise parameter and pose Jacobians for the covariance: (m, F), (m, 6), pose of row."""
        dq_dparams, dq_dpose = self.jacobian_blocks(x)
        return (
            dq_dparams.reshape(self.m, self.F),
            dq_dpose.reshape(self.m, 6),
            np.repeat(self.pose_of_obs, 2),
        )


LSMR_OPTIONS = {"atol": 1e-12, "btol": 1e-12, "maxiter": 200}
"""Tolerances of the inner sparse solver of each trust-region step: tight, because
inexact steps stall the final convergence (scipy's defaults leave ~1e-6 relative)."""
RESTART_MIN_GAIN = 1e-6
"""Relative cost decrease for which a fit stopped by ``xtol`` is started again."""
_PRECONDITION_RIDGE = 1e-10  # relative ridge keeping the start's normal matrix factorable


def scaled_normal_matrix(J) -> tuple[np.ndarray, np.ndarray]:
    """The normal matrix ``J^T J`` (dense) of a sparse Jacobian, scaled to unit diagonal:
    ``(D J^T J D, d)`` with ``D = diag(d)``, ``d = diag(J^T J)^-1/2`` (1 where a column
    is zero), so that its solves are not ruled by the unknowns' units."""
    N = (J.T @ J).toarray()
    diag = np.diag(N).copy()
    d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    return N * d[:, None] * d[None, :], d


def _least_squares(problem: BundleProblem, x0: np.ndarray, max_nfev: int):
    """``scipy.optimize.least_squares`` (trust-region reflective, LSMR steps), whitened.

    The unknowns are made unitless and decorrelated at the start: with the start's
    normal matrix ``N0 = J0^T J0`` (small and dense: F + 6 I unknowns), column-scaled
    by ``D = diag(N0)^-1/2`` and factored ``D N0 D = L L^T``, the solver works on
    ``z`` with ``x = x0 + D L^-T z``. Near the start the Jacobian in ``z`` is
    orthonormal, so each LSMR step solve takes a handful of iterations instead of
    hundreds (distortion terms are strongly correlated).

    Why not MINPACK's Levenberg-Marquardt: a trial step that loses a few corners (a ray
    at the edge of total internal reflection) makes it shrink its step until ``xtol``
    stops it far from the minimum; the trust-region solver recovers.
    """
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import least_squares
    from scipy.sparse.linalg import LinearOperator

    Nn, d = scaled_normal_matrix(problem.jacobian(x0))
    Nn[np.diag_indices_from(Nn)] += _PRECONDITION_RIDGE
    L = cholesky(Nn, lower=True)
    P = d[:, None] * solve_triangular(L, np.eye(L.shape[0]), lower=True, trans="T")

    def fun(z):
        return problem.residuals(x0 + P @ z)

    # a unit step in z changes the linearised residuals by 1 px (RSS): let the first
    # trust region reach the size of the residual to be removed
    radius = max(1.0, float(np.linalg.norm(problem.residuals(x0))))

    def jac(z):
        J = problem.jacobian(x0 + P @ z)
        return LinearOperator(
            J.shape, matvec=lambda v: J @ (P @ v), rmatvec=lambda u: P.T @ (J.T @ u)
        )

    ls = least_squares(
        fun,
        np.zeros_like(x0),
        jac=jac,
        method="trf",
        x_scale=radius,
        tr_solver="lsmr",
        tr_options=LSMR_OPTIONS,
        ftol=1e-12,
        xtol=1e-12,
        gtol=1e-10,
        max_nfev=max_nfev,
    )
    ls.x = x0 + P @ ls.x
    return ls


def refine(
    model: CameraModel,
    obs: Observations,
    rvecs: np.ndarray,
    tvecs: np.ndarray,
    use: np.ndarray,
    max_nfev: int,
    state: np.ndarray | None = None,
) -> Fit:
    """Jointly refine the free model parameters and the poses of the used observations.

    ``state`` is a previous fit's projector state over the same observations (warm starts).
    """
    problem = BundleProblem(model, obs, use, state)
    ls = _least_squares(problem, problem.pack(model, rvecs, tvecs), max_nfev)
    nfev = ls.nfev
    # xtol: the trust region shrank to nothing. In a long, narrow valley (the glass index
    # against the face tilts) that can happen far from the minimum, because the start's
    # whitening no longer fits the valley: start again, whitened where it stopped, while
    # that still lowers the cost
    while ls.status == 3 and nfev < max_nfev:
        again = _least_squares(problem, ls.x, max_nfev - nfev)
        nfev += again.nfev
        if not again.cost < ls.cost * (1.0 - RESTART_MIN_GAIN):
            break
        ls = again
    ls.nfev = nfev
    try:
        fitted, rv, tv = problem.unpack(ls.x)
    except ValueError as exc:
        raise CalibrationError(
            f"the {model.NAME} calibration did not converge (it left the model's valid "
            f"domain: {exc})",
            hint="check the detections, or add images at more distances and tilts",
        ) from None
    rvecs, tvecs = rvecs.copy(), tvecs.copy()
    rvecs[problem.images] = rv
    tvecs[problem.images] = tv
    new_state = problem.projector.state()
    if new_state is not None:
        full = np.full((obs.image.size, new_state.shape[1]), np.nan)
        if state is not None:
            full[:] = state
        full[problem.rows] = new_state
        new_state = full
    return Fit(fitted, rvecs, tvecs, int(ls.status), str(ls.message), int(ls.nfev), new_state)


def all_residuals(model, obs: Observations, rvecs, tvecs, state=None) -> np.ndarray:
    """Projected minus detected pixels of every observation, shape (M, 2), NaN where failed."""
    projector = model.projector(obs.half, state)
    R = rotation_matrix(rvecs)[obs.image]
    P = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    q, ok = projector.project(model, P)
    r = q - obs.pixels
    r[~ok] = np.nan
    return r


class OutlierFit(NamedTuple):
    """The last fit of :func:`fit_with_outliers` and what the outlier rule decided."""

    fit: Fit
    residuals: np.ndarray  # (M, 2) px, every observation, NaN where the projection failed
    inliers: np.ndarray  # (M,) bool: the observations of the last fit
    threshold_px: float  # residual length above which observations were dropped
    nfev: int  # residual evaluations over all rounds
    rounds: int  # fits run


def fit_with_outliers(
    model: CameraModel,
    obs: Observations,
    rvecs: np.ndarray,
    tvecs: np.ndarray,
    *,
    max_nfev: int,
    outlier_sigmas: float,
    max_rounds: int,
    state: np.ndarray | None = None,
) -> OutlierFit:
    """Refine, drop outliers by the rule in the module docstring, refit, until no new
    outlier appears or ``max_rounds`` outlier rounds have run."""
    use = np.ones(obs.image.size, dtype=bool)
    nfev = 0
    rounds = 0
    while True:
        fit = refine(model, obs, rvecs, tvecs, use, max_nfev, state)
        nfev += fit.nfev
        rounds += 1
        model, rvecs, tvecs, state = fit.model, fit.rvecs, fit.tvecs, fit.state
        r = all_residuals(model, obs, rvecs, tvecs, state)
        sigma = 1.4826 * float(np.nanmedian(np.abs(r[use])))
        threshold = max(outlier_sigmas * sigma, OUTLIER_FLOOR_PX)
        fit, r, spent = _repose(fit, obs, r, threshold, max_nfev)
        model, rvecs, tvecs, state = fit.model, fit.rvecs, fit.tvecs, fit.state
        nfev += spent
        new_use = np.linalg.norm(r, axis=-1) <= threshold  # NaN (failed) counts as an outlier
        if np.array_equal(new_use, use) or rounds > max_rounds:
            return OutlierFit(fit, r, use, threshold, nfev, rounds)
        use = new_use


def _repose(fit: Fit, obs: Observations, r: np.ndarray, threshold: float, max_nfev: int):
    """Re-fit the pose of every view with most of its corners above ``threshold``, the
    model held, robustly to the view's corners (:func:`_trimmed_pose`), from its pose and
    from that pose mirrored (:func:`mirrored_pose`); keep the new pose that fits the most
    of them, if more than before.

    Returns the fit with the new poses, the residuals ``r`` updated and the evaluations
    spent.
    """
    length = np.linalg.norm(r, axis=-1)
    bad = ~(length <= threshold)
    nfev = 0
    held = fit.model.with_config(fixed=frozenset(fit.model.PARAM_NAMES))
    rvecs, tvecs, state = fit.rvecs.copy(), fit.tvecs.copy(), fit.state
    changed = False
    for image in np.unique(obs.image[bad]):
        rows = obs.image == image
        if bad[rows].mean() <= 0.5:
            continue
        best, fitting = None, np.sum(~bad[rows])
        centre = obs.board_points[rows].mean(axis=0)
        for start in ((rvecs[image], tvecs[image]),
                      mirrored_pose(rvecs[image], tvecs[image], centre)):  # fmt: skip
            rv, tv = rvecs.copy(), tvecs.copy()
            rv[image], tv[image] = start
            posed, r_new, spent = _trimmed_pose(held, obs, rv, tv, rows, max_nfev, state)
            nfev += spent
            count = np.sum(np.linalg.norm(r_new, axis=-1) <= threshold)
            if count > fitting:
                best, fitting = (posed, r_new), count
        if best is not None:
            posed, r_new = best
            rvecs[image], tvecs[image] = posed.rvecs[image], posed.tvecs[image]
            state = posed.state
            r = r.copy()
            r[rows] = r_new
            changed = True
    if changed:
        fit = fit._replace(rvecs=rvecs, tvecs=tvecs, state=state)
    return fit, r, nfev


POSE_TRIM_STEPS = 5  # a cap on the concentration steps; they stop when the subset holds
MIN_POSE_CORNERS = 4  # a plane's pose needs four points


def _trimmed_pose(held, obs: Observations, rvecs, tvecs, rows: np.ndarray, max_nfev: int, state):
    """One view's pose, the model ``held``, by least trimmed squares over its ``rows``:
    fitted to all of them, then repeatedly to the half with the smallest residuals
    (concentration steps), so that a minority of gross corners cannot pull it. Returns
    (fit, residuals of ``rows``, evaluations spent)."""
    posed = refine(held, obs, rvecs, tvecs, rows, max_nfev, state)
    nfev = posed.nfev
    r = all_residuals(held, obs, posed.rvecs, posed.tvecs, posed.state)[rows]
    subset = None
    for _ in range(POSE_TRIM_STEPS):
        length = np.where(np.isfinite(r).all(axis=-1), np.linalg.norm(r, axis=-1), np.inf)
        keep = np.argsort(length, kind="stable")[: max(MIN_POSE_CORNERS, (rows.sum() + 1) // 2)]
        if subset is not None and np.array_equal(np.sort(keep), subset):
            break
        subset = np.sort(keep)
        use = np.zeros_like(rows)
        use[np.flatnonzero(rows)[subset]] = True
        posed = refine(held, obs, posed.rvecs, posed.tvecs, use, max_nfev, posed.state)
        nfev += posed.nfev
        r = all_residuals(held, obs, posed.rvecs, posed.tvecs, posed.state)[rows]
    return posed, r, nfev


def mirrored_pose(rvec: np.ndarray, tvec: np.ndarray, centre: np.ndarray):
    """The other pose of a plane that images alike to first order: the board turned about
    its point ``centre`` (board frame) so that its normal is mirrored about the line of
    sight from the frame's origin, its in-plane orientation kept. (A half-turn about the
    line of sight, then one about the new normal: the offsets across the line of sight
    are kept, the depth offsets change sign.) Returns (rvec, tvec)."""
    R = rotation_matrix(np.asarray(rvec, dtype=float))
    c = R @ centre + tvec
    sight = c / np.linalg.norm(c)
    normal = 2.0 * (R[:, 2] @ sight) * sight - R[:, 2]
    F = rotation_matrix(np.pi * normal) @ rotation_matrix(np.pi * sight)
    return rotation_vector(F @ R), F @ (tvec - c) + c
