"""Marginal covariance of model parameters from a bundle Jacobian (board poses marginalised).

The calibration Jacobian has the arrow structure of bundle adjustment: every residual
depends on the shared model parameters and on one board pose. The normal matrix is

    J^T J = [[A,   B ],
             [B^T, C ]]     C block-diagonal, one 6x6 block per image,

and the covariance of the model parameters with the poses marginalised out is the
top-left block of ``s^2 (J^T J)^-1``, i.e. ``s^2 S^-1`` with the Schur complement
``S = A - sum_i B_i C_i^-1 B_i^T`` (the poses are nuisance parameters; their
uncertainty widens the parameters' through the ``B C^-1 B^T`` term). ``s^2 = SSR / (m - n)``
is the residual variance per residual component, with ``m`` residuals and ``n`` unknowns
(parameters and poses).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["MarginalCovariance", "marginal_covariance", "SINGULAR_RCOND"]

SINGULAR_RCOND = 1e-10
"""Smallest eigenvalue of the correlation-scaled Schur complement, relative to its
largest, below which a parameter combination counts as undetermined. Determined
combinations of realistic calibrations sit above 1e-6; a true null direction sits at
the level of the Jacobian's rounding (below 1e-14)."""
_NULL_LOADING = 0.25  # components of a null eigenvector above this name a parameter


class MarginalCovariance(NamedTuple):
    covariance: np.ndarray | None  # (F, F) in parameter units^2, None when singular
    information: np.ndarray  # (F, F) Schur complement S (unscaled by s^2)
    undetermined: tuple[int, ...]  # indices of parameters in null directions
    rcond: float  # smallest / largest eigenvalue of the correlation-scaled S


def marginal_covariance(
    J_params: np.ndarray,
    J_poses: np.ndarray,
    pose_of_row: np.ndarray,
    n_poses: int,
    residual_variance: float,
) -> MarginalCovariance:
    """Covariance of the model parameters with the board poses marginalised out.

    Parameters
    ----------
    J_params : ndarray, shape (m, F)
        Residual Jacobian with respect to the free model parameters.
    J_poses : ndarray, shape (m, 6)
        Each row's Jacobian with respect to its own pose (rotation vector, translation).
    pose_of_row : ndarray of int, shape (m,)
        Which pose each residual row belongs to.
    n_poses : int
    residual_variance : float, px^2
        ``s^2``.

    Returns
    -------
    MarginalCovariance
        ``covariance = s^2 S^-1``; ``undetermined`` lists the parameters that load on
        near-null directions of S (then ``covariance`` is None), including poses whose
        own block is singular (their parameters are then reported through S).
    """
    F = J_params.shape[1]
    A = J_params.T @ J_params
    S = A.copy()
    for i in range(n_poses):
        rows = pose_of_row == i
        if not np.any(rows):
            continue
        Jp, Jq = J_params[rows], J_poses[rows]
        B = Jp.T @ Jq
        C = Jq.T @ Jq
        S -= B @ np.linalg.pinv(C, rcond=1e-12, hermitian=True) @ B.T
    S = 0.5 * (S + S.T)
    diag = np.diag(S).copy()
    dead = np.flatnonzero(~(diag > 0))
    scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    Sn = S * scale[:, None] * scale[None, :]
    w, V = np.linalg.eigh(Sn)
    rcond = float(w[0] / w[-1]) if w[-1] > 0 else 0.0
    null = w < SINGULAR_RCOND * max(w[-1], 0.0)
    bad = set(dead.tolist())
    for k in np.flatnonzero(null):
        bad.update(np.flatnonzero(np.abs(V[:, k]) > _NULL_LOADING).tolist())
    if bad or F == 0:
        return MarginalCovariance(None, S, tuple(sorted(bad)), rcond)
    cov_n = (V / w[None, :]) @ V.T
    cov = residual_variance * cov_n * scale[:, None] * scale[None, :]
    return MarginalCovariance(0.5 * (cov + cov.T), S, (), rcond)
