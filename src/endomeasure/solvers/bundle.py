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
    "gauss_newton_step",
    "OUTLIER_FLOOR_PX",
    "NUMERICAL_FLOOR_PX",
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

    def normal_equations(self, x: np.ndarray, r: np.ndarray, active: np.ndarray):
        """``(J^T J, J^T r)`` over the ``active`` residual components (dense, n x n and
        n), assembled from the per-observation blocks: the parameters' block, each
        pose's 6 x 6 block and their cross terms, without the sparse Jacobian."""
        A, B = self.jacobian_blocks(x)
        w = active.reshape(-1, 2, 1)
        A, B, rw = np.where(w, A, 0.0), np.where(w, B, 0.0), np.where(active, r, 0.0)
        F, M = self.F, self.rows.size
        At, Bt = A.transpose(0, 2, 1), B.transpose(0, 2, 1)
        cross = self._per_pose((At @ B).reshape(M, 6 * F)).reshape(self.images.size, F, 6)
        poses = self._per_pose((Bt @ B).reshape(M, 36)).reshape(-1, 6, 6)
        N = np.zeros((self.n, self.n))
        A2 = A.reshape(2 * M, F)
        N[:F, :F] = A2.T @ A2
        N[:F, F:] = cross.transpose(1, 0, 2).reshape(F, self.n - F)
        N[F:, :F] = N[:F, F:].T
        for k, block in enumerate(poses):
            N[F + 6 * k : F + 6 * k + 6, F + 6 * k : F + 6 * k + 6] = block
        g_poses = self._per_pose((Bt @ rw.reshape(M, 2, 1)).reshape(M, 6))
        g = np.concatenate([A2.T @ rw, g_poses.reshape(-1)])
        return N, g

    def _per_pose(self, values: np.ndarray) -> np.ndarray:
        """Sums of per-observation rows ``values`` (M, k) over each pose's observations."""
        order = np.argsort(self.pose_of_obs, kind="stable")
        starts = np.searchsorted(self.pose_of_obs[order], np.arange(self.images.size))
        return np.add.reduceat(values[order], starts, axis=0)

    def blocks(self, x: np.ndarray):
        """Row-wise parameter and pose Jacobians for the covariance: (m, F), (m, 6), pose of row."""
        dq_dparams, dq_dpose = self.jacobian_blocks(x)
        return (
            dq_dparams.reshape(self.m, self.F),
            dq_dpose.reshape(self.m, 6),
            np.repeat(self.pose_of_obs, 2),
        )


STEP_TOL_SIGMAS = 1e-3
"""A fit has converged when the Gauss-Newton step still to take moves the unknowns by
less than this many of their own standard deviations (in the Mahalanobis norm of the
normal matrix, the noise estimated from the current cost): any further change is
invisible against the calibration's uncertainty."""
NUMERICAL_FLOOR_PX = 1e-6
"""The precision the models' projections promise (SPEC 4): residuals below it are
round-off, which no parameter explains, and a step whose predicted gain is below it
over every unknown is not worth taking."""
MAX_DAMPING = 1e12
"""Damping (the step is ``1 / (1 + damping)`` of the Gauss-Newton step) beyond which
the fit has stalled: no step along it lowers the cost (it loses corners at once, or
the cost is at its round-off)."""
EDGE_FRACTION = 0.01
"""The largest share of a fit's corners that one step may leave out at the model's
domain edge (:func:`_least_squares`); a step that loses more is a wild one."""
_RIDGE = 1e-10  # relative ridge keeping a singular normal matrix factorable


class _Solution(NamedTuple):
    x: np.ndarray
    cost: float
    status: int  # -1 cannot go on, 0 evaluations used up, 2 converged, 3 stalled (as scipy)
    message: str
    nfev: int


