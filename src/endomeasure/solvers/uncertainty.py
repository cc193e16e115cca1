"""Uncertainty of measurements: unscented transform, linear propagation, Monte Carlo.

A measurement ("triangulate the points, then apply the kind's formula") is treated as a
black box ``f`` of one stacked input vector (SPEC section 8, the paper's Section 4)

    x = [u_L, v_L, u_R, v_R of point 1, ..., of point n,  free model parameters]

with a Gaussian input covariance ``P`` built from the pixel noise ``sigma``, its
correlations and, optionally, the calibration covariance of the free parameters. Three
propagators answer "what are the mean and the standard deviation of ``f(x)``":

- :func:`unscented` — the scaled unscented transform (Julier 2002), 2L+1 sigma points;
  the paper's choice: no derivatives, and second-order exact for the mean (the
  *bias* ``E f - f(x0)`` that linear propagation cannot see). Optionally with *cross
  points* on chosen columns (:data:`CROSS_AUTO`), which make the variance second-order
  exact too, where the plain UT is exact only for curvature of rank one;
- :func:`linearised` — first order, ``J P J^T`` with a central-difference Jacobian along
  the columns of ``sqrt(P)``; a cheap cross-check, zero bias by construction;
- :func:`monte_carlo` — the reference, N seeded samples.

All three are vectorised over M measurements of the same kind and point count: the
black box takes inputs ``(M, K, L)`` and returns values ``(M, K)``, and every
propagator makes a single call for all samples of all measurements (the measurement
function batches them into one triangulation per parameter vector).

Budget by source: when ``P`` is block-diagonal over named blocks (``image`` pixels,
``calibration`` parameters), each propagator also reports the bias and standard
deviation due to each block alone (:attr:`Propagation.parts`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.defaults import MAX_SIGMA_PX
from endomeasure.errors import BadInputError
from endomeasure.geometry.rays import intersect_plane, plane_through
from endomeasure.models.base import ParamBatch
from endomeasure.solvers.triangulate import triangulate

if TYPE_CHECKING:
    from endomeasure.models.base import CameraModel

__all__ = [
    "CROSS_AUTO",
    "DEFAULT_ALPHA",
    "DEFAULT_BETA",
    "DEFAULT_KAPPA",
    "METHODS",
    "MeasurementFunction",
    "Propagation",
    "input_covariance",
    "linearised",
    "monte_carlo",
    "pixel_covariance",
    "pixel_sigmas",
    "checked_sigma",
    "propagate",
    "unscented",
]

METHODS = ("ut", "linear", "mc")

DEFAULT_ALPHA = 0.1
"""Spread of the sigma points: they lie at ``+-alpha sqrt(L + kappa)`` standard deviations
along the columns of ``sqrt(P)``. The variance the UT returns is (see
:func:`unscented`) ``sum_i Wi [(f+_i - f0)^2 + (f-_i - f0)^2] + (beta - alpha^2) b^2``:
for a quadratic ``f`` the first sum over-counts the quartic terms by ``(L + lambda) / 4``
per axis, so a *small* alpha is what makes the scaled UT second-order accurate.
Not smaller than 0.1: the sigma points then stay at ~0.3 sigma
from the centre, far above the triangulation's ~1e-9 px convergence noise, and the
centre weight ``1 - 1/alpha^2 = -99`` amplifies no round-off (the textbook 1e-3 gives
-1e6)."""

DEFAULT_BETA = 2.0
"""Prior knowledge of the input distribution: 2 is optimal for Gaussian inputs (it makes
the variance exact for quadratic ``f`` with a rank-one Hessian, e.g. a length, in the
small-alpha limit); it must be >= alpha^2 for the variance to stay non-negative.