def gauss_newton_step(N: np.ndarray, g: np.ndarray) -> np.ndarray | None:
    """The Gauss-Newton step ``-N^-1 g`` of the normal matrix ``N`` and gradient ``g``,
    solved by Cholesky on ``N`` scaled to unit diagonal (so that the unknowns' units do
    not rule it) plus a relative ridge; None where even that cannot be factored."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    diag = np.diag(N)
    d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    Nn = N * d[:, None] * d[None, :]
    Nn[np.diag_indices_from(Nn)] += _RIDGE
    try:
        factor = cho_factor(Nn, lower=True, check_finite=False)
    except (LinAlgError, ValueError):
        return None
    return -d * cho_solve(factor, d * g, check_finite=False)


def _least_squares(problem: BundleProblem, x0: np.ndarray, max_nfev: int) -> _Solution:
    """Gauss-Newton on the exact normal equations, its steps shortened by a damping in
    their own metric (Nielsen's update).

    The unknowns are few (F + 6 per image, a few hundred), so every step solves the
    normal equations ``N = J^T J`` exactly by Cholesky: a few milliseconds, where an
    iterative solve of the sparse system (LSMR) took most of a calibration's time and
    left each step inexact.

    The step taken is the Gauss-Newton step ``-N^-1 g`` divided by ``1 + damping``: the
    Levenberg-Marquardt step with the damping matrix ``N`` itself. It keeps the Gauss-
    Newton direction, along the valley of strongly correlated unknowns (the glass index
    against the face tilts, a pinhole's radial terms), where a damping of the identity
    or of Marquardt's diagonal turns the step across the valley and crawls. A trial step
    that raises the cost is rejected and the damping raised; one that lowers it is taken
    and the damping lowered by how well the quadratic model predicted the gain. Stops
    when converged (:data:`STEP_TOL_SIGMAS`), stalled (no shortened step lowers the
    cost: :data:`MAX_DAMPING`) or after ``max_nfev`` residual evaluations.

    A corner that a trial step pushes out of the model's domain costs
    :data:`FAILED_RESIDUAL_PX`, so wild steps are rejected. But a corner at the domain's
    edge (at total internal reflection, on a face's rim) fails under any step however
    short, and would stall the fit where it stands: when a rejected step's only fault is
    a few such corners (at most :data:`EDGE_FRACTION` of the fit's corners) and it
    lowers the cost of the others, they are left out of the rest of this fit and the
    step is taken. The outlier rule then judges them with every other corner.
    """
    x, r = x0, problem.residuals(x0)
    active = ~_failed(r)  # per residual component
    nfev, damping, growth = 1, 1e-3, 2.0
    if not active.any():
        return _Solution(x, np.inf, -1, "no corner can be projected from the start", nfev)
    dof = max(problem.m - problem.n, 1)
    while True:
        rw = np.where(active, r, 0.0)
        cost = 0.5 * float(rw @ rw)
        N, g = problem.normal_equations(x, r, active)
        newton = gauss_newton_step(N, g)
        if newton is None:
            return _Solution(x, cost, -1, "the normal matrix is not finite", nfev)
        left = -0.5 * float(g @ newton)  # the gain the full step predicts
        # converged: that gain against the noise the cost implies
        tolerance = max(STEP_TOL_SIGMAS**2 * cost / dof, 0.5 * problem.n * NUMERICAL_FLOOR_PX**2)
        if left <= tolerance:
            return _Solution(x, cost, 2, "converged: the step left is below "
                             f"{STEP_TOL_SIGMAS:g} standard deviations", nfev)  # fmt: skip
        while True:
            t = 1.0 / (1.0 + damping)
            predicted = left * t * (2.0 - t)
            if damping > MAX_DAMPING or predicted <= tolerance:
                return _Solution(x, cost, 3, "stalled: no step lowers the cost", nfev)
            if nfev >= max_nfev:
                return _Solution(x, cost, 0, "the evaluations allowed were used up", nfev)
            x_new = x + t * newton
            r_new = problem.residuals(x_new)
            nfev += 1
            keep = active & ~_failed(r_new)
            lost = int(np.sum(active & ~keep)) // 2
            if lost and lost > max(1, int(EDGE_FRACTION * active.sum() / 2)):
                keep = active  # a wild step: it pays for every corner it loses
            kept_new = np.where(keep, r_new, 0.0)
            kept_old = np.where(keep, r, 0.0)
            rho = 0.5 * float(kept_old @ kept_old - kept_new @ kept_new) / predicted
            if rho > 0:
                x, r, active = x_new, r_new, keep
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                growth = 2.0
                break
            damping, growth = damping * growth, growth * 2.0


def _failed(r: np.ndarray) -> np.ndarray:
    """Residual components of corners whose projection failed (see :meth:`residuals`)."""
    return np.abs(r) >= FAILED_RESIDUAL_PX


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