Why rank one: with a small alpha the 2L+1 points see the curvature only through its
diagonal in the sigma-point basis, and the variance they return is ``J P J^T + beta/4
tr(HP)^2`` where the truth (Gaussian input, quadratic ``f``) is ``J P J^T + 1/2
tr((HP)^2)``. The two agree for every ``H`` only if ``HP`` has a single non-zero
eigenvalue. A polyline of k segments facing the probe curves along k independent depth
differences and a polygon along its two tilts, so no single beta is right for them:
the plain UT over-predicts the std of such measurements (the mean stays right; the
figures are in ``docs/accuracy.md``, "UT against Monte Carlo"). Cross points
(``cross``, :func:`unscented`) remove that error; beta then only acts on the columns
without them (the calibration parameters)."""

CROSS_AUTO = "auto"
"""``cross`` value of :func:`unscented` that takes the columns from the black box's
``cross_columns`` attribute (None when it has none): the measurement black box knows
which of its inputs carry curvature of rank above one (:class:`MeasurementFunction`)."""

DEFAULT_KAPPA = 0.0
"""Secondary scaling (Julier 2002); 0 is the usual choice with a small alpha."""

FALLBACK_ALPHAS = (0.03, 0.01)
"""Smaller spreads tried, in order, for a measurement whose sigma points hit invalid
geometry (a pixel pushed out of its half, a ray in total internal reflection, a
parameter vector the model rejects). Julier's scaled UT exists for exactly this: it
keeps the second-order accuracy of the mean and covariance while moving the sigma
points towards the mean."""

LINEAR_STEP = 1e-2
"""Central-difference step of the linear method, in standard deviations along each
column of ``sqrt(P)``: small enough for an O(step^2) truncation error of 1e-4
relative, large enough that the triangulation's ~1e-9 px convergence noise is
negligible."""

MC_CHUNK = 200_000
"""Monte Carlo samples (times measurements) evaluated per black-box call: bounds memory."""


class Propagation(NamedTuple):
    """Predicted distribution of M measurement values (all arrays shape (M,))."""

    value: np.ndarray
    """``f(x0)``: the measurement of the observed input (mm or mm^2)."""
    mean: np.ndarray
    """Predicted mean of ``f(x)``."""
    bias: np.ndarray
    """``mean - value``: the predicted systematic error of the measurement."""
    std: np.ndarray
    """Predicted standard deviation."""
    parts: dict[str, tuple[np.ndarray, np.ndarray]]
    """Per input block (``'image'``, ``'calibration'``): ``(bias, std)`` due to that block
    alone. Empty when the covariance is not block-diagonal over the blocks."""
    n_invalid: np.ndarray
    """Sigma points / samples that fell into invalid geometry (first attempt for UT)."""
    alpha: np.ndarray
    """UT spread actually used (after fallbacks); NaN for other methods."""
    method: str


# ----- input covariance -------------------------------------------------------------------


def pixel_sigmas(sigma) -> np.ndarray:
    """``(sigma_u, sigma_v)`` of an image-noise argument: one number for both coordinates or
    a pair (u, v), px. Anything else, negative or not finite is a :class:`BadInputError`."""
    s = np.asarray(sigma, dtype=np.float64) if sigma is not None else np.array(np.nan)
    if s.ndim == 0:
        s = np.repeat(s, 2)
    if s.shape != (2,) or not (np.all(np.isfinite(s)) and np.all(s >= 0)):
        raise BadInputError(
            f"sigma must be a non-negative number of pixels or a pair (u, v), got {sigma}"
        )
    if np.any(s > MAX_SIGMA_PX):
        raise BadInputError(
            f"sigma {sigma} px is beyond {MAX_SIGMA_PX:g} px: detected points scatter by "
            "well under a pixel, and no error propagation means anything at such noise",
            hint="give the image noise in pixels, e.g. --sigma 0.05",
        )
    return s


def checked_sigma(sigma) -> float | tuple[float, float]:
    """An image-noise argument validated by :func:`pixel_sigmas`, as given: a float, or a
    ``(sigma_u, sigma_v)`` pair of floats."""
    s = pixel_sigmas(sigma)
    return float(s[0]) if np.ndim(sigma) == 0 else (float(s[0]), float(s[1]))


def pixel_covariance(
    n_points: int, sigma, rho_images: float = 0.0, rho_points: float = 0.0
) -> np.ndarray:
    """Covariance of the stacked pixel coordinates of a measurement's points.

    Parameters
    ----------
    n_points : int
    sigma : float or (float, float), px
        Standard deviation of each image coordinate, or of u and of v separately (the
        detection noise along the baseline, which sets the disparity, and across it need
        not be the same).
    rho_images : float
        Correlation between the errors of one point's left and right pixel (same
        coordinate, u with u and v with v).
    rho_points : float
        Correlation between the errors of different points (same half, same coordinate).

    Returns
    -------
    ndarray, shape (4 n, 4 n), px^2
        In the order ``u_L, v_L, u_R, v_R`` per point.

    Notes
    -----
    ``P = C_points (x) C_halves (x) diag(sigma_u^2, sigma_v^2)`` with ``C_points = (1 -
    rho_points) I + rho_points 1 1^T`` and ``C_halves = [[1, rho_images], [rho_images, 1]]``
    (Kronecker products), so a left u of one point and a right u of another correlate by
    ``rho_points * rho_images``. It is positive semi-definite exactly when both factors
    are: ``|rho_images| <= 1`` and ``-1/(n-1) <= rho_points <= 1``.
    """
    s = pixel_sigmas(sigma)
    if not (-1.0 <= rho_images <= 1.0):
        raise BadInputError(f"rho_images must lie in [-1, 1], got {rho_images}")
    low = -1.0 / (n_points - 1) if n_points > 1 else -1.0
    if not (low <= rho_points <= 1.0):
        raise BadInputError(
            f"rho_points must lie in [{low:g}, 1] for {n_points} points, got {rho_points}"
        )
    c_points = (1.0 - rho_points) * np.eye(n_points) + rho_points
    c_halves = np.array([[1.0, rho_images], [rho_images, 1.0]])
    return np.kron(np.kron(c_points, c_halves), np.diag(s**2))


def input_covariance(
    n_points: int,
    sigma: float | tuple[float, float] | None,
    rho_images: float = 0.0,
    rho_points: float = 0.0,
    param_cov: np.ndarray | None = None,
    *,
    pixel_std: np.ndarray | None = None,
    pixel_rho: np.ndarray | None = None,
    model_cov: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, slice]]:
    """Covariance of the stacked input ``[pixels, (offsets,) free parameters]`` and its
    blocks.

    Parameters
    ----------
    n_points, sigma, rho_images, rho_points
        See :func:`pixel_covariance`.
    pixel_std : ndarray, shape (n_points, 2 or 4) or (M, n_points, 2 or 4), px, optional
        Instead of ``sigma`` and the correlations: an independent standard deviation per
        point for its left and its right pixel (both coordinates alike), or for each of
        ``u_L, v_L, u_R, v_R``, e.g. an exact clicked pixel (0) and an automatic match at
        its own precision; with a leading M, one such table per measurement (each
        measured on its own image), and a batched covariance.
    pixel_rho : ndarray, shape (..., n_points, 2), optional
        With ``pixel_std``: the correlation of each point's u_L with its u_R and of its
        v_L with its v_R (errors shared by the two views of one point); else 0.
    param_cov : ndarray, shape (F, F), optional
        Covariance of the model's free parameters (in ``PARAM_NAMES`` order of the free
        ones), e.g. from calibration. Image and calibration errors are independent, so
        the result is block-diagonal.
    model_cov : ndarray, shape (4 n, 4 n) or (M, 4 n, 4 n), px^2, optional
        Covariance of the pixels' model-misfit offsets
        (:meth:`~endomeasure.solvers.misfit.ModelMisfit.covariance`), independent of the
        image noise and the parameters: the block ``model`` after the pixels.

    Returns
    -------
    cov : ndarray, shape (L, L) or (M, L, L), L = 4 n (+ 4 n) + F
    blocks : dict
        ``{'image': slice, 'model': slice, 'calibration': slice}`` (``model`` only with
        ``model_cov``, ``calibration`` only with ``param_cov``).
    """
    if pixel_std is not None:
        # input order per point: u_L, v_L, u_R, v_R
        var = np.asarray(pixel_std, dtype=np.float64) ** 2
        if var.shape[-1] == 2:  # one std for both coordinates of a half
            var = np.repeat(var, 2, axis=-1)
        var = var.reshape(*var.shape[:-2], 4 * n_points)
        pix = var[..., None] * np.eye(4 * n_points)
        if pixel_rho is not None:
            std = np.sqrt(var).reshape(*var.shape[:-1], n_points, 2, 2)  # (point, half, uv)
            cross = np.asarray(pixel_rho, dtype=np.float64) * std[..., 0, :] * std[..., 1, :]
            left = 4 * np.arange(n_points)[:, None] + np.arange(2)  # (n, 2): u_L, v_L
            cross = np.broadcast_to(cross, (*pix.shape[:-2], n_points, 2))
            pix[..., left, left + 2] = cross
            pix[..., left + 2, left] = cross
    elif sigma is None:
        raise BadInputError("the image noise is not given", hint="give sigma or pixel_std")
    else:
        pix = pixel_covariance(n_points, sigma, rho_images, rho_points)
    parts = {"image": pix}
    if model_cov is not None:
        mc = np.asarray(model_cov, dtype=np.float64)
        if mc.shape[-2:] != (4 * n_points, 4 * n_points) or not np.all(np.isfinite(mc)):
            raise BadInputError(
                f"the model-misfit covariance must be finite of shape (..., {4 * n_points}, "
                f"{4 * n_points}), got {mc.shape}"
            )
        parts["model"] = mc
    if param_cov is not None:
        pc = np.asarray(param_cov, dtype=np.float64)
        if pc.ndim != 2 or pc.shape[0] != pc.shape[1] or not np.all(np.isfinite(pc)):
            raise BadInputError(
                f"the parameter covariance must be a finite square matrix, got {pc.shape}"
            )
        parts["calibration"] = pc
    if len(parts) == 1:
        return pix, {"image": slice(0, 4 * n_points)}
    lead = np.broadcast_shapes(*(p.shape[:-2] for p in parts.values()))
    size = sum(p.shape[-1] for p in parts.values())
    cov = np.zeros((*lead, size, size))
    blocks, start = {}, 0
    for name, block in parts.items():
        sl = slice(start, start + block.shape[-1])
        cov[..., sl, sl] = block
        blocks[name] = sl
        start = sl.stop
    return cov, blocks


def _sqrt_columns(cov: np.ndarray, blocks: Mapping[str, slice] | None):
    """A square root ``S`` (``S S^T = cov``), batched (..., L, L), computed per block
    when ``cov`` is block-diagonal over ``blocks`` so that each column belongs to one
    block. Returns ``(S, separable)``."""
    cov = np.asarray(cov, dtype=np.float64)
    L = cov.shape[-1]
    separable = False
    if blocks:
        mask = np.zeros((L, L), dtype=bool)
        for sl in blocks.values():
            mask[sl, sl] = True
        covered = sum(sl.stop - sl.start for sl in blocks.values()) == L
        separable = covered and not np.any(cov[..., ~mask])
    parts = list(blocks.values()) if separable else [slice(0, L)]
    S = np.zeros(cov.shape)
    for sl in parts:
        w, v = np.linalg.eigh(cov[..., sl, sl])
        if np.any(w < -1e-9 * np.maximum(np.abs(w).max(axis=-1, keepdims=True), 1e-300)):
            raise BadInputError("the input covariance is not positive semi-definite")
        S[..., sl, sl] = v * np.sqrt(np.clip(w, 0.0, None))[..., None, :]
    return S, separable


def _as_batch(x0: np.ndarray, cov: np.ndarray):
    x0 = np.asarray(x0, dtype=np.float64)
    if x0.ndim == 1:
        x0 = x0[None]
    cov = np.asarray(cov, dtype=np.float64)
    L = x0.shape[-1]
    if cov.shape[-2:] != (L, L):
        raise ValueError(f"covariance shape {cov.shape} does not match inputs of length {L}")
    return x0, cov


def _block_columns(blocks: Mapping[str, slice], separable: bool) -> dict[str, np.ndarray]:
    if not separable:
        return {}
    return {name: np.arange(sl.start, sl.stop) for name, sl in blocks.items()}


# ----- the three propagators ----------------------------------------------------------------

BlackBox = Callable[[np.ndarray], np.ndarray]


def _ut_weights(L: int, alpha: float, beta: float, kappa: float):
    lam = alpha**2 * (L + kappa) - L
    c2 = L + lam
    wm0 = lam / c2
    wc0 = wm0 + 1.0 - alpha**2 + beta
    wi = 1.0 / (2.0 * c2)
    return np.sqrt(c2), wm0, wc0, wi


def _ut_moments(y: np.ndarray, L: int, alpha, beta, kappa, columns, cross=None):
    """Mean, variance and per-block parts from sigma-point values.

    ``y`` (M, 2L+1+P): the centre, the + and - points of every column, then one point
    ``x0 + c (s_i + s_j)`` per cross pair ``cross = (cols, iu, ju)`` (P pairs of the
    columns ``cols``; None for the plain UT).
    """
    c, wm0, wc0, wi = _ut_weights(L, alpha, beta, kappa)
    f0 = y[:, 0]
    dp = y[:, 1 : L + 1] - f0[:, None]
    dm = y[:, L + 1 : 2 * L + 1] - f0[:, None]
    b_i = wi * (dp + dm)  # (M, L) bias contribution of each column (h_ii / 2)
    # plain UT: cov = Wc0 (f0 - m)^2 + sum_i Wi [(f+ - m)^2 + (f- - m)^2]
    #               = sum_i D_i + (beta - alpha^2) b^2
    d_i = wi * (dp**2 + dm**2)
    curved = np.zeros(L, dtype=bool)
    pair_sq = np.zeros((y.shape[0], 0))
    if cross is not None:
        cols, iu, ju = cross
        curved[cols] = True
        # second-order exact on these columns: g_i^2 + h_ii^2 / 2 per column and h_ij^2
        # per pair, with g_i the central and h_ij the one-sided second difference
        g = (dp - dm) / (2.0 * c)
        h = (dp + dm) / c**2
        d_i = np.where(curved, g**2 + 0.5 * h**2, d_i)
        h_ij = (y[:, 2 * L + 1 :] - y[:, 1 + cols[iu]] - y[:, 1 + cols[ju]] + f0[:, None]) / c**2
        pair_sq = h_ij**2
        pair_cols = (cols[iu], cols[ju])
    bias = b_i.sum(axis=1)
    b_plain = b_i[:, ~curved].sum(axis=1)
    var = d_i.sum(axis=1) + pair_sq.sum(axis=1) + (beta - alpha**2) * b_plain**2
    parts = {}
    for name, cols_b in columns.items():
        bb = b_i[:, cols_b].sum(axis=1)
        plain = cols_b[~curved[cols_b]]
        vb = d_i[:, cols_b].sum(axis=1) + (beta - alpha**2) * b_i[:, plain].sum(axis=1) ** 2
        if pair_sq.shape[1]:
            inside = np.isin(pair_cols[0], cols_b) & np.isin(pair_cols[1], cols_b)
            vb = vb + pair_sq[:, inside].sum(axis=1)
        parts[name] = (bb, np.sqrt(np.clip(vb, 0.0, None)))
    del wm0, wc0  # folded into the closed form above
    return f0 + bias, bias, np.sqrt(np.clip(var, 0.0, None)), parts


def _cross_columns(f, cross, L: int, blocks, separable: bool) -> np.ndarray | None:
    """Column indices that get cross points, or None for the plain UT."""
    if cross is CROSS_AUTO or (isinstance(cross, str) and cross == CROSS_AUTO):
        cross = getattr(f, "cross_columns", None)
    if cross is None or cross is False:
        return None
    if cross is True:
        cols = np.arange(L)
    elif isinstance(cross, slice):
        cols = np.arange(L)[cross]
    elif isinstance(cross, (list, tuple)) and cross and all(isinstance(c, str) for c in cross):
        if not blocks or any(name not in blocks for name in cross):
            raise ValueError(f"unknown input blocks {cross!r} for cross points")
        # cross points must cover whole blocks; a non-separable covariance mixes them
        cols = (
            np.arange(L)
            if not separable
            else np.concatenate([np.arange(L)[blocks[name]] for name in cross])
        )
    else:
        cols = np.unique(np.asarray(cross, dtype=np.int64))
    if cols.size < 2:
        return None if cols.size == 0 else cols
    return cols


def unscented(
    f: BlackBox,
    x0: np.ndarray,
    cov: np.ndarray,
    *,
    alpha: float = DEFAULT_ALPHA,
    beta: float = DEFAULT_BETA,
    kappa: float = DEFAULT_KAPPA,
    blocks: Mapping[str, slice] | None = None,
    fallback_alphas: tuple[float, ...] = FALLBACK_ALPHAS,
    cross=CROSS_AUTO,
) -> Propagation:
    """Scaled unscented transform of a scalar black box.

    Parameters
    ----------
    f : callable
        ``f(X)``, ``X`` shape (M, K, L) -> values (M, K); NaN marks invalid inputs.
    x0 : ndarray, shape (M, L) or (L,)
        Input means.
    cov : ndarray, shape (L, L) or (M, L, L)
        Input covariance.
    alpha, beta, kappa : float
        Scaled-UT parameters (see :data:`DEFAULT_ALPHA`, :data:`DEFAULT_BETA`,
        :data:`DEFAULT_KAPPA`).
    blocks : mapping of name -> slice, optional
        Named input blocks for the budget (:attr:`Propagation.parts`).
    fallback_alphas : tuple of float
        Spreads tried in turn for measurements with invalid sigma points.
    cross : None, True, slice, int array, sequence of block names, or ``'auto'``
        Columns of ``sqrt(P)`` that also get cross points (see Notes): None for the
        plain 2L+1-point UT, True for all columns; ``'auto'`` (default) asks ``f`` (its
        ``cross_columns`` attribute, None if absent).

    Returns
    -------
    Propagation

    Notes
    -----
    With ``lambda = alpha^2 (L + kappa) - L`` and ``S S^T = P`` (``S = V sqrt(W)`` from the
    eigendecomposition of each block of ``P``, so that singular covariances, e.g.
    ``rho_images = 1``, work and each column belongs to one block), the sigma points are
    ``x0`` and ``x0 +- sqrt(L + lambda) S[:, i]``; the weights ``Wm0 = lambda / (L +
    lambda)``, ``Wc0 = Wm0 + 1 - alpha^2 + beta``, ``Wi = 1 / (2 (L + lambda))``. The
    covariance sum reduces to ``sum_i Wi [(f+_i - f0)^2 + (f-_i - f0)^2] + (beta -
    alpha^2) b^2`` with the bias ``b = sum_i Wi (f+_i + f-_i - 2 f0)``; the parts of a
    block are the same sums over its own columns (they add up to the total up to the
    cross term ``2 (beta - alpha^2) b_image b_calibration``, of fourth order).

    Cross points: for a chosen set C of columns, one more point ``x0 + c (s_i + s_j)``
    per pair i < j of C (``c = sqrt(L + lambda)``) gives the off-diagonal curvature
    ``h_ij = (f_ij - f+_i - f+_j + f0) / c^2``, and the variance of those columns becomes
    ``sum_i (g_i^2 + h_ii^2 / 2) + sum_{i<j} h_ij^2`` with ``g_i = (f+_i - f-_i) / 2c`` and
    ``h_ii = (f+_i + f-_i - 2 f0) / c^2``: exact for a quadratic ``f`` of Gaussian input
    whatever the rank of its curvature (the plain UT's ``beta b^2`` is exact only for
    rank one, see :data:`DEFAULT_BETA`). Columns outside C keep the UT sums and beta;
    cross curvature between C and the other columns is left out (image noise and
    calibration parameters: fourth order in two small quantities). The mean is the
    same in both forms. Cost: ``|C| (|C| - 1) / 2`` more evaluations.

    Invalid sigma points: a measurement with any NaN among its values is
    recomputed with the next smaller alpha of ``fallback_alphas``; if all fail its
    results are NaN. ``n_invalid`` counts the invalid points of the first attempt and
    ``alpha`` reports the spread used. A NaN ``f(x0)`` is NaN whatever the spread.
    """
    x0, cov = _as_batch(x0, cov)
    M, L = x0.shape
    S, separable = _sqrt_columns(cov, blocks)
    columns = _block_columns(blocks or {}, separable)
    ccols = _cross_columns(f, cross, L, blocks, separable)
    if ccols is not None:
        iu, ju = np.triu_indices(ccols.size, 1)
        cross_spec = (ccols, iu, ju)
    else:
        cross_spec = None
    if S.ndim == 2:
        S = np.broadcast_to(S, (M, L, L))
    out_mean = np.full(M, np.nan)
    out_bias = np.full(M, np.nan)
    out_std = np.full(M, np.nan)
    out_parts = {name: (np.full(M, np.nan), np.full(M, np.nan)) for name in columns}
    used = np.full(M, np.nan)
    n_invalid = np.zeros(M, dtype=np.int64)
    value = np.full(M, np.nan)
    todo = np.arange(M)
    for attempt, a in enumerate((alpha, *fallback_alphas)):
        if todo.size == 0:
            break
        c, *_ = _ut_weights(L, a, beta, kappa)
        cols = c * np.swapaxes(S[todo], 1, 2)  # (m, L, L): row i is column i of S
        parts_x = [x0[todo, None], x0[todo, None] + cols, x0[todo, None] - cols]
        if cross_spec is not None:
            parts_x.append(x0[todo, None] + cols[:, ccols[iu]] + cols[:, ccols[ju]])
        X = np.concatenate(parts_x, axis=1)
        y = np.asarray(f(X), dtype=np.float64)
        bad = ~np.isfinite(y)
        if attempt == 0:
            n_invalid[todo] = bad.sum(axis=1)
            value[todo] = y[:, 0]
        good = ~bad.any(axis=1)
        if good.any():
            idx = todo[good]
            mean, bias, std, parts = _ut_moments(y[good], L, a, beta, kappa, columns, cross_spec)
            out_mean[idx], out_bias[idx], out_std[idx] = mean, bias, std
            for name, (pb, ps) in parts.items():
                out_parts[name][0][idx] = pb
                out_parts[name][1][idx] = ps
            used[idx] = a
        # a centre that is itself invalid cannot be rescued by a smaller spread
        todo = todo[~good & np.isfinite(y[:, 0])]
    return Propagation(value, out_mean, out_bias, out_std, out_parts, n_invalid, used, "ut")


def linearised(
    f: BlackBox,
    x0: np.ndarray,
    cov: np.ndarray,
    *,
    blocks: Mapping[str, slice] | None = None,
    step: float = LINEAR_STEP,
) -> Propagation:
    """First-order propagation ``var = J P J^T`` with a numerical Jacobian.

    Parameters
    ----------
    f, x0, cov, blocks
        As in :func:`unscented`.
    step : float
        Central-difference step in standard deviations along each column of
        ``sqrt(P)`` (see :data:`LINEAR_STEP`).

    Returns
    -------
    Propagation
        ``bias`` is zero by construction (first order), ``mean == value``.

    Notes
    -----
    With ``S S^T = P``, ``J P J^T = sum_i (J s_i)^2`` and each directional derivative
    ``J s_i = (f(x0 + h s_i) - f(x0 - h s_i)) / (2 h)``, so all 2L+1 evaluations go in
    one call, as for the UT.
    """
    x0, cov = _as_batch(x0, cov)
    M, L = x0.shape
    S, separable = _sqrt_columns(cov, blocks)
    columns = _block_columns(blocks or {}, separable)
    cols = step * np.swapaxes(np.broadcast_to(S, (M, L, L)), 1, 2)
    X = np.concatenate([x0[:, None], x0[:, None] + cols, x0[:, None] - cols], axis=1)
    y = np.asarray(f(X), dtype=np.float64)
    n_invalid = (~np.isfinite(y)).sum(axis=1)
    js = (y[:, 1 : L + 1] - y[:, L + 1 :]) / (2.0 * step)  # (M, L): J s_i
    std = np.sqrt(np.sum(js**2, axis=1))
    zero = np.zeros(M)
    parts = {
        name: (np.where(np.isfinite(std), zero, np.nan), np.sqrt(np.sum(js[:, c] ** 2, axis=1)))
        for name, c in columns.items()
    }
    value = y[:, 0]
    bias = np.where(np.isfinite(std), zero, np.nan)
    return Propagation(
        value, value + bias, bias, std, parts, n_invalid, np.full(M, np.nan), "linear"
    )


def monte_carlo(
    f: BlackBox,
    x0: np.ndarray,
    cov: np.ndarray,
    *,
    n_samples: int = 20_000,
    seed: int | np.random.Generator = 0,
    blocks: Mapping[str, slice] | None = None,
    parts: bool = False,
) -> Propagation:
    """Monte Carlo propagation with Gaussian input samples.

    Parameters
    ----------
    f, x0, cov, blocks
        As in :func:`unscented`.
    n_samples : int
        Samples per measurement.
    seed : int or numpy Generator
        Makes the result reproducible.
    parts : bool
        Also sample each block alone for the budget (one more run per block).

    Returns
    -------
    Propagation
        Sample mean and standard deviation (ddof=1) of the valid samples;
        ``n_invalid`` counts the invalid ones (they are left out).
    """
    if n_samples < 2:
        raise BadInputError(f"Monte Carlo needs at least 2 samples, got {n_samples}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    x0, cov = _as_batch(x0, cov)
    M, L = x0.shape
    S, separable = _sqrt_columns(cov, blocks)
    S = np.broadcast_to(S, (M, L, L))
    value = np.asarray(f(x0[:, None]), dtype=np.float64)[:, 0]

    def run(column_mask: np.ndarray):
        total = np.zeros(M)
        total2 = np.zeros(M)
        count = np.zeros(M)
        per_call = max(1, MC_CHUNK // M)
        for start in range(0, n_samples, per_call):
            k = min(per_call, n_samples - start)
            # the same normal draws for every measurement (common random numbers): each
            # measurement's samples are still exact draws, and measurements that share
            # the parameter covariance share parameter samples, which the measurement
            # black box then triangulates with one model per sample
            z = rng.standard_normal((k, L)) * column_mask
            y = np.asarray(f(x0[:, None] + np.einsum("mij,kj->mki", S, z)), dtype=np.float64)
            ok = np.isfinite(y)
            d = np.where(ok, y - value[:, None], 0.0)  # shifted sums: no cancellation
            total += d.sum(axis=1)
            total2 += (d * d).sum(axis=1)
            count += ok.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = total / count
            var = (total2 - count * shift**2) / (count - 1)
        return value + shift, shift, np.sqrt(np.clip(var, 0.0, None)), n_samples - count

    mean, bias, std, n_bad = run(np.ones(L))
    out_parts = {}
    if parts:
        for name, cols in _block_columns(blocks or {}, separable).items():
            mask = np.zeros(L)
            mask[cols] = 1.0
            _, pb, ps, _ = run(mask)
            out_parts[name] = (pb, ps)
    return Propagation(
        value, mean, bias, std, out_parts, n_bad.astype(np.int64), np.full(M, np.nan), "mc"
    )


def propagate(f: BlackBox, x0, cov, method: str = "ut", *, blocks=None, **options) -> Propagation:
    """Dispatch to :func:`unscented`, :func:`linearised` or :func:`monte_carlo` by name.

    When ``blocks`` has one block holding every input, its part of the budget is the
    whole (:attr:`Propagation.parts`), whatever the method computes for parts.
    """
    propagators = {"ut": unscented, "linear": linearised, "mc": monte_carlo}
    if method not in propagators:
        raise BadInputError(
            f"unknown propagation method {method!r}", hint=f"use one of {', '.join(METHODS)}"
        )
    result = propagators[method](f, x0, cov, blocks=blocks, **options)
    if blocks and len(blocks) == 1:
        ((name, sl),) = blocks.items()
        if range(*sl.indices(np.shape(x0)[-1])) == range(np.shape(x0)[-1]):
            result = result._replace(parts={name: (result.bias, result.std)})
    return result


# ----- the measurement as a black box ---------------------------------------------------------


class MeasurementFunction:
    """``f``: stacked inputs -> measurement values, for one model, formula and point count.

    Parameters
    ----------
    model : CameraModel
        The nominal model; parameter columns of the input replace its free parameters.
    formula : callable
        Points ``(..., n, 3)`` mm -> values ``(...)``, vectorised and not raising for
        degenerate sets (e.g. a kind of :mod:`endomeasure.measure.kinds`; the measure
        layer passes it in, so the solvers do not depend on it).
    n_points : int
    with_params : bool
        Whether inputs carry the free parameters after the pixels.
    with_offsets : bool
        Whether inputs carry, after the pixels, an offset of each pixel coordinate that
        adds to it: the model misfit (:mod:`endomeasure.solvers.misfit`), an input of its
        own so that the budget can name it.
    method : str
        Triangulation method (``'ml'`` default).
    on_plane : ndarray of bool, shape (n_points,), optional
        Points that are not triangulated but placed where their left ray meets the plane
        through points 0, 1 and 2 (which must not be among them): a measurement plane.
        Their right-pixel inputs are carried but not used.

    Notes
    -----
    Calling it with ``X`` of shape ``(..., L)`` triangulates every distinct pair of
    pixels and parameter vector once (the UT's sigma points repeat most of them), all
    in one batched solve with a parameter vector per correspondence
    (:func:`~endomeasure.solvers.triangulate.triangulate`'s ``params``), and returns
    values of shape ``(...)``, NaN where a point fails, a ray misses the plane (parallel,
    or behind its origin) or the parameter vector is not a valid model.
    """

    def __init__(
        self,
        model: CameraModel,
        formula: Callable[[np.ndarray], np.ndarray],
        n_points: int,
        *,
        with_params: bool = False,
        with_offsets: bool = False,
        method: str = "ml",
        on_plane: np.ndarray | None = None,
    ):
        self.model = model
        self.formula = formula
        self.n_points = n_points
        self.method = method
        self.on_plane = np.zeros(n_points, dtype=bool)
        if on_plane is not None:
            self.on_plane = np.asarray(on_plane, dtype=bool).reshape(-1)
            if self.on_plane.shape != (n_points,) or self.on_plane[:3].any():
                raise ValueError("on_plane needs one flag per point, none on points 0-2")
        self.free = np.flatnonzero(model.free_mask) if with_params else np.zeros(0, dtype=np.int64)
        self.n_pixel_inputs = 4 * n_points * (2 if with_offsets else 1)
        """Pixels, and their offsets when ``with_offsets``; the parameters follow."""
        self.n_inputs = self.n_pixel_inputs + self.free.size
        self.cross_columns = slice(0, self.n_pixel_inputs) if n_points > 2 else None
        """Columns the UT gives cross points (:data:`CROSS_AUTO`): the pixels (and their
        offsets), when there are more than two points. The curvature of a measurement
        comes from the depth noise of its points (13-80 times their lateral noise at
        10-60 mm behind the default preset's prism): two points curve along one
        direction, their depth difference, where the plain UT with beta = 2 is exact;
        three or more curve along several (a polygon's two tilts, a polyline's
        segments), where it is not (:data:`DEFAULT_BETA`)."""

    def inputs(self, pixels_left: np.ndarray, pixels_right: np.ndarray) -> np.ndarray:
        """The stacked input ``x0`` (M, L) of measurements with pixels (M, n, 2) per half."""
        ql = np.asarray(pixels_left, dtype=np.float64)
        qr = np.asarray(pixels_right, dtype=np.float64)
        if ql.shape != qr.shape or ql.shape[-2:] != (self.n_points, 2):
            raise BadInputError(
                f"a measurement of {self.n_points} points needs left and right pixels of shape "
                f"(..., {self.n_points}, 2), got {ql.shape} and {qr.shape}"
            )
        lead = ql.shape[:-2]
        pix = np.concatenate([ql, qr], axis=-1).reshape(*lead, 4 * self.n_points)
        offsets = np.zeros((*lead, self.n_pixel_inputs - 4 * self.n_points))
        params = np.broadcast_to(self.model.params[self.free], (*lead, self.free.size))
        return np.concatenate([pix, offsets, params], axis=-1)

    def _points(self, corr: np.ndarray, params: ParamBatch | None) -> np.ndarray:
        """Triangulate the distinct rows of ``corr`` (R, 4) under the model, or each under
        its own parameter vector (``params``, index (R,)), in one batched solve; NaN rows
        where not OK."""
        rows = corr if params is None else np.column_stack([corr, params.index])
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        key = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(-1)
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        tri = triangulate(
            self.model,
            corr[first, :2],
            corr[first, 2:],
            self.method,
            reproject=False,
            params=None if params is None else params.take(first),
        )
        pts = np.where((tri.status == Status.OK)[:, None], tri.points, np.nan)
        return pts[inverse.reshape(-1)]

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        lead = X.shape[:-1]
        flat = X.reshape(-1, X.shape[-1])
        n, k = self.n_points, self.n_pixel_inputs
        corr = flat[:, : 4 * n]
        if k > 4 * n:
            corr = corr + flat[:, 4 * n : k]
        corr = corr.reshape(-1, 4)
        params = None
        if self.free.size:
            # every input row is a model; its few distinct parameter vectors form the
            # batch's table (invalid ones, e.g. n_glass <= 1, give NaN points and values)
            free, index = np.unique(flat[:, k:], axis=0, return_inverse=True)
            table = np.repeat(np.asarray(self.model.params)[None], free.shape[0], axis=0)
            table[:, self.free] = free
            params = ParamBatch(table, np.repeat(index.reshape(-1), n))
        if not self.on_plane.any():
            pts = self._points(corr, params).reshape(flat.shape[0], n, 3)
            return self.formula(pts).reshape(lead)
        # the triangulated points first (the plane's among them), then the left rays of
        # the others cut with the plane of each input row
        item = np.arange(corr.shape[0]).reshape(flat.shape[0], n)
        tri, ray = item[:, ~self.on_plane].reshape(-1), item[:, self.on_plane]
        pts = np.full((corr.shape[0], 3), np.nan)
        pts[tri] = self._points(corr[tri], None if params is None else params.take(tri))
        pts = pts.reshape(flat.shape[0], n, 3)
        normal, distance = plane_through(pts[:, 0], pts[:, 1], pts[:, 2])
        flat_ray = ray.reshape(-1)
        batch = None if params is None else params.take(flat_ray)
        rays = self.model.rays(corr[flat_ray, :2], Half.LEFT, batch)
        shape = (*ray.shape, 3)
        hit = intersect_plane(rays.origins.reshape(shape), rays.directions.reshape(shape),
                              normal[:, None, :], distance[:, None])  # fmt: skip
        pts[:, self.on_plane] = hit.points
        return self.formula(pts).reshape(lead)
